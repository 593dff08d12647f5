"""What one identifier step returns: the type every model, the interfaces and the pipeline
share, in a module of its own so that ``interface`` and ``models`` both import it and
neither imports the other."""

from __future__ import annotations

from typing import Literal, NamedTuple

__all__ = ["STATUSES", "Estimate", "Status", "new_estimate"]

Status = Literal["ok", "rejected", "diverged", "frozen"]
STATUSES: tuple[str, ...] = ("ok", "rejected", "diverged", "frozen")


class Estimate(NamedTuple):
    """Result of one ``step`` (immutable; a named tuple because four are made per sample).

    ``alpha`` = (α₀, α₁, …) are the U-model coefficients *that produced y_hat*, i.e.
    y_hat = α₀ + Σ α_i u_prev^i (up to rounding): for ``rls-arx`` α₁ is b₁ and α₀ the rest
    of the ARX sum; for ``persistence`` alpha = (y(t−1),). ``weights`` are the other adapted
    parameters before this step's update: RBF weights (``paper``), [c, a_1..a_na, b_2..b_nb]
    (``dynamic``, which has no RBF), the full ARX vector (``rls-arx``).
    For a rejected sample, ``error`` is 0.0 and a non-finite ``y`` is replaced by ``y_hat``
    so that no field is ever NaN.
    """

    model: str
    status: Status
    y: float
    y_hat: float
    error: float
    alpha: tuple[float, ...]
    weights: tuple[float, ...]


def new_estimate(
    model: str,
    status: Status,
    y: float,
    y_hat: float,
    error: float,
    alpha: tuple[float, ...],
    weights: tuple[float, ...],
) -> Estimate:
    """``Estimate(...)``, the same tuple, made by ``tuple.__new__``: the named tuple's own
    ``__new__`` is a Python function, a frame for each of the four estimates a sample
    makes from compiled code."""
    return tuple.__new__(Estimate, (model, status, y, y_hat, error, alpha, weights))
