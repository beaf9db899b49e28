"""recoil-jax: differentiable recoil-system models (barrel + impact absorber) in JAX."""

import jax as _jax

# Physics needs float64: contact penetrations are ~1e-3 m against stiffness ~1e8.
# (Set before the submodules import, hence E402 below.)
_jax.config.update("jax_enable_x64", True)

from ._design import (
    METRICS as METRICS,
    differentiable_peaks as differentiable_peaks,
)
from ._gradients import (
    DESIGN_PARAMETERS as DESIGN_PARAMETERS,
    GRADIENT_OPTIONS as GRADIENT_OPTIONS,
    PeakGradients as PeakGradients,
    SmoothMax as SmoothMax,
    parameter_scale as parameter_scale,
    peak_gradients as peak_gradients,
    peak_jacobian as peak_jacobian,
)
from ._model import (
    RECOIL_TERM as RECOIL_TERM,
    Forces as Forces,
    characteristic_penetration as characteristic_penetration,
    contact_width as contact_width,
    forces as forces,
    future_metric_bounds as future_metric_bounds,
    initial_state as initial_state,
    model_args as model_args,
    positive_power as positive_power,
    smooth_relu as smooth_relu,
    vector_field as vector_field,
)
from ._optimise import (
    Constraint as Constraint,
    DesignProblem as DesignProblem,
    Objective as Objective,
    OptimiseResult as OptimiseResult,
    constraint_report as constraint_report,
    default_optimiser as default_optimiser,
    evaluate_design as evaluate_design,
    optimise as optimise,
)
from ._paper import (
    case_params as case_params,
    paper_cases as paper_cases,
)
from ._params import (
    PARAMETER_NAMES as PARAMETER_NAMES,
    Absorber as Absorber,
    Barrel as Barrel,
    Contact as Contact,
    ParameterError as ParameterError,
    RecoilParams as RecoilParams,
    Smoothing as Smoothing,
    SolverOptions as SolverOptions,
    params_from_values as params_from_values,
    params_to_values as params_to_values,
)
from ._solve import (
    PEAK_KEYS as PEAK_KEYS,
    History as History,
    Peaks as Peaks,
    SolveError as SolveError,
    Status as Status,
    hermite_max as hermite_max,
    peak_metrics as peak_metrics,
    peaks as peaks,
    simulate as simulate,
)
from ._sweep import (
    SweepResult as SweepResult,
    batch_params as batch_params,
    grid as grid,
    sweep as sweep,
    sweep_grid as sweep_grid,
)

__version__ = "0.1.0"
