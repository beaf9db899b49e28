"""What the figures show, read back from the matplotlib figure before it is saved: the
lowest point of each sweep curve marked and named, the front's designs as markers, the
heatmap's optimum starred, units on every axis, one style for all."""

import numpy as np
import pytest

from recoil_jax.apps._figures import designs, histories


@pytest.fixture
def saved(monkeypatch):
    """The figures the figure modules save, kept open for inspection."""
    figures = []

    def keep(fig, path):
        figures.append(fig)
        return path

    for module in (designs, histories):
        monkeypatch.setattr(module, "save", keep)
    return figures


def test_sweep_curves_mark_and_name_their_lowest_point(saved):
    gap = np.linspace(0.0, 0.12, 121)
    force = 5500.0 + 2e5 * (gap - 0.062) ** 2
    histories.plot_series(
        {"m = 1500 kg": (gap, force)},
        "unused.png",
        xlabel="gap (mm)",
        ylabel="peak anchoring force (N)",
        xscale=1e3,
        minima="N",
    )
    (ax,) = saved[0].axes
    (text,) = [t.get_text() for t in ax.get_legend().get_texts()]
    assert text == "m = 1500 kg: min 5500 N at 62"
    marker = [line for line in ax.lines if line.get_marker() == "v"]
    assert len(marker) == 1 and marker[0].get_xydata().tolist() == [[62.0, 5500.0]]
    assert ax.get_xlabel() == "gap (mm)" and ax.get_ylabel() == "peak anchoring force (N)"
    assert not ax.spines["top"].get_visible()  # the shared style


def test_front_points_carry_markers(saved):
    histories.plot_series(
        {"best design": ([100.0, 500.0, 1500.0], [6900.0, 6500.0, 5324.0])},
        "unused.png",
        xlabel="m (kg)",
        ylabel="peak anchoring force (N)",
        markers=True,
    )
    (line,) = saved[0].axes[0].lines
    assert line.get_marker() == "o"


def test_heatmap_stars_the_lowest_point(saved):
    gap, mass = np.linspace(0.0, 0.12, 13), np.array([500.0, 1000.0, 1500.0])
    values = np.add.outer(-mass, 1e4 * (gap - 0.06) ** 2)  # lowest at m = 1500, gap = 0.06
    values[0, 0] = np.nan  # a failed point stays blank
    designs.plot_heatmap(
        gap, mass, values, "unused.png", xlabel="gap (m)", ylabel="m (kg)", label="F (N)"
    )
    ax = saved[0].axes[0]
    (star,) = [line for line in ax.lines if line.get_marker() == "*"]
    np.testing.assert_allclose(star.get_xydata(), [[0.06, 1500.0]])
    assert "lowest: -1500 at gap (m) = 0.06, m (kg) = 1500" in ax.get_title()


def test_many_sweep_lines_are_told_apart_by_a_colour_scale(saved):
    gap = np.linspace(0.0, 0.12, 13)
    masses = np.linspace(500.0, 3000.0, 26)
    series = {f"m = {m:g} kg": (gap, 5000.0 + m * (gap - 0.06) ** 2) for m in masses}
    histories.plot_series(
        series, "unused.png", xlabel="gap (mm)", ylabel="F (N)", colour_by=("m (kg)", masses)
    )
    ax, bar = saved[0].axes  # the plot and its colour bar, no legend
    assert ax.get_legend() is None and bar.get_ylabel() == "m (kg)"
    colours = [tuple(line.get_color()) for line in ax.lines]
    assert len(set(colours)) == 26  # one colour per value, none repeated


def test_heatmap_cells_are_the_swept_values(saved):
    """Uneven values (m = 100, 500, 1000, 1500) get equal cells labelled by the values
    swept, never a cell reaching below the smallest; an even axis ends at its first and
    last value."""
    gap, mass = np.linspace(0.0, 120.0, 13), np.array([100.0, 500.0, 1000.0, 1500.0])
    values = np.add.outer(-mass, (gap - 60.0) ** 2)
    designs.plot_heatmap(
        gap, mass, values, "unused.png", xlabel="gap (mm)", ylabel="m (kg)", label="F (N)"
    )
    ax = saved[0].axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["100", "500", "1000", "1500"]
    assert ax.get_ylim() == pytest.approx((-0.5, 3.5))
    assert ax.get_xlim() == pytest.approx((0.0, 120.0))
    (star,) = [line for line in ax.lines if line.get_marker() == "*"]
    np.testing.assert_allclose(star.get_xydata(), [[60.0, 3.0]])  # m = 1500: the 4th row
    assert "lowest: -1500 at gap (mm) = 60, m (kg) = 1500" in ax.get_title()


def test_a_history_marks_its_peaks_and_shows_the_impact(saved):
    """The peaks from the solve are marked and named; the impact (tens of ms) gets an
    inset; the time axis ends where the motion has died down; without an absorber, no
    absorber line and no empty force panel."""
    import recoil_jax as rj

    history = rj.simulate(rj.params_from_values(m=1500.0, gap=0.062))
    histories.plot_history(history, "unused.png")
    top, middle, bottom = saved[0].axes[:3]
    names = " ".join(t.get_text() for ax in (top, middle, bottom) for t in ax.texts)
    p = history.peaks
    assert f"peak $x_M$ {1e3 * float(p.peak_displacement):.4g} mm" in names
    assert f"peak $F_{{AN}}$ {1e-3 * float(p.peak_anchoring_force):.4g} kN" in names
    assert f"peak $F_{{ct}}$ {1e-3 * float(p.peak_contact_force):.4g} kN" in names
    (inset,) = bottom.child_axes
    low, high = inset.get_xlim()  # ms around the impact at 128 ms
    assert 100 < low < 128 < high < 160
    assert bottom.get_xlim()[1] < 10.0 and "of 10 s" in bottom.get_xlabel()
    plain = rj.simulate(rj.params_from_values(m=0.0))
    histories.plot_history(plain, "unused.png")
    axes = saved[1].axes
    assert len(axes) == 2
    assert [line.get_label() for line in axes[0].lines if line.get_marker() != "o"] == [
        "barrel $x_M$"
    ]


def test_convergence_axes_carry_the_unit_and_every_run_s_end(saved):
    from types import SimpleNamespace

    import recoil_jax as rj

    problem = rj.DesignProblem(
        params=rj.RecoilParams(),
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        tune=("gap",),
        bounds={"gap": (0.0, 0.12)},
    )
    steps, runs = 50, 3
    objective = np.full((steps, runs), 6000.0)
    objective[:, 0] = np.linspace(9000.0, 5400.0, steps)  # converges
    objective[:, 1] = 5500.0  # a plateau near the best
    objective[:, 2] = np.linspace(20000.0, 7000.0, steps)  # a run stuck far above
    history = {
        "objective": objective,
        "violations": np.zeros((steps, runs, 0)),
        "status": np.zeros((steps, runs), dtype=int),
    }
    designs.plot_convergence(SimpleNamespace(history=history, problem=problem), "unused.png")
    (ax,) = saved[0].axes
    assert ax.get_ylabel() == "best feasible: peak anchoring force (N)"
    assert ax.get_ylim()[0] < 5400.0 and ax.get_ylim()[1] > 7000.0  # every run's end
