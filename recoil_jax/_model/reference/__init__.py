"""An independent reference solver: scipy `solve_ivp`, hard switches, event-located.

Shares no model code with the JAX model: the equations are written out again here in
NumPy. Each switch (contact onset `δ = 0`, damping sign `v_M = 0`, the no-pull clamp
`1 + λ_c δ̇ = 0`, the barrel crossing an orifice knot) ends an integration segment at an
exactly located event, and each round's firing and each point of a force table ends one
too, so every segment is smooth and the integrator keeps its full order. Peaks are located
as events of their time derivatives (and checked at every segment end), not read off a
grid. A barrel that reaches 0.95 of the recuperator's gas column is reported
(`status`), like the JAX model does.

The firing envelope (`docs/model.md`) is in it with hard switches too: gravity
along the rails, the recuperator preload, the battery stop (Hunt–Crossley, its onset and
its no-pull clamp events), the counter-recoil buffer (events at `x_M = L_b` and
`v_M = 0`) and **exact stick–slip** Coulomb friction. Sliding, the friction is
`F_max·sign(v_M)`; at `v_M = 0` the barrel sticks if the net force on it from everything
but friction, `N`, is within `±F_max`: a stick mode holds `x_M` and `v_M = 0` while the
friction takes `N`, and ends at the event `|N| = F_max`, where the barrel slips the way
`N` pushes. Its metrics (`return_time`, `battery_speed`, `residual_displacement`,
`stability_margin`) come from the event-located solution. A design whose envelope
parameters have no effect (zero elevation, friction, stop, buffer and preload) runs the
paper's code path, operation for operation.

Revision 2 of the envelope (`docs/model.md`): the gun fires from its **static rest**
`x_r <= 0`, the root of `F_AN(x, v = 0) = (M + m) g sin θ` (friction aside) in the
battery stop where a preload above the axial weight presses the barrel into it
(`reference_rest`; else `x_r = 0`); displacements and the return are measured from it;
the **stability margin** takes the recoiling parts' axial weight out of the overturning
force, `K = F_AN − (M + m) g sin θ`, and the stabilising moment counts their travel from
the start; and two metrics join,
`peak_pull_force` (the largest `−F_AN`, located at the rising zeros of `dF_AN/dt`) and
`peak_mount_load` (the largest `|F_AN|`).

Used by the tests as ground truth across the documented ranges, and as the serial
baseline of the benchmarks.

The folder: `physics` (the model with hard switches, mode by mode), `switching` (its
events and modes), `segments` (the segment loop); here, what the tests and benchmarks
call.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..._model.params import params_from_values, params_to_values
from ..._model.reference.physics import GRAVITY
from ..._model.reference.segments import initial_state, integrate
from ..._model.reference.switching import HardModel
from ..._model.registry import ParameterError

__all__ = ["reference_energy", "reference_history", "reference_peaks", "reference_rest"]


def reference_peaks(
    values: Mapping[str, float] | None = None,
    t1: float | None = None,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
    force_table=None,
) -> dict:
    """Peaks of the hard-switch model, by an independent scipy solver.

    **Arguments:**

    - `values`: flat parameter values (names as `params_from_values`; defaults fill in).
    - `t1`: end time (s); default 10 s after the last round.
    - `rtol`, `atol`, `method`: `scipy.integrate.solve_ivp` settings per segment.
    - `max_segments`: the most integration segments (one per switch event or stop).
    - `force_table`: `(t, F)` of one round (s, N), replacing the impulse or pulse.

    **Returns:** the metrics by name with the times of the timed ones
    (`peak_anchoring_force`, `peak_anchoring_force_time`, ..., `min_stroke`,
    `max_stroke`), `segments`, and `status`: `"ok"`, or `"bottomed_out"` when x_M
    reaches 0.95 of the recuperator's gas column (the peaks are then those up to there).
    Also the firing envelope's metrics (`docs/model.md`, revision 2): `rest_position` (m,
    the static rest `x_r <= 0` the solve starts from, as `reference_rest`);
    `peak_displacement` is `max (x_M − x_r)`; `return_time` (s, from the last round's
    firing to the barrel's first forward crossing of `x_M = x_r + 1 mm` after it; None
    if it never comes back), `battery_speed` (m/s, `−v_M` at that crossing; None
    likewise), `returned` (bool), `residual_displacement` (m, `x_M − x_r` at the end),
    `peak_pull_force` (N, `max(0, −min F_AN)`) and `peak_pull_force_time` (s, where
    `F_AN` is least), `peak_mount_load` (N, `max |F_AN|`) and `peak_mount_load_time`,
    `stability_margin` (the least `(S − K d) / (m_g g L_w)`, `K = F_AN − (M + m) g sin θ`)
    and `stability_margin_time` (None without a mount), `end_time` (s, `t1` unless the
    solve stopped early) and `sticks`, `slips` (the times, s, at which friction held the
    barrel and let it go).

    **Raises:** `RuntimeError` if more than `max_segments` segments are needed (contact
    chatter when the system comes to rest on the contact boundary, at gap 0 after
    ~1.5 s: use a shorter `t1` for such designs), or if scipy fails.
    """
    model = _model_of(values, force_table)
    if t1 is None:
        t1 = 10.0 + (model.shots - 1) * model.interval
    done = integrate(model, t1, rtol, atol, method, max_segments)
    return (
        done.running.metrics(model.x_r)
        | {"segments": done.segments, "status": done.status}
        | done.envelope.metrics(done.t, done.y)
    )


def reference_energy(
    values: Mapping[str, float] | None = None,
    t1: float | None = None,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
    force_table=None,
) -> dict[str, float]:
    """The energy balance of the hard-switch model over `[0, t1]` (J), the work and the
    dissipation integrated as two more states of the same event-located solve:
    `breech_work` (the breech force's, impulses as their kinetic energy), `gravity_work`,
    `dissipated` (dampers, orifice, counter-recoil buffer, friction, and the contacts'
    Hunt–Crossley parts), `stored_change` (kinetic energy, springs, gas column and
    contacts' potentials: at the end less at rest in battery before the first round);
    they balance,
    `breech_work + gravity_work = dissipated + stored_change`. Arguments as
    `reference_peaks`."""
    model = _model_of(values, force_table)
    if t1 is None:
        t1 = 10.0 + (model.shots - 1) * model.interval
    done = integrate(model, t1, rtol, atol, method, max_segments, audit=True)
    y0 = initial_state(model)
    y0[1] = 0.0  # at rest in battery, before the first round's impulse (its work)
    y = done.y
    gravity = model.M * (y[0] - y0[0])
    if model.absorber:
        gravity += model.mass_m * (y[2] - y0[2])
    return {
        "breech_work": float(y[4]),
        "gravity_work": float(GRAVITY * model.sin * gravity),
        "dissipated": float(y[5]),
        "stored_change": float(model.stored_energy(y) - model.stored_energy(y0)),
        "end_time": float(done.t),
    }


def reference_rest(values: Mapping[str, float] | None = None) -> float:
    """The static rest `x_r` (m, `<= 0`) of the hard-switch model for flat parameter
    values (as `reference_peaks`): the root of `F_AN(x, v = 0) = (M + m) g sin θ` with
    friction left out, `k x + F_g + F_p − k_s (−x)^n_s`, with a battery stop
    (`stop_stiffness > 0`) and a preload above the axial weight; else 0."""
    return _model_of(values, None).x_r


def _model_of(values, force_table) -> HardModel:
    design = params_from_values(values or {})
    if design.added:  # (its laws are the package's built-in forces, written out)
        raise ParameterError(
            "the hard-switch reference has only the built-in forces: "
            f"{', '.join(p.GROUP.name for p in design.added)} is not one of them"
        )
    flat = params_to_values(design)
    return HardModel({name: float(np.asarray(v)) for name, v in flat.items()}, force_table)


def reference_history(
    values: Mapping[str, float] | None = None,
    ts=None,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
    force_table=None,
) -> dict[str, np.ndarray]:
    """Time histories of the hard-switch model by the independent scipy solver (as
    `reference_peaks`), at the sorted times `ts` (s, shape `(n,)`, from 0): the state
    `x_M, v_M, x_m, v_m` and the forces `F_AN`, `F_ct`, by name, shape `(n,)` each; from
    each segment's dense output. At a round's firing the value is the one after it (its
    impulse applied), as at `t = 0` and as `rj.simulate` gives it."""
    model = _model_of(values, force_table)
    ts = np.asarray(ts, dtype=float)
    samples = {
        name: np.full(ts.shape, np.nan) for name in ("x_M", "v_M", "x_m", "v_m", "F_AN", "F_ct")
    }
    integrate(model, float(ts[-1]), rtol, atol, method, max_segments, ts, samples)
    return samples
