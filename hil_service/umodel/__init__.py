"""Online U-model identification and inverse control (Abbasi et al. 2015), pure numerics.

No I/O: numpy and the standard library only; deterministic for a given seed.
"""

from .guards import DIVERGENCE_ACTIONS, DivergenceMonitor, GuardConfig
from .interface import PredictiveModel
from .inverse import (
    CommandShaper,
    InverseResult,
    ShapedCommand,
    solve_inverse,
)
from .models import (
    MODEL_NAMES,
    STATUSES,
    U_MODELS,
    DynamicUModel,
    Estimate,
    OneStepModel,
    PaperUModel,
    PersistenceModel,
    RlsArxModel,
    Status,
    build_model,
    from_config,
    option_names,
    paper_preset,
)
from .nlms import DEFAULT_EPS, NLMS
from .rbf import GaussianRBF, evenly_spaced_centres
from .rls import RLS

__all__ = [
    "DEFAULT_EPS",
    "DIVERGENCE_ACTIONS",
    "MODEL_NAMES",
    "NLMS",
    "RLS",
    "STATUSES",
    "U_MODELS",
    "CommandShaper",
    "DivergenceMonitor",
    "DynamicUModel",
    "Estimate",
    "GaussianRBF",
    "GuardConfig",
    "InverseResult",
    "OneStepModel",
    "PaperUModel",
    "PersistenceModel",
    "PredictiveModel",
    "RlsArxModel",
    "ShapedCommand",
    "Status",
    "build_model",
    "evenly_spaced_centres",
    "from_config",
    "option_names",
    "paper_preset",
    "solve_inverse",
]
