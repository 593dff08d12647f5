"""The identifier interfaces the service and the controller rely on.

A module of its own, kept interpreted: ``runtime_checkable`` needs a protocol class that
CPython built, and ``models`` is compiled (see ``setup.py``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from .dynamics import ModelDynamics
    from .estimate import Estimate


@runtime_checkable
class OneStepModel(Protocol):
    """One-step-ahead identifier (every model, baselines included): a-priori prediction,
    update, history handling after gaps, configuration and state."""

    @property
    def name(self) -> str: ...

    @property
    def history_length(self) -> int: ...

    def predict(self, u_prev: float) -> float: ...

    def step(self, u_prev: float, y: float) -> Estimate: ...

    def observe_only(self, u_prev: float, y: float) -> bool: ...

    def config(self) -> dict[str, Any]: ...

    def snapshot(self) -> dict[str, Any]: ...

    def reset(self) -> None: ...


@runtime_checkable
class PredictiveModel(OneStepModel, Protocol):
    """What the controller uses: an identifier that also gives its multi-step map."""

    def dynamics(self) -> ModelDynamics: ...

    def undo_last_update(self) -> bool:
        """Restore the parameters from before the last update (a reading found, one
        sample later, to have been served ahead of its tick); False when not kept."""
        ...
