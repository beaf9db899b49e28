"""recoil-jax: differentiable recoil-system models (barrel + impact absorber) in JAX.

The engine lives in the private modules of this package; this file is its public API.
The applications built on it (command line, studies, benchmarks, figures) live in
`recoil_jax.apps`, which imports from here and never the other way round. The model is
specified in `docs/model.md`.
"""

import jax as _jax

# Physics needs float64: contact penetrations are ~1e-3 m against stiffness ~1e8.
# (Set before the submodules import, hence E402 below.)
_jax.config.update("jax_enable_x64", True)

# The lower-level interfaces (extension parts, batches, codes): `recoil_jax.extend`.
from . import extend as extend
from ._calibration.calibrate import calibrate as calibrate
from ._calibration.posterior import sample_posterior as sample_posterior
from ._calibration.predict import predict as predict
from ._calibration.result import CalibrationResult as CalibrationResult
from ._calibration.spec import Calibration as Calibration
from ._calibration.traces import read_trace as read_trace
from ._campaigns.progress import (
    CampaignProgress as CampaignProgress,
    campaign_progress as campaign_progress,
)
from ._design.lagrangian import AugmentedLagrangian as AugmentedLagrangian
from ._design.local import (
    SLSQP as SLSQP,
    EpigraphMinimax as EpigraphMinimax,
    OptaxLocal as OptaxLocal,
    TrustRegionLP as TrustRegionLP,
)
from ._design.optimise import (
    Stopping as Stopping,
    default_optimiser as default_optimiser,
    optimise as optimise,
)
from ._design.problem import (
    Agreement as Agreement,
    Condition as Condition,
    Constraint as Constraint,
    DesignProblem as DesignProblem,
    Objective as Objective,
    closest_miss as closest_miss,
    constraint_report as constraint_report,
    metric_violations as metric_violations,
)
from ._design.result import OptimiseResult as OptimiseResult
from ._design.search import (
    BasinHopping as BasinHopping,
    SobolStarts as SobolStarts,
    minimise as minimise,
    search as search,
)
from ._global_sensitivity.analysis import (
    DGSM as DGSM,
    MorrisEffects as MorrisEffects,
    SensitivityResult as SensitivityResult,
    SobolIndices as SobolIndices,
    sensitivity as sensitivity,
)
from ._model.derivatives import (
    DESIGN_PARAMETERS as DESIGN_PARAMETERS,
    GRADIENT_OPTIONS as GRADIENT_OPTIONS,
    parameter_scale as parameter_scale,
    peak_gradients as peak_gradients,
    peak_jacobian as peak_jacobian,
)
from ._model.differentiable import differentiable_peaks as differentiable_peaks
from ._model.feasibility import (
    FEASIBILITY_TOLERANCE as FEASIBILITY_TOLERANCE,
    feasible as feasible,
)
from ._model.hazards import peaks_hazards as peaks_hazards
from ._model.metrics import (
    METRICS as METRICS,
    PeakGradients as PeakGradients,
    Peaks as Peaks,
)
from ._model.paper import (
    case_params as case_params,
    paper_cases as paper_cases,
)
from ._model.parameter_table import PARAMETERS as PARAMETERS
from ._model.params import (
    Absorber as Absorber,
    Barrel as Barrel,
    BatteryStop as BatteryStop,
    Buffer as Buffer,
    Contact as Contact,
    CounterRecoilBuffer as CounterRecoilBuffer,
    ForceTable as ForceTable,
    Load as Load,
    Mount as Mount,
    Rails as Rails,
    RecoilParams as RecoilParams,
    Recuperator as Recuperator,
    params_from_values as params_from_values,
    params_to_values as params_to_values,
    values_of as values_of,
    with_values as with_values,
)
from ._model.programs import (
    enable_compilation_cache as enable_compilation_cache,
    use_avx2_codegen as use_avx2_codegen,
)
from ._model.reference import reference_peaks as reference_peaks
from ._model.registry import ParameterError as ParameterError
from ._model.settings import Smoothing as Smoothing, SolverOptions as SolverOptions
from ._model.smooth_max import MetricSeries as MetricSeries, SmoothMax as SmoothMax
from ._model.solve import (
    History as History,
    peak_metrics as peak_metrics,
    peaks as peaks,
    simulate as simulate,
)
from ._model.status import (
    SolveError as SolveError,
    Status as Status,
    failure_message as failure_message,
)
from ._planning.plan import FiringPlan as FiringPlan, plan_firings as plan_firings
from ._planning.problem import PlanProblem as PlanProblem, Sensor as Sensor
from ._sweeps.batches import with_table as with_table
from ._sweeps.grid import grid as grid
from ._sweeps.result import SweepResult as SweepResult, load_sweep as load_sweep
from ._sweeps.sweep import (
    sweep as sweep,
    sweep_grid as sweep_grid,
    sweep_to_store as sweep_to_store,
)
from ._version import __version__ as __version__

__all__ = [  # noqa: RUF022 (grouped by topic, as the docs)
    # Designs and parameters
    "PARAMETERS", "Absorber", "Barrel", "Buffer", "Contact", "ForceTable", "Load",
    "ParameterError", "RecoilParams", "Recuperator", "Rails", "BatteryStop",
    "CounterRecoilBuffer", "Mount", "Smoothing", "SolverOptions",
    "params_from_values", "params_to_values", "values_of", "with_values", "with_table",
    "case_params", "paper_cases",
    # Solving
    "History", "Peaks", "METRICS", "peaks_hazards", "SolveError", "Status", "failure_message",
    "peak_metrics", "peaks", "simulate", "reference_peaks", "enable_compilation_cache",
    "use_avx2_codegen",
    # Gradients
    "DESIGN_PARAMETERS", "GRADIENT_OPTIONS", "MetricSeries", "PeakGradients", "SmoothMax",
    "differentiable_peaks", "parameter_scale", "peak_gradients", "peak_jacobian",
    # Sweeps and campaigns
    "SweepResult", "grid", "load_sweep", "sweep", "sweep_grid", "sweep_to_store",
    "CampaignProgress", "campaign_progress",
    # Design problems and optimisers
    "FEASIBILITY_TOLERANCE", "Agreement", "Condition", "Constraint", "DesignProblem", "Objective",
    "OptimiseResult", "closest_miss", "constraint_report", "feasible", "metric_violations",
    "search", "minimise", "SobolStarts", "BasinHopping", "SLSQP", "EpigraphMinimax",
    "TrustRegionLP", "OptaxLocal", "optimise", "default_optimiser", "AugmentedLagrangian",
    "Stopping",
    # Calibration
    "Calibration", "CalibrationResult", "calibrate", "read_trace", "predict",
    "sample_posterior",
    # Global sensitivity
    "sensitivity", "SensitivityResult", "SobolIndices", "MorrisEffects", "DGSM",
    # Planning a firing test
    "PlanProblem", "Sensor", "plan_firings", "FiringPlan",
]  # fmt: skip
