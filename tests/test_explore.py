"""The design explorer: the numbers it shows are `simulate`'s, bad input shows the
error message, an update after the first compilation is fast; and, in a real headless
browser (Debian's chromium), the served page loads, typing a value updates the shown
peak to the value `simulate` gives, and a bad value shows the message, no traceback."""

import contextlib
import shutil
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

import recoil_jax as rj

pytest.importorskip("panel")

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _peak(**values):
    return rj.peaks(rj.params_from_values(values)).to_dict()


@pytest.mark.slow  # compiles the explorer's program
def test_explorer_shows_simulate_numbers_and_errors():
    from recoil_jax.apps._explore.explorer import Explorer, _tuned

    explorer = Explorer()
    # A measured trace is drawn over the histories, in their units (mm, kN).
    trace = rj.extend.Trace.of([0.0, 0.1], x_M=[0.0, 0.05], F_AN=[1000.0, 2000.0])
    overlaid = Explorer(trace=trace)
    assert list(overlaid.measured.data["x_M"]) == [0.0, 50.0]
    assert list(overlaid.measured.data["F_AN"]) == [1.0, 2.0]
    assert explorer.measured is None
    explorer.set("gap", 0.05)
    expected = _peak(m=1500.0, gap=0.05)
    shown = explorer.peaks_pane.object
    assert (
        'id="peak_anchoring_force" style="text-align:right">'
        f"{expected['peak_anchoring_force_N']:.6g}" in shown
    )
    assert f"{expected['peak_displacement_m']:.6g}" in shown
    assert explorer.message.object == ""
    # The bars: the peak force's change for +1 % of each parameter, from peak_jacobian.
    values = explorer.values()
    wrt = _tuned(values)
    _, gradients = rj.peak_jacobian(rj.params_from_values(values), wrt=wrt)
    change = np.asarray(gradients.peak_anchoring_force) * np.array([values[n] for n in wrt]) * 0.01
    bars = dict(zip(explorer.bars.data["name"], explorer.bars.data["change"], strict=True))
    np.testing.assert_allclose([bars[n] for n in wrt], change, rtol=1e-9)
    assert explorer.update_ms is not None and explorer.update_ms > 0
    # A bad value: the message, under its field, names the parameter and its range;
    # the views are cleared (they would show a design the fields no longer describe).
    for typed, message in (
        ("-1", "Absorber.gap = -1 m is invalid"),
        ("abc", "gap = &#x27;abc&#x27; is not a number"),
        ("nan", "must be finite"),
    ):
        explorer.set("gap", typed)
        assert message in explorer.field_errors["gap"].object
        assert (
            explorer.message.object == "" and "Traceback" not in explorer.field_errors["gap"].object
        )
        assert "no results" in explorer.peaks_pane.object and not explorer.bars.data["name"]
        assert not len(explorer.force.data["t"])
    explorer.set("gap", 0.062)
    assert explorer.field_errors["gap"].object == "" and explorer.message.object == ""
    assert "peak_anchoring_force" in explorer.peaks_pane.object
    # Each card says whether its part is on, and what turns it off (the registry's
    # `Group.off`); the barrel's and the absorber's open, the others collapsed.
    assert (
        explorer.cards["recuperator"].title
        == "Gas recuperator (off: recuperator_force = recuperator_preload = 0)"
    )
    assert explorer.cards["rails"].title == (
        "Rails: elevation and friction (off: elevation = friction_force = friction_coefficient = 0)"
    )
    assert [g for g, card in explorer.cards.items() if not card.collapsed] == [
        "barrel",
        "absorber",
    ]
    # A failed solve (the barrel bottoms out the recuperator): why, and no peaks, limits
    # or gradient bars.
    explorer.set("m", 0.0)
    explorer.set("recuperator_length", 0.2)
    explorer.set("recuperator_force", 100.0)
    assert explorer.cards["recuperator"].title == "Gas recuperator (on)"
    assert "bottomed out" in explorer.message.object
    assert "no peaks: the solve failed" in explorer.peaks_pane.object
    assert "bottomed out" not in explorer.peaks_pane.object  # the reason said once
    assert "within the limit" not in explorer.peaks_pane.object and not explorer.bars.data["name"]
    # The histories end where the solve stopped (NaN after it, drawn as nothing).
    x = np.asarray(explorer.motion.data["x_M"])
    assert np.isfinite(x[0]) and np.isnan(x[-1])


# Waits, in the page, until the element with this id (inside any shadow root) shows the
# text; returns the page's clock then (ms since the epoch). Fails after 30 s.
_WAIT_FOR_TEXT = """async ([id, text]) => {
  const find = (root) => {
    const found = root.querySelector('#' + id);
    if (found) return found;
    for (const e of root.querySelectorAll('*')) {
      if (e.shadowRoot) { const inner = find(e.shadowRoot); if (inner) return inner; }
    }
    return null;
  };
  const start = Date.now();
  while (Date.now() - start < 30000) {
    const el = find(document);
    if (el && el.textContent === text) return Date.now();
    await new Promise(r => requestAnimationFrame(r));
  }
  throw new Error('timed out waiting for ' + text);
}"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def _explorer_served(*arguments):
    """`recoil-jax explore *arguments` served on a free port, without a browser: its
    address once it answers (5 minutes at most); stopped on leaving."""
    port = _free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "recoil_jax.apps._cli", "explore", *arguments,
         "--port", str(port), "--no-browser"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        url = f"http://localhost:{port}/"
        deadline = time.time() + 300
        while True:
            try:
                urllib.request.urlopen(url, timeout=5)
                break
            except OSError:
                assert server.poll() is None, server.stdout.read() if server.stdout else ""
                assert time.time() < deadline, "the explorer did not start"
                time.sleep(1)
        yield url
    finally:
        server.terminate()
        server.wait(timeout=30)


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_explorer_page_in_headless_chromium():
    playwright = pytest.importorskip("playwright.sync_api")
    # A new structure compiles for seconds: the spinner shows.
    with _explorer_served("--no-cache") as url:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True)
            page = browser.new_page()
            page.goto(url)
            force = page.locator("#peak_anchoring_force")
            force.wait_for(timeout=120_000)
            paper = _peak(m=1500.0, gap=0.062)["peak_anchoring_force_N"]
            assert force.inner_text() == f"{paper:.6g}"

            field = page.locator(".field-gap input")
            for gap in (0.05, 0.055, 0.06, 0.045):
                expected = f"{_peak(m=1500.0, gap=gap)['peak_anchoring_force_N']:.6g}"
                field.fill(str(gap))
                pressed = 1e3 * time.time()  # the page's Date.now() reads the same clock
                field.press("Enter")
                shown = page.evaluate(_WAIT_FOR_TEXT, ["peak_anchoring_force", expected])
                print(
                    f"gap {gap}: the page showed the new peak {shown - pressed:.0f} ms after Enter"
                )
                assert page.locator("#peak_anchoring_force").inner_text() == expected

            # A bad value: its message right under the field, the peaks gone.
            for typed, message in (("-1", "Absorber.gap = -1 m is invalid"),
                                   ("abc", "gap = 'abc' is not a number")):  # fmt: skip
                field.fill(typed)
                field.press("Enter")
                page.locator(".error-gap .error", has_text=message).wait_for(timeout=30_000)
                assert page.locator("#peak_anchoring_force").count() == 0
            assert "Traceback" not in page.content()
            field.fill("0.062")
            field.press("Enter")
            force.wait_for(timeout=30_000)
            # A new structure (the recuperator on) compiles for seconds: a spinner shows
            # at once; then a failed solve says why, with no peaks.
            page.get_by_text(
                "Gas recuperator (off: recuperator_force = recuperator_preload = 0)"
            ).click()
            page.locator(".field-recuperator_length input").fill("0.15")  # 0.95 L_r < 0.175 m
            page.locator(".field-recuperator_length input").press("Enter")
            force.wait_for(timeout=60_000)
            recuperator = page.locator(".field-recuperator_force input")
            recuperator.fill("100")
            recuperator.press("Enter")
            page.locator(".pn-loading").first.wait_for(timeout=5_000)
            page.get_by_text("compiling the program of this structure").wait_for(timeout=5_000)
            page.get_by_text("no peaks: the solve failed").wait_for(timeout=120_000)
            page.locator(".message .error", has_text="bottomed out").wait_for(timeout=5_000)
            browser.close()


#: The envelope study's hand design (issue 62) and the first study's violent one.
HOWITZER = dict(
    M=1800.0, v0=10.0, m=0.0, pulse_time=0.004, k=0.0, friction_force=1500.0,
    friction_coefficient=0.05, stop_stiffness=2.1e8, recuperator_length=1.8,
    buffer_length=0.15, mount_mass=8000.0, cg_distance=3.2, trunnion_height=1.1,
    spade_distance=3.6, c_out=16000.0, c_ret=30000.0, recuperator_preload=30000.0,
    buffer_damping=40000.0,
)  # fmt: skip
VIOLENT = dict(c_out=7574.0, c_ret=2292.0, recuperator_preload=51225.0, buffer_damping=100215.0)


def _at(design, elevation, duration=2.0):
    """What the envelope view shows of `design` at `elevation`: `simulate`'s peaks."""
    params = rj.params_from_values(design | {"elevation": elevation})
    peaks = rj.simulate(params, ts=np.linspace(0.0, duration, 400)).peaks
    return peaks.to_dict(), [h["name"] for h in rj.peaks_hazards(params, peaks)]


@pytest.mark.slow  # compiles the explorer's programs of the envelope's structure
def test_the_envelope_view_shows_each_elevation_and_its_hazards():
    """A design with the firing envelope: each elevation's metrics are `simulate`'s, held
    against their limits, and its hazards are named; they follow the fields; bad
    elevations say why; a design without the envelope says how to get the view."""
    from recoil_jax.apps._explore.explorer import Explorer

    explorer = Explorer(HOWITZER)
    table = explorer.envelope.table.object
    for k, elevation in enumerate((0.0, 35.0, 70.0)):
        report, hazards = _at(HOWITZER, elevation)
        for name in ("peak_mount_load", "peak_pull_force", "stability_margin", "return_time"):
            key = rj.METRICS[name].key
            assert f'id="env-{name}-{k}" class="within">{report[key]:.6g}<' in table or (
                f'id="env-{name}-{k}" class="">{report[key]:.6g}<' in table
            ), (name, elevation)
        assert hazards == [] and f"{elevation:g}°: no hazard" in explorer.envelope.hazards.object
    assert len(explorer.envelope.forces.objects) == 3
    # The violent design: it slams at every elevation and lifts the gun at 35 and 70.
    for name, value in VIOLENT.items():
        explorer.set(name, value)
    shown = explorer.envelope.hazards.object
    for k, elevation in enumerate((0.0, 35.0, 70.0)):
        _, hazards = _at(HOWITZER | VIOLENT, elevation)
        assert "slams" in hazards and (elevation == 0.0 or "lifts" in hazards)
        for hazard in hazards:
            assert f'id="env-hazard-{k}-{hazard}"' in shown
    assert 'class="over"' in explorer.envelope.table.object  # the margin's limit, 0.1
    # The elevations are a field: two conditions, then a bad one.
    explorer.envelope.elevations.value = "10, 60"
    assert len(explorer.envelope.forces.objects) == 2 and "10°" in explorer.envelope.table.object
    explorer.envelope.elevations.value = "10, 95"
    assert "elevation = 95 deg is invalid" in explorer.envelope.message.object
    assert explorer.envelope.table.object == "" and not explorer.envelope.forces.objects
    # Without the envelope, the view says what would give it.
    paper = Explorer()
    assert "no firing envelope" in paper.envelope.message.object


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_the_envelope_view_in_headless_chromium():
    """Served with the howitzer: the page shows each elevation's mount load as
    `simulate` gives it; typing a return damper updates the pull at 70° and names the
    hazards it brings."""
    playwright = pytest.importorskip("playwright.sync_api")
    assignments = [f"{k}={v}" for k, v in HOWITZER.items()]
    with _explorer_served(*assignments) as url:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True)
            page = browser.new_page()
            page.goto(url)
            for k, elevation in enumerate((0.0, 35.0, 70.0)):
                report, _ = _at(HOWITZER, elevation)
                expected = f"{report['peak_mount_load_N']:.6g}"
                page.evaluate(_WAIT_FOR_TEXT, [f"env-peak_mount_load-{k}", expected])
            field = page.locator(".field-c_ret input")
            field.fill("2292")
            field.press("Enter")
            report, hazards = _at(HOWITZER | {"c_ret": 2292.0}, 70.0)
            page.evaluate(
                _WAIT_FOR_TEXT, ["env-peak_pull_force-2", f"{report['peak_pull_force_N']:.6g}"]
            )
            for hazard in hazards:
                page.locator(f"#env-hazard-2-{hazard}").wait_for(timeout=30_000)
            assert "Traceback" not in page.content()
            browser.close()
