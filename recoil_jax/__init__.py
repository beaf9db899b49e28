"""recoil-jax: differentiable recoil-system models (barrel + impact absorber) in JAX."""

import jax as _jax

# Physics needs float64: contact penetrations are ~1e-3 m against stiffness ~1e8.
# (Set before the submodules import, hence E402 below.)
_jax.config.update("jax_enable_x64", True)

from ._gradients import (
    DESIGN_PARAMETERS as DESIGN_PARAMETERS,
)
from ._gradients import (
    GRADIENT_OPTIONS as GRADIENT_OPTIONS,
)
from ._gradients import (
    PeakGradients as PeakGradients,
)
from ._gradients import (
    parameter_scale as parameter_scale,
)
from ._gradients import (
    peak_gradients as peak_gradients,
)
from ._gradients import (
    peak_jacobian as peak_jacobian,
)
from ._model import (
    RECOIL_TERM as RECOIL_TERM,
)
from ._model import (
    Forces as Forces,
)
from ._model import (
    characteristic_penetration as characteristic_penetration,
)
from ._model import (
    contact_width as contact_width,
)
from ._model import (
    forces as forces,
)
from ._model import (
    initial_state as initial_state,
)
from ._model import (
    model_args as model_args,
)
from ._model import (
    positive_power as positive_power,
)
from ._model import (
    smooth_relu as smooth_relu,
)
from ._model import (
    vector_field as vector_field,
)
from ._params import (
    PARAMETER_NAMES as PARAMETER_NAMES,
)
from ._params import (
    Absorber as Absorber,
)
from ._params import (
    Barrel as Barrel,
)
from ._params import (
    Contact as Contact,
)
from ._params import (
    ParameterError as ParameterError,
)
from ._params import (
    RecoilParams as RecoilParams,
)
from ._params import (
    Smoothing as Smoothing,
)
from ._params import (
    SolverOptions as SolverOptions,
)
from ._params import (
    params_from_values as params_from_values,
)
from ._params import (
    params_to_values as params_to_values,
)
from ._solve import (
    PEAK_KEYS as PEAK_KEYS,
)
from ._solve import (
    History as History,
)
from ._solve import (
    Peaks as Peaks,
)
from ._solve import (
    SolveError as SolveError,
)
from ._solve import (
    Status as Status,
)
from ._solve import (
    hermite_max as hermite_max,
)
from ._solve import (
    peak_metrics as peak_metrics,
)
from ._solve import (
    peaks as peaks,
)
from ._solve import (
    simulate as simulate,
)
from ._sweep import (
    SweepResult as SweepResult,
)
from ._sweep import (
    batch_params as batch_params,
)
from ._sweep import (
    grid as grid,
)
from ._sweep import (
    sweep as sweep,
)
from ._sweep import (
    sweep_grid as sweep_grid,
)

__version__ = "0.1.0"
