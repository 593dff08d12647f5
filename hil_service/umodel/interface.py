"""The identifier interface the service, the forecast and the inverse controller rely on.

A module of its own, kept interpreted: ``runtime_checkable`` needs a protocol class that
CPython built, and ``models`` is compiled (see ``setup.py``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from .models import Estimate


@runtime_checkable
class OneStepModel(Protocol):
    """One-step-ahead identifier: a-priori prediction, update, and the map the inverse uses."""

    @property
    def name(self) -> str: ...

    @property
    def history_length(self) -> int: ...

    def predict(self, u_prev: float) -> float: ...

    def step(self, u_prev: float, y: float) -> Estimate: ...

    def observe_only(self, u_prev: float, y: float) -> bool: ...

    def output_given_input(self, u: float) -> float: ...

    def output_derivative(self, u: float) -> float: ...

    def config(self) -> dict[str, Any]: ...

    def snapshot(self) -> dict[str, Any]: ...

    def reset(self) -> None: ...
