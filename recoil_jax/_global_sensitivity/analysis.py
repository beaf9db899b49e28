"""Global sensitivity over a tolerance box: which parameters move the peaks, and which can
be left loose.

SALib samples the box and analyses the outputs (Sobol indices, Morris elementary
effects); the library's sweep evaluates the designs, in one batched program (a store
resumes it, a Dask client scales it out). DGSM comes from the sweep's exact forward
sensitivities instead of SALib's finite differences. A method is a class the caller
passes in (`SobolIndices`, `MorrisEffects`, `DGSM`).
"""

from __future__ import annotations

import abc
import collections
import dataclasses
import math
import sys
import time
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, final

import equinox as eqx
import numpy as np

from .._design.problem import Objective
from .._model.metrics import METRICS, metric
from .._model.parameter_table import PARAMETERS
from .._model.params import RecoilParams, params_from_values, params_to_values
from .._model.registry import ParameterError, check_integer
from .._model.settings import Smoothing, SolverOptions
from .._model.status import SolveError
from .._sweeps.result import SweepResult
from .._sweeps.sweep import sweep

__all__ = [
    "DGSM",
    "SENSITIVITY_METHODS",
    "MorrisEffects",
    "SensitivityMethod",
    "SensitivityResult",
    "SobolIndices",
    "sensitivity",
    "sensitivity_box",
]

#: The metric name of a study's objective (`Objective`) among the metrics.
OBJECTIVE = "objective"

#: The most designs one analysis evaluates (in memory: the samples and every peak).
MAX_DESIGNS = 2**24

#: The level of every interval (SALib's `conf_level`).
CONFIDENCE = 0.95


def _problem(names: Sequence[str], lower: np.ndarray, upper: np.ndarray) -> dict[str, Any]:
    """SALib's problem dictionary."""
    bounds = [[float(lo), float(hi)] for lo, hi in zip(lower, upper, strict=True)]
    return {"num_vars": len(names), "names": list(names), "bounds": bounds}


#: The most bootstrap resamples (each redraws every design's output).
MAX_RESAMPLES = 10_000


def _count(owner: str, key: str, value: Any, least: int, most: int | None = None) -> None:
    check_integer(f"{owner}.{key}", value, least, most)


class SensitivityMethod(eqx.Module):
    """A global sensitivity method: how it samples the box and what it computes from
    the outputs. `group(d)`: rows that are analysed together (a failed solve in a group
    leaves the whole group out); `gradients`: whether it needs each design's gradient."""

    name: ClassVar[str]
    gradients: ClassVar[bool] = False
    #: The keys of its indices per parameter, and the one they are ranked by.
    keys: ClassVar[tuple[str, ...]]
    main: ClassVar[str]

    @abc.abstractmethod
    def sample(self, problem: dict) -> np.ndarray:
        """`(n, d)`: the designs' values of the ranged parameters."""

    @abc.abstractmethod
    def group(self, d: int) -> int:
        """Rows per group."""

    @abc.abstractmethod
    def designs(self, d: int) -> int:
        """How many designs its sample of `d` parameters has (checked before sampling)."""

    @abc.abstractmethod
    def analyse(
        self, problem: dict, x: np.ndarray, y: np.ndarray, gradient: np.ndarray | None
    ) -> tuple[dict[str, dict[str, float]], dict[str, dict[str, float]] | None]:
        """Indices per parameter, and second-order indices per pair (`"a,b"`) or None,
        from the complete groups: `x (n, d)`, `y (n,)` and, if `gradients`, `(n, d)`."""

    def settings(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@final
class SobolIndices(SensitivityMethod):
    """Sobol first-order (`S1`) and total (`ST`) indices with bootstrap 95 % intervals
    (`S1_conf`, `ST_conf`: half-widths), from Saltelli's sampling: `samples` base points
    (a power of 2, at least 64), `samples·(d + 2)` designs, or `samples·(2d + 2)` with
    `second_order` (then `S2` per pair too). SALib samples and analyses."""

    samples: int = 1024
    second_order: bool = False
    resamples: int = 100
    seed: int = 0

    name: ClassVar[str] = "sobol"
    keys: ClassVar[tuple[str, ...]] = ("S1", "S1_conf", "ST", "ST_conf")
    main: ClassVar[str] = "ST"

    def __check_init__(self):
        _count("SobolIndices", "samples", self.samples, 64)
        if self.samples & (self.samples - 1):
            low = 2 ** int(math.log2(self.samples))
            raise ParameterError(
                f"SobolIndices.samples = {self.samples}: Saltelli's sampling needs a power "
                f"of 2 (e.g. {low} or {2 * low})"
            )
        _count("SobolIndices", "resamples", self.resamples, 10, MAX_RESAMPLES)
        _count("SobolIndices", "seed", self.seed, 0)
        if not isinstance(self.second_order, bool):
            raise ParameterError(
                f"SobolIndices.second_order = {self.second_order!r}: give true or false"
            )

    def group(self, d: int) -> int:
        return 2 * d + 2 if self.second_order else d + 2

    def designs(self, d: int) -> int:
        return self.samples * self.group(d)

    def sample(self, problem: dict) -> np.ndarray:
        from SALib.sample import sobol

        return sobol.sample(
            problem, self.samples, calc_second_order=self.second_order, seed=self.seed
        )

    def analyse(self, problem, x, y, gradient):
        from SALib.analyze import sobol

        # SALib seeds its bootstrap only from a seed that is not 0 (`if seed:`).
        s = sobol.analyze(
            problem, y, calc_second_order=self.second_order, num_resamples=self.resamples,
            conf_level=CONFIDENCE, seed=self.seed + 1,
        )  # fmt: skip
        names = problem["names"]
        indices = {n: {k: float(s[k][i]) for k in self.keys} for i, n in enumerate(names)}
        pairs = None
        if self.second_order:
            pairs = {
                f"{a},{b}": {"S2": float(s["S2"][i, j]), "S2_conf": float(s["S2_conf"][i, j])}
                for i, a in enumerate(names)
                for j, b in enumerate(names)
                if j > i
            }
        return indices, pairs


@final
class MorrisEffects(SensitivityMethod):
    """Morris elementary effects for screening many parameters: `trajectories` one-at-a-
    time paths on a grid of `levels` (even) per parameter, `trajectories·(d + 1)`
    designs. Per parameter `mu_star` (mean |effect|, with its bootstrap 95 %
    half-width `mu_star_conf`), `mu` and `sigma` (spread: interaction or nonlinearity);
    an effect is the change of the metric over a step in the box's normalised units
    (metric units per whole range). SALib samples and analyses."""

    trajectories: int = 64
    levels: int = 4
    resamples: int = 100
    seed: int = 0

    name: ClassVar[str] = "morris"
    keys: ClassVar[tuple[str, ...]] = ("mu", "mu_star", "sigma", "mu_star_conf")
    main: ClassVar[str] = "mu_star"

    def __check_init__(self):
        _count("MorrisEffects", "trajectories", self.trajectories, 4)
        _count("MorrisEffects", "levels", self.levels, 2)
        if self.levels % 2:
            raise ParameterError(f"MorrisEffects.levels = {self.levels}: give an even number")
        _count("MorrisEffects", "resamples", self.resamples, 10, MAX_RESAMPLES)
        _count("MorrisEffects", "seed", self.seed, 0)

    def group(self, d: int) -> int:
        return d + 1

    def designs(self, d: int) -> int:
        return self.trajectories * (d + 1)

    def sample(self, problem: dict) -> np.ndarray:
        from SALib.sample import morris

        return morris.sample(problem, self.trajectories, num_levels=self.levels, seed=self.seed)

    def analyse(self, problem, x, y, gradient):
        from SALib.analyze import morris

        s = morris.analyze(
            problem, x, y, num_resamples=self.resamples, conf_level=CONFIDENCE,
            num_levels=self.levels, seed=self.seed,
        )  # fmt: skip
        names = problem["names"]
        return {n: {k: float(s[k][i]) for k in self.keys} for i, n in enumerate(names)}, None


@final
class DGSM(SensitivityMethod):
    """Derivative-based global sensitivity measures from the exact gradients (the
    sweep's forward sensitivities, no finite differences): at `samples` points of the box
    (SALib's DGSM sequence, so that its finite-difference estimate can be run on the
    same points), per parameter `vi = E[(∂f/∂x_i)²]` (metric unit² / parameter unit²) and
    `dgsm = vi·(b_i − a_i)²/(π²·Var f)`, the upper bound it implies on the Sobol total
    index `ST` of a parameter uniform on `[a_i, b_i]` (Sobol & Kucherenko 2009), each
    with a bootstrap 95 % half-width (`vi_conf`, `dgsm_conf`; `resamples`, `seed`)."""

    samples: int = 1024
    resamples: int = 100
    seed: int = 0

    name: ClassVar[str] = "dgsm"
    keys: ClassVar[tuple[str, ...]] = ("vi", "vi_conf", "dgsm", "dgsm_conf")
    main: ClassVar[str] = "dgsm"
    gradients: ClassVar[bool] = True

    def __check_init__(self):
        _count("DGSM", "samples", self.samples, 16)
        _count("DGSM", "resamples", self.resamples, 10, MAX_RESAMPLES)
        _count("DGSM", "seed", self.seed, 0)

    def group(self, d: int) -> int:
        return 1

    def designs(self, d: int) -> int:
        return self.samples

    def sample(self, problem: dict) -> np.ndarray:
        from SALib.sample import finite_diff

        # Its base points (every (d + 1)-th row); the others are its finite differences.
        return finite_diff.sample(problem, self.samples)[:: problem["num_vars"] + 1]

    def analyse(self, problem, x, y, gradient):
        assert gradient is not None
        width = np.diff(np.asarray(problem["bounds"], dtype=float), axis=1)[:, 0]
        rng = np.random.default_rng(self.seed)
        draws = rng.integers(len(y), size=(self.resamples, len(y)))
        z = _normal_quantile()

        def measures(rows):
            vi = np.mean(np.square(gradient[rows]), axis=0)  # (d,)
            return vi, vi * width**2 / (np.pi**2 * np.var(y[rows]))

        vi, bound = measures(np.arange(len(y)))
        vi_draws, bound_draws = (np.stack(m) for m in zip(*map(measures, draws), strict=True))
        vi_conf = z * np.std(vi_draws, axis=0, ddof=1)
        bound_conf = z * np.std(bound_draws, axis=0, ddof=1)
        indices = {
            n: {
                "vi": float(vi[i]),
                "vi_conf": float(vi_conf[i]),
                "dgsm": float(bound[i]),
                "dgsm_conf": float(bound_conf[i]),
            }
            for i, n in enumerate(problem["names"])
        }
        return indices, None


def _normal_quantile() -> float:
    from scipy.stats import norm

    return float(norm.ppf(0.5 + CONFIDENCE / 2))


@dataclasses.dataclass(frozen=True)
class SensitivityResult:
    """What `sensitivity` found.

    - `method`: `"sobol"`, `"morris"` or `"dgsm"`; `settings`: the method's settings;
      `keys`: the keys of its indices, `main` the one parameters are ranked by (`ST`,
      `mu_star` or `dgsm`).
    - `parameters (d,)`, `lower (d,)`, `upper (d,)`: the box (SI units); `design`: the
      base design's flat values (every value not ranged).
    - `metrics`: the metric names analysed (`METRICS`, and `"objective"` if given).
    - `indices`: `{metric: {parameter: {key: value}}}`: Sobol `S1`, `S1_conf`, `ST`,
      `ST_conf` (SALib's names); Morris `mu`, `mu_star`, `sigma`, `mu_star_conf`; DGSM
      `vi`, `vi_conf`, `dgsm`, `dgsm_conf`. `second_order`: Sobol's `S2`, `S2_conf` per
      pair `"a,b"` (with `second_order=True`), else None.
    - `samples (n, d)`: every design's ranged values; `outputs`: metric → `(n,)` (NaN
      where the solve failed); `gradients`: DGSM's metric → `(n, d)`, else None.
    - `ok (n,)`: which solves succeeded; `failures`: reason → count; `used`: how many
      designs the indices rest on (a failed solve leaves its whole group out: a Saltelli
      block, a Morris trajectory, a DGSM point); `constant`: metrics that did not vary
      over the designs used (their indices are 0).
    - `seconds`: wall time; `stored`: designs read from a store rather than solved.
    """

    method: str
    settings: dict[str, Any]
    keys: tuple[str, ...]
    main: str
    parameters: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    design: dict[str, float]
    metrics: tuple[str, ...]
    indices: dict[str, dict[str, dict[str, float]]]
    second_order: dict[str, dict[str, dict[str, float]]] | None
    samples: np.ndarray
    outputs: dict[str, np.ndarray]
    gradients: dict[str, np.ndarray] | None
    ok: np.ndarray
    failures: dict[str, int]
    used: int
    constant: tuple[str, ...]
    seconds: float
    stored: int = 0

    def ranking(self, metric: str) -> list[str]:
        """The parameters from the most to the least important for `metric`."""
        by = self.indices[metric]
        return sorted(self.parameters, key=lambda p: -by[p][self.main])

    def to_json(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "settings": self.settings,
            "parameters": {
                n: [float(lo), float(hi)]
                for n, lo, hi in zip(self.parameters, self.lower, self.upper, strict=True)
            },
            "design": self.design,
            "metrics": list(self.metrics),
            "indices": self.indices,
            "second_order": self.second_order,
            "ranking": {m: self.ranking(m) for m in self.metrics},
            "designs": len(self.ok),
            "failed": int((~self.ok).sum()),
            "failures": self.failures,
            "used": self.used,
            "constant": list(self.constant),
            "seconds": self.seconds,
            "stored": self.stored,
        }


#: The methods by name (a file's `[method] name`).
SENSITIVITY_METHODS: dict[str, type[SensitivityMethod]] = {
    cls.name: cls for cls in (SobolIndices, MorrisEffects, DGSM)
}


def sensitivity_box(
    design: RecoilParams | Mapping[str, float], ranges: Mapping[str, Any]
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """The box of `ranges` around `design` (`RecoilParams` or flat values, the paper's
    elsewhere): `(names, lower, upper)`. A range is `(low, high)` in SI units, or a
    relative half-width `r` (0 < r < 1): `value·(1 ∓ r)`. Raises `ParameterError` naming
    the parameter and its valid range."""
    design = _design_values(design)
    if not ranges:
        raise ParameterError("ranges is empty: range at least one parameter")
    names, lower, upper = [], [], []
    for name, given in ranges.items():
        if name not in PARAMETERS:
            raise PARAMETERS.unknown(name)
        if PARAMETERS[name].integer:
            raise ParameterError(
                f"ranges: {name} is a count, not a tolerance; sweep its values instead"
            )
        if name not in design:
            raise ParameterError(
                f"ranges: {name} has no value in the design (m = 0 has no absorber; a knot "
                "needs an orifice; a load, buffer or recuperator value needs that hardware "
                "in the design), so ranging it would add that part; give it in the design"
            )
        if isinstance(given, int | float | np.floating) and not isinstance(given, bool):
            if not 0.0 < given < 1.0:
                raise ParameterError(
                    f"ranges: {name} = {given!r}: a relative half-width is in (0, 1); "
                    "give [low, high] for a wider range"
                )
            value = float(design[name])
            if value == 0.0:
                raise ParameterError(
                    f"ranges: {name} is 0 in the design, so a relative range is empty; "
                    "give [low, high]"
                )
            lo, hi = sorted((value * (1.0 - given), value * (1.0 + given)))
        else:
            try:
                lo, hi = np.asarray(given, dtype=float).tolist()
            except (TypeError, ValueError):
                raise ParameterError(
                    f"ranges: {name} = {given!r}: give [low, high] or a relative half-width"
                ) from None
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ParameterError(f"ranges: {name} = [{lo!r}, {hi!r}]: need finite low < high")
        names.append(name)
        lower.append(lo)
        upper.append(hi)
    fixed = {k: v for k, v in design.items() if k != "t1"}
    for side, ends in (("low", lower), ("high", upper)):
        try:
            params_from_values({**fixed, **dict(zip(names, ends, strict=True))})
        except ParameterError as error:
            raise ParameterError(f"ranges, at their {side} ends: {error}") from None
    return tuple(names), np.asarray(lower), np.asarray(upper)


def _check_metrics(metrics: Sequence[str], objective: Objective | None) -> tuple[str, ...]:
    if isinstance(metrics, str):
        metrics = (metrics,)
    metrics = tuple(metrics) + ((OBJECTIVE,) if objective is not None else ())
    if not metrics:
        raise ParameterError("metrics is empty: name at least one of " + ", ".join(METRICS))
    for name in metrics:
        if name == OBJECTIVE and objective is None:
            raise ParameterError(f"metric {OBJECTIVE!r} needs objective= (an rj.Objective)")
        if name != OBJECTIVE:
            metric(name)
    if objective is not None and objective.scatter is not None:
        raise ParameterError(
            "the objective's scatter (a worst case over a scatter) is not a function of one "
            "design; range the scattered parameters instead"
        )
    return tuple(dict.fromkeys(metrics))


def _design_values(design: RecoilParams | Mapping[str, float]) -> dict[str, float]:
    """Every flat value of the base design (names not given take the paper's values),
    and `t1`, the end time, if a mapping gives it."""
    if isinstance(design, RecoilParams):
        if design.load is not None and design.load.table is not None:
            raise ParameterError(
                "the design's load is a force table, which a sweep takes apart "
                "(sweep(force_table=...)); sensitivity analyses designs with an impulse "
                "or a pulse"
            )
        values = params_to_values(design)
        if any(np.ndim(v) for v in values.values()):
            raise ParameterError("the design is a batch of designs: give one")
        return {k: float(v) for k, v in values.items()}
    if not isinstance(design, Mapping):
        raise ParameterError(f"design = {design!r}: give RecoilParams or {{name: value}}")
    given = {k: float(v) for k, v in design.items()}
    t1 = {"t1": given.pop("t1")} if "t1" in given else {}
    values = params_to_values(params_from_values(given))
    return {k: float(v) for k, v in values.items()} | t1


def sensitivity(
    design: RecoilParams | Mapping[str, float],
    ranges: Mapping[str, Any],
    metrics: Sequence[str] = ("peak_anchoring_force", "peak_displacement"),
    method: SensitivityMethod = SobolIndices(),
    *,
    objective: Objective | None = None,
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions | None = None,
    store: Any = None,
    client: Any = None,
    workers: int | None = None,
    progress: bool | None = None,
) -> SensitivityResult:
    """Global sensitivity of peak metrics to parameters over a box.

    **Arguments:**

    - `design`: the base design (`RecoilParams`, or flat values by name); every value not
      ranged keeps its value.
    - `ranges`: parameter → `(low, high)` (SI units) or a relative half-width `r`
      (`value·(1 ∓ r)`): any parameter but the counts, orifice knots and hardware
      included (`sensitivity_box`). Sampled uniformly.
    - `metrics`: names of `METRICS`; with `objective` (an `Objective`) also `"objective"`,
      the weighted sum of its metrics, is analysed.
    - `method`: `SobolIndices()` (default), `MorrisEffects()` or `DGSM()`.
    - `smoothing`, `options`: as for `sweep` (DGSM: `GRADIENT_OPTIONS` by default).
    - `store`, `client`, `workers`: the sweep's (a store resumes a stopped analysis: the
      samples are the same for the same method and seed).
    - `progress`: the phases and the sweep's progress bar on stderr (default: on a
      terminal).

    **Returns:** `SensitivityResult` (`indices[metric][parameter][key]`).

    **Raises:** `ParameterError` for a bad name, range, metric or count, before anything
    is compiled; `SolveError` when no group of designs solved completely.
    """
    if not isinstance(method, SensitivityMethod):
        raise ParameterError(f"method = {method!r}: give SobolIndices(), MorrisEffects() or DGSM()")
    values = _design_values(design)
    names, lower, upper = sensitivity_box(values, ranges)
    metrics = _check_metrics(metrics, objective)
    problem = _problem(names, lower, upper)
    shown = sys.stderr.isatty() if progress is None else progress
    start = time.perf_counter()

    def say(line: str) -> None:
        if shown:
            print(f"sensitivity: {line}", file=sys.stderr, flush=True)

    x = _samples(method, problem)
    say(f"{method.name} over {len(names)} parameters: {len(x):,} designs")
    columns = {name: np.full(len(x), value) for name, value in values.items()}
    columns |= {name: x[:, i] for i, name in enumerate(names)}
    swept = sweep(
        columns, smoothing=smoothing, options=options, wrt=names if method.gradients else None,
        store=store, client=client, workers=workers, progress=shown,
    )  # fmt: skip
    outputs, gradients = _outputs(swept, metrics, names, objective, method.gradients)
    say(f"analysing ({method.name}, {getattr(method, 'resamples', 0)} bootstrap resamples)")
    result = _analysed(method, problem, x, outputs, swept.ok, gradients)
    return dataclasses.replace(
        result,
        design=values,
        failures=_failures(swept, result.ok),
        seconds=time.perf_counter() - start,
        stored=swept.stored,
    )


def _samples(method: SensitivityMethod, problem: dict) -> np.ndarray:
    """The method's samples of the box, `(n, d)`; `ParameterError` for more than
    `MAX_DESIGNS`, before any is drawn."""
    count = method.designs(problem["num_vars"])
    if count > MAX_DESIGNS:
        raise ParameterError(
            f"{method.name}: {count:,} designs is more than {MAX_DESIGNS:,}; use fewer "
            "samples or parameters"
        )
    return method.sample(problem)


def _outputs(
    swept: SweepResult,
    metrics: tuple[str, ...],
    names: tuple[str, ...],
    objective: Objective | None,
    gradients: bool,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """`(outputs, gradients)` of the sweep `swept` for the `metrics` (in their order):
    metric → `(n,)`, the objective's the weighted sum of its metrics; with `gradients`,
    metric → `(n, d)` with respect to the parameters `names` (else None)."""
    outputs = {m: swept.peaks[m] for m in metrics if m in METRICS}
    if objective is not None:
        outputs[OBJECTIVE] = np.asarray(objective(swept.peaks), dtype=float)
    jacobians = None
    if gradients:
        assert swept.gradients is not None
        by_metric = swept.gradients

        def jacobian(metric: str) -> np.ndarray:  # (n, d)
            if metric == OBJECTIVE:
                assert objective is not None
                terms = [w * jacobian(m) for m, w in objective.weights.items()]
                return np.sum(terms, axis=0)
            return np.stack([by_metric[metric][p] for p in names], axis=1)

        jacobians = {m: jacobian(m) for m in metrics}
    return {m: outputs[m] for m in metrics}, jacobians


def _failures(swept: SweepResult, ok: np.ndarray) -> dict[str, int]:
    """Why the designs not `ok` were left out: the sweep's message of each failed solve,
    by count. A solve that succeeded with a non-finite output (never seen) is counted
    too."""
    messages = swept.messages()
    failures = collections.Counter(
        messages[i] if not swept.ok[i] else "a non-finite output" for i in np.flatnonzero(~ok)
    )
    return dict(failures)


def _analysed(
    method: SensitivityMethod,
    problem: dict,
    x: np.ndarray,
    outputs: dict[str, np.ndarray],
    ok: np.ndarray,
    gradients: dict[str, np.ndarray] | None = None,
) -> SensitivityResult:
    """The analysis of evaluated samples (any function's: the tests feed analytic ones):
    complete groups only; a metric constant over them has indices 0."""
    d = problem["num_vars"]
    size = method.group(d)
    finite = [np.isfinite(y) for y in outputs.values()]
    finite += [np.isfinite(g).all(axis=1) for g in (gradients or {}).values()]
    ok = np.asarray(ok, dtype=bool) & np.all(finite, axis=0)
    complete = np.repeat(ok.reshape(-1, size).all(axis=1), size)
    used = int(complete.sum())
    if used == 0:
        raise SolveError(
            f"{method.name}: no group of {size} designs solved completely ({int((~ok).sum())} "
            f"of {len(ok)} solves failed); nothing to analyse"
        )
    indices, second, constant = {}, {}, []
    for name, y in outputs.items():
        y_used = y[complete]
        gradient = gradients[name][complete] if gradients is not None else None
        if np.ptp(y_used) <= 1e-12 * max(1.0, float(np.max(np.abs(y_used)))):
            constant.append(name)
            indices[name] = {p: dict.fromkeys(method.keys, 0.0) for p in problem["names"]}
            continue
        indices[name], pairs = method.analyse(problem, x[complete], y_used, gradient)
        if pairs is not None:
            second[name] = pairs
    return SensitivityResult(
        method=method.name,
        settings=method.settings(),
        keys=method.keys,
        main=method.main,
        parameters=tuple(problem["names"]),
        lower=np.asarray([b[0] for b in problem["bounds"]]),
        upper=np.asarray([b[1] for b in problem["bounds"]]),
        design={},
        metrics=tuple(outputs),
        indices=indices,
        second_order=second or None,
        samples=x,
        outputs=outputs,
        gradients=gradients,
        ok=ok,
        failures={},
        used=used,
        constant=tuple(constant),
        seconds=0.0,
    )
