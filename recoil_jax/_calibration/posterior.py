"""The posterior of a calibration (`sample_posterior`): NUTS (blackjax, with Stan's window
adaptation) on the fit's own likelihood, with the exact forward sensitivities as its
gradient, and ArviZ's diagnostics (split R̂, bulk and tail ESS) and draws' format.

The least-squares fit's Laplace intervals are the curvature at the optimum; where the
model is far from linear over them (friction measured at one elevation, a gap the barrel
barely closes, a value near its bound) the posterior is a ridge, a banana or a
half-distribution, and only draws show it.

**Coordinates.** The chains move in `y`, with `z = _box(y)` the fit's box coordinates
(the bounds 0 and 1, linear or logarithmic: `SearchSpace`): the identity on the box's
inside, bent within `EDGE` of each bound so that no draw leaves it. A ridge straight in
the values (friction at one elevation) stays straight in `y`, where a per-axis logit bent
it. The density carries the transform's Jacobian, so that a uniform prior is uniform in
the parameter itself. The likelihood is the fit's: `−½ Σ ρ(r²)` over every experiment,
signal and sample (`r` in noise units, `ρ` the calibration's loss), under the noise the
fit settled on (given, or estimated from the traces and then held fixed), or with
`sample_noise` that noise sampled too (`−n log σ − Σ r²/2σ²`, a half-normal prior).

**Programs.** Warm-up and sampling are one compiled program each, run chain by chain
(and the draws in blocks, for the progress line), as many chains at once as there are
cores (`parallel_chains`: threads, each calling the compiled program, which keeps one
core busy and lets the others run): on a CPU, chains in lockstep (`vmap`) would each wait
for the longest trajectory of the batch, and a vmapped solve selects its whole carry at
every step (`docs/speed.md`). A chain's draws do not depend on how many run at once.
Compilation is timed apart.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
import warnings
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from typing import Any, NamedTuple, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._campaigns.progress import Progress
from .._model.programs import compiled_ahead
from .._model.registry import ParameterError
from .._model.status import OK_CODE
from .._sweeps.memory import default_workers
from .layout import Layout, prepare
from .least_squares import (
    FitSettings,
    evaluate,
    evaluate_program,
    jumps_at,
    model_residuals,
    robust,
)
from .predict import FittedParameters
from .report import unresolved_samples
from .result import CalibrationResult
from .spec import Calibration

__all__ = [
    "DEFAULT_CHAINS",
    "DEFAULT_DRAWS",
    "DEFAULT_WARMUP",
    "ModelMisfitError",
    "Posterior",
    "PosteriorDensity",
    "PosteriorPredictive",
    "Prior",
    "check_posterior_settings",
    "posterior_density",
    "sample_posterior",
]

#: Draws per chain, warm-up steps per chain and chains, unless told.
DEFAULT_DRAWS = 1000
DEFAULT_WARMUP = 1000
DEFAULT_CHAINS = 4
#: The most draws (or warm-up steps) per chain, and chains, a call accepts: past these a
#: run is a mistake, not a study (a million solves at the least).
MAX_DRAWS = 100_000
MAX_CHAINS = 64

#: The honesty gates (Vehtari et al. 2021): split R̂ over this, or a bulk ESS under
#: `MIN_ESS`, or any divergent transition, and the sampler has not converged.
MAX_RHAT = 1.01
MIN_ESS = 400
#: Where the posterior's 95 % interval and the Laplace one differ by more than this
#: share of the Laplace interval's width (at either end), the report says so.
DISAGREEMENT = 0.2
#: Two values whose draws correlate beyond this (either sign), each still spread over
#: more than half its prior's sd, are not separated by the data: only a combination of
#: them is determined, and the report says so.
UNSEPARATED = 0.95
#: A normal prior with more than this share of its mass outside the bounds is warned of.
PRIOR_MASS_OUTSIDE = 0.5

_KINDS = ("uniform", "normal", "lognormal")
#: The posterior draws a predictive band is made of, unless told (thinned evenly over
#: every chain): its 2.5 and 97.5 % points to about ±1.1 % in probability (one sd).
PREDICTIVE_DRAWS = 200


class ModelMisfitError(RuntimeError):
    """The model check failed: the model does not explain the traces, so its posterior
    would be a statement about the wrong model (not sampled)."""


@dataclasses.dataclass(frozen=True)
class Prior:
    """A fitted value's prior, within its bounds (truncated to them): `"uniform"` (the
    default: flat over the bounds, in the value itself), `"normal"` with `mean` and `sd`,
    or `"lognormal"` with the `mean` and `sd` of the value (not of its logarithm; the
    value must be positive over its bounds). SI units."""

    kind: str = "uniform"
    mean: float | None = None
    sd: float | None = None

    def __post_init__(self):
        if self.kind not in _KINDS:
            raise ParameterError(f"prior kind {self.kind!r}: one of {', '.join(_KINDS)}")
        if self.kind == "uniform":
            if self.mean is not None or self.sd is not None:
                raise ParameterError("a uniform prior takes no mean or sd (it is the bounds)")
            return
        for name in ("mean", "sd"):
            value = getattr(self, name)
            number = isinstance(value, (int, float, np.integer, np.floating))
            if isinstance(value, bool) or not number or not math.isfinite(float(value)):
                raise ParameterError(
                    f"a {self.kind} prior needs a finite number for its {name}, got {value!r}"
                )
        if float(self.sd) <= 0:  # pyright: ignore[reportArgumentType]
            raise ParameterError(f"prior sd must be > 0, got {self.sd}")
        if self.kind == "lognormal" and float(self.mean) <= 0:  # pyright: ignore[reportArgumentType]
            raise ParameterError(f"a lognormal prior's mean must be > 0, got {self.mean}")

    @classmethod
    def of(cls, spec) -> Prior:
        """A `Prior` from itself, a kind's name, or a mapping `{kind, mean, sd}` (`kind`
        "normal" where a mean and sd are given without one)."""
        if isinstance(spec, Prior):
            return spec
        if isinstance(spec, str):
            return cls(spec)
        if isinstance(spec, Mapping):
            unknown = set(spec) - {"kind", "mean", "sd"}
            if unknown:
                raise ParameterError(f"prior: unknown key {sorted(unknown)[0]!r} (kind, mean, sd)")
            return cls(str(spec.get("kind", "normal")), spec.get("mean"), spec.get("sd"))
        raise ParameterError(f"prior: a kind's name or a table {{kind, mean, sd}}, got {spec!r}")

    def log_parameters(self) -> tuple[int, float, float]:
        """`(kind index, location, scale)` of the density's kernel: a normal's mean and
        sd; a lognormal's in the logarithm (from the value's mean and sd)."""
        if self.kind == "uniform":
            return 0, 0.0, 1.0
        mean, sd = float(self.mean), float(self.sd)  # pyright: ignore[reportArgumentType]
        if self.kind == "normal":
            return 1, mean, sd
        variance = math.log1p((sd / mean) ** 2)
        return 2, math.log(mean) - variance / 2, math.sqrt(variance)


class _Noise(eqx.Module):
    """The noises sampled (`sample_noise`), `(Q,)` each: the experiment's and signal's
    flat index into `(E, S)`, its samples in the likelihood, and its half-normal prior's
    scale in units of the likelihood's noise (`data.sigma`, the fit's). The chains move
    in `u = log(σ / σ_fit)`."""

    slots: jax.Array
    samples: jax.Array
    scale: jax.Array

    def log_density(self, u, squares):
        """The log-likelihood's and prior's terms in `u (Q,)`, given each experiment's
        and signal's Σ r² `squares (E·S,)` in units of the fit's noise: `−n u −
        ½ e^{−2u} Σ r²` (a Gaussian's normalisation), the half-normal `−½ (e^u /
        scale)²` and the Jacobian of `u → σ`, `u`; less the `−½ Σ r²` the likelihood
        holds already."""
        chi2 = squares[self.slots]
        likelihood = -self.samples * u - 0.5 * (jnp.exp(-2.0 * u) - 1.0) * chi2
        return jnp.sum(likelihood - 0.5 * (jnp.exp(u) / self.scale) ** 2 + u)


class _Priors(eqx.Module):
    """The priors as arrays over the fitted values `(P,)`: kind index, location, scale;
    and the sampled noises (`_Noise`), or None where the noise is held fixed."""

    kind: jax.Array
    location: jax.Array
    scale: jax.Array
    noise: _Noise | None = None

    def log_density(self, theta):
        """Σ log prior(θ), up to a constant (finite everywhere: double `where`)."""
        standard = (theta - self.location) / self.scale
        positive = theta > 0
        log_theta = jnp.log(jnp.where(positive, theta, 1.0))
        logged = (log_theta - self.location) / self.scale
        lognormal = jnp.where(positive, -log_theta - 0.5 * logged**2, -jnp.inf)
        terms = jnp.where(
            self.kind == 1, -0.5 * standard**2, jnp.where(self.kind == 2, lognormal, 0.0)
        )
        return jnp.sum(terms)


def _require_extra() -> None:
    """blackjax and ArviZ are there, or a `ModuleNotFoundError` naming the extra that
    installs them (before any fit runs)."""
    for module in ("blackjax", "arviz"):
        try:
            __import__(module)
        except ModuleNotFoundError as error:
            raise ModuleNotFoundError(
                f"sample_posterior needs {module}, which the core install leaves out: "
                "pip install 'recoil-jax[posterior]'",
                name=module,
            ) from error


def _check_count(name: str, value, least: int, most: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ParameterError(f"{name} must be an integer in [{least}, {most}], got {value!r}")
    if not least <= int(value) <= most:
        raise ParameterError(f"{name} must be in [{least}, {most}], got {value}")
    return int(value)


def _priors(priors, layout: Layout) -> tuple[_Priors, dict[str, Prior]]:
    """The priors by fitted label (uniform where none is given), checked against the
    fitted labels and their bounds."""
    if priors is not None and not isinstance(priors, Mapping):
        raise ParameterError(f"priors: a mapping of fitted names to priors, got {priors!r}")
    given = dict(priors or {})
    labels = list(layout.labels)
    for name in given:
        if name not in labels:
            raise ParameterError(
                f"prior for {name!r}: not a fitted value (fitted: {', '.join(labels)})"
            )
    chosen = {label: Prior.of(given.get(label, "uniform")) for label in labels}
    lower, upper = np.asarray(layout.lower, float), np.asarray(layout.upper, float)
    for i, (label, prior) in enumerate(chosen.items()):
        if prior.kind == "lognormal" and lower[i] < 0:
            raise ParameterError(
                f"prior for {label!r}: lognormal needs positive values, but its bounds are "
                f"[{lower[i]:g}, {upper[i]:g}]"
            )
        if prior.kind == "normal":
            inside = _normal_mass(lower[i], upper[i], float(prior.mean), float(prior.sd))  # pyright: ignore[reportArgumentType]
            if 1.0 - inside > PRIOR_MASS_OUTSIDE:
                warnings.warn(
                    f"prior for {label!r}: normal({prior.mean:g}, {prior.sd:g}) puts "
                    f"{1 - inside:.0%} of its mass outside the bounds [{lower[i]:g}, "
                    f"{upper[i]:g}]; the posterior is truncated to them",
                    stacklevel=4,
                )
    kinds, locations, scales = zip(*(p.log_parameters() for p in chosen.values()), strict=True)
    arrays = _Priors(jnp.asarray(kinds), jnp.asarray(locations, float), jnp.asarray(scales, float))
    return arrays, chosen


def _normal_mass(lower: float, upper: float, mean: float, sd: float) -> float:
    """A normal's mass within `[lower, upper]`."""
    cdf = lambda x: 0.5 * math.erfc(-(x - mean) / (sd * math.sqrt(2.0)))  # noqa: E731
    return cdf(upper) - cdf(lower)


def _residual_function(static: FitSettings):
    """`(θ, data) → residuals (E, S, n)` in noise units, whose derivative
    (`custom_jvp`) is the forward sensitivities of the same solve: one solve gives the
    log density and its gradient."""

    @jax.custom_jvp
    def residuals(theta, data):
        return evaluate(theta, data, static).residuals

    @residuals.defjvp
    def _(primals, tangents):
        theta, data = primals
        evaluation = evaluate(theta, data, static)
        return evaluation.residuals, jnp.einsum("esnp,p->esn", evaluation.jacobian, tangents[0])

    return residuals


#: The width, in the box coordinates `z`, of the chains' coordinates' bend at each
#: bound (`_box`): inside it `y = z`, so that a ridge straight in the values is straight
#: in `y`; within it of a bound, `y` is logarithmic in the distance to it.
EDGE = 0.01


def _box(y):
    """`y → z = δ·softplus(y/δ) − δ·softplus((y − 1)/δ)` (δ = `EDGE`): the identity on
    the box's inside, `z → 0` as `y → −∞` and `z → 1` as `y → ∞`, each as `e^{−|y|/δ}`
    (elementwise)."""
    # Each bound's side from its own end (softplus(x) − softplus(−x) = x), so that
    # rounding keeps z inside [0, 1]: both forms are finite, one `where` suffices.
    lower = EDGE * (jax.nn.softplus(y / EDGE) - jax.nn.softplus((y - 1.0) / EDGE))
    upper = 1.0 - EDGE * (jax.nn.softplus((1.0 - y) / EDGE) - jax.nn.softplus(-y / EDGE))
    return jnp.where(y < 0.5, lower, upper)


def _log_box_slope(y):
    """`log dz/dy` of `_box`, up to a constant: `dz/dy = σ(y/δ) − σ((y − 1)/δ)
    = σ(y/δ)·σ((1 − y)/δ)·(1 − e^{−1/δ})`, in log-sigmoid form (finite for any y)."""
    return jax.nn.log_sigmoid(y / EDGE) + jax.nn.log_sigmoid((1.0 - y) / EDGE)


def _box_inverse(z):
    """`_box`'s inverse for `z` in (0, 1) (numpy; exact to `e^{−1/δ}`)."""
    z = np.asarray(z, dtype=float)
    # δ·log(expm1(x/δ)) = x + δ·log(−expm1(−x/δ)), the latter finite for any δ.
    return z + EDGE * (np.log(-np.expm1(-z / EDGE)) - np.log(-np.expm1((z - 1.0) / EDGE)))


class _Whitening(eqx.Module):
    """The chains' coordinates `w`, with `y = centre + factor @ w` and `z = _box(y)` the
    fit's box coordinates: the Laplace approximation in `y` made a standard normal
    (`factor` its Cholesky factor), so that the warm-up, which assumes values of unit
    scale (Stan's regularisation of the mass matrix toward 10⁻³·I), sees them so; a
    fitted value's `y` is 10⁻³ wide."""

    centre: jax.Array
    factor: jax.Array
    #: The sampled noises' `u = log(σ / σ_fit)` per unit of `w` (`(Q,)`): the
    #: posterior's sd of `u` at the optimum, `1/√(2n)` (the χ² of n samples).
    noise_sd: jax.Array = eqx.field(default_factory=lambda: jnp.zeros(0))

    def y(self, w):
        """`w (..., P + Q)` → `y (..., P)`."""
        return self.centre + w[..., : self.centre.shape[0]] @ self.factor.T

    def z(self, w):
        """`w (..., P + Q)` → the box coordinates `z (..., P)`, in [0, 1]."""
        return _box(self.y(w))

    def log_noise(self, w):
        """`w (..., P + Q)` → the sampled noises' `u (..., Q)`."""
        return w[..., self.centre.shape[0] :] * self.noise_sd


def _log_density(
    w, data, priors: _Priors, whitening: _Whitening, static: FitSettings, gradient: bool = True
):
    """The log posterior density of the chains' coordinates `w (P + Q,)` (Q sampled
    noises, `_Noise`), up to a constant: the fit's log-likelihood, the priors, and the
    Jacobian of `y → z → θ` (that of `w → y` is constant). `gradient` (static):
    differentiable by the solve's forward sensitivities; without, one solve of the state
    alone (for a sampler that needs no gradient: a sixth to a tenth of the cost on the
    bench's 5-value fit)."""
    y = whitening.y(w)
    z = _box(y)
    theta, slope = jax.jvp(data.space.theta, (z,), (jnp.ones_like(z),))  # θ(z) is elementwise
    if gradient:
        r = _residual_function(static)(theta, data)
    else:
        r = model_residuals(theta, data, static)
    squares = robust(r, static.loss, static.f_scale) ** 2
    log_likelihood = -0.5 * jnp.sum(squares)
    if priors.noise is not None:
        log_likelihood += priors.noise.log_density(
            whitening.log_noise(w), jnp.sum(squares, axis=-1).reshape(-1)
        )
    log_jacobian = jnp.sum(_log_box_slope(y) + jnp.log(jnp.abs(slope)))
    return log_likelihood + priors.log_density(theta) + log_jacobian


class _Settings(NamedTuple):
    """What shapes the sampler's programs (static): each program is given only its own
    (the warm-up's `block` as 0; the sampling's `warmup` and `target_acceptance` as 0
    and `dense` false, the mass matrix's shape saying it), so that another number of
    draws does not compile the warm-up again, nor another warm-up the sampling."""

    static: FitSettings
    dense: bool
    warmup: int
    block: int
    target_acceptance: float


def _warm_up(key, w0, data, priors, whitening, settings: _Settings):
    """One chain's window adaptation from `w0`: its last state and the tuned step size
    and inverse mass matrix."""
    import blackjax
    from blackjax.adaptation.base import get_filter_adapt_info_fn

    def log_density(w):
        return _log_density(w, data, priors, whitening, settings.static)

    # blackjax's annotations are generic: its results are read by name (Any).
    adaptation: Any = blackjax.window_adaptation(
        blackjax.nuts,
        log_density,
        is_mass_matrix_diagonal=not settings.dense,
        target_acceptance_rate=settings.target_acceptance,
        adaptation_info_fn=get_filter_adapt_info_fn(),  # keep no warm-up history
    )
    (state, parameters), _ = adaptation.run(key, w0, num_steps=settings.warmup)
    return state, parameters["step_size"], parameters["inverse_mass_matrix"]


class _Block(NamedTuple):
    """A block of one chain's draws: positions `(B, P)` in `w`, and each transition's
    log density, divergence, leapfrog steps, energy and acceptance."""

    position: jax.Array
    log_density: jax.Array
    diverging: jax.Array
    steps: jax.Array
    energy: jax.Array
    acceptance: jax.Array


class _Stopped(Exception):
    """A chain's thread told to stop (another chain failed, or Ctrl-C)."""


def _each_chain(
    run: Callable[[int], Any], chains: int, workers: int, stopping: threading.Event
) -> list:
    """`run(c)` for each chain `c`, in chain order, `workers` of them at once on threads:
    a compiled program lets go of the interpreter while it runs and keeps about one core
    busy, so chains on threads run at the same time (measured, `docs/calibration.md`).

    Where any chain fails, or the caller is interrupted (Ctrl-C), `stopping` is set: the
    chains not started never start, and each running one stops at its next checkpoint
    (`run` raises `_Stopped` there: after its next block of draws, or at the end of its
    warm-up, which is one compiled call); then the first failure is raised."""
    if workers == 1:
        return [run(c) for c in range(chains)]

    def guarded(chain: int):
        if stopping.is_set():  # started after a failure, before the pool was shut down
            raise _Stopped
        try:
            return run(chain)
        except BaseException:
            stopping.set()  # at once, whichever chain it is
            raise

    pool = ThreadPoolExecutor(workers, thread_name_prefix="chain")
    futures = [pool.submit(guarded, c) for c in range(chains)]
    try:
        wait(futures, return_when=FIRST_EXCEPTION)
    except BaseException:  # interrupted while waiting
        stopping.set()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    failures = [
        error
        for f in futures
        if not f.cancelled() and (error := f.exception()) is not None
        and not isinstance(error, _Stopped)
    ]  # fmt: skip
    if failures:
        raise failures[0]
    return [f.result() for f in futures]


def _sample_block(key, state, step_size, inverse_mass, data, priors, whitening, settings):
    """`settings.block` NUTS transitions from `state`: the last state and the block."""
    import blackjax

    def log_density(w):
        return _log_density(w, data, priors, whitening, settings.static)

    kernel = blackjax.nuts(log_density, step_size=step_size, inverse_mass_matrix=inverse_mass)

    def one(state, key):
        state, info = kernel.step(key, state)
        state, info = cast(Any, state), cast(Any, info)
        return state, _Block(
            state.position,
            state.logdensity,
            info.is_divergent,
            info.num_integration_steps,
            info.energy,
            info.acceptance_rate,
        )

    return jax.lax.scan(one, state, jax.random.split(key, settings.block))


@dataclasses.dataclass(frozen=True)
class Posterior:
    """What `sample_posterior` gives.

    - `labels`: the fitted values' labels (as `CalibrationResult.fitted`); `draws
      (chains, draws, P)`: the draws in SI units.
    - `summary`: per label, the posterior's `mean`, `sd`, `q2.5`, `q50`, `q97.5`,
      `r_hat` (rank-normalised split R̂), `ess_bulk`, `ess_tail`, and beside them the
      least-squares `value`, its Laplace `stderr` and `ci95` (None where the fit gives
      none) and whether the two intervals `disagree` (by more than 20 % of the Laplace
      interval's width at either end).
    - `converged`: two chains or more, R̂ ≤ 1.01 and bulk ESS ≥ 400 on every value,
      and no divergent transition; `problems`: what failed, naming the value and what to try;
      `disagreements`: the values whose Laplace interval misstates the posterior, in
      words; `unseparated`: the pairs of values the data do not separate (draws
      correlated beyond ±0.95, each spread over more than half its prior's sd), in
      words. `divergences`: the divergent transitions,
      all chains.
    - `priors`: the prior of each value; `step_size (chains,)`; `seconds`: `compile`,
      `warmup` and `sampling` (compilation excluded from the other two; wall time,
      with `parallel_chains` chains running at once); `ess_per_second`: the least bulk
      ESS over the values per second of sampling.
    - `inference_data`: ArviZ's `InferenceData` (`posterior`: `theta` over `chain`,
      `draw`, `parameter`; `sample_stats`; `observed_data`: the traces);
      `to_netcdf(path)` writes it.
    - `fit`: the least-squares result the chains started from; `noise`: the
      likelihood's, per experiment and signal (`{"sigma", "given"}`: given, or estimated
      by the fit; held fixed, or with `sample_noise` the chains' start and `"sampled"`:
      its posterior's statistics as a value's, and its `half_normal_scale`).
    """

    labels: tuple[str, ...]
    draws: np.ndarray
    summary: dict[str, dict[str, Any]]
    converged: bool
    problems: list[str]
    disagreements: list[str]
    divergences: int
    priors: dict[str, Prior]
    step_size: np.ndarray
    seconds: dict[str, float]
    ess_per_second: float
    inference_data: Any
    fit: CalibrationResult
    #: The likelihood's noise, per experiment and signal: `{"sigma", "given"}` (given
    #: in the calibration, or estimated by the fit from the residuals and held fixed).
    noise: list[dict[str, dict[str, Any]]] = dataclasses.field(default_factory=list)
    #: The pairs of values whose draws correlate beyond ±0.95, each spread over more
    #: than half its prior's sd, in words: the data do not separate them (a ridge), and
    #: each one's interval is the priors' doing.
    unseparated: list[str] = dataclasses.field(default_factory=list)
    #: Samples left out of the likelihood: either side of a jump in the model's signal,
    #: or on an event the sampling does not resolve (the likelihood is a cliff there).
    left_out: int = 0
    #: The chains that ran at once, each on a thread (and a core) of its own.
    parallel_chains: int = 1
    #: `(thetas (N, P)) → ({signal: the model's (N, E, n)}, solve codes (N, E))` on the
    #: calibration's traces (`predictive`).
    _signals: Any = dataclasses.field(default=None, repr=False, compare=False)

    def predictive(self, draws: int = PREDICTIVE_DRAWS, seed: int = 0) -> PosteriorPredictive:
        """The traces under the posterior (`PosteriorPredictive`): the model solved at
        `draws` posterior draws (thinned evenly over every chain), each signal's band over
        them, and that band widened by the likelihood's noise (`seed` its draws).

        **Raises:** `ParameterError` for `draws` not an integer in [2, 100,000], where
        fewer than 2 of the draws solve, or for a `Posterior` not made by
        `sample_posterior` (it has no model to solve).
        """
        draws = _check_count("draws", draws, 2, MAX_DRAWS)
        seed = _check_count("seed", seed, 0, 2**63 - 1)
        if self._signals is None:
            raise ParameterError("posterior.predictive: this Posterior holds no model to "
                                 "solve (make it with sample_posterior)")  # fmt: skip
        flat = self.draws.reshape(-1, self.draws.shape[-1])
        chosen = flat[np.linspace(0, len(flat) - 1, min(draws, len(flat))).round().astype(int)]
        signals, codes = self._signals(chosen)
        ok = np.all(codes == OK_CODE, axis=1)
        signals = {name: values[ok] for name, values in signals.items()}
        if ok.sum() < 2:
            raise ParameterError(
                f"the posterior predictive: {int((~ok).sum())} of {len(chosen)} draws failed "
                "to solve; no band to give"
            )
        return _predictive(self.fit, self.noise, signals, int((~ok).sum()), seed)

    def hardware(self) -> FittedParameters:
        """The fitted hardware values (as `CalibrationResult.hardware`) with the
        posterior's draws of them, for `predict`: its samples are then the draws (every
        chain's, thinned), its linear band the draws' covariance through the gradients
        at the least-squares values. Every value counts as determined: the posterior,
        bounded by its prior, is a distribution wherever the data leave it."""
        hardware = self.fit.hardware()
        index = [self.labels.index(name) for name in hardware.names]
        draws = self.draws.reshape(-1, len(self.labels))[:, index]
        return dataclasses.replace(
            hardware,
            covariance=np.atleast_2d(np.cov(draws, rowvar=False)),
            identifiable=np.ones(len(index), dtype=bool),
            draws=draws,
        )

    def to_netcdf(self, path) -> None:
        """Write the draws, sample statistics and traces (`inference_data`) to `path`."""
        self.inference_data.to_netcdf(str(path))

    def to_json(self) -> dict[str, Any]:
        """The summary and diagnostics as JSON-ready values."""
        return {
            "summary": self.summary,
            "converged": self.converged,
            "problems": self.problems,
            "disagreements": self.disagreements,
            "unseparated": self.unseparated,
            "left_out": self.left_out,
            "divergences": self.divergences,
            "priors": {k: dataclasses.asdict(p) for k, p in self.priors.items()},
            "step_size": self.step_size.tolist(),
            "seconds": self.seconds,
            "ess_per_second": self.ess_per_second,
            "noise": self.noise,
            "chains": int(self.draws.shape[0]),
            "draws": int(self.draws.shape[1]),
            "parallel_chains": self.parallel_chains,
        }


@dataclasses.dataclass(frozen=True)
class PosteriorPredictive:
    """The traces under the posterior (`Posterior.predictive`), per experiment (lists,
    as `CalibrationResult.times`), each signal by name:

    - `experiments`: their names; `times (n,)`, `measured (n,)` (NaN where not sampled);
    - `model (3, n)`: the model's signal over the posterior's draws, its 2.5, 50 and
      97.5 % points (where the model itself may lie);
    - `observed (2, n)`: the 2.5 and 97.5 % points of a repeated firing's samples (the
      model at each draw plus the likelihood's noise, Gaussian of its σ);
    - `coverage`: the share of the measured samples inside `observed` (near 0.95 where
      the model and its noise explain the traces), every sample counted (those the
      likelihood leaves out too), the noise Gaussian whatever the fit's loss;
    - `draws`: the draws solved; `failed`: those whose solve failed (left out).
    """

    experiments: list[str]
    times: list[np.ndarray]
    measured: list[dict[str, np.ndarray]]
    model: list[dict[str, np.ndarray]]
    observed: list[dict[str, np.ndarray]]
    coverage: list[dict[str, float]]
    draws: int
    failed: int

    def to_json(self) -> dict[str, Any]:
        """The coverage and counts (the bands are `posterior_predictive.png`'s)."""
        return {"coverage": self.coverage, "draws": self.draws, "failed": self.failed}


def _predictive(fit: CalibrationResult, noise, signals, failed: int, seed: int):
    """`PosteriorPredictive` from the model's `signals` by name `(N, E, n)` at N draws
    that solved, on the fit's traces, with the likelihood's `noise` (`Posterior.noise`)."""
    rng = np.random.default_rng(seed)
    model, observed, coverage = [], [], []
    for e, (times, measured) in enumerate(zip(fit.times, fit.measured, strict=True)):
        n = len(times)
        model_e, observed_e, coverage_e = {}, {}, {}
        for name, values in measured.items():
            drawn = signals[name][:, e, :n]
            model_e[name] = np.percentile(drawn, [2.5, 50.0, 97.5], axis=0)
            # A sampled noise at its posterior median (its spread is a few % on a trace).
            sigma = noise[e][name].get("sampled", {}).get("q50", noise[e][name]["sigma"])
            repeated = drawn + sigma * rng.standard_normal(drawn.shape)
            observed_e[name] = np.percentile(repeated, [2.5, 97.5], axis=0)
            sampled = np.isfinite(values)
            inside = (values >= observed_e[name][0]) & (values <= observed_e[name][1])
            coverage_e[name] = float(inside[sampled].mean())
        model.append(model_e)
        observed.append(observed_e)
        coverage.append(coverage_e)
    return PosteriorPredictive(
        [str(experiment["name"]) for experiment in fit.experiments],
        list(fit.times),
        list(fit.measured),
        model,
        observed,
        coverage,
        len(next(iter(signals.values()))),
        failed,
    )


def check_posterior_settings(
    calibration: Calibration,
    *,
    draws: int = DEFAULT_DRAWS,
    warmup: int = DEFAULT_WARMUP,
    chains: int = DEFAULT_CHAINS,
    seed: int = 0,
    priors: Mapping[str, Prior | str | Mapping[str, Any]] | None = None,
    dense_mass: bool = False,
    target_acceptance: float = 0.8,
    sample_noise: bool = False,
    noise_scale: Mapping[str, float] | None = None,
    parallel_chains: int | None = None,
) -> None:
    """Check `sample_posterior`'s settings for `calibration` (its arguments, as named
    there) without running anything: the command line calls it before the fit.

    **Raises:** `ParameterError` naming the setting and its valid range: draws or
    warm-up not an integer in [1, 100,000], chains not in [1, 64], a seed not in
    [0, 2⁶³), `dense_mass` not a boolean, a target acceptance outside [0.5, 1), a
    prior for a value not fitted, of an unknown kind, or with an sd ≤ 0; `sample_noise`
    not a boolean, or true with a robust loss; a `noise_scale` without it, for a signal
    not measured, or not a positive number; `parallel_chains` neither None nor in
    [1, 64]. Warns of a normal prior mostly outside its bounds.
    `ModuleNotFoundError` naming the `posterior` extra without blackjax or ArviZ.
    """
    _check_count("draws", draws, 1, MAX_DRAWS)
    _check_count("warmup", warmup, 1, MAX_DRAWS)
    _check_count("chains", chains, 1, MAX_CHAINS)
    if parallel_chains is not None:
        _check_count("parallel_chains", parallel_chains, 1, MAX_CHAINS)
    _check_count("seed", seed, 0, 2**63 - 1)
    if not isinstance(dense_mass, (bool, np.bool_)):
        raise ParameterError(f"dense_mass must be True or False, got {dense_mass!r}")
    number = isinstance(target_acceptance, (int, float, np.integer, np.floating))
    if isinstance(target_acceptance, bool) or not number or not 0.5 <= target_acceptance < 1.0:
        raise ParameterError(f"target_acceptance must be in [0.5, 1), got {target_acceptance!r}")
    layout = Layout.of(calibration)
    _priors(priors, layout)
    _noise_scales(calibration, layout, sample_noise, noise_scale)
    _require_extra()


def _noise_scales(calibration, layout: Layout, sample_noise, noise_scale) -> dict[str, float]:
    """The half-normal priors' scales by signal (`noise_scale`, checked), with
    `sample_noise` checked."""
    if not isinstance(sample_noise, (bool, np.bool_)):
        raise ParameterError(f"sample_noise must be True or False, got {sample_noise!r}")
    if sample_noise and calibration.loss != "linear":
        raise ParameterError(
            f"sample_noise needs the linear loss (a {calibration.loss} loss has no "
            "normalised likelihood in the noise); the calibration's loss is "
            f"{calibration.loss!r}"
        )
    if noise_scale is None:
        return {}
    if not sample_noise:
        raise ParameterError("noise_scale is the sampled noise's prior: give sample_noise=True")
    if not isinstance(noise_scale, Mapping):
        raise ParameterError(f"noise_scale: a mapping of signals to scales, got {noise_scale!r}")
    scales = {}
    for name, value in noise_scale.items():
        if name not in layout.signals:
            raise ParameterError(f"noise_scale for {name!r}: not a measured signal "
                                 f"(measured: {', '.join(layout.signals)})")  # fmt: skip
        number = isinstance(value, (int, float, np.integer, np.floating))
        if isinstance(value, bool) or not number or not 0 < float(value) < math.inf:
            raise ParameterError(f"noise_scale for {name!r} must be a number > 0, got {value!r}")
        scales[name] = float(value)
    return scales


def _noise(data, layout: Layout, scales: dict[str, float]) -> _Noise:
    """Every experiment's and signal's noise with samples in the likelihood, sampled
    under a half-normal of scale `scales[signal]`, or twice the fit's noise where not
    given (weak: its median is 1.35 times the fit's noise, its 95 % point 4.5 times)."""
    present = np.asarray(data.present)
    samples = present.sum(axis=-1).reshape(-1)
    slots = np.flatnonzero(samples > 0)
    sigma = np.asarray(data.sigma).reshape(-1)
    names = np.tile(np.asarray(layout.signals, dtype=object), present.shape[0])
    scale = np.array([scales.get(names[q], 2.0 * sigma[q]) / sigma[q] for q in slots])
    return _Noise(jnp.asarray(slots), jnp.asarray(samples[slots], dtype=float),
                  jnp.asarray(scale, dtype=float))  # fmt: skip


def sample_posterior(
    calibration: Calibration,
    *,
    fit: CalibrationResult | None = None,
    draws: int = DEFAULT_DRAWS,
    warmup: int = DEFAULT_WARMUP,
    chains: int = DEFAULT_CHAINS,
    seed: int = 0,
    priors: Mapping[str, Prior | str | Mapping[str, Any]] | None = None,
    dense_mass: bool = False,
    target_acceptance: float = 0.8,
    sample_noise: bool = False,
    noise_scale: Mapping[str, float] | None = None,
    parallel_chains: int | None = None,
    progress: bool | None = None,
) -> Posterior:
    """Sample the posterior of `calibration.fit`'s values given its experiments' traces,
    by NUTS on the fit's likelihood.

    **Arguments:**

    - `calibration`: the `Calibration`; `fit`: its least-squares result
      (`calibrate(calibration)` when not given), whose model check must pass, whose
      noise the likelihood uses and whose optimum and covariance start the chains.
    - `draws`, `warmup`: per chain (default 1000 each); `chains` (default 4); `seed`.
    - `priors`: by fitted label, a `Prior`, a kind's name or `{kind, mean, sd}`;
      uniform over the bounds where none is given.
    - `dense_mass`: adapt a dense mass matrix (for strongly correlated values) instead
      of a diagonal one; `target_acceptance`: the step size's target (raise it, e.g. to
      0.95, where there are divergences).
    - `sample_noise`: sample each experiment's and signal's noise too (σ, under a
      half-normal prior of scale `noise_scale[signal]`, or twice the fit's noise where
      not given), instead of holding the fit's fixed; the linear loss only.
    - `parallel_chains`: chains run at once, each on a thread of its own (None: on a CPU
      as many as the cores this process may use, else one per device; at most
      `chains`); the draws are the same whatever it is.
    - `progress`: a progress line on stderr (None: on a terminal).

    **Returns:** a `Posterior` (draws, summary beside the Laplace intervals,
    diagnostics, ArviZ `InferenceData`).

    **Raises:** `ParameterError` for bad settings or priors (before anything compiles);
    `ModelMisfitError` where the fit's model check fails (the model does not explain
    the traces: a posterior would describe the wrong model).
    """
    check_posterior_settings(
        calibration,
        draws=draws,
        warmup=warmup,
        chains=chains,
        seed=seed,
        priors=priors,
        dense_mass=dense_mass,
        target_acceptance=target_acceptance,
        sample_noise=sample_noise,
        noise_scale=noise_scale,
        parallel_chains=parallel_chains,
    )
    layout = Layout.of(calibration)
    scales = _noise_scales(calibration, layout, sample_noise, noise_scale)
    with warnings.catch_warnings():  # said once, by the check above
        warnings.simplefilter("ignore")
        prior_arrays, chosen = _priors(priors, layout)

    if fit is None:
        from .calibrate import calibrate

        fit = calibrate(calibration, progress=progress)
    if not fit.explains:
        failing = ", ".join(f"{c.signal} in {c.experiment}" for c in fit.check.failing)
        raise ModelMisfitError(
            f"the model does not explain the traces ({failing}): its posterior is not sampled"
        )
    bounds = {
        k: (float(lo), float(hi))
        for k, lo, hi in zip(layout.labels, layout.lower, layout.upper, strict=True)
    }
    if (
        list(fit.fitted) != list(layout.labels)
        or {k: tuple(v) for k, v in fit.bounds.items()} != bounds
    ):
        raise ParameterError(
            "fit: a result of another calibration (its fitted values or their bounds differ)"
        )

    data, static, left_out = _likelihood(calibration, fit, layout)
    block = max(1, math.ceil(draws / 10))
    settings = _Settings(static, bool(dense_mass), warmup, block, float(target_acceptance))
    whitening = _whitening(fit, layout, data, static, prior_arrays)
    if sample_noise:
        noise = _noise(data, layout, scales)
        prior_arrays = dataclasses.replace(prior_arrays, noise=noise)
        whitening = dataclasses.replace(whitening, noise_sd=1.0 / jnp.sqrt(2.0 * noise.samples))
    dimensions = len(layout.labels) + len(whitening.noise_sd)
    w0 = np.random.default_rng(seed).standard_normal((chains, dimensions))

    bar = Progress(
        "posterior", chains * (warmup + block * math.ceil(draws / block)), "transitions", progress
    )
    bar.update(0, "compiling")
    key = jax.random.key(seed)
    warm_keys, sample_keys = jax.random.split(jax.random.fold_in(key, 1), (2, chains))
    warm_settings, sample_settings = (
        settings._replace(block=0),
        settings._replace(dense=False, warmup=0, target_acceptance=0.0),
    )
    warm, compile_warm = compiled_ahead(
        _warm_up, warm_keys[0], jnp.asarray(w0[0]), data, prior_arrays, whitening, warm_settings
    )

    workers = min(chains, parallel_chains or default_workers(jax.devices()))
    at_once = f"{workers} chains at a time" if workers > 1 else "one chain at a time"
    lock, done, stopping = threading.Lock(), [0], threading.Event()

    def advance(transitions: int, note: str) -> None:
        if stopping.is_set():
            raise _Stopped
        with lock:  # the chains' threads share the line
            done[0] += transitions
            bar.update(done[0], note)

    def warm_chain(c: int):
        warmed = jax.block_until_ready(
            warm(warm_keys[c], jnp.asarray(w0[c]), data, prior_arrays, whitening, warm_settings)
        )
        advance(warmup, f"warm-up, {at_once}")
        return warmed

    bar.update(0, f"warm-up, {at_once}")
    clock = time.perf_counter()
    warmed = _each_chain(warm_chain, chains, workers, stopping)
    states, step_sizes, masses = zip(*warmed, strict=True)
    seconds_warmup = time.perf_counter() - clock

    sample, compile_sample = compiled_ahead(
        _sample_block,
        sample_keys[0],
        states[0],
        step_sizes[0],
        masses[0],
        data,
        prior_arrays,
        whitening,
        sample_settings,
    )

    def sample_chain(c: int):
        state, blocks = states[c], []
        for block_key in jax.random.split(sample_keys[c], math.ceil(draws / block)):
            state, out = sample(
                block_key,
                state,
                step_sizes[c],
                masses[c],
                data,
                prior_arrays,
                whitening,
                sample_settings,
            )
            blocks.append(jax.tree.map(np.asarray, out))
            advance(block, f"sampling, {at_once}")
        return jax.tree.map(lambda *a: np.concatenate(a)[:draws], *blocks)

    clock = time.perf_counter()
    chain_blocks = _each_chain(sample_chain, chains, workers, stopping)
    seconds_sampling = time.perf_counter() - clock
    bar.update(bar.total, "done", final=True)

    def signals(thetas):
        # One solve a draw, by the fit's own program (its sensitivities unused): a few
        # hundred draws cost a fraction of the sampling's gradients.
        solved = [evaluate_program(jnp.asarray(theta), data, static) for theta in thetas]
        stacked = np.stack([np.asarray(s.signals) for s in solved])
        codes = np.stack([np.asarray(s.codes) for s in solved])
        return {name: stacked[:, :, s] for s, name in enumerate(layout.signals)}, codes

    out = jax.tree.map(lambda *a: np.stack(a), *chain_blocks)  # (chains, draws, ...)
    theta = np.asarray(data.space.theta(whitening.z(jnp.asarray(out.position))))
    sigma = None  # the sampled noises (chains, draws, Q), in SI units
    if prior_arrays.noise is not None:
        fitted_sigma = np.asarray(data.sigma).reshape(-1)[np.asarray(prior_arrays.noise.slots)]
        sigma = fitted_sigma * np.exp(np.asarray(whitening.log_noise(jnp.asarray(out.position))))
    return _report(
        fit,
        layout,
        data,
        theta,
        out,
        chosen,
        np.asarray(step_sizes),
        {
            "compile": compile_warm + compile_sample,
            "warmup": seconds_warmup,
            "sampling": seconds_sampling,
        },
        left_out,
        signals,
        sigma,
        prior_arrays.noise,
        parallel_chains=workers,
    )


class PosteriorDensity(NamedTuple):
    """The log density `sample_posterior` samples (uniform priors, the noise held), in
    its chains' coordinates `w (P,)`, with its parts (`posterior_density`): so that a
    benchmark gives another sampler the very same density (`bench-calibration
    --posterior`)."""

    layout: Layout
    data: Any
    priors: _Priors
    whitening: _Whitening
    static: FitSettings

    def log_density(self, w, gradient: bool = True):
        """The log density at `w (P,)` (`gradient`: differentiable by the solve's
        sensitivities; without, one solve of the state alone)."""
        return _log_density(w, self.data, self.priors, self.whitening, self.static, gradient)

    def theta(self, w):
        """`w (..., P)` → the values `θ (..., P)` (SI units)."""
        return self.data.space.theta(self.whitening.z(w))

    def nuts_transitions(self, key, state, step_size, inverse_mass, transitions: int):
        """`transitions` NUTS transitions from `state` (`_sample_block`, as
        `sample_posterior` runs them): the last state and the transitions' `_Block`."""
        settings = _Settings(self.static, False, 0, transitions, 0.0)
        return _sample_block(key, state, step_size, inverse_mass, self.data, self.priors,
                             self.whitening, settings)  # fmt: skip


def posterior_density(calibration: Calibration, fit: CalibrationResult) -> PosteriorDensity:
    """The `PosteriorDensity` `sample_posterior(calibration, fit=fit)` samples."""
    layout = Layout.of(calibration)
    priors, _ = _priors(None, layout)
    data, static, _ = _likelihood(calibration, fit, layout)
    return PosteriorDensity(layout, data, priors, _whitening(fit, layout, data, static, priors),
                            static)  # fmt: skip


def _likelihood(calibration: Calibration, fit: CalibrationResult, layout: Layout):
    """The likelihood's data (the traces, under the noise the fit used, off the jumps:
    `_off_the_jumps`), the settings of its program, and how many samples it leaves out."""
    data = prepare(calibration, calibration.experiments, layout)
    sigma = np.array(data.sigma)
    for e, noise in enumerate(fit.sigma):
        for s, name in enumerate(layout.signals):
            if name in noise:
                sigma[e, s] = noise[name]
    data = eqx.tree_at(lambda d: d.sigma, data, jnp.asarray(sigma))
    static = FitSettings(
        layout.wrt, layout.signals, calibration.loss, calibration.f_scale, 1, estimate_noise=False
    )
    data, left_out = _off_the_jumps(data, static, fit, layout)
    return data, static, left_out


def _off_the_jumps(data, static, fit: CalibrationResult, layout: Layout):
    """`data` without the samples either side of a jump in the model's signal at the
    optimum (`jumps_at`, as the fit leaves out), and those the fit
    found on an event their sampling does not resolve (`unresolved_samples`, as
    `CalibrationResult.unresolved`), and how many were left out: the likelihood is a
    cliff there, which no gradient sampler crosses. The fit's standard errors leave
    the unresolved ones out for the same reason."""
    evaluation = evaluate_program(jnp.asarray([fit.values[k] for k in layout.labels]), data,
                                  static)  # fmt: skip
    present = np.array(data.present)
    signals, rates = np.asarray(evaluation.signals), np.asarray(evaluation.rates)
    times, sigma = np.asarray(data.times), np.asarray(data.sigma)
    before = int(present.sum())
    present &= ~np.asarray(jumps_at(evaluation, data))
    # The fit's own test, on the same evaluation (so no lookup by name or time).
    present &= ~unresolved_samples(times, signals, rates, np.asarray(data.present), sigma)
    left_out = before - int(present.sum())
    return eqx.tree_at(lambda d: d.present, data, jnp.asarray(present)), left_out


def _whitening(fit: CalibrationResult, layout: Layout, data, static, priors: _Priors):
    """The chains' coordinates (`_Whitening`): centred on the least-squares optimum
    (kept a standard error, at most 2 % of the box, inside its bounds), scaled by the
    posterior's curvature there in `y`: the data's Gauss–Newton `JᵀJ` (noise units)
    plus the priors' (a uniform's variance standing in for its curvature). Where the
    data determine every value this is the Laplace covariance; along a direction they do
    not (friction at one elevation: a ridge), the priors bound it, so the chains are
    scaled along the ridge and across it alike."""
    labels = list(layout.labels)
    value = np.array([fit.values[k] for k in labels])
    # Kept inside the bounds by its standard error in z (at most 2 % of the box), so
    # that the centre is finite and, near a bound, still where the posterior is.
    z_raw = np.clip(np.asarray(data.space.z(value), dtype=float), 1e-12, 1.0 - 1e-12)
    slope_raw = np.asarray(jax.jvp(data.space.theta, (jnp.asarray(z_raw),),
                                   (jnp.ones_like(jnp.asarray(z_raw)),))[1])  # fmt: skip
    stderr = np.array([fit.fitted[k].stderr or np.nan for k in labels], dtype=float)
    sd_z = np.abs(stderr / slope_raw)
    margin = np.where(np.isfinite(sd_z) & (sd_z > 0), np.minimum(sd_z, 0.02), 0.02)
    z_hat = np.clip(z_raw, margin, 1.0 - margin)
    theta_hat, slope = jax.jvp(
        data.space.theta, (jnp.asarray(z_hat),), (jnp.ones_like(jnp.asarray(z_hat)),)
    )
    y_hat = _box_inverse(z_hat)
    # dθ/dy = dθ/dz · dz/dy; dz/dy the bend's where the value's posterior is within a
    # bend (its standard error in z under the bend's width), else the inside's, 1: a
    # ridge runs across the box, and a frame at its slope in a bend is tilted against
    # it (measured, by 2 % at 4 widths from μ's bound: 40 times the ridge's width).
    dz_dy = np.exp(np.asarray(_log_box_slope(jnp.asarray(y_hat)))) * -np.expm1(-1.0 / EDGE)
    dz_dy = np.where(np.isfinite(sd_z) & (sd_z < EDGE), dz_dy, 1.0)
    dtheta_dy = np.asarray(slope) * dz_dy
    jacobian = np.asarray(evaluate_program(theta_hat, data, static).jacobian)
    jacobian = jacobian.reshape(-1, len(labels)) * dtheta_dy
    # −d²/dy² of a normal (lognormal) prior, (dθ/dy)² / sd² (/ θ² s²); a uniform's has
    # none, and its variance (1/12 of the box in z) stands in, so that along a
    # direction the data do not determine (friction at one elevation: a ridge) the
    # chains are scaled as the prior is. The transform's own curvature is left out:
    # it is local to a bound's bend, and would tilt a ridge's frame where the centre
    # lies in one (measured: the ridge then runs diagonally across w).
    theta = np.asarray(theta_hat)
    kind, scale = np.asarray(priors.kind), np.asarray(priors.scale)
    lognormal_theta = np.where(kind == 2, theta, 1.0)  # positive there (the bounds' check)
    prior_curvature = np.where(kind == 1, 1.0 / scale**2,
                               np.where(kind == 2, 1.0 / (lognormal_theta * scale) ** 2,
                                        0.0))  # fmt: skip
    precision = jacobian.T @ jacobian + np.diag(
        prior_curvature * dtheta_dy**2 + np.where(kind == 0, 12.0 * dz_dy**2, 0.0)
    )
    covariance = np.linalg.inv(precision)
    covariance = 0.5 * (covariance + covariance.T)
    sd_y = np.sqrt(np.diag(covariance))
    # Near-singular to rounding: nudge the diagonal until it factors.
    for jitter in (0.0, 1e-10, 1e-8, 1e-6, 1e-4):
        try:
            factor = np.linalg.cholesky(covariance + jitter * np.diag(sd_y**2))
            break
        except np.linalg.LinAlgError:
            continue
    else:
        factor = np.diag(sd_y)
    return _Whitening(jnp.asarray(y_hat), jnp.asarray(factor))


def _report(
    fit,
    layout,
    data,
    theta,
    out: _Block,
    priors,
    step_sizes,
    seconds,
    left_out,
    signals,
    sigma=None,
    noise: _Noise | None = None,
    parallel_chains: int = 1,
) -> Posterior:
    """The `Posterior` of the draws `theta (C, D, P)` (and of the sampled noises `sigma
    (C, D, Q)`, `noise` theirs): ArviZ's diagnostics, the summary beside the Laplace
    intervals, the honesty gates."""
    import arviz as az

    labels = tuple(layout.labels)
    observed = {}
    for e, experiment in enumerate(fit.measured):
        for name, values in experiment.items():
            observed[f"{name} in experiment {e}"] = np.asarray(values)
    # ArviZ logs a warning for fewer than 2 chains; `converged` and the R-hat's absence
    # say what that means here.
    quiet = logging.getLogger("arviz")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    noise_labels = []
    if noise is not None:
        slots = np.asarray(noise.slots)
        S = len(layout.signals)
        noise_labels = [f"noise of {layout.signals[q % S]} in experiment {q // S}" for q in slots]
    try:
        idata, rhat, ess_bulk, ess_tail = _diagnosed(
            az, theta, out, observed, labels, sigma, noise_labels
        )
    finally:
        quiet.setLevel(level)
    flat = theta.reshape(-1, theta.shape[-1])
    flat_all = flat if sigma is None else np.hstack([flat, sigma.reshape(-1, sigma.shape[-1])])
    quantiles = np.quantile(flat_all, [0.025, 0.5, 0.975], axis=0)
    chains = theta.shape[0]
    summary, problems, disagreements = {}, [], []

    def statistics(i):
        return {
            "mean": float(flat_all[:, i].mean()),
            "sd": float(flat_all[:, i].std(ddof=1)),
            "q2.5": float(quantiles[0, i]),
            "q50": float(quantiles[1, i]),
            "q97.5": float(quantiles[2, i]),
            "r_hat": float(rhat[i]) if chains > 1 else None,
            "ess_bulk": float(ess_bulk[i]),
            "ess_tail": float(ess_tail[i]),
        }

    for i, label in enumerate((*labels, *noise_labels)):
        if i >= len(labels):  # a sampled noise: no Laplace interval beside it
            _gate(problems, label, statistics(i), chains)
            continue
        fitted = fit.fitted[label]
        row = statistics(i) | {
            "value": fitted.value,
            "stderr": fitted.stderr,
            "ci95": None if fitted.ci95 is None else list(fitted.ci95),
        }
        row["disagree"] = _disagree(row)
        summary[label] = row
        if row["disagree"]:
            disagreements.append(_disagreement_words(label, row))
        _gate(problems, label, row, chains)
    if chains == 1:
        problems.append("one chain: whether it has converged cannot be checked (split R-hat "
                        "needs 2 chains or more)")  # fmt: skip
    divergences = int(np.sum(out.diverging))
    if divergences:
        problems.append(
            f"{divergences} divergent transition{'s' if divergences > 1 else ''} "
            "(a higher target acceptance, e.g. 0.95, or a dense mass matrix)"
        )
    least_ess = float(np.min(ess_bulk))
    prior_sd = [_prior_sd(priors[label], *fit.bounds[label]) for label in labels]
    unseparated = _unseparated(flat, labels, np.asarray(prior_sd))
    noises = [
        {name: {"sigma": float(data.sigma[e, s]), "given": bool(data.sigma_given[e, s])}
         for s, name in enumerate(layout.signals) if name in fit.sigma[e]}
        for e in range(len(fit.sigma))
    ]  # fmt: skip
    if noise is not None:
        S, sigma_scale = len(layout.signals), np.asarray(data.sigma).reshape(-1)
        for j, q in enumerate(np.asarray(noise.slots)):
            e, name = int(q) // S, layout.signals[int(q) % S]
            noises[e][name]["sampled"] = statistics(len(labels) + j) | {
                "half_normal_scale": float(noise.scale[j] * sigma_scale[q])
            }
    return Posterior(
        labels=labels,
        draws=theta,
        summary=summary,
        converged=not problems,
        problems=problems,
        disagreements=disagreements,
        divergences=divergences,
        priors=priors,
        step_size=step_sizes,
        seconds=seconds,
        ess_per_second=least_ess / max(seconds["sampling"], 1e-9),
        inference_data=idata,
        fit=fit,
        noise=noises,
        unseparated=unseparated,
        left_out=left_out,
        parallel_chains=parallel_chains,
        _signals=signals,
    )


def _gate(problems: list[str], label: str, row: dict, chains: int) -> None:
    """The honesty gates on one value's draws (`row`: its statistics), each failure
    added to `problems` in words naming it and what to try."""
    if chains > 1 and not row["r_hat"] <= MAX_RHAT:
        problems.append(
            f"{label}: split R-hat {row['r_hat']:.3f} over {MAX_RHAT} (the chains "
            "disagree: a longer warm-up, or more draws)"
        )
    if not row["ess_bulk"] >= MIN_ESS:
        problems.append(
            f"{label}: bulk ESS {row['ess_bulk']:.0f} under {MIN_ESS} (more draws, "
            "or a dense mass matrix for correlated values)"
        )


def _prior_sd(prior: Prior, lower: float, upper: float) -> float:
    """A prior's standard deviation (a uniform's over the bounds; a normal's or
    lognormal's own, within the bounds' uniform's)."""
    uniform = (upper - lower) / math.sqrt(12.0)
    return uniform if prior.kind == "uniform" else min(float(prior.sd), uniform)  # pyright: ignore[reportArgumentType]


def _unseparated(flat: np.ndarray, labels, prior_sd: np.ndarray) -> list[str]:
    """The pairs of values the data do not separate, in words: draws `flat (N, P)`
    correlated beyond ±`UNSEPARATED`, each value still spread over more than half its
    prior's sd `prior_sd (P,)` (a pair both well determined may correlate as strongly:
    the paper absorber's k and c_out, −0.985)."""
    if len(labels) < 2:
        return []
    correlation = np.corrcoef(flat, rowvar=False)
    loose = flat.std(axis=0, ddof=1) > 0.5 * prior_sd
    words = []
    for i, j in zip(*np.triu_indices(len(labels), 1), strict=True):
        if abs(correlation[i, j]) > UNSEPARATED and loose[i] and loose[j]:
            words.append(
                f"{labels[i]} and {labels[j]}: correlation {correlation[i, j]:+.3f} in the "
                "draws, each spread over most of its prior: the data do not separate them "
                "(only a combination of the two is determined), and each one's interval is "
                "as wide as the priors let the ridge run"
            )
    return words


def _diagnosed(az, theta, out: _Block, observed, labels, sigma=None, noise_labels=()):
    """The draws as ArviZ's `InferenceData`, and its rank-normalised split R̂, bulk and
    tail ESS per value `(P,)` each, followed by the sampled noises' `(Q,)` where
    `sigma (C, D, Q)` is given."""
    posterior = {"theta": theta}
    coords: dict[str, list[str]] = {"parameter": list(labels)}
    dims = {"theta": ["parameter"]}
    if sigma is not None:
        posterior["sigma"] = sigma
        coords["noise"] = list(noise_labels)
        dims["sigma"] = ["noise"]
    idata = az.from_dict(
        posterior=posterior,
        sample_stats={
            "diverging": out.diverging,
            "lp": out.log_density,
            "n_steps": out.steps,
            "energy": out.energy,
            "acceptance_rate": out.acceptance,
        },
        observed_data=observed,
        coords=coords,
        dims=dims,
    )
    diagnostics: Any = {m: az.ess(idata, method=m) for m in ("bulk", "tail")}
    diagnostics["rhat"] = az.rhat(idata, method="rank")
    rhat, ess_bulk, ess_tail = (
        np.concatenate([np.asarray(diagnostics[m][v]) for v in posterior])
        for m in ("rhat", "bulk", "tail")
    )
    return idata, rhat, ess_bulk, ess_tail


def _disagree(row) -> bool:
    """The posterior's 95 % interval and the Laplace one differ at either end by more
    than `DISAGREEMENT` of the Laplace interval's width (or the fit gives none)."""
    if row["ci95"] is None:
        return True
    low, high = row["ci95"]
    width = max(high - low, 1e-300)
    apart = max(abs(row["q2.5"] - low), abs(row["q97.5"] - high))
    return apart > DISAGREEMENT * width


def _disagreement_words(label, row) -> str:
    if row["ci95"] is None:
        return (
            f"{label}: the fit gives no interval (the data do not confine it); the "
            f"posterior's 95 % interval is [{row['q2.5']:.6g}, {row['q97.5']:.6g}]"
        )
    low, high = row["ci95"]
    return (
        f"{label}: the Laplace interval [{low:.6g}, {high:.6g}] misstates the posterior's "
        f"[{row['q2.5']:.6g}, {row['q97.5']:.6g}]"
    )
