import contextlib
import json
import os
from pathlib import Path

import pytest

import recoil_jax  # enables float64 before any test builds arrays

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"

# The command line keeps compiled programs on disk; in-process CLI tests must not write
# to the user's cache. Tests of the cache set it per subprocess.
os.environ["RECOIL_JAX_CACHE"] = "off"

# The code the command line runs (and the same bits): AVX2 on x86-64, for this process
# and, through XLA_FLAGS, every process it starts.
recoil_jax.use_avx2_codegen()

# One persistent compilation cache for the test session and every process it starts
# (notebook kernels, commands, the explorer, xdist's workers): the modules and processes
# solve the same structures, and a program compiled once is loaded after that. A fresh
# clone (CI) starts it empty; `RECOIL_JAX_TEST_CACHE` names another folder, `off` none.
_TEST_CACHE = os.environ.setdefault(
    "RECOIL_JAX_TEST_CACHE", str(ROOT / ".pytest_cache" / "jax-compilation")
)
if _TEST_CACHE.lower() != "off":
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _TEST_CACHE
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    recoil_jax.enable_compilation_cache(_TEST_CACHE)


@pytest.fixture(scope="session")
def reference_cases():
    """The paper's numbers and the independent hard-switch reference: from
    `../shared/reference/paper_cases.json` beside the checkout where it exists (CI has
    it), else the copy the package ships (a plain clone)."""
    path = SHARED / "reference" / "paper_cases.json"
    if path.exists():
        return json.loads(path.read_text())["cases"]
    return recoil_jax.paper_cases()


def documented_value(rng, name: str) -> float:
    """A value of parameter `name` drawn over its documented range (`rj.PARAMETERS`, where
    accuracy is tested): log-uniform where the range starts above 0 and spans a decade or
    more, else uniform."""
    import math

    low, high = recoil_jax.PARAMETERS[name].documented
    if low > 0 and high / low >= 10:
        return float(10 ** rng.uniform(math.log10(low), math.log10(high)))
    return float(rng.uniform(low, high))


#: The absorber's parameters, in the order the random-design tests draw them.
ABSORBER = ("m", "gap", "k_r", "c_r", "k_c", "n_c", "lambda_c")


def documented_values(rng, names) -> dict[str, float]:
    """`documented_value` of each of `names`, drawn in their order: `{name: value}`."""
    return {name: documented_value(rng, name) for name in names}


def batch_params(designs):
    """A list of flat-name dicts as one `RecoilParams` with a leading batch axis."""
    import recoil_jax.extend as rjx

    return rjx.batch_params(designs)[0]


def batch_peaks(designs, smoothing=None, options=None):
    """`peak_metrics` over a list of designs in one vmapped, jitted call."""
    import equinox as eqx
    import jax

    import recoil_jax as rj

    smoothing = smoothing if smoothing is not None else rj.Smoothing()
    options = options if options is not None else rj.SolverOptions()
    run = eqx.filter_jit(jax.vmap(rj.peak_metrics, in_axes=(0, None, None)))
    return run(batch_params(designs), smoothing, options)


@contextlib.contextmanager
def compiled_programs():
    """The names of the programs XLA compiles inside the block (a list, filled as they
    are; one loaded from the persistent cache counts too: JAX's event wraps the load)."""
    import jax.monitoring

    names = []

    def listen(event, duration, **kwargs):
        if event.endswith("backend_compile_duration"):
            names.append(str(kwargs.get("fun_name")))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def all_ok(status) -> bool:
    """Every element of a (batched) `Status` is `Status.ok`."""
    import numpy as np

    import recoil_jax as rj

    return bool(np.all(status == rj.Status.ok))


# Each compiled program keeps its machine code in its own memory mappings (about 700 per
# solver program, measured), and Linux allows a process 65,530 of them
# (`vm.max_map_count`): past that, LLVM cannot place new code and the process aborts or
# segfaults. One process compiles hundreds of programs in the full suite, so compiled code
# is dropped after any test that leaves the count high (not after each module: a later
# module traces again what an earlier one had, measured slower).
_MAX_MAPPINGS = 30_000


def _mappings() -> int:
    try:
        with open("/proc/self/maps") as maps:
            return sum(1 for _ in maps)
    except OSError:  # not Linux
        return 0


@pytest.fixture(autouse=True)
def _release_compiled_code_when_mappings_run_high():
    yield
    if _mappings() > _MAX_MAPPINGS:
        import jax

        jax.clear_caches()


def assert_complete_result(result, method: str, dimension: int):
    """Every optimiser returns one `OptimiseResult`, built complete: per scenario its
    best and closest points; every run the same `RunRecord`; a trace whose best
    feasible evaluation is the reported best (an independent read of the same
    evaluations)."""
    import numpy as np

    import recoil_jax as rj
    import recoil_jax.extend as rjx

    assert type(result) is rj.OptimiseResult and result.method == method
    scenarios = result.scenarios
    assert result.best_theta.shape == result.closest_theta.shape == (scenarios, dimension)
    assert result.best_objective.shape == result.closest_violation.shape == (scenarios,)
    assert result.scenario_limits.shape[0] == scenarios and result.runs
    for run in result.runs:
        assert type(run) is rjx.RunRecord
        for name in ("theta0", "theta", "best_theta"):
            assert np.shape(getattr(run, name)) == (dimension,), name
        if result.feasible[run.scenario]:
            assert run.best_objective >= result.best_objective[run.scenario]
    trace = result.trace
    assert {"seconds", "scenario", "objective", "feasible", "gradient", "phase"} <= set(trace)
    assert len({len(column) for column in trace.values()}) == 1
    assert np.all(np.diff(trace["seconds"]) >= 0)
    for s in range(scenarios):
        held = trace["feasible"] & (trace["scenario"] == s)
        best = np.min(trace["objective"][held]) if held.any() else np.nan
        np.testing.assert_array_equal(best, result.best_objective[s])
        assert result.best_so_far(s)[-1] == (best if held.any() else np.inf)
    assert result.simulations == result.solves + result.gradient_solves


def study_text(
    *,
    description: str | None = None,
    design: str | None = None,
    tune: str = "gap = [0.0, 0.1]",
    objective: str = "peak_anchoring_force = 1.0",
    constraints: str | None = None,
    optimiser: str | None = None,
    rest: str = "",
) -> str:
    """A study file's text, its sections' bodies given as TOML (None leaves one out): by
    default the paper's absorber tuned in its gap for the lowest peak anchoring force,
    with nothing else set. `rest`: more sections, as they are written (`[check]`,
    `[[front]]`, ...). `SMALL_STUDY` holds the small gap study that several tests run."""
    text = "" if description is None else f"description = {json.dumps(description)}\n"
    sections = dict(
        design=design, tune=tune, objective=objective, constraints=constraints,
        optimiser=optimiser,
    )  # fmt: skip
    for name, body in sections.items():
        if body is not None:
            text += f"[{name}]\n{body.strip()}\n"
    return text + rest


#: The small gap study: the paper's absorber (m 1500 kg) tuned in its gap for the
#: lowest peak anchoring force with the stroke within 0.15 m (`study_text`'s settings).
SMALL_STUDY = dict(
    design="m = 1500.0\ngap = 0.05",
    tune="gap = [0.0, 0.12]",
    constraints="max_stroke = { max = 0.15 }",
)


def drop_programs():
    """Drop this process's compiled programs from its bounded cache (`set_max_programs`),
    so that a test counts its own compilations whatever ran before it on its worker (a
    program built by an earlier test would otherwise be reused: no compilation)."""
    import jax.numpy as jnp

    import recoil_jax.extend as rjx

    previous = rjx.set_max_programs(1)
    rjx.structure_jit(lambda x: x)(jnp.ones(1))  # the one kept: a program of its own
    rjx.set_max_programs(previous)


def gap_problem(limit: float = 0.15):
    """The small gap study as a `DesignProblem` (`SMALL_STUDY`): the paper's absorber
    (m 1500 kg) tuned in its gap for the lowest peak anchoring force, the stroke within
    `limit` (m). One compiled program for every test that solves it."""
    import recoil_jax as rj

    return rj.DesignProblem(
        params=rj.params_from_values(m=1500.0, gap=0.05),
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        tune=("gap",),
        bounds={"gap": (0.0, 0.12)},
        constraints=(rj.Constraint("max_stroke", upper=limit),),
    )


#: A force defined in a script's `__main__` (or a notebook): cloudpickle sends its
#: class by value, as Dask does to its workers.
SCRIPT_FORCE = """
from __future__ import annotations

from typing import Any, ClassVar

import recoil_jax as rj
import recoil_jax.extend as rjx


class MainSpring(rjx.Force):
    GROUP = rjx.Group("main_spring", "MainSpring", "Spring to the mount", "hardware",
                      ("main_spring_stiffness",))
    ROWS = (rjx.Parameter(name="main_spring_stiffness", group="main_spring", default=0.0,
                          unit="N/m", lower=0.0, documented=(0.0, 1e6), meaning="a spring"),)
    SCALE: ClassVar[float] = 1.0  # not a field
    main_spring_stiffness: Any = rjx.float_leaf(0.0)

    def anchoring(self, y, t, design, smoothing):
        assert isinstance(self, MainSpring)  # its class by its name
        return {"main_spring": self.SCALE * self.main_spring_stiffness * y[0]}

    def potential(self, x_M, design):
        return super().potential(x_M, design)  # None: the energy not known
"""
