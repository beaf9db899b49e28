"""The engine's lower-level interfaces, for building on it (as `jax.extend` is JAX's):
what a new local method, global phase or evaluator is written against, and the batching,
compiled-program and status-code helpers the applications use. `import recoil_jax` does
not need them; `docs/developers.md` shows how to plug a part in.

**Optimisers' parts**

- `LocalMethod` (abstract; subclass it, declare `maxiter` and write `run`),
  `MinimaxMethod` (abstract: a method whose last level is the minimax, with its stall
  watch and local maxima), `LocalRun` (one run's state:
  `evaluate`, `start_level`, `slsqp`, `level_done`), `LocalEvaluation` (what an
  evaluator gives a local run), `run_local` (one run, recorded), `RunRecord` (one run's
  outcome, the same for every method), `default_local` (what `search` picks);
  `GlobalPhase` (abstract; `SobolStarts` is one): the samples, and the starts chosen.
- `BatchEvaluator` / `BatchEvaluation` (points of the box through one sweep),
  `GradientEvaluator` (one sensitivity solve), `StoredEvaluator` (either, through a
  study's store), `MinimaxWindow` and `MinimaxEvaluator` (a peak over time as a
  minimax), `minimax_metric`.
- `SearchSpace` and `log_coordinates` (the normalised box), `evaluate_design` and
  `DesignEvaluation` (one design as a differentiable function of its tuned values).

**Programs, batches, codes and names**

- `structure_jit`, `live_programs`, `set_max_programs`: programs per structure of the
  arguments, in a bounded cache (`docs/campaigns.md`).
- `batch_params`, `shard_batch`, `default_workers`: designs as a batched pytree, split
  over devices, and the sweep's default worker count; `Grid`: a grid whose designs
  `sweep` and `sweep_to_store` make a chunk at a time (a streamed grid's memory does not
  grow with it).
- `status_codes`, `status_messages`, `status_table`, `OK_CODE`: a `Status` item's
  integer codes and messages, every code with its message, and the code of success.
- `PEAK_FIELDS`, `gradient_key`, `Metric`, `Parameter`: the keys of the files and the
  registries' entries; `GROUPS`, `Group`: the parameters' groups, each a part of the
  gun (its title, whether it is the paper's, hardware or the firing envelope's);
  `T1_LIMITS`: the end time's valid and documented range; `end_time`: a design's end
  time (refusing a load that does not fit); `Forces`: the model's forces at a state;
  `Part`, `Force`, `float_leaf`, `forget_part`: the forces family, to add a part or a
  force of one's own (`docs/developers.md`, *Adding a force*);
  `StoredSweep`: a sweep read back from its store; `worst_case`: each metric's worst
  over a scatter of designs; `read_text`: a text file, or one line saying why not
  (`MAX_TEXT_BYTES`: the most it reads); `written`: a file written whole or not at all,
  a failure naming it;
  `check_memory`: refuse a count whose arrays would take over half the free memory;
  `check_integer`: an integer setting (a count, a seed) in its range, or the one refusal.
- `HAZARDS`, `Hazard`, `design_hazards`, `hazard_flags`: the hazards every report names
  unasked (`docs/model.md`), their registry, one design's from its values and metrics,
  and a batch's as boolean arrays (`rj.peaks_hazards` takes a solved design).

**Calibration's parts**

- `Experiment` (a trace and what is known of its firing), `Trace`, `SIGNALS` (the
  measurable signals, with units), `T_SHIFT` (the trigger delay's range), `LOSSES`;
  `Fitted` (one fitted value with its uncertainty); `ModelCheck` and `SignalCheck` (the
  test of a fit's residuals against each trace's own noise, `trace_noise`, and for
  whiteness: does the model explain the traces?); `validate` (score a fit on a trace
  it did not see); `fit_many` (many data sets of the same experiments, fitted as one
  batch); `signal_sensitivities` (the signals at chosen times with their exact
  derivatives); `FittedParameters` (a fit's hardware values with their covariance,
  from a result or its `result.json`) and `Prediction` (what `predict` gives);
  `Posterior`, `Prior` and `ModelMisfitError` (what `sample_posterior` gives, takes
  and refuses), `PosteriorPredictive` (the traces' bands under it),
  `check_posterior_settings` (its settings checked before a fit);
  `reference_history` (time histories by the independent hard-switch scipy solver: a
  synthetic firing test the library shares no code with); `Continuation` (the
  smoothing widths a fit starts from, narrowed to the calibration's; `calibrate`'s
  `DEFAULT_CONTINUATION`) and `DEFAULT_STARTS`.

**Test planning's parts**

- `PlanReport` (what one plan predicts: its firings, criterion, standard errors and
  what it leaves undetermined), `candidate_information` (`JᵀJ/σ²` of every candidate
  firing and signal from the exact sensitivities, in one program), `check_plan` (noisy
  tests of a plan fitted by the calibration, against the prediction) with `PlanCheck`
  and `check_tests_memory` (its traces against the free memory, refused before the work),
  and `plan_calibration` (the calibration of a plan's firings from their traces).

**Global sensitivity's parts**

- `SensitivityMethod` (abstract: how a method samples the box and analyses the outputs;
  `SobolIndices`, `MorrisEffects` and `DGSM` are three; `SENSITIVITY_METHODS` by name),
  `sensitivity_box` (the box of a design's ranges, absolute or relative, checked).
"""

from ._calibration.calibrate import DEFAULT_STARTS, fit_many, validate
from ._calibration.continuation import DEFAULT_CONTINUATION, Continuation
from ._calibration.model_check import ModelCheck, SignalCheck, trace_noise
from ._calibration.posterior import (
    ModelMisfitError,
    Posterior,
    PosteriorPredictive,
    Prior,
    check_posterior_settings,
)
from ._calibration.predict import FittedParameters, Prediction
from ._calibration.result import Fitted
from ._calibration.spec import LOSSES
from ._calibration.traces import T_SHIFT, Experiment, Trace
from ._design.evaluators import (
    BatchEvaluation,
    BatchEvaluator,
    GradientEvaluator,
    MinimaxEvaluator,
    MinimaxWindow,
    StoredEvaluator,
    minimax_metric,
)
from ._design.local import LocalEvaluation, LocalMethod, LocalRun, MinimaxMethod, run_local
from ._design.problem import (
    DesignEvaluation,
    evaluate_design,
)
from ._design.result import RunRecord
from ._design.search import GlobalPhase, default_local
from ._global_sensitivity.analysis import SENSITIVITY_METHODS, SensitivityMethod, sensitivity_box
from ._model.derivatives import SIGNALS, signal_sensitivities
from ._model.forces.family import Force, Part, forget_part
from ._model.forces.system import Forces
from ._model.hazards import HAZARDS, Hazard, design_hazards, hazard_flags
from ._model.metrics import PEAK_FIELDS, Metric, gradient_key, worst_case
from ._model.programs import live_programs, set_max_programs, structure_jit
from ._model.reference import reference_history
from ._model.registry import GROUPS, Group, Parameter, check_integer, float_leaf
from ._model.settings import T1_LIMITS, end_time
from ._model.status import OK_CODE, status_codes, status_messages, status_table
from ._model.text_files import MAX_TEXT_BYTES, read_text, written
from ._planning.check import PlanCheck, check_plan, check_tests_memory, plan_calibration
from ._planning.information import candidate_information
from ._planning.plan import PlanReport
from ._sweeps.batches import batch_params, shard_batch
from ._sweeps.grid import Grid
from ._sweeps.memory import check_memory, default_workers
from ._sweeps.result import StoredSweep
from ._sweeps.space import SearchSpace, log_coordinates

__all__ = [
    "DEFAULT_CONTINUATION",
    "DEFAULT_STARTS",
    "GROUPS",
    "HAZARDS",
    "LOSSES",
    "MAX_TEXT_BYTES",
    "OK_CODE",
    "PEAK_FIELDS",
    "SENSITIVITY_METHODS",
    "SIGNALS",
    "T1_LIMITS",
    "T_SHIFT",
    "BatchEvaluation",
    "BatchEvaluator",
    "Continuation",
    "DesignEvaluation",
    "Experiment",
    "Fitted",
    "FittedParameters",
    "Force",
    "Forces",
    "GlobalPhase",
    "GradientEvaluator",
    "Grid",
    "Group",
    "Hazard",
    "LocalEvaluation",
    "LocalMethod",
    "LocalRun",
    "Metric",
    "MinimaxEvaluator",
    "MinimaxMethod",
    "MinimaxWindow",
    "ModelCheck",
    "ModelMisfitError",
    "Parameter",
    "Part",
    "PlanCheck",
    "PlanReport",
    "Posterior",
    "PosteriorPredictive",
    "Prediction",
    "Prior",
    "RunRecord",
    "SearchSpace",
    "SensitivityMethod",
    "SignalCheck",
    "StoredEvaluator",
    "StoredSweep",
    "Trace",
    "batch_params",
    "candidate_information",
    "check_integer",
    "check_memory",
    "check_plan",
    "check_posterior_settings",
    "check_tests_memory",
    "default_local",
    "default_workers",
    "design_hazards",
    "end_time",
    "evaluate_design",
    "fit_many",
    "float_leaf",
    "forget_part",
    "gradient_key",
    "hazard_flags",
    "live_programs",
    "log_coordinates",
    "minimax_metric",
    "plan_calibration",
    "read_text",
    "reference_history",
    "run_local",
    "sensitivity_box",
    "set_max_programs",
    "shard_batch",
    "signal_sensitivities",
    "status_codes",
    "status_messages",
    "status_table",
    "structure_jit",
    "trace_noise",
    "validate",
    "worst_case",
    "written",
]
