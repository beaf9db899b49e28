"""The benchmark's anchor: a compiled scalar loop (numba) solving the paper's absorber
model one design at a time on one core, as a hand-written C or Fortran loop would.

It is the yardstick for the cost of a step, not a second model: it exists only in the
benchmark (`recoil-jax bench`, the `bench` extra), and a test checks that its vector
field equals the library's (`vector_field`) and that it takes the same steps. What it
shares with the library is read from the library, never restated: the Tsit5 tableau
(diffrax's), the step-size rule (diffrax's PID rule with the loop's coefficients, its
safety and clipping factors and its initial step), the error order, the tolerances, the
parameters of each design and its contact smoothing width. So, alone of the
applications, it imports the engine's modules (`tests/test_layout.py` allows it).

What it leaves out, so that it is the fastest honest loop: no early stop (it runs to
`t1`), no peak location between steps (the running maxima of `x_M` and `F_AN` are read
at each accepted step's end), no events, no gradients, the paper model only.
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._sweeps.memory import cores

__all__ = ["ANCHOR_PARAMETERS", "anchor_field", "anchor_peaks", "cores"]

#: The columns of a design's row, in order (flat names; the last two are the smoothing
#: widths of the damping switch and of the contact's onset).
ANCHOR_PARAMETERS = ("M", "k", "c_out", "c_ret", "m", "gap", "k_r", "c_r", "k_c", "n_c", "lambda_c")


class _Functions(NamedTuple):
    """The compiled functions: the vector field (for the test that it is the library's)
    and the loop that solves designs one after the other."""

    field: Any
    solve_all: Any


_FUNCTIONS: _Functions | None = None


def _compiled() -> _Functions:
    """The numba functions, compiled on first use (numba is imported only here)."""
    global _FUNCTIONS
    if _FUNCTIONS is None:
        numba = _numba()
        field = _field_kernel(numba)
        solve = _solve_kernel(numba, field, _rms_kernel(numba))
        _FUNCTIONS = _Functions(field, _solve_all_kernel(numba, solve))
    return _FUNCTIONS


def _numba():
    """The numba module, or `ParameterError` (saying how to install it) without it."""
    try:
        import numba
    except ImportError:
        raise rj.ParameterError(
            "the compiled scalar loop needs numba: pip install 'recoil-jax[bench]'"
        ) from None
    return numba


def _field_kernel(numba):
    """The model's vector field, `field(y, p, out)`: dy/dt into `out`, returning F_AN."""

    @numba.njit(inline="always")
    def ramp(x, width):  # smooth_relu: the C² quartic inside the band, max(0, x) outside
        if width > 0.0 and abs(x) < width:
            s = x / width
            return width * (s + 1.0) ** 3 * (3.0 - s) / 16.0
        return max(x, 0.0)

    @numba.njit(inline="always")
    def field(y, p, out):
        """dy/dt into `out`; returns the anchoring force F_AN."""
        mass, k, c_out, c_ret, m, gap, k_r, c_r, k_c, n_c, lam, w_v, w_c = (
            p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11], p[12]
        )  # fmt: skip
        x_big, v_big, x_small, v_small = y[0], y[1], y[2], y[3]
        anchoring = k * x_big + c_ret * v_big + (c_out - c_ret) * ramp(v_big, w_v)
        penetration = ramp(x_big - x_small - gap, w_c)
        elastic = k_c * penetration**n_c if penetration > 0.0 else 0.0
        contact = elastic * ramp(1.0 + lam * (v_big - v_small), lam * w_v)
        coupling = k_r * (x_big - x_small) + c_r * (v_big - v_small)
        out[0] = v_big
        out[1] = -(anchoring + coupling + contact) / mass
        out[2] = v_small
        out[3] = (coupling + contact) / m
        return anchoring

    return field


def _rms_kernel(numba):
    """The root mean square of a vector, `rms(x)`."""

    @numba.njit
    def rms(x):
        total = 0.0
        for value in x:
            total += value * value
        return np.sqrt(total / x.shape[0])

    return rms


def _solve_kernel(numba, field, rms):
    """One design's solve to `t1`, `solve(p, v0, t1, *settings)`: Tsit5 with diffrax's
    initial step and PID step-size rule, returning the running maxima of x_M and F_AN
    at the accepted steps' ends, the accepted steps and the attempts."""

    @numba.njit
    def solve(p, v0, t1, rtol, atol, order, pcoeff, icoeff, rule, a, b_error, max_steps):
        safety, factor_min, factor_max = rule[0], rule[1], rule[2]
        y = np.array([0.0, v0, 0.0, 0.0])
        k = np.zeros((7, 4))
        stage, y1, error, f1 = np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4)
        best_force = field(y, p, k[0])
        best_x = 0.0
        # diffrax's initial step (Hairer & Wanner's rule).
        scale = atol + np.abs(y) * rtol
        d0, d1 = rms(y / scale), rms(k[0] / scale)
        h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
        for j in range(4):
            stage[j] = y[j] + h0 * k[0, j]
        field(stage, p, f1)
        d2 = rms((f1 - k[0]) / scale) / h0
        largest = max(d1, d2)
        h1 = max(1e-6, h0 * 1e-3) if largest <= 1e-15 else (0.01 / largest) ** (1.0 / order)
        dt = min(100.0 * h0, h1)
        t, previous, steps, attempts = 0.0, 1.0, 0, 0
        exponent_now = (pcoeff + icoeff) / order
        exponent_before = -pcoeff / order
        while t < t1 and attempts < max_steps:
            dt = min(dt, t1 - t)
            for s in range(1, 7):  # k[0] is f(t, y) (first same as last)
                for j in range(4):
                    total = y[j]
                    for r in range(s):
                        total += dt * a[s, r] * k[r, j]
                    stage[j] = total
                field(stage, p, k[s])
            # Tsit5's last stage is at y1 (its last row of `a` is its solution weights).
            squares = 0.0
            for j in range(4):
                y1[j] = stage[j]
                e = 0.0
                for r in range(7):
                    e += b_error[r] * k[r, j]
                error[j] = dt * e
                scaled = error[j] / (atol + max(abs(y[j]), abs(y1[j])) * rtol)
                squares += scaled * scaled
            scaled_error = np.sqrt(squares / 4.0)
            keep = scaled_error < 1.0
            inverse = 1.0 / scaled_error if scaled_error > 0.0 else np.inf
            factor = safety * inverse**exponent_now * previous**exponent_before
            if keep:
                factor = min(max(factor, 1.0), factor_max)
            else:
                factor = min(max(factor, factor_min), safety)
            if inverse == 0.0 or np.isinf(inverse):
                inverse = 1.0
            attempts += 1
            if keep:
                t += dt
                steps += 1
                previous = inverse
                for j in range(4):
                    y[j] = y1[j]
                    k[0, j] = k[6, j]
                force = field(y, p, f1)  # F_AN at the step's end
                best_x = max(best_x, y[0])
                best_force = max(best_force, force)
            dt = dt * factor
        return best_x, best_force, steps, attempts

    return solve


def _solve_all_kernel(numba, solve):
    """The loop over designs, `solve_all(rows, v0, t1, *settings, out)`: each row's
    `solve` in turn, its four results into its row of `out`."""

    @numba.njit
    def solve_all(rows, v0, t1, rtol, atol, order, pcoeff, icoeff, rule, a, b_error, limit, out):
        for i in range(rows.shape[0]):
            x, force, steps, attempts = solve(
                rows[i], v0[i], t1, rtol, atol, order, pcoeff, icoeff, rule, a, b_error, limit
            )
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = x, force, steps, attempts

    return solve_all


class _Rows(NamedTuple):
    """The designs as the loop reads them: one parameter row each (`ANCHOR_PARAMETERS`,
    then the two widths), and each one's `v0`."""

    rows: np.ndarray
    v0: np.ndarray


def _rows(columns: dict[str, np.ndarray], smoothing: rj.Smoothing) -> _Rows:
    """Each design's parameter row (`ANCHOR_PARAMETERS`, then the two widths) and `v0`."""
    from recoil_jax._model.forces.absorber import contact_width

    params, _ = rjx.batch_params(columns)
    values = np.stack([np.asarray(v) for v in rj.values_of(params, ANCHOR_PARAMETERS)], axis=-1)
    widths = np.asarray(contact_width(params, smoothing))
    damping = np.full(len(values), float(smoothing.damping_width))
    rows = np.column_stack([values, damping, np.broadcast_to(widths, damping.shape)])
    return _Rows(
        np.ascontiguousarray(rows), np.asarray(rj.values_of(params, ("v0",))[0], dtype=float)
    )


class _Settings(NamedTuple):
    """The loop's settings, in the order `solve` takes them after `t1`: the tolerances,
    the error order, the PID coefficients, the rule (safety, smallest and largest
    factor), Tsit5's tableau (`a`, the error weights) and the most attempts."""

    rtol: float
    atol: float
    order: float
    pcoeff: float
    icoeff: float
    rule: np.ndarray
    a: np.ndarray
    b_error: np.ndarray
    max_steps: int


def _settings(options: rj.SolverOptions) -> _Settings:
    """The loop's step-size rule and tableau, from the library and diffrax."""
    import diffrax

    from recoil_jax._model.equations import RECOIL_TERM
    from recoil_jax._model.settings import with_default_tolerances
    from recoil_jax._model.stepping import PeakLoop, make_controller

    options = with_default_tolerances(rj.RecoilParams(absorber=rj.Absorber()), options)
    controller = make_controller(options)
    tableau = diffrax.Tsit5.tableau
    a = np.zeros((7, 7))
    for i, row in enumerate(tableau.a_lower):
        a[i + 1, : len(row)] = np.asarray(row, dtype=float)
    order = float(PeakLoop(RECOIL_TERM, lambda t, y, args: {}, options).error_order)
    rule = np.array([controller.safety, controller.factormin, controller.factormax], float)
    return _Settings(
        rtol=float(options.rtol),
        atol=float(options.atol),
        order=order,
        pcoeff=float(controller.pcoeff),
        icoeff=float(controller.icoeff),
        rule=rule,
        a=a,
        b_error=np.asarray(tableau.b_error, dtype=float),
        max_steps=int(options.max_steps),
    )


def anchor_field(y, columns: dict[str, np.ndarray], smoothing=rj.Smoothing()) -> np.ndarray:
    """The anchor's `dy/dt` at states `y` (shape `(n, 4)`) of designs `columns` (one row
    each; paper model with an absorber): for the test that it is the library's model."""
    field = _compiled().field
    rows = _rows(columns, smoothing).rows
    out = np.zeros((len(rows), 4))
    for i in range(len(rows)):
        field(np.asarray(y[i], dtype=float), rows[i], out[i])
    return out


def anchor_peaks(
    columns: dict[str, np.ndarray],
    smoothing: rj.Smoothing = rj.Smoothing(),
    options: rj.SolverOptions = rj.SolverOptions(),
    t1: float = 10.0,
) -> dict:
    """Solve designs (flat-name columns of the paper's absorber model) one after the
    other on this core with the compiled scalar loop, each to `t1`.

    **Returns:** a dict: `peak_displacement`, `peak_anchoring_force` (the running maxima
    at the accepted steps' ends), `num_steps`, `num_attempts` (arrays, one per design) and
    `seconds` (the loop's wall time, compilation excluded).

    **Raises:** `ParameterError` if numba is not installed (the `bench` extra).
    """
    solve_all = _compiled().solve_all
    rows, v0 = _rows(columns, smoothing)
    settings = _settings(options)
    out = np.zeros((len(rows), 4))
    solve_all(rows[:1], v0[:1], t1, *settings, out[:1])  # compiles (not timed)
    start = time.perf_counter()
    solve_all(rows, v0, t1, *settings, out)
    seconds = time.perf_counter() - start
    return {
        "peak_displacement": out[:, 0],
        "peak_anchoring_force": out[:, 1],
        "num_steps": out[:, 2].astype(int),
        "num_attempts": out[:, 3].astype(int),
        "seconds": seconds,
    }
