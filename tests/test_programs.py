"""The compiled programs a process keeps are bounded (`rjx.set_max_programs`): the least
recently used is dropped, and its memory (the memory regions XLA maps for it, of which
Linux allows a process about 65,000) is freed."""

import gc
import inspect
import json
import os
import subprocess
import sys
import textwrap
import weakref

import jax.numpy as jnp
import pytest

import recoil_jax as rj
import recoil_jax._model.programs as cache
import recoil_jax.extend as rjx


@pytest.fixture
def limit():
    """Set the limit for one test; the suite's own limit comes back after it."""
    previous = rjx.set_max_programs(32)
    yield rjx.set_max_programs
    rjx.set_max_programs(previous)


def test_least_recently_used_programs_are_dropped(limit):
    traces = []

    @rjx.structure_jit
    def total(x, power):
        traces.append((x.shape, power))  # runs once per compilation (trace)
        return jnp.sum(x**power)

    limit(3)
    for n in (1, 2, 3):
        assert float(total(jnp.ones(n), 2)) == n
    assert len(traces) == 3 and rjx.live_programs() <= 3
    total(jnp.ones(1), 2)  # used again: no new program, and now the most recent
    assert len(traces) == 3
    dropped = [weakref.ref(p) for k, p in cache._programs.items() if k[0] is total.__wrapped__]
    total(jnp.ones(4), 2)  # a fourth structure: shape 2, the least recently used, goes
    assert len(traces) == 4 and rjx.live_programs() == 3
    total(jnp.ones(1), 2)
    total(jnp.ones(3), 2)
    assert len(traces) == 4  # kept
    total(jnp.ones(2), 2)
    assert len(traces) == 5  # compiled again
    total(jnp.ones(2), 3)  # a non-array argument is part of the structure
    assert traces[-1] == ((2,), 3)
    # Nothing but the cache held a dropped program: it is freed.
    gc.collect()
    assert sum(ref() is None for ref in dropped) >= 2
    with pytest.raises(rj.ParameterError, match="max programs"):
        limit(0)


#: Run in a fresh process: in the test process, the regions freed by programs an earlier
#: test dropped are reused by the next program, which then seems to map nothing.
_MAPPINGS = """
import gc, json
import jax.numpy as jnp
import numpy as np
import recoil_jax as rj
import recoil_jax.extend as rjx


def mappings():
    with open("/proc/self/maps") as maps:
        return sum(1 for _ in maps)
"""


def _in_fresh_process(code: str) -> dict:
    """Run `_MAPPINGS` then `code` in a fresh Python process; the JSON it prints last."""
    done = subprocess.run(
        [sys.executable, "-c", _MAPPINGS + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_many_structures_stay_below_a_bound_of_memory_mappings():
    """Solves of 6 model structures (2 to 7 orifice knots) in one process, 2 programs
    kept: the memory mappings after all of them are about those of 2 programs, not 6."""
    figures = _in_fresh_process(
        """
        def design(knots):
            values = {f"orifice_{i}": 4e-4 for i in range(knots)}
            return rj.params_from_values(values | {"piston_area": 0.01, "orifice_length": 0.2})

        rjx.set_max_programs(2)
        gc.collect()
        base = mappings()
        rj.peaks(design(2))
        gc.collect()
        one = mappings() - base  # what one structure's program maps
        finite = [
            bool(np.isfinite(float(rj.peaks(design(k)).peak_anchoring_force))) for k in range(3, 8)
        ]
        gc.collect()
        print(json.dumps(
            {"one": one, "grown": mappings() - base, "live": rjx.live_programs(), "finite": finite}
        ))
        """
    )
    assert all(figures["finite"]) and figures["live"] <= 2
    # Unbounded, 6 programs would map about 6 times one; bounded, about 2.
    assert figures["one"] > 100, figures
    assert figures["grown"] < 3.5 * figures["one"], figures


@pytest.mark.slow
def test_five_hundred_structures_in_one_process_stay_below_a_bound():
    """500 structures through one `structure_jit` function in one process, 8 programs
    kept: after the first 8, the process maps no more memory regions, though each new
    program maps about 3 (small programs: 878 more mappings for 292 of them, measured
    unbounded), and the model's about 460."""
    figures = _in_fresh_process(
        """
        traces = []

        @rjx.structure_jit
        def power_sum(x, power):
            traces.append(power)
            return jnp.sum(jnp.sin(x) ** power) + power

        rjx.set_max_programs(8)
        for power in range(8):
            power_sum(jnp.ones(3), power)
        gc.collect()
        base = mappings()
        wrong = [
            p for p in range(8, 500)
            if not np.isclose(float(power_sum(jnp.ones(3), p)), 3 * np.sin(1.0) ** p + p)
        ]
        gc.collect()
        print(json.dumps({"grown": mappings() - base, "traces": len(traces),
                          "live": rjx.live_programs(), "wrong": wrong}))
        """
    )
    assert figures["wrong"] == [] and figures["traces"] == 500 and figures["live"] <= 8
    # Unbounded, 492 more programs would map about 1,500 more regions.
    assert figures["grown"] < 100, figures


#: In a fresh process: the flag counts only if set before the CPU backend starts. `WHEN`:
#: call `use_avx2_codegen` before the first computation, after it, or not at all.
_AVX2 = """
import json, os, platform
import numpy as np
import recoil_jax as rj
when = os.environ["WHEN"]
first = rj.use_avx2_codegen() if when == "before" else None
designs = {"m": np.linspace(100.0, 3000.0, 48), "gap": np.linspace(0.0, 0.15, 48)}
peaks = rj.sweep(designs, progress=False, workers=1).peaks
later = rj.use_avx2_codegen() if when == "after" else None
print(json.dumps({"first": first, "later": later, "flags": os.environ.get("XLA_FLAGS", ""),
                  "x86": platform.machine(),
                  "peaks": {k: np.asarray(v).tolist() for k, v in peaks.items()}}))
"""


def _fresh(when: str, flags: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"} | {"WHEN": when}
    if flags is not None:
        env["XLA_FLAGS"] = flags
    out = subprocess.run(
        [sys.executable, "-c", _AVX2], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.splitlines()[-1])


def test_avx2_codegen_is_set_before_the_backend_and_changes_no_result():
    """`rj.use_avx2_codegen()` sets the flag on x86-64 in a fresh process, leaves a cap
    the user chose alone (reporting whether it is AVX2), and does nothing once JAX has
    computed; the peaks come out the same to the bit as with XLA's own choice (on an
    AVX-512 machine the code differs)."""
    chosen = _fresh("before")
    x86 = chosen["x86"].lower() in ("x86_64", "amd64")
    assert chosen["first"] is x86
    assert ("--xla_cpu_max_isa=AVX2" in chosen["flags"]) is x86
    late = _fresh("after")
    assert late["later"] is False and late["flags"] == ""
    own = _fresh("before", "--xla_cpu_max_isa=SSE4_2")
    assert own["first"] is False and own["flags"] == "--xla_cpu_max_isa=SSE4_2"
    assert _fresh("before", "--xla_cpu_max_isa=avx2")["first"] is True  # already AVX2
    default = _fresh("never")
    assert default["flags"] == "" and chosen["peaks"] == default["peaks"]


def _as_the_package_s(fn):
    """`fn`, named as a function of the package (only those are exported)."""
    fn.__module__ = "recoil_jax._probe"
    return fn


def test_programs_are_exported_only_where_their_key_says_what_they_compute(
    tmp_path, monkeypatch, limit
):
    """With a cache folder, `structure_jit(..., exported=...)` exports a package
    function's program, and a second build of it loads the file instead of tracing
    (the same result); a program JAX cannot export (`equinox.error_if`'s host callback)
    is marked refused, so that later builds trace it once, not twice; a function from
    outside the package, or a static argument named by its address, writes nothing.
    Every build counts (`program_builds`), loaded or compiled."""
    import dataclasses

    import equinox as eqx

    pytest.importorskip("flatbuffers")  # (jax.export's files: the apps extra)
    monkeypatch.setattr(cache, "_export_folder", lambda: str(tmp_path))
    folder = tmp_path / "exported"
    traces = []

    def scaled(x, power):
        traces.append("scaled")
        return x**power

    program = cache.structure_jit(_as_the_package_s(scaled), exported=lambda leaves: leaves[0])
    assert float(program(jnp.array(3.0), 2)) == 9.0
    (written,) = folder.iterdir()
    assert written.name.startswith("scaled-") and len(traces) == 1
    limit(1)  # drop it from memory: built again, from the file
    rjx.structure_jit(lambda x: x)(jnp.ones(1))
    assert float(program(jnp.array(4.0), 2)) == 16.0
    assert len(traces) == 1 and cache.program_builds(scaled) == 2

    def checked(x):
        traces.append("checked")
        return eqx.error_if(x, x < 0, "negative")

    guarded = cache.structure_jit(_as_the_package_s(checked), exported=lambda leaves: leaves[0])
    assert float(guarded(jnp.array(2.0))) == 2.0  # traced to export, then to compile
    assert [p.suffix for p in folder.glob("checked-*")] == [".refused"]
    rjx.structure_jit(lambda x: x)(jnp.ones(1))
    assert float(guarded(jnp.array(5.0))) == 5.0  # refused: traced once, to compile
    assert traces.count("checked") == 3 and cache.program_builds(checked) == 2

    class Scale:  # no value repr: named by its address
        def __init__(self, value):
            self.value = value

    def outside(x):
        return 2.0 * x

    times = cache.structure_jit(
        _as_the_package_s(lambda x, scale: scale.value * x), exported=lambda leaves: leaves[0]
    )
    assert float(times(jnp.array(1.0), Scale(3.0))) == 3.0
    assert float(cache.structure_jit(outside, exported=lambda out: out[0])(jnp.array(1.0))) == 2.0

    @dataclasses.dataclass(frozen=True)
    class Gain:  # a value's repr, but a type from outside the package
        value: float

    gained = cache.structure_jit(
        _as_the_package_s(lambda x, gain: gain.value * x), exported=lambda leaves: leaves[0]
    )
    assert float(gained(jnp.array(1.0), Gain(4.0))) == 4.0
    assert sorted(p.name.split("-")[0] for p in folder.iterdir()) == ["checked", "scaled"]


def test_the_solves_raise_outside_their_programs_so_that_they_are_kept(
    tmp_path, monkeypatch, limit
):
    """`rj.peaks`, `rj.simulate` and `rj.peak_jacobian` check their status after the
    compiled program, not in it: none of the three programs holds a host callback (JAX
    keeps none that do in its persistent cache), where the same solve with
    `raise_on_failure` inside does. `rj.peaks`' program, with the default `throw=True`,
    is exported and loaded again after being dropped from memory; a failure that the
    loaded program reports raises `SolveError` with the status's message."""
    import jax

    from recoil_jax._model import derivatives, solve
    from recoil_jax._model.status import raise_on_failure

    params = rj.params_from_values(m=500.0, gap=0.0)
    smoothing, options = rj.Smoothing(), rj.SolverOptions(max_steps=100)
    ts = jnp.linspace(0.0, 0.1, 11)
    wrt = ("gap",)

    def lowered(fn) -> str:
        return jax.jit(fn).lower().as_text()

    def peaks():
        return solve._peaks_jit(params, smoothing, options)

    programs = {
        "peaks": peaks,
        "simulate": lambda: solve._simulate_jit(params, smoothing, options, ts),
        "peak_jacobian": lambda: derivatives._peak_jacobian_jit(params, smoothing, options, wrt),
    }
    for name, program in programs.items():
        assert "callback" not in lowered(program), name
    assert "callback" in lowered(lambda: raise_on_failure(peaks(), peaks().status))

    pytest.importorskip("flatbuffers")  # (jax.export's files: the apps extra)
    monkeypatch.setattr(cache, "_export_folder", lambda: str(tmp_path))
    limit(1)
    rjx.structure_jit(lambda x: x)(jnp.ones(1))  # drop what earlier tests built
    builds = cache.program_builds(inspect.unwrap(solve._peaks_jit))
    fine = rj.peaks(rj.params_from_values(m=500.0, gap=0.15), smoothing, options)
    assert fine.status == rj.Status.ok
    (written,) = (tmp_path / "exported").iterdir()
    assert written.name.startswith("_peaks_jit-") and written.suffix != ".refused"
    rjx.structure_jit(lambda x: x)(jnp.ones(1))
    loads = []
    monkeypatch.setattr(jax.export, "deserialize", _counted(jax.export.deserialize, loads))
    with pytest.raises(rj.SolveError, match="max_steps reached before t1") as info:
        rj.peaks(params, smoothing, options)
    assert rj.failure_message(info.value) == rj.Status[rj.Status.max_steps]
    assert len(loads) == 1 and cache.program_builds(inspect.unwrap(solve._peaks_jit)) == builds + 2
    quiet = rj.peaks(params, smoothing, options, throw=False)
    assert quiet.status == rj.Status.max_steps and len(loads) == 1  # the same program


def _counted(fn, calls):
    def counted(*args, **kwargs):
        calls.append(1)
        return fn(*args, **kwargs)

    return counted
