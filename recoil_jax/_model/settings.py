"""The settings of a solve: the smoothing widths of the model's switches (`Smoothing`),
the solver's options (`SolverOptions`, with `T1_LIMITS` and `MAX_STEPS`), a design's end
time and default tolerances, and the check that a design's load fits in its solve
(`check_load_fits`).

Every value is a pytree leaf; configuration that changes the compiled program
(`max_steps`, `autodiff`) is static. Values are validated when they are concrete, as the
parameters are (`registry`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._model.forces.family import Design
from .._model.registry import (
    Limits,
    ParameterError,
    Validated,
    float_leaf,
    is_concrete,
)

__all__ = [
    "MAX_STEPS",
    "PULSE_LENGTHS",
    "T1_LIMITS",
    "Smoothing",
    "SolverOptions",
    "check_load_fits",
    "default_end_time",
    "end_time",
    "with_default_tolerances",
]


class Smoothing(Validated):
    """Widths, in physical units, over which the model's switches are smoothed.

    Each switch `max(0, x)` is replaced by a C² ramp that equals it exactly for
    `|x| >= width` (see `smooth_relu`), so the smoothed model differs from the exact one
    only inside the band.

    - `damping_width` (m/s): the damping switch at `v_M = 0` and the contact's no-pull
      clamp at `1 + λ_c δ̇ = 0` (in relative velocity).
    - `contact_width` (m): the contact onset at `δ = 0`. `None` (default) picks
      `contact_width_fraction` × the characteristic penetration of a head-on impact,
      `δ* = ((n_c+1) μ v0² / (2 k_c))^(1/(n_c+1))` with `μ = M m / (M + m)`,
      so the relative smoothing error is the same over the whole range of `k_c`, `n_c`, `m`, `v0`.
    - `knot_width_fraction`: the kinks of the orifice profile at its knots, over this
      fraction of the knot spacing.
    - `stop_width` (m): the battery stop's onset at `x_M = 0`.
    - `buffer_width` (m): the counter-recoil buffer's engagement at `x_M = buffer_length`.

    The rails' friction has no width: its stick and slip are a mode of the solve,
    switched exactly at events (`docs/model.md`, *Sticking*).

    A width of 0 makes its switch exact. `Smoothing.exact()` sets every width to 0: the
    hard-switch model (not differentiable at the switches; for reference and checks). It
    runs through the same code path and, its widths being values, the same compiled
    program as the smoothed model.

    See `docs/model.md`, *Smoothing*.
    """

    damping_width: Any = float_leaf(1e-4)
    contact_width: Any = float_leaf(None)
    contact_width_fraction: Any = float_leaf(0.005)
    knot_width_fraction: Any = float_leaf(1e-4)
    stop_width: Any = float_leaf(1e-7)
    buffer_width: Any = float_leaf(1e-6)

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        "damping_width": Limits(
            unit="m/s",
            lower=0.0,
            documented=(1e-4, 1e-1),
            meaning="damping and clamp smoothing width; 0 is the exact switch",
        ),
        "contact_width": Limits(
            unit="m",
            lower=0.0,
            documented=(1e-6, 1e-3),
            meaning="contact onset smoothing width; 0 is the exact switch",
        ),
        "knot_width_fraction": Limits(
            unit="",
            lower=0.0,
            upper=0.5,
            meaning="orifice knot smoothing width / knot spacing",
        ),
        "contact_width_fraction": Limits(
            unit="",
            lower=0.0,
            upper=1.0,
            meaning="contact width / characteristic penetration",
        ),
        "stop_width": Limits(
            unit="m",
            lower=0.0,
            documented=(0.0, 1e-4),
            meaning="battery stop onset smoothing width; 0 is the exact switch",
        ),
        "buffer_width": Limits(
            unit="m",
            lower=0.0,
            documented=(0.0, 5e-3),
            meaning="counter-recoil buffer engagement smoothing width; 0 is the exact switch",
        ),
    }

    @classmethod
    def exact(cls) -> Smoothing:
        """The hard-switch model: every width 0."""
        return cls(
            damping_width=0.0,
            contact_width_fraction=0.0,
            knot_width_fraction=0.0,
            stop_width=0.0,
            buffer_width=0.0,
        )

    @property
    def hard(self) -> bool:
        """Whether every switch is exact (every width 0); for concrete widths."""
        contact = self.contact_width_fraction if self.contact_width is None else self.contact_width
        widths = (self.damping_width, contact, self.knot_width_fraction)
        return all(bool(np.all(np.asarray(w) == 0)) for w in widths)


#: Limits of the end time, the one solver setting that may differ between the points
#: of a sweep (`t1` on the command line and in `sweep --points`).
T1_LIMITS = Limits(unit="s", lower=0.0, lower_open=True, documented=(0.1, 60.0), meaning="end time")


#: The most solver steps a solve may be given (`SolverOptions.max_steps`): a step count
#: is a 32-bit integer on some devices.
MAX_STEPS = 2**31 - 1


class SolverOptions(Validated):
    """Time span and adaptive-step settings (Tsit5 with a PID controller).

    - `t1` (s): end of the simulation; `None` (default) is the model's end time,
      `default_end_time` (10 s).
    - `rtol`, `atol`: tolerances of the step-size controller; `None` (default) is
      1e-6 and 1e-9 for the paper's model, and 1e-7 and 1e-10 for designs with a load,
      buffer or recuperator, whose peaks then agree with the hard-switch reference to
      1e-4 (`with_default_tolerances`). atol is in SI units of the
      state: m and m/s).
    - `max_steps` (static): bound on solver steps (accepted + rejected); reaching it is
      reported as a failure, never a truncated result.
    - `autodiff` (static): `"forward"` (default) runs the stepping loop as a
      `lax.while_loop`: fastest, supports `jax.jvp`/`jax.jacfwd`. `"reverse"` runs it as a
      checkpointed loop that supports `jax.grad`/`jax.vjp` (not forward mode).
    """

    t1: Any = float_leaf(None)
    rtol: Any = float_leaf(None)
    atol: Any = float_leaf(None)
    max_steps: int = eqx.field(default=65536, static=True)
    autodiff: str = eqx.field(default="forward", static=True)

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        "t1": T1_LIMITS,
        "rtol": Limits(
            unit="", lower=0.0, lower_open=True, upper=1.0, meaning="relative tolerance"
        ),
        "atol": Limits(unit="", lower=0.0, lower_open=True, meaning="absolute tolerance"),
    }

    def __check_init__(self):
        super().__check_init__()
        if not isinstance(self.max_steps, int) or not 1 <= self.max_steps <= MAX_STEPS:
            raise ParameterError(
                f"SolverOptions.max_steps = {self.max_steps!r} is invalid: valid max_steps is "
                f"an integer from 1 to {MAX_STEPS:,}"
            )
        if self.autodiff not in ("forward", "reverse"):
            raise ParameterError(
                f"SolverOptions.autodiff = {self.autodiff!r} is invalid: valid autodiff is "
                "'forward' or 'reverse'"
            )


def default_end_time(params: Design) -> Any:
    """The model's end time when `SolverOptions.t1` is not given: 10 s after the last
    round, `10 + (shots - 1) · fire_interval` (10 s, the paper's, for one round)."""
    ten = jnp.full(jnp.shape(params.barrel.v0), 10.0)
    load = params.load
    if load is None or load.shots == 1:
        return ten
    return ten + (load.shots - 1) * jnp.asarray(load.fire_interval, dtype=float)


def with_default_tolerances(params: Design, options: SolverOptions) -> SolverOptions:
    """`options` with the tolerances it leaves to the design filled in: rtol 1e-6 and
    atol 1e-9 for the paper's model; 1e-7 and 1e-10 with a load, buffer or recuperator
    (pulses of hundreds of kN and the orifice's `v²/A²` need a tighter tolerance for the
    peaks to hold 1e-4)."""
    if options.rtol is not None and options.atol is not None:
        return options
    hardware = any(part.GROUP.part == "hardware" for part in params.parts().values())
    rtol, atol = (1e-7, 1e-10) if hardware else (1e-6, 1e-9)
    return dataclasses.replace(
        options,
        rtol=rtol if options.rtol is None else options.rtol,
        atol=atol if options.atol is None else options.atol,
    )


def end_time(params: Design, options: SolverOptions) -> Any:
    """The end time of a solve (s): `options.t1`, or the model's default.

    **Raises:** `ParameterError`, for concrete inputs, when the load does not fit
    (`check_load_fits`): the solve would be cut short or could not finish."""
    t1 = default_end_time(params) if options.t1 is None else options.t1
    t1 = jnp.asarray(t1, dtype=float)
    if is_concrete((params, t1)):
        check_load_fits(params, t1, options.max_steps)
    return t1


#: A gamma pulse has delivered all but 11 e^-10 (0.05 %) of its momentum after this many
#: `pulse_time`s: the pulse's length, for `check_load_fits`.
PULSE_LENGTHS = 10.0


def check_load_fits(params: Design, t1: Any, max_steps: int, labels: Any = None) -> None:
    """Refuse, before anything is compiled, a load that a solve to `t1` (s, scalar or per
    design) could not deliver or finish: a round fired after `t1`, a pulse (its
    `PULSE_LENGTHS` pulse times) or a force table that `t1` cuts short, or more load
    breakpoints (the later rounds' firings and every table point of every round, each
    of which ends a solver step) than `max_steps` steps. `labels`: each design's index
    for messages (default: its place in the batch)."""
    load = params.load
    if load is None:
        return
    t1 = np.asarray(t1, dtype=float)
    last = (load.shots - 1) * np.asarray(load.fire_interval, dtype=float)
    if load.table is not None:  # each design's own table (`ForceTable.stacked`) may end apart
        length, what = np.asarray(load.table.t, dtype=float)[..., -1], "the force table"
    else:
        length, what = PULSE_LENGTHS * np.asarray(load.pulse_time, dtype=float), "the pulse"
    last, length, t1 = np.broadcast_arrays(last, length, t1)
    ends = (last + length).reshape(-1)
    last, t1 = last.reshape(-1), t1.reshape(-1)
    short = ends > t1
    if np.any(short):
        i = int(np.argmax(short))
        label = i if labels is None else int(labels[i])
        if last[i] >= t1[i]:
            cause = f"the last of {load.shots} rounds fires at {last[i]:g} s"
        else:
            cause = f"{what} of the last round lasts until {ends[i]:g} s"
        raise ParameterError(
            f"the load does not fit in the solve{f' (design {label})' if ends.size > 1 else ''}: "
            f"{cause}, after t1 = {t1[i]:g} s, so the recoil would be cut short; give "
            f"t1 >= {ends[i]:g} s (or a shorter load)"
        )
    rows = 0 if load.table is None else int(np.shape(load.table.t)[-1])
    breakpoints = (load.shots - 1) + load.shots * rows
    if breakpoints >= max_steps:
        raise ParameterError(
            f"the load has {breakpoints:,} breakpoints ({load.shots} round{'s' * (load.shots > 1)}"
            + (f" x {rows:,} force-table points" if rows else "")
            + f"), each of which ends a solver step, but max_steps is {max_steps:,}: give "
            f"max_steps > {breakpoints:,} (command line: --max-steps), or fewer points"
        )
