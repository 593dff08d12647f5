"""Online U-model identification and inverse control (Abbasi et al. 2015), pure numerics.

No I/O: numpy and the standard library only; deterministic for a given seed.
"""

from .guards import DIVERGENCE_ACTIONS, DivergenceMonitor, GuardConfig
from .inverse import (
    CommandShaper,
    ImcReference,
    InverseResult,
    InvertibleModel,
    ShapedCommand,
    imc_target,
    invert_model,
    solve_inverse,
)
from .models import (
    MODEL_NAMES,
    STATUSES,
    DynamicUModel,
    Estimate,
    OneStepModel,
    PaperUModel,
    PersistenceModel,
    RlsArxModel,
    Status,
    build_model,
    from_config,
    paper_preset,
)
from .nlms import DEFAULT_EPS, NLMS, nlms_gain, nlms_update
from .rbf import GaussianRBF, evenly_spaced_centres
from .rls import RLS

__all__ = [
    "DEFAULT_EPS",
    "DIVERGENCE_ACTIONS",
    "MODEL_NAMES",
    "NLMS",
    "RLS",
    "STATUSES",
    "CommandShaper",
    "DivergenceMonitor",
    "DynamicUModel",
    "Estimate",
    "GaussianRBF",
    "GuardConfig",
    "ImcReference",
    "InverseResult",
    "InvertibleModel",
    "OneStepModel",
    "PaperUModel",
    "PersistenceModel",
    "RlsArxModel",
    "ShapedCommand",
    "Status",
    "build_model",
    "evenly_spaced_centres",
    "from_config",
    "imc_target",
    "invert_model",
    "nlms_gain",
    "nlms_update",
    "paper_preset",
    "solve_inverse",
]
