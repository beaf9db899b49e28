"""Choosing a test plan from information matrices: which firings (repeats allowed) and
which signals each records, within a budget, for the best criterion.

- `Options`: every way one firing may be made, a candidate condition and a set of
  signals whose cost fits, with its information `(R, P, P)` (the sum of its signals')
  at each of `R` truths (one, or the robust plan's draws from the box).
- `criterion_value`: D (log det), A (−Σ variances) or one parameter's (−its variance)
  of an information matrix, higher better; `plan_value` its mean over the truths.
- `greedy`, `exchange` (Fedorov's exchange from several starts) and `exhaustive` (every
  multiset, for tests) choose `firings` options.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

__all__ = [
    "Options",
    "Plan",
    "criterion_value",
    "exchange",
    "exhaustive",
    "greedy",
    "options",
    "plan_value",
]


class Options(NamedTuple):
    """The ways to make one firing: `candidate (O,)` (index of the condition),
    `signals` (O tuples of signal indices), `information (O, R, P, P)` at each of `R`
    truths."""

    candidate: np.ndarray
    signals: list[tuple[int, ...]]
    information: np.ndarray  # (O, R, P, P)


class Plan(NamedTuple):
    """Chosen options `(n,)` (indices into `Options`, sorted) and the criterion's
    value of their summed information."""

    chosen: tuple[int, ...]
    value: float


def options(information: np.ndarray, costs, cap: float | None = None) -> Options:
    """Every (candidate, signal set) a firing may take: `information (C, S, P, P)` per
    candidate and signal (or `(R, C, S, P, P)` at `R` truths), `costs (S,)`, `cap` the
    most one firing's signals may cost (None: no cap). A signal set is kept only if no
    affordable larger set contains it (more signals never lose information)."""
    information = np.asarray(information, dtype=float)
    if information.ndim == 4:
        information = information[None]
    information = np.moveaxis(information, 0, 2)  # (C, S, R, P, P)
    costs = np.asarray(costs, dtype=float)
    C, S = information.shape[:2]
    if not (costs.shape == (S,) and np.all(np.isfinite(costs)) and np.all(costs >= 0)):
        raise ValueError(f"costs {costs!r}: give {S} finite costs >= 0")
    affordable = [
        subset
        for size in range(1, S + 1)
        for subset in itertools.combinations(range(S), size)
        if cap is None or costs[list(subset)].sum() <= cap * (1 + 1e-12)
    ]
    maximal = [a for a in affordable if not any(set(a) < set(b) for b in affordable)]
    candidate, signals, blocks = [], [], []
    for c in range(C):
        for subset in maximal:
            candidate.append(c)
            signals.append(subset)
            blocks.append(information[c, list(subset)].sum(axis=0))
    return Options(np.asarray(candidate, dtype=int), signals, np.asarray(blocks))


def criterion_value(matrix: np.ndarray, name: str | int = "D") -> float:
    """The criterion of an information matrix `(P, P)`, higher better: `"D"` log det,
    `"A"` minus the sum of the variances, an integer `j` minus parameter `j`'s variance;
    −inf where it does not determine what the criterion needs."""
    matrix = 0.5 * (matrix + matrix.T)
    eigenvalues, vectors = np.linalg.eigh(matrix)
    singular = eigenvalues <= 1e-12 * max(float(eigenvalues[-1]), 1e-300)
    if name == "D":
        return -np.inf if singular.any() else float(np.sum(np.log(eigenvalues)))
    if singular.any():
        if name == "A":
            return -np.inf
        # One parameter's variance is finite if it is orthogonal to every null direction.
        if np.any(np.abs(vectors[int(name), singular]) > 1e-9):
            return -np.inf
    inverse = (vectors[:, ~singular] / eigenvalues[~singular]) @ vectors[:, ~singular].T
    return float(-np.trace(inverse)) if name == "A" else float(-inverse[int(name), int(name)])


def plan_value(matrices: np.ndarray, name: str | int = "D") -> float:
    """The criterion of a plan's information `(R, P, P)` at `R` truths: its mean (−inf
    if any truth leaves the criterion undetermined)."""
    return float(np.mean([criterion_value(m, name) for m in matrices]))


def _value(opts: Options, chosen, name) -> float:
    return plan_value(opts.information[list(chosen)].sum(axis=0), name)


def greedy(opts: Options, firings: int, name: str | int = "D", ridge: float = 1e-9) -> Plan:
    """One firing at a time, each the option that most improves the criterion of the
    plan so far (a small ridge, relative to the options' largest information, lets the
    first choices be made while the plan is still singular)."""
    scale = ridge * max(float(np.max(np.trace(opts.information, axis1=-2, axis2=-1))), 1e-300)
    regular = scale * np.eye(opts.information.shape[-1])
    chosen: list[int] = []
    for _ in range(firings):
        base = opts.information[chosen].sum(axis=0) + regular
        scores = [plan_value(base + block, name) for block in opts.information]
        chosen.append(int(np.argmax(scores)))
    return Plan(tuple(sorted(chosen)), _value(opts, chosen, name))


def exchange(
    opts: Options, firings: int, name: str | int = "D", starts: int = 8, seed: int = 0
) -> Plan:
    """Fedorov's exchange: from the greedy plan and `starts − 1` random ones, replace
    one chosen firing by the option that improves the criterion most, until no exchange
    improves it; the best plan found."""
    rng = np.random.default_rng(seed)
    count = len(opts.candidate)
    first = list(greedy(opts, firings, name).chosen)
    plans = [first] + [list(rng.integers(0, count, firings)) for _ in range(starts - 1)]
    best = Plan((), -np.inf)
    for chosen in plans:
        value = _value(opts, chosen, name)
        while True:
            gain, move = 0.0, None
            for i in range(firings):
                rest = chosen[:i] + chosen[i + 1 :]
                base = opts.information[rest].sum(axis=0)
                for o in range(count):
                    trial = plan_value(base + opts.information[o], name)
                    better = trial > value + 1e-12 * max(1.0, abs(value)) or (
                        np.isinf(value) and np.isfinite(trial)
                    )
                    if better and (move is None or trial - value > gain):
                        gain, move = trial - value, (i, o, trial)
            if move is None:
                break
            i, o, value = move
            chosen[i] = o
        if value > best.value or not best.chosen:
            best = Plan(tuple(sorted(int(c) for c in chosen)), float(value))
    return best


def exhaustive(opts: Options, firings: int, name: str | int = "D") -> Plan:
    """Every multiset of `firings` options: the optimum (for tests: C(O + n − 1, n)
    evaluations)."""
    best = Plan((), -np.inf)
    for chosen in itertools.combinations_with_replacement(range(len(opts.candidate)), firings):
        value = _value(opts, chosen, name)
        if value > best.value or not best.chosen:
            best = Plan(tuple(chosen), value)
    return best
