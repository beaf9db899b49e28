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
  over devices, and the sweep's default worker count.
- `status_codes`, `status_messages`, `status_table`, `OK_CODE`: a `Status` item's
  integer codes and messages, every code with its message, and the code of success.
- `PEAK_FIELDS`, `gradient_key`, `Metric`, `Parameter`: the keys of the files and the
  registries' entries; `T1_LIMITS`: the end time's valid and documented range;
  `end_time`: a design's end time (refusing a load that does not
  fit); `Forces`: the model's forces; `StoredSweep`: a sweep read back from its store;
  `worst_case`: each metric's worst over a scatter of designs.
"""

from ._cache import live_programs, set_max_programs, structure_jit
from ._evaluators import (
    BatchEvaluation,
    BatchEvaluator,
    GradientEvaluator,
    MinimaxEvaluator,
    MinimaxWindow,
    SearchSpace,
    StoredEvaluator,
    log_coordinates,
    minimax_metric,
)
from ._local import LocalEvaluation, LocalMethod, LocalRun, MinimaxMethod, run_local
from ._metrics import PEAK_FIELDS, Metric, gradient_key, worst_case
from ._model import Forces
from ._params import T1_LIMITS, Parameter, end_time
from ._problem import DesignEvaluation, evaluate_design
from ._result import RunRecord
from ._search import GlobalPhase, default_local
from ._status import OK_CODE, status_codes, status_messages, status_table
from ._sweep import StoredSweep, batch_params, default_workers, shard_batch

__all__ = [
    "OK_CODE",
    "PEAK_FIELDS",
    "T1_LIMITS",
    "BatchEvaluation",
    "BatchEvaluator",
    "DesignEvaluation",
    "Forces",
    "GlobalPhase",
    "GradientEvaluator",
    "LocalEvaluation",
    "LocalMethod",
    "LocalRun",
    "Metric",
    "MinimaxEvaluator",
    "MinimaxMethod",
    "MinimaxWindow",
    "Parameter",
    "RunRecord",
    "SearchSpace",
    "StoredEvaluator",
    "StoredSweep",
    "batch_params",
    "default_local",
    "default_workers",
    "end_time",
    "evaluate_design",
    "gradient_key",
    "live_programs",
    "log_coordinates",
    "minimax_metric",
    "run_local",
    "set_max_programs",
    "shard_batch",
    "status_codes",
    "status_messages",
    "status_table",
    "structure_jit",
    "worst_case",
]
