"""recoil-jax: differentiable recoil-system models (barrel + impact absorber) in JAX.

The engine lives in the private modules of this package; this file is its public API.
The applications built on it (command line, studies, benchmarks, figures) live in
`recoil_jax.apps`, which imports from here and never the other way round. The model is
specified in `docs/model.md`.
"""

import importlib.metadata

import jax as _jax

# Physics needs float64: contact penetrations are ~1e-3 m against stiffness ~1e8.
# (Set before the submodules import, hence E402 below.)
_jax.config.update("jax_enable_x64", True)

from ._cache import (
    enable_compilation_cache as enable_compilation_cache,
    live_programs as live_programs,
    set_max_programs as set_max_programs,
    structure_jit as structure_jit,
    use_avx2_codegen as use_avx2_codegen,
)
from ._design import differentiable_peaks as differentiable_peaks
from ._gradients import (
    DESIGN_PARAMETERS as DESIGN_PARAMETERS,
    GRADIENT_OPTIONS as GRADIENT_OPTIONS,
    MetricSeries as MetricSeries,
    SmoothMax as SmoothMax,
    parameter_scale as parameter_scale,
    peak_gradients as peak_gradients,
    peak_jacobian as peak_jacobian,
)
from ._local import (
    SLSQP as SLSQP,
    EpigraphMinimax as EpigraphMinimax,
    LocalEvaluation as LocalEvaluation,
    LocalMethod as LocalMethod,
    LocalRun as LocalRun,
    OptaxLocal as OptaxLocal,
    TrustRegionLP as TrustRegionLP,
)
from ._metrics import (
    METRICS as METRICS,
    PEAK_FIELDS as PEAK_FIELDS,
    Metric as Metric,
    PeakGradients as PeakGradients,
    Peaks as Peaks,
    gradient_key as gradient_key,
)
from ._model import Forces as Forces
from ._optimise import (
    Stopping as Stopping,
    default_optimiser as default_optimiser,
    optimise as optimise,
)
from ._paper import (
    case_params as case_params,
    paper_cases as paper_cases,
)
from ._params import (
    PARAMETERS as PARAMETERS,
    Absorber as Absorber,
    Barrel as Barrel,
    Buffer as Buffer,
    Contact as Contact,
    ForceTable as ForceTable,
    Load as Load,
    Parameter as Parameter,
    ParameterError as ParameterError,
    RecoilParams as RecoilParams,
    Recuperator as Recuperator,
    Smoothing as Smoothing,
    SolverOptions as SolverOptions,
    end_time as end_time,
    params_from_values as params_from_values,
    params_to_values as params_to_values,
    values_of as values_of,
    with_values as with_values,
)
from ._parts import AugmentedLagrangian as AugmentedLagrangian
from ._problem import (
    FEASIBILITY_TOLERANCE as FEASIBILITY_TOLERANCE,
    Agreement as Agreement,
    Constraint as Constraint,
    DesignEvaluation as DesignEvaluation,
    DesignProblem as DesignProblem,
    Objective as Objective,
    closest_miss as closest_miss,
    constraint_report as constraint_report,
    evaluate_design as evaluate_design,
    feasible as feasible,
    metric_violations as metric_violations,
)
from ._reference import reference_peaks as reference_peaks
from ._result import (
    OptimiseResult as OptimiseResult,
    RunRecord as RunRecord,
)
from ._search import (
    BasinHopping as BasinHopping,
    SobolStarts as SobolStarts,
    default_local as default_local,
    minimise as minimise,
    search as search,
)
from ._solve import (
    History as History,
    peak_metrics as peak_metrics,
    peaks as peaks,
    simulate as simulate,
)
from ._space import (
    SearchSpace as SearchSpace,
    log_coordinates as log_coordinates,
)
from ._status import (
    SolveError as SolveError,
    Status as Status,
    failure_message as failure_message,
    status_codes as status_codes,
    status_messages as status_messages,
    status_table as status_table,
)
from ._store import (
    CampaignProgress as CampaignProgress,
    campaign_progress as campaign_progress,
)
from ._sweep import (
    StoredSweep as StoredSweep,
    SweepResult as SweepResult,
    batch_params as batch_params,
    default_workers as default_workers,
    grid as grid,
    load_sweep as load_sweep,
    shard_batch as shard_batch,
    sweep as sweep,
    sweep_grid as sweep_grid,
    sweep_to_store as sweep_to_store,
    with_table as with_table,
)

__version__ = importlib.metadata.version("recoil-jax")
