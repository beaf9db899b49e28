"""The breech force (`docs/model.md`, *Load*): its parameters (`Load`, a `ForceTable`),
a round's impulse, pulse or force table, the rounds of a burst, where a step must end for
them, the velocity jumps of impulse rounds, and the momentum still to come."""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..._model.forces.family import Design, Part, group_limits, registered
from ..._model.registry import (
    GROUPS,
    Group,
    Limits,
    ParameterError,
    as_float_array,
    check_value,
    is_concrete,
)
from ..._model.text_files import read_text

__all__ = [
    "ForceTable",
    "Load",
    "breech_force",
    "is_impulse",
    "load_jump",
    "load_stops",
    "remaining_impulse",
    "restart_step",
]


#: The spacing (s) of the zero-force points that pad a shorter table (`ForceTable.stacked`).
_PAD_SPACING = 1e-9


class ForceTable(eqx.Module):
    """A tabulated breech force of one round: `F` (N) at times `t` (s, from the round's
    firing), linear between points and zero outside them; shape `(n,)` each, `n >= 2`
    (or `(B, n)`: each design of a batch its own, `ForceTable.stacked`), `t` strictly
    increasing from `t[0] >= 0`. The table's integral is the round's
    momentum (`Barrel.v0` is not used). `ForceTable.from_csv` reads a CSV file with the
    header `t_s,F_N`."""

    t: Any = eqx.field(converter=as_float_array)
    F: Any = eqx.field(converter=as_float_array)

    def __check_init__(self):
        if not is_concrete((self.t, self.F)):
            return
        check_value("ForceTable", "t", self.t, Limits(unit="s", lower=0.0))
        check_value("ForceTable", "F", self.F, Limits(unit="N", lower=-math.inf))
        t, F = np.asarray(self.t), np.asarray(self.F)
        if t.ndim < 1 or F.shape != t.shape or t.shape[-1] < 2:
            raise ParameterError(
                f"ForceTable: t and F must be of the same length >= 2, got shapes "
                f"{t.shape} and {F.shape}"
            )
        rows = t.reshape(-1, t.shape[-1])  # a batch: each design's table
        bad = np.diff(rows, axis=-1) <= 0
        if np.any(bad):
            row, i = np.unravel_index(int(np.argmax(bad)), bad.shape)
            times, i = rows[row], int(i) + 1
            where = f" (table {row})" if len(rows) > 1 else ""
            raise ParameterError(
                f"ForceTable.t[{i}] = {times[i]:g} s is invalid{where}: times must increase "
                f"strictly (t[{i - 1}] = {times[i - 1]:g} s)"
            )

    @classmethod
    def stacked(cls, tables: Sequence[ForceTable]) -> ForceTable:
        """One batched table `(B, n)` of `tables` (one round each), for designs that
        each fire their own: the shorter padded to the longest with points of zero force
        1 ns apart after their end. That is exact for a table that ends at zero force
        (outside its points a table's force is zero); one that ends at F_last gains a
        1 ns ramp to zero, an impulse of F_last · 0.5 ns."""
        length = max(int(np.shape(t.t)[-1]) for t in tables)
        times, forces = [], []
        for table in tables:
            t, F = np.asarray(table.t, dtype=float), np.asarray(table.F, dtype=float)
            if t.ndim != 1:
                raise ParameterError("ForceTable.stacked: each table must be of one round, (n,)")
            extra = length - len(t)
            times.append(np.concatenate([t, t[-1] + _PAD_SPACING * np.arange(1, extra + 1)]))
            forces.append(np.concatenate([F, np.zeros(extra)]))
        return cls(np.stack(times), np.stack(forces))

    @classmethod
    def from_csv(cls, path) -> ForceTable:
        """Read a table from a CSV file whose header is `t_s,F_N` (seconds, newtons)."""
        path = Path(path)
        rows = list(csv.DictReader(read_text(path, "force table").splitlines()))
        if not rows:
            raise ParameterError(f"{path}: no rows of t_s,F_N values (a header alone, or empty)")
        if set(rows[0]) != {"t_s", "F_N"}:
            raise ParameterError(f"{path}: expected a CSV with the header t_s,F_N")
        try:
            t = [float(r["t_s"]) for r in rows]
            F = [float(r["F_N"]) for r in rows]
        except (TypeError, ValueError):
            raise ParameterError(f"{path}: every t_s and F_N must be a number") from None
        return cls(t=t, F=F)


class Load(Part):
    """The breech force and the firing rhythm (`docs/model.md`, *Load*).

    - `pulse_time` (s): 0 is the paper's impulse (the barrel starts at `v0`); `t_p > 0` is
      a gamma pulse of the same momentum, `F_b = (M v0 / t_p) (t/t_p) exp(-t/t_p)`, with the
      barrel starting at rest.
    - `shots` (static): rounds fired, at `t_j = j · fire_interval`; each adds a velocity
      jump of `v0` (impulse), or its own pulse or table.
    - `fire_interval` (s): time between rounds.
    - `table`: a `ForceTable` of one round, which replaces the pulse or impulse.
    """

    pulse_time: Any = registered("pulse_time")
    shots: int = eqx.field(default=1, static=True)
    fire_interval: Any = registered("fire_interval")
    table: ForceTable | None = None

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        n: p for n, p in group_limits("load").items() if n != "shots"
    }
    GROUP: ClassVar[Group] = GROUPS["load"]

    def __check_init__(self):
        super().__check_init__()
        if isinstance(self.shots, bool) or not isinstance(self.shots, int) or self.shots < 1:
            raise ParameterError(
                f"Load.shots = {self.shots!r} is invalid: valid shots is an integer >= 1 "
                "(rounds fired)"
            )


def breech_force(t, params: Design):
    """The breech force `F_b(t)` (N) of the design's rounds, fired at `j · fire_interval`:
    a gamma pulse of momentum `M v0` each (`pulse_time > 0`), or the force table; zero
    for impulse loads (their momentum enters as velocity jumps) and before each round."""
    load = params.load
    assert load is not None
    delay = t - jnp.arange(load.shots) * load.fire_interval
    if load.table is not None:
        table = load.table
        return jnp.sum(jnp.interp(delay, table.t, table.F, left=0.0, right=0.0))
    tp = load.pulse_time
    pulse = tp > 0
    safe_tp = jnp.where(pulse, tp, 1.0)
    started = delay >= 0
    u = jnp.where(started, delay, 0.0) / safe_tp
    momentum = params.barrel.M * params.barrel.v0
    each = jnp.where(started, momentum / safe_tp * u * jnp.exp(-u), 0.0)
    return jnp.where(pulse, jnp.sum(each), 0.0)


def is_impulse(load: Load):
    """Whether each round is an impulse (a velocity jump of `v0`): no table and
    `pulse_time == 0`."""
    return jnp.logical_and(load.table is None, load.pulse_time <= 0)


def load_stops(params: Design):
    """The times (s) at which a step must end, shape `(n,)`, or None (no load): the
    firing of every later round, and with a force table each of its points for every
    round, so that no short pulse or kink is stepped over."""
    load = params.load
    if load is None:
        return None
    firing = jnp.arange(load.shots) * jnp.asarray(load.fire_interval, dtype=float)
    if load.table is None:
        return firing[1:] if load.shots > 1 else None
    knots = (firing[:, None] + jnp.asarray(load.table.t)[None, :]).reshape(-1)
    return jnp.concatenate([firing[1:], knots])


def load_jump(t, y, params: Design):
    """The state right after a stop at time `t`: at a later round's firing under an
    impulse load the barrel's velocity jumps by `v0`; otherwise unchanged."""
    load = params.load
    if load is None or load.shots == 1:
        return y
    firing = jnp.arange(1, load.shots) * jnp.asarray(load.fire_interval, dtype=float)
    fired = jnp.any(firing == t) & is_impulse(load)
    return y.at[1].add(jnp.where(fired, params.barrel.v0, 0.0))


def restart_step(params: Design):
    """The longest first step at the start and after a stop (s): a fraction of the
    pulse's rise time, so that the step-size controller cannot step over a pulse; no
    limit (inf) for impulse and table loads (a table's points are stops)."""
    load = params.load
    if load is None or load.table is not None:
        return jnp.inf
    return jnp.where(load.pulse_time > 0, 0.25 * load.pulse_time, jnp.inf)


def remaining_impulse(t, params: Design):
    """An upper bound on the breech's momentum still to come after time `t` (N·s):
    `∫_t^∞ |F_b|` plus the impulses of later rounds (0 without a load)."""
    load = params.load
    if load is None:
        return 0.0
    firing = jnp.arange(load.shots) * jnp.asarray(load.fire_interval, dtype=float)
    delay = t - firing
    momentum = params.barrel.M * params.barrel.v0
    table = load.table
    if table is not None:
        times, force = jnp.asarray(table.t), jnp.abs(jnp.asarray(table.F))
        # |F| is convex on each linear piece: the trapezoid of |F| bounds its integral.
        pieces = 0.5 * (force[1:] + force[:-1]) * jnp.diff(times)
        after = jnp.concatenate([jnp.cumsum(pieces[::-1])[::-1], jnp.zeros(1)])

        def rest(d):
            i = jnp.clip(jnp.searchsorted(times, d, side="right") - 1, 0, times.shape[0] - 2)
            here = jnp.abs(jnp.interp(d, times, jnp.asarray(table.F)))
            partial = 0.5 * (here + force[i + 1]) * (times[i + 1] - d) + after[i + 1]
            return jnp.where(d <= times[0], after[0], jnp.where(d >= times[-1], 0.0, partial))

        return jnp.sum(jnp.vectorize(rest)(delay))
    tp = load.pulse_time
    pulse = tp > 0
    u = jnp.maximum(delay, 0.0) / jnp.where(pulse, tp, 1.0)
    pulses = jnp.sum(momentum * (1.0 + u) * jnp.exp(-u))
    impulses = momentum * jnp.sum(firing > t)
    return jnp.where(pulse, pulses, impulses)
