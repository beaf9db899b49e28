"""Continuation over the smoothing widths (`Continuation`): a fit first made at wide
switches, then narrowed stage by stage to the calibration's own widths.

Why: a switch that makes a signal jump samples a step into χ². The counter-recoil
buffer's engagement is the sharp one: the buffer's force `c_b v` comes on within
`buffer_width` (1 µm), so the anchoring force jumps by ~100 kN in less than one sample.
A parameter that moves the engagement across a sample time moves χ² by `(ΔF / σ)²`,
~4·10⁵ for a 200 N noise, and Levenberg–Marquardt stops on that step (measured on the
shipped plan `optimise/plans/envelope_friction.toml`: χ² rises from 1.8·10⁴ at the
truth to 7.4·10⁵ with `c_out` 0.1 % higher). At a width of 1 cm the same jump is a ramp
over ~10 samples, χ² is smooth, and the fit goes to the basin from far starts;
each narrower stage starts where the wider one ended (`docs/calibration.md`).

The rails' friction has no width to continue: its stick and slip are a mode of the
solve, exact at every stage (`docs/model.md`, *Sticking*).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp

from .._model.params import RecoilParams
from .._model.registry import ParameterError
from .._model.settings import Smoothing

__all__ = ["DEFAULT_CONTINUATION", "Continuation", "acting_smoothing"]

_MODEL = Smoothing()  # the model's own widths

#: Each width continued, and the part of a design that has its switch: a width a design
#: does not use is not continued (a stage there would refit the same χ²).
_SWITCH_OF = {
    "buffer_width": "counter_recoil_buffer",
    "stop_width": "battery_stop",
    "damping_width": "barrel",
}


def acting_smoothing(params: RecoilParams, smoothing: Smoothing) -> Smoothing:
    """`smoothing` with each width of `_SWITCH_OF` whose part the design `params` lacks at
    the model's own: it acts on nothing there, and a fit (and its store's identity) is
    then the one it was before a calibration had widths of its own."""
    unused = [n for n, part in _SWITCH_OF.items() if getattr(params, part) is None]
    return eqx.tree_at(lambda s: [getattr(s, n) for n in unused], smoothing,
                       [getattr(_MODEL, n) for n in unused])  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Continuation:
    """The widths a fit starts from, narrowed stage by stage to the calibration's own.

    - `widths`: smoothing width name → its value at each stage before the fit's own,
      widest first, in the width's unit (`Smoothing.LIMITS`); every name the same
      number of stages. The fit runs Levenberg–Marquardt at each stage from the last
      stage's optimum, then at the calibration's widths (where its result, its χ² and its
      uncertainty are).

    Default: `buffer_width` 1 cm, 1 mm, 0.1 mm, 10 µm and the model's 1 µm, a decade a
    stage (the counter-recoil buffer's engagement, the switch whose jump in `F_AN` makes
    χ² stepped); then the calibration's widths. Measured on the shipped plan's reference
    traces (`docs/calibration.md`): two stages a hundredfold apart left 2 of 4 draws on a
    tread that four a decade apart reached the truth from.

    A width it does not name is at the fit's own at every stage.

    `for_design` keeps what acts on one fit: the widths of the parts its design has, the
    stages that differ from the one before and from the fit's own widths. A design
    without a counter-recoil buffer or rails is fitted at its own widths only.

    - `fallback`: another continuation, the path `calibrate` fits its starts through
      again where the best point of this one fails the model check, before it says the
      model does not explain the traces (its best of both paths is the result); None:
      no second path.

    **Raises:** `ParameterError` for a name that is not a continued smoothing width, or
    widths that are not positive, finite and never widening, or of different counts.
    """

    widths: Mapping[str, tuple[float, ...]] = dataclasses.field(
        default_factory=lambda: {
            "buffer_width": (1e-2, 1e-3, 1e-4, 1e-5, float(_MODEL.buffer_width)),
        }
    )
    fallback: Continuation | None = None

    def __post_init__(self):
        if self.fallback is not None and not isinstance(self.fallback, Continuation):
            raise ParameterError(
                f"continuation.fallback = {self.fallback!r}: give a Continuation, or None"
            )
        widths = {}
        for name, values in dict(self.widths).items():
            if name not in _SWITCH_OF:
                raise ParameterError(
                    f"continuation: {name!r} is not a width it can continue: valid "
                    f"{', '.join(_SWITCH_OF)}"
                )
            try:
                stages = tuple(float(v) for v in values)
            except (TypeError, ValueError):
                raise ParameterError(
                    f"continuation.{name} = {values!r}: give its widths as a list of numbers"
                ) from None
            if not stages or not all(math.isfinite(v) and v > 0 for v in stages):
                raise ParameterError(
                    f"continuation.{name} = {list(stages)}: give one width or more, each > 0"
                )
            if any(b > a for a, b in itertools.pairwise(stages)):
                raise ParameterError(
                    f"continuation.{name} = {list(stages)}: the widths must not widen, widest first"
                )
            widths[name] = stages
        counts = {len(v) for v in widths.values()}
        if len(counts) > 1:
            raise ParameterError(
                "continuation: every width needs the same number of stages ("
                + ", ".join(f"{n}: {len(v)}" for n, v in widths.items())
                + ")"
            )
        # Sorted, as a tuple: hashable, and one order for a store's identity.
        object.__setattr__(self, "widths", dict(sorted(widths.items())))

    def __hash__(self):
        return hash((tuple(self.widths.items()), self.fallback))

    def for_design(self, params: RecoilParams, smoothing: Smoothing) -> Continuation | None:
        """The stages that act on a fit of the design `params` at the widths `smoothing`:
        the widths of the parts it has (whose switches it has), each stage kept where it
        differs from the one before and from `smoothing`'s own, each width where it
        differs from its own at some stage; None where none is left."""
        used = {n: v for n, v in self.widths.items() if getattr(params, _SWITCH_OF[n]) is not None}
        final = tuple(float(getattr(smoothing, n)) for n in used)
        stages, last = [], None
        for stage in zip(*used.values(), strict=True):
            if stage not in (last, final):
                stages.append(stage)
            last = stage
        kept = {
            name: values
            for name, values, own in zip(used, zip(*stages, strict=True), final, strict=False)
            if any(v != own for v in values)  # a width at the fit's own at every stage
        }
        if not kept:
            return None
        fallback = None if self.fallback is None else self.fallback.for_design(params, smoothing)
        if fallback is not None and fallback.widths == kept:  # the same path again
            fallback = None
        return Continuation(kept, fallback)

    @property
    def stages(self) -> int:
        """How many stages come before the calibration's own widths."""
        return len(next(iter(self.widths.values()), ()))

    def smoothing(self, smoothing: Smoothing, stage: int) -> Smoothing:
        """`smoothing` with the widths of stage `stage` (0: the widest): leaves of the
        same dtype and shape, so that every stage runs the same compiled program."""
        for name, values in self.widths.items():
            value = jnp.asarray(values[stage], dtype=jnp.asarray(getattr(smoothing, name)).dtype)
            smoothing = eqx.tree_at(lambda s, n=name: getattr(s, n), smoothing, value)
        return smoothing

    def describe(self, stage: int) -> str:
        """Stage `stage`'s widths, for a progress line: `buffer_width 0.01, ...`."""
        return ", ".join(f"{n} {v[stage]:g}" for n, v in self.widths.items())

    def to_json(self) -> dict[str, list[float]]:
        """The widths of each stage by name (not the fallback's)."""
        return {n: list(v) for n, v in self.widths.items()}

    def identity(self) -> tuple[dict[str, list[float]], ...]:
        """What a calibration's store is identified by: the widths, then the fallback's
        (none without one, so a store made before fallbacks keeps its identity)."""
        return (self.to_json(), *(() if self.fallback is None else self.fallback.identity()))


#: The continuation `calibrate` and `fit_many` run unless told otherwise: the buffer's
#: stages (`Continuation()`), without a fallback.
DEFAULT_CONTINUATION = Continuation()
