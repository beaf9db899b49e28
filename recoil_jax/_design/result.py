"""`OptimiseResult`: the one outcome of every optimiser (`search`, `minimise`,
`optimise`), built complete by the method that ran, and read the same way whatever
the method: the best and closest designs per scenario, every local run, every
evaluation in order."""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import numpy as np

from .._design.problem import Agreement, DesignProblem
from .._model.params import RecoilParams, params_to_values, with_values
from .._model.registry import ParameterError

__all__ = ["Found", "OptimiseResult", "RunRecord", "build_result"]


@dataclasses.dataclass(frozen=True)
class RunRecord:
    """One local run of an optimiser, whatever the method (`OptimiseResult.runs`).

    - `phase`: `"start"` (from the given design, a sample or a Latin start) or `"hop"`
      (basin hopping);
    - `theta0`, `theta`: where it began and ended (`(P,)`);
    - `objective`: what the method minimised, at its end (the smoothed objective at a
      smoothed level; NaN if the run ended before a level did);
    - `best_objective`, `best_theta`: the best feasible point it evaluated (inf and NaN
      if none);
    - `evaluations` (0 for a run the time budget stopped before its first),
      `iterations`, `converged` (its own test ended it, not a limit, a failure or the
      budget), `message`, `seconds` (its start and end);
    - `scenario`; `region` (starts that began in one region of the box share it; None
      for basin hopping's runs and runs that evaluated nothing);
    - `no_impact` (`optimise`): whether it ended with no impact at all (on the plateau
      where the gap gradient is exactly zero); None where not known.

    Fields also read by subscript, `run["phase"]` (as the dicts of earlier versions
    were read); it is not a mapping otherwise.
    """

    phase: str
    theta0: np.ndarray
    theta: np.ndarray
    objective: float
    best_objective: float
    best_theta: np.ndarray
    evaluations: int
    iterations: int
    converged: bool
    message: str
    seconds: tuple[float, float]
    scenario: int = 0
    region: int | None = None
    no_impact: bool | None = None

    def __getitem__(self, name: str) -> Any:
        if name not in self.__dataclass_fields__:
            raise KeyError(name)
        return getattr(self, name)


@dataclasses.dataclass(frozen=True)
class OptimiseResult:
    """Outcome of an optimiser: `search`, `minimise` or `optimise` (host NumPy values;
    `S` scenarios, `P` tuned parameters; `search` and `minimise` solve one scenario).

    - `method`: `"search"`, `"minimise"` or `"optax"` (`optimise`).
    - `problem`: the `DesignProblem` (None for `minimise` of a bare function, whose
      `θ` are the box coordinates `z`).
    - `best_theta (S, P)`, `best_objective (S,)`: per scenario, the best point that held
      every limit, of every evaluation (exact objective, true peaks; NaN where none
      did: `feasible (S,)` is False and the problem is reported infeasible).
    - `closest_theta (S, P)`, `closest_violation (S,)`: per scenario, the evaluated point
      whose largest normalised violation is least (of the successful solves; NaN if
      none), and that violation: where nothing is feasible, which limit is missed and by
      how much.
    - `runs`: every local run, in order, a `RunRecord` each (the same record for every
      method).
    - `trace`: every evaluation in order, arrays by name: `seconds` of the time budget
      (since the start; on a resumed store the earlier runs' included), `scenario`,
      `objective` (exact), `feasible`, `gradient` (whether it was a gradient solve),
      `phase` (`"sample"` and `"local"` for `search`; `"step"` for `optimise`, or
      `"stopped"` for a stopped run evaluated again where it stopped, as every step
      solves every run).
    - `solves`, `gradient_solves`: plain solves and solves with sensitivities
      (`simulations`: both); `seconds`; `compilations`: gradient programs built
      (compiled, or with `search` loaded exported from the compilation cache's folder);
      `replayed`: evaluations read back from a study's store instead of solved.
    - `scenario_params`: the base design of each scenario (leading axis `S`; None for
      `minimise`); `scenario_limits (S, C)`: their metric limits.
    - `samples` (`search`, `minimise`): the global phase: `z (N, P)`, `objective (N,)`,
      `violation (N,)` (largest normalised), `ok (N,)`. `history` (`optimise`): per
      step, `(steps, S·starts, ...)` arrays by name: `theta`, `objective`,
      `smooth_objective`, `violations`, `status`, and each metric.
    """

    method: str
    problem: DesignProblem | None
    best_theta: np.ndarray
    best_objective: np.ndarray
    closest_theta: np.ndarray
    closest_violation: np.ndarray
    runs: tuple[RunRecord, ...]
    trace: dict[str, np.ndarray]
    solves: int
    gradient_solves: int
    seconds: float
    compilations: int
    scenario_params: RecoilParams | None
    scenario_limits: np.ndarray
    samples: dict[str, np.ndarray] | None = None
    history: dict[str, np.ndarray] | None = None
    replayed: int = 0

    @property
    def feasible(self) -> np.ndarray:
        """`(S,)`: whether each scenario has a feasible design."""
        return np.isfinite(self.best_objective)

    @property
    def scenarios(self) -> int:
        return len(self.best_objective)

    @property
    def tune(self) -> tuple[str, ...]:
        if self.problem is None:
            return tuple(f"z{j}" for j in range(self.best_theta.shape[1]))
        return self.problem.tune

    @property
    def simulations(self) -> int:
        """Every solve, plain or with sensitivities."""
        return self.solves + self.gradient_solves

    def _base(self, scenario: int) -> RecoilParams:
        if self.problem is None or self.scenario_params is None:
            raise ParameterError(f"{self.method} of a bare function has no design parameters")
        return jax.tree.map(lambda x: x[scenario], self.scenario_params)

    def best_params(self, scenario: int = 0) -> RecoilParams:
        """The best design of `scenario` (`ParameterError` if none was feasible)."""
        if not self.feasible[scenario]:
            raise ParameterError("no feasible design was found: there is no best design")
        return with_values(self._base(scenario), self.tune, self.best_theta[scenario])

    def best_design(self, scenario: int = 0) -> dict[str, float]:
        """Every parameter of the best design of `scenario`, by flat name."""
        params = self.best_params(scenario)
        return {k: float(np.asarray(v)) for k, v in params_to_values(params).items()}

    def closest_params(self, scenario: int = 0) -> RecoilParams:
        """The least violating design of `scenario` (`closest_theta`)."""
        if not np.isfinite(self.closest_violation[scenario]):
            raise ParameterError("no solve succeeded: there is no closest design")
        return with_values(self._base(scenario), self.tune, self.closest_theta[scenario])

    def _runs_of(self, scenario: int) -> list[RunRecord]:
        return [run for run in self.runs if run.scenario == scenario]

    def agreement(self, scenario: int = 0, rtol: float = 1e-3) -> Agreement:
        """How firmly the best design of `scenario` was found (`Agreement`): of the
        runs from the starts that evaluated a point, grouped by the region of the box
        they began in, how many regions reached a feasible design within `rtol` of the
        best objective. One region alone means the best basin was found once: another
        seed may well end elsewhere (measured on `burst_recuperator`:
        `optimise/README.md`). `search` groups its starts by its global phase's
        `spacing` (`SobolStarts`); each start of `optimise` is its own region."""
        best = self.best_objective[scenario]
        limit = best + rtol * abs(best)  # NaN where none was feasible: none reached
        regions: dict[Any, bool] = {}
        starts = 0
        for run in self._runs_of(scenario):
            if run.phase != "start" or run.evaluations == 0:
                continue
            starts += 1
            reached = bool(run.best_objective <= limit)  # NaN limit: none feasible
            regions[run.region] = regions.get(run.region, False) or reached
        return Agreement(sum(regions.values()), len(regions), starts, rtol)

    def clusters(self, scenario: int = 0, rtol: float = 1e-3) -> list[dict]:
        """Where the runs of `scenario` ended: groups of runs whose best feasible
        objectives agree within `rtol`, best first, each with its `count`, the indices
        of its `runs` (into `runs`), how many `converged`, the group's best `design`,
        and (`optimise`) how many ended with no impact at all (`no_impact`: on the
        plateau where the gap gradient is exactly zero). Runs that found nothing
        feasible are groups of one with `objective` None."""
        indices = [i for i, run in enumerate(self.runs) if run.scenario == scenario]
        order = sorted(indices, key=lambda i: self.runs[i].best_objective)
        groups: list[dict] = []
        for i in order:
            run = self.runs[i]
            value = run.best_objective
            finite = bool(np.isfinite(value))
            for group in groups if finite else []:
                if group["objective"] is not None and abs(value - group["objective"]) <= rtol * abs(
                    group["objective"]
                ):
                    break
            else:
                group = {
                    "objective": float(value) if finite else None,
                    "count": 0,
                    "runs": [],
                    "design": (
                        dict(zip(self.tune, map(float, run.best_theta), strict=True))
                        if finite
                        else None
                    ),
                    "converged": 0,
                }
                if run.no_impact is not None:
                    group["no_impact"] = 0
                groups.append(group)
            group["count"] += 1
            group["runs"].append(i)
            group["converged"] += int(run.converged)
            if "no_impact" in group:
                group["no_impact"] += int(bool(run.no_impact))
        return groups

    def best_so_far(self, scenario: int = 0) -> np.ndarray:
        """The best feasible objective of `scenario` after each of its evaluations in
        `trace` (inf before the first)."""
        mine = self.trace["scenario"] == scenario
        values = np.where(self.trace["feasible"][mine], self.trace["objective"][mine], np.inf)
        return np.minimum.accumulate(values)

    def seconds_to(self, target: float, scenario: int = 0) -> float | None:
        """Wall seconds until a feasible objective ≤ `target` was found for `scenario`
        (None if never)."""
        hits = np.nonzero(self.best_so_far(scenario) <= target)[0]
        seconds = self.trace["seconds"][self.trace["scenario"] == scenario]
        return float(seconds[hits[0]]) if hits.size else None


class Found(NamedTuple):
    """What an optimiser found, before `build_result` (leading axis `S`: scenarios), its
    points in the optimiser's own coordinates: the best feasible points (`best_theta (S,
    P)`, NaN where none) and their objectives (NaN where none), the least violating
    points and their largest violations, every local run, every evaluation (`trace`),
    the solves and the seconds; the global phase's samples (`search`) or every step
    (`optimise`)."""

    best_theta: np.ndarray
    best_objective: np.ndarray
    closest_theta: np.ndarray
    closest_violation: np.ndarray
    runs: list[RunRecord]
    trace: dict[str, np.ndarray]
    solves: int
    gradient_solves: int
    seconds: float
    samples: dict[str, np.ndarray] | None = None
    history: dict[str, np.ndarray] | None = None


def build_result(
    method: str,
    problem: DesignProblem | None,
    found: Found,
    *,
    compilations: int,
    replayed: int = 0,
    to_theta=None,
    scenario_params: RecoilParams | None = None,
    scenario_limits: np.ndarray | None = None,
) -> OptimiseResult:
    """The one builder of an `OptimiseResult`, whatever the method: `found`'s points
    mapped to parameter values by `to_theta` (a point `(P,)` at a time; NaN stays NaN;
    None: they are values already), one scenario's trace given its `scenario` column,
    and the scenarios' base designs and limits (default: `problem`'s, one scenario)."""

    def mapped(z) -> np.ndarray:
        z = np.asarray(z, dtype=float)
        if to_theta is None:
            return z
        return np.asarray(to_theta(z)) if np.all(np.isfinite(z)) else np.full(z.shape, np.nan)

    runs = tuple(
        dataclasses.replace(
            run, theta0=mapped(run.theta0), theta=mapped(run.theta),
            best_theta=mapped(run.best_theta),
        )
        for run in found.runs
    )  # fmt: skip
    trace = found.trace
    if "scenario" not in trace:
        trace = trace | {"scenario": np.zeros(len(trace["seconds"]), dtype=int)}
    if scenario_params is None and problem is not None:
        scenario_params = jax.tree.map(lambda x: np.asarray(x)[None], problem.params)
    if scenario_limits is None:
        limits = [] if problem is None else [limit for _, _, limit in problem.metric_constraints]
        scenario_limits = np.asarray([limits], dtype=float).reshape(1, len(limits))
    return OptimiseResult(
        method=method,
        problem=problem,
        best_theta=np.stack([mapped(z) for z in found.best_theta]),
        best_objective=np.asarray(found.best_objective),
        closest_theta=np.stack([mapped(z) for z in found.closest_theta]),
        closest_violation=np.asarray(found.closest_violation),
        runs=runs,
        trace=trace,
        solves=found.solves,
        gradient_solves=found.gradient_solves,
        seconds=found.seconds,
        compilations=compilations,
        scenario_params=scenario_params,
        scenario_limits=scenario_limits,
        samples=found.samples,
        history=found.history,
        replayed=replayed,
    )
