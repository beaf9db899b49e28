"""The parameter pytrees and the flat-name conversions.

The pytrees (`Barrel`, `Absorber`, `Contact`, `Load` with its `ForceTable`, `Buffer`,
`Recuperator`, the firing envelope's `Rails`, `BatteryStop`, `CounterRecoilBuffer` and
`Mount`, and `RecoilParams`, which holds one of each), their validation, the
flat-name conversions (`params_from_values`, `params_to_values`, `with_values`,
`values_of`) and every error message derive from the registry (`PARAMETERS`,
`parameter_table`).

Every physical parameter is a pytree leaf (so `jax.grad`, `jax.jacfwd` and `jax.vmap`
apply to it); configuration that changes the compiled program (`Load.shots`) is static.
Values are validated in `__check_init__` whenever they are concrete (Python numbers,
NumPy or JAX arrays), i.e. before anything is compiled. Tracers (values inside
`jit`/`grad`/`vmap`) are not checked: they were checked when the concrete inputs were
built.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.parameter_table import PAPER_BARREL_MASS, PARAMETERS, parameter
from .._model.registry import (
    ENVELOPE_GROUPS,
    GROUP_CLASSES,
    MAX_KNOTS,
    MIN_KNOTS,
    Limits,
    Parameter,
    ParameterError,
    Validated,
    as_float_array,
    check_value,
    element_label,
    float_leaf,
    is_concrete,
)
from .._model.text_files import read_text

__all__ = [
    "Absorber",
    "Barrel",
    "BatteryStop",
    "Buffer",
    "Contact",
    "CounterRecoilBuffer",
    "ForceTable",
    "Load",
    "Mount",
    "Rails",
    "RecoilParams",
    "Recuperator",
    "check_design",
    "check_present",
    "params_from_values",
    "params_to_values",
    "values_of",
    "with_values",
]


def _registered(name: str) -> Any:
    """A pytree leaf for the registered parameter `name`, with its default."""
    return float_leaf(PARAMETERS[name].default)


def _group_limits(group: str) -> dict[str, Limits]:
    """The registry entries of `group` by name: the `LIMITS` of its pytree."""
    return {name: p for name, p in PARAMETERS.items() if p.group == group}


class Barrel(Validated):
    """The recoiling barrel, its recoil spring and its direction-dependent damper.

    Defaults are the paper's values. Units: kg, N/m, N·s/m, m/s.

    - `M`: recoiling mass.
    - `k`: recoil spring stiffness (barrel to mounting wall P).
    - `c_out`: recoil damping while the barrel moves rearwards (`v_M > 0`).
    - `c_ret`: damping on the return stroke (`v_M < 0`).
    - `v0`: barrel velocity right after the shot; see `Barrel.from_shot`.
    """

    M: Any = _registered("M")
    k: Any = _registered("k")
    c_out: Any = _registered("c_out")
    c_ret: Any = _registered("c_ret")
    v0: Any = _registered("v0")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("barrel")

    @classmethod
    def from_shot(
        cls, projectile_mass: Any, muzzle_velocity: Any, M: Any = PAPER_BARREL_MASS, **kwargs
    ) -> Barrel:
        """Barrel whose initial velocity comes from momentum conservation at the shot:
        `v0 = projectile_mass * muzzle_velocity / M` (kg, m/s, kg)."""
        check_value(
            "Barrel.from_shot",
            "projectile_mass",
            projectile_mass,
            Limits(unit="kg", lower=0.0, lower_open=True),
        )
        check_value(
            "Barrel.from_shot",
            "muzzle_velocity",
            muzzle_velocity,
            Limits(unit="m/s", lower=0.0, lower_open=True),
        )
        check_value("Barrel", "M", M, cls.LIMITS["M"])
        return cls(M=M, v0=projectile_mass * muzzle_velocity / M, **kwargs)


class Absorber(Validated):
    """The on-board absorber mass, its coupling to the barrel and its clearance.

    Units: kg, m, N/m, N·s/m. Defaults: the paper's best design (m = 1500 kg, gap = 62 mm)
    with the paper's coupling (k_r = 13000 N/m, c_r = 3675 N·s/m).

    - `m`: absorber mass.
    - `gap`: clearance between the absorber and wall A (fixed to the barrel behind it).
    - `k_r`, `c_r`: spring and damper between absorber and barrel.
    """

    m: Any = _registered("m")
    gap: Any = _registered("gap")
    k_r: Any = _registered("k_r")
    c_r: Any = _registered("c_r")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("absorber")

    def __check_init__(self):  # before Validated's range check: m = 0 is a model, not a mass
        zero = _first_zero(self.m)
        if zero is not None:
            batch = "; a batch that mixes m = 0 and m > 0 is a sweep (rj.sweep)" if zero else ""
            raise ParameterError(
                f"Absorber.m{zero} = 0 kg: an absorber has a mass (m > 0); a design without "
                "absorber is absorber=None (RecoilParams(absorber=None)), or m=0 in the "
                f"flat-name forms (params_from_values, the command line){batch}"
            )


def _all_zero(value: Any) -> bool:
    """A concrete number or array that is zero everywhere (False if not a number)."""
    try:
        return bool(np.all(np.asarray(value, dtype=np.float64) == 0))
    except (TypeError, ValueError):
        return False


def _first_zero(value: Any) -> str | None:
    """Where a concrete `value` first is zero: `""` for a scalar, `"[i]"` in an array;
    None if nowhere, or for a tracer, `None` or a value that is not a number (the range
    check reports the latter)."""
    if value is None or not is_concrete(value):
        return None
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    zero = array.reshape(-1) == 0
    return element_label(array, int(np.argmax(zero))) if zero.any() else None


class Contact(Validated):
    """Hunt–Crossley contact between wall A and the absorber.

    `F_ct = max(0, k_c δ^n_c (1 + λ_c δ̇))` for penetration `δ > 0`.

    - `k_c`: contact stiffness, N/m^n_c.
    - `n_c`: contact exponent (1: linear, 1.5: Hertz), dimensionless, >= 1.
    - `lambda_c`: Hunt–Crossley damping factor, s/m.
    """

    k_c: Any = _registered("k_c")
    n_c: Any = _registered("n_c")
    lambda_c: Any = _registered("lambda_c")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("contact")


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


class Load(Validated):
    """The breech force and the firing rhythm (`docs/model.md`, *Load*).

    - `pulse_time` (s): 0 is the paper's impulse (the barrel starts at `v0`); `t_p > 0` is
      a gamma pulse of the same momentum, `F_b = (M v0 / t_p) (t/t_p) exp(-t/t_p)`, with the
      barrel starting at rest.
    - `shots` (static): rounds fired, at `t_j = j · fire_interval`; each adds a velocity
      jump of `v0` (impulse), or its own pulse or table.
    - `fire_interval` (s): time between rounds.
    - `table`: a `ForceTable` of one round, which replaces the pulse or impulse.
    """

    pulse_time: Any = _registered("pulse_time")
    shots: int = eqx.field(default=1, static=True)
    fire_interval: Any = _registered("fire_interval")
    table: ForceTable | None = None

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        n: p for n, p in _group_limits("load").items() if n != "shots"
    }

    def __check_init__(self):
        super().__check_init__()
        if isinstance(self.shots, bool) or not isinstance(self.shots, int) or self.shots < 1:
            raise ParameterError(
                f"Load.shots = {self.shots!r} is invalid: valid shots is an integer >= 1 "
                "(rounds fired)"
            )


class Buffer(Validated):
    """The hydraulic recoil buffer with a throttling orifice (`docs/model.md`,
    *Hydraulic buffer*): `F_h = ρ A_p³ v|v| / (2 C_d² A_o(x)²)`.

    - `oil_density` ρ (kg/m³), `piston_area` A_p (m², 0: no buffer force),
      `discharge_coefficient` C_d, `orifice_length` x_a (m).
    - `orifice` (m², shape `(K,)`, 2 <= K <= 32): the orifice area at `x = x_a i/(K-1)`,
      linear between knots and constant outside `[0, x_a]`; flat names `orifice_<i>`.
    """

    oil_density: Any = _registered("oil_density")
    piston_area: Any = _registered("piston_area")
    discharge_coefficient: Any = _registered("discharge_coefficient")
    orifice_length: Any = _registered("orifice_length")
    orifice: Any = float_leaf(None)

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("buffer")

    def __check_init__(self):
        super().__check_init__()
        if self.orifice is None:
            if is_concrete(self.piston_area) and np.any(np.asarray(self.piston_area) > 0):
                raise ParameterError(
                    "Buffer.piston_area > 0 needs the orifice: give the knots orifice_0 ... "
                    f"orifice_<K-1> ({MIN_KNOTS} <= K <= {MAX_KNOTS}), areas in m^2"
                )
            return
        count = self.knots
        if not MIN_KNOTS <= count <= MAX_KNOTS:
            raise ParameterError(
                f"Buffer.orifice has {count} knots: valid {MIN_KNOTS} to {MAX_KNOTS} "
                "(orifice_0 ... orifice_<K-1>)"
            )
        if is_concrete(self.orifice):
            knots = np.asarray(self.orifice, dtype=np.float64).reshape(-1, count)
            for i in range(count):
                name = f"orifice_{i}"
                check_value("Buffer", name, knots[:, i].squeeze(), PARAMETERS[name])

    @property
    def knots(self) -> int:
        """K, the number of orifice knots (0 without an orifice)."""
        return 0 if self.orifice is None else int(jnp.shape(self.orifice)[-1])


class Recuperator(Validated):
    """The gas recuperator, a nonlinear air spring (`docs/model.md`, *Gas recuperator*):
    `F_g = F_r ((L_r / (L_r - x_M))^γ - 1)`.

    - `recuperator_force` F_r (N), `recuperator_length` L_r (m), `polytropic_index` γ.

    A solve in which `x_M` reaches `0.95 L_r` fails with `Status.bottomed_out`.
    """

    recuperator_force: Any = _registered("recuperator_force")
    recuperator_length: Any = _registered("recuperator_length")
    polytropic_index: Any = _registered("polytropic_index")
    recuperator_preload: Any = _registered("recuperator_preload")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("recuperator")


class Rails(Validated):
    """The rails the recoiling parts slide on: their elevation and Coulomb friction
    (`docs/model.md`, *Firing envelope*).

    - `elevation` θ (degrees above horizontal, -10 to 85): gravity pulls the barrel and
      the absorber rearward along the rails with `g sin θ`.
    - `friction_force` F_0 (N) and `friction_coefficient` μ: the friction's largest
      value `F_max = F_0 + μ (M + m) g cos θ`, which holds a barrel at rest as long as
      the net force on it is within `±F_max`.
    """

    elevation: Any = _registered("elevation")
    friction_force: Any = _registered("friction_force")
    friction_coefficient: Any = _registered("friction_coefficient")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("rails")


class BatteryStop(Validated):
    """The battery stop at `x_M = 0`, a Hunt–Crossley contact the barrel cannot pass
    forward: `F_s = k_s δ^n_s (1 + λ_s δ̇)`, `δ = −x_M > 0`, never pulling.

    - `stop_stiffness` k_s (N/m^n_s; 0 is no stop), `stop_exponent` n_s (1 to 2),
      `stop_damping` λ_s (s/m).
    """

    stop_stiffness: Any = _registered("stop_stiffness")
    stop_exponent: Any = _registered("stop_exponent")
    stop_damping: Any = _registered("stop_damping")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("battery_stop")


class CounterRecoilBuffer(Validated):
    """The counter-recoil buffer, a dashpot acting only on the way back over the last
    stretch before battery: `F_cb = c_b v_M` while `v_M < 0` and `x_M < L_b`.

    - `buffer_damping` c_b (N·s/m), `buffer_length` L_b (m).
    """

    buffer_damping: Any = _registered("buffer_damping")
    buffer_length: Any = _registered("buffer_length")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("counter_recoil_buffer")


class Mount(Validated):
    """The gun on the ground, for the stability margin (its wheels must not lift).

    - `mount_mass` m_g (kg): the whole gun, recoiling parts included; 0 is no mount,
      else at least `M + m`.
    - `cg_distance` L_w (m): from the spade forward to the gun's centre of gravity, in
      battery, horizontally.
    - `trunnion_height` h (m): the bore axis at the trunnion above the spade's ground
      contact.
    - `spade_distance` L_s (m): from the spade forward to the trunnion, horizontally.
    """

    mount_mass: Any = _registered("mount_mass")
    cg_distance: Any = _registered("cg_distance")
    trunnion_height: Any = _registered("trunnion_height")
    spade_distance: Any = _registered("spade_distance")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("mount")


class RecoilParams(eqx.Module):
    """All physical parameters of one design. `absorber=None` is the simplified model
    (barrel, spring and damper only). The hardware beyond the paper is optional:
    `load=None` is one impulse of `v0`, `buffer=None` no hydraulic buffer,
    `recuperator=None` no gas recuperator, each as in the paper; so is the firing
    envelope: `rails=None` is level frictionless rails, `battery_stop=None` no stop,
    `counter_recoil_buffer=None` no counter-recoil buffer and `mount=None` no mount.

    Checked across the groups (when the values are concrete): a recuperator preload
    needs the battery stop, and a mount is at least as heavy as its recoiling parts."""

    barrel: Barrel = Barrel()
    absorber: Absorber | None = Absorber()
    contact: Contact = Contact()
    load: Load | None = None
    buffer: Buffer | None = None
    recuperator: Recuperator | None = None
    rails: Rails | None = None
    battery_stop: BatteryStop | None = None
    counter_recoil_buffer: CounterRecoilBuffer | None = None
    mount: Mount | None = None

    def __check_init__(self):
        check_design(self)


def _first_bad(*arrays: Any, bad) -> tuple[str, tuple[float, ...]] | None:
    """Where `bad(*arrays)` (broadcast) is first true, and the arrays' values there; None
    if nowhere or if a value is not concrete."""
    if not is_concrete(arrays):
        return None
    try:
        values = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in arrays))
    except (TypeError, ValueError):
        return None  # the range checks report a value that is not a number
    mask = np.asarray(bad(*values)).reshape(-1)
    if not mask.any():
        return None
    index = int(np.argmax(mask))
    return element_label(values[0], index), tuple(float(v.reshape(-1)[index]) for v in values)


def check_design(params: RecoilParams) -> None:
    """The checks that span parameter groups, on concrete values (`ParameterError`, one
    line each): a recuperator preload needs the battery stop (`stop_stiffness > 0`), and
    a mount (`mount_mass > 0`) is at least as heavy as its recoiling parts, `M + m`."""
    if params.recuperator is not None:
        stop = 0.0 if params.battery_stop is None else params.battery_stop.stop_stiffness
        found = _first_bad(
            params.recuperator.recuperator_preload, stop, bad=lambda p, k: (p > 0) & ~(k > 0)
        )
        if found is not None:
            where, (preload, _) = found
            raise ParameterError(
                f"Recuperator.recuperator_preload{where} = {preload:g} N is invalid: a preload "
                "needs the battery stop to hold the barrel in battery against it; valid "
                "recuperator_preload 0 without a stop, >= 0 N with stop_stiffness > 0"
            )
    if params.mount is not None:
        absorber = 0.0 if params.absorber is None else params.absorber.m
        found = _first_bad(
            params.mount.mount_mass,
            params.barrel.M,
            absorber,
            bad=lambda mg, M, m: (mg != 0) & (mg < M + m),
        )
        if found is not None:
            where, (mass, M, m) = found
            raise ParameterError(
                f"Mount.mount_mass{where} = {mass:g} kg is invalid: a mount lighter than its "
                f"recoiling parts cannot carry them; valid mount_mass 0 (no mount) or >= M + m "
                f"= {M + m:g} kg (the whole gun on the ground, recoiling parts included)"
            )


#: The pytree of each parameter group, by the class name the registry gives it.
_GROUPS: dict[str, type[Validated]] = {
    group: globals()[name] for group, name in GROUP_CLASSES.items()
}


def _knots(names: dict[str, Any]) -> Any:
    """The orifice knots given by flat name, as one array `(..., K)`; holes are errors."""
    indices = sorted(PARAMETERS[n].index or 0 for n in names)
    missing = [i for i in range(len(indices)) if i not in indices]
    if missing:
        raise ParameterError(
            f"orifice knots must be numbered from 0 without holes: orifice_{missing[0]} is "
            f"missing (given: {', '.join(f'orifice_{i}' for i in indices)})"
        )
    if len(indices) < MIN_KNOTS:
        raise ParameterError(
            f"orifice_0 alone is not a profile: give at least {MIN_KNOTS} knots "
            "(orifice_0, orifice_1, ...)"
        )
    return jnp.stack(
        [jnp.asarray(names[f"orifice_{i}"], dtype=float) for i in range(len(indices))], axis=-1
    )


def params_from_values(values: Mapping[str, Any] | None = None, **kwargs: Any) -> RecoilParams:
    """Build `RecoilParams` from flat parameter names (`PARAMETERS`).

    **Arguments:**

    - `values`, `**kwargs`: flat name → value (scalars, or arrays for a batch); names not
      given take their defaults. `m = 0` gives the simplified model (no absorber). The
      load, buffer and recuperator are present when any of their parameters is given.

    **Returns:** the validated `RecoilParams`.

    **Raises:** `ParameterError` for an unknown name, a value outside its valid range,
    absorber parameters given with `m = 0`, orifice knots with a hole or without
    `piston_area`, or different `shots` in one batch.
    """
    values = {**(values or {}), **kwargs}
    grouped: dict[str, dict[str, Any]] = {g: {} for g in _GROUPS}
    for name, value in values.items():
        grouped[parameter(name).group][name] = value
    m = grouped["absorber"].get("m", None)
    simplified = m is not None and is_concrete(m) and bool(np.all(np.asarray(m) == 0))
    if simplified:
        extra = sorted(set(grouped["absorber"]) - {"m"})
        if extra:
            raise ParameterError(
                f"m = 0 selects the simplified model (no absorber), so {', '.join(extra)} "
                "cannot be set; give m > 0 to use them"
            )
        absorber = None
    else:
        absorber = Absorber(**grouped["absorber"])
    optional: dict[str, Any] = {}
    load = dict(grouped["load"])
    if load:
        if "shots" in load:
            shots = np.unique(np.asarray(load["shots"], dtype=float))
            if shots.size != 1:
                raise ParameterError(
                    f"shots differ within one RecoilParams ({', '.join(f'{x:g}' for x in shots)}):"
                    " shots is static; sweep() runs each value as its own group"
                )
            check_value("Load", "shots", shots[0], PARAMETERS["shots"])
            if shots[0] != int(shots[0]):
                raise ParameterError(
                    f"Load.shots = {shots[0]:g} is invalid: valid shots is an integer >= 1 "
                    "(rounds fired)"
                )
            load["shots"] = int(shots[0])
        optional["load"] = Load(**load)
    buffer = dict(grouped["buffer"])
    if buffer:
        knots = {n: buffer.pop(n) for n in list(buffer) if PARAMETERS[n].index is not None}
        if knots and "piston_area" not in buffer:
            first = min(knots, key=lambda n: PARAMETERS[n].index or 0)
            raise ParameterError(
                f"{first} is given without piston_area: the orifice throttles the buffer's "
                "oil, so give piston_area (m^2) too"
            )
        optional["buffer"] = Buffer(**buffer, orifice=_knots(knots) if knots else None)
    if grouped["recuperator"]:
        optional["recuperator"] = Recuperator(**grouped["recuperator"])
    for group in ENVELOPE_GROUPS:
        if grouped[group]:
            optional[group] = _GROUPS[group](**grouped[group])
    return RecoilParams(
        barrel=Barrel(**grouped["barrel"]),
        absorber=absorber,
        contact=Contact(**grouped["contact"]),
        **optional,
    )


def params_to_values(params: RecoilParams) -> dict[str, Any]:
    """Inverse of `params_from_values`: the flat name → value mapping (m = 0 for the
    simplified model, whose other absorber parameters are absent; absent hardware groups
    give no names; the orifice knots come as `orifice_<i>`)."""
    out: dict[str, Any] = {}
    for name, p in PARAMETERS.items():
        module = getattr(params, p.group)
        if module is None:
            if name == "m":
                out[name] = 0.0
            continue
        out[name] = getattr(module, name)
    if params.buffer is not None and params.buffer.orifice is not None:
        for i in range(params.buffer.knots):
            out[f"orifice_{i}"] = params.buffer.orifice[..., i]
    return out


def _get(params: RecoilParams, p: Parameter) -> Any:
    value = getattr(getattr(params, p.group), p.attribute)
    return value if p.index is None else value[..., p.index]


def check_present(params: RecoilParams, p: Parameter) -> None:
    """Raise `ParameterError` unless parameter `p` is part of `params` and set by value
    (not an integer count)."""
    module = getattr(params, p.group)
    if module is None or (p.index is not None and p.index >= module.knots):
        raise ParameterError(f"{p.name} is not part of this design (its {p.group} is absent)")
    if p.integer:
        raise ParameterError(f"{p.name} is an integer count: it cannot be set by value here")


def with_values(params: RecoilParams, names: Sequence[str], values: Any) -> RecoilParams:
    """`params` with the parameters `names` (flat names) set to `values` (shape
    `(len(names),)`). Concrete values are validated like the constructors do (tracers,
    inside transformations, are not)."""
    knots: dict[int, Any] = {}  # orifice index -> value
    for j, name in enumerate(names):
        p = parameter(name)
        check_present(params, p)
        value = values[j]
        check_value(p.owner, name, value, p)
        value = jnp.asarray(value, dtype=float)
        if p.index is None:
            params = eqx.tree_at(
                lambda q, p=p: getattr(getattr(q, p.group), p.attribute), params, value
            )
        else:
            knots[p.index] = value
    if knots:
        # All knots in one update: this runs in every stage of a tangent solve, where
        # a scatter per knot made the 22-parameter program larger and slower.
        assert params.buffer is not None  # (check_present)
        orifice = jnp.asarray(params.buffer.orifice, dtype=float)
        given = jnp.stack(jnp.broadcast_arrays(*knots.values()), axis=-1)
        if list(knots) == list(range(orifice.shape[-1])):
            orifice = jnp.broadcast_to(given, jnp.broadcast_shapes(given.shape, orifice.shape))
        else:
            orifice = orifice.at[..., np.asarray(list(knots))].set(given)
        params = eqx.tree_at(lambda q: q.buffer.orifice, params, orifice)
    check_design(params)  # the checks across groups (`tree_at` does not run them)
    return params


def values_of(params: RecoilParams, names: Sequence[str]) -> jax.Array:
    """The parameters `names` of `params` as one array, shape `(len(names),)`."""
    return jnp.stack([jnp.asarray(_get(params, parameter(n)), dtype=float) for n in names])
