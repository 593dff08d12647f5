"""An optimal LP basis kept across solves whose right-hand sides and bounds change.

For min cᵀx s.t. r_lo ≤ A x ≤ r_hi, lo ≤ x ≤ hi with c and A fixed, a basis (which
columns are basic, at which bound each non-basic column sits, which rows are active and at
which of their bounds) stays dual feasible whatever the bounds become: only its primal
values move. So when the basis that was optimal for the last solve is still primal
feasible for the new bounds, it is optimal again, and its primal values are the LP's
solution, the one a warm-started simplex returns after zero iterations. ``OptimalBasis``
checks exactly that, with one solve against a factorisation kept per basis: a small
fraction of a call into the solver, which re-factorises and re-checks from scratch on
every run.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

Array = NDArray[np.float64]
Index = NDArray[np.intp]

#: A basis whose square part is more ill-conditioned than this (LAPACK's reciprocal
#: condition estimate) is not used: its primal values would not be trusted to the
#: feasibility tolerance.
MIN_RCOND = 1e-12


class OptimalBasis:
    """The basis of an optimum: the basic columns, the non-basic ones' bounds, the active
    rows and the bound each sits at, and the square system of the active rows over the
    basic columns (square: a basis has as many basic columns as active rows), factorised.

    Most of that system is column singletons: a basic column that appears in one active
    row only (the oracle's error parts e⁺ and e⁻, a slack), whose value follows from that
    row once the other columns are known. Those are taken out first, and only what remains
    is LU-factorised densely (for the oracle's depth LP on a disturbed mission, a median
    132 × 132 square part leaves 27 × 27), which keeps the factorisation a small part of a
    solve."""

    __slots__ = (
        "_a_active_n",
        "_a_inactive",
        "_active",
        "_at_upper",
        "_basic",
        "_coupling",
        "_diagonal",
        "_inactive",
        "_lu",
        "_nonbasic",
        "_pivots",
        "_rest_cols",
        "_rest_rows",
        "_row_at_upper",
        "_single_cols",
        "_single_rows",
    )

    def __init__(
        self,
        a: Array,
        basic_cols: NDArray[np.bool_],
        at_upper: NDArray[np.bool_],
        active_rows: NDArray[np.bool_],
        row_at_upper: NDArray[np.bool_],
    ) -> None:
        """``basic_cols``; ``at_upper``: the non-basic columns at their upper bound (the
        others sit at their lower); ``active_rows``: the non-basic rows (A_i x at a bound of
        row i); ``row_at_upper``: the rows that sit at their upper bound when active (the
        others at their lower). ValueError when the active rows over the basic columns are
        not a square, well-conditioned matrix."""
        self._basic: Index = np.flatnonzero(basic_cols)
        self._nonbasic: Index = np.flatnonzero(~basic_cols)
        self._at_upper = at_upper[self._nonbasic]
        self._active: Index = np.flatnonzero(active_rows)
        self._inactive: Index = np.flatnonzero(~active_rows)
        self._row_at_upper = np.asarray(row_at_upper, dtype=bool)[self._active]
        square = a.take(self._active, 0).take(self._basic, 1)
        size = square.shape[0]
        if size != square.shape[1]:
            raise ValueError(f"not a basis: {size} active rows, {square.shape[1]} basic")
        nonzero = square != 0.0
        single_cols = np.flatnonzero(nonzero.sum(axis=0) == 1)
        single_rows = nonzero[:, single_cols].argmax(axis=0)
        owned = np.bincount(single_rows, minlength=size)
        if owned.size and owned.max() > 1:  # two singletons on one row: no shortcut
            single_cols = single_rows = np.zeros(0, dtype=np.intp)
            owned = np.zeros(size, dtype=np.intp)
        rest_rows = np.flatnonzero(owned == 0)
        single_mask = np.zeros(size, dtype=bool)
        single_mask[single_cols] = True
        rest_cols = np.flatnonzero(~single_mask)
        self._single_cols, self._single_rows = single_cols, single_rows
        self._rest_cols, self._rest_rows = rest_cols, rest_rows
        self._diagonal = square[single_rows, single_cols]
        if self._diagonal.size and not (
            np.min(np.abs(self._diagonal)) >= MIN_RCOND * np.max(np.abs(square))
        ):
            raise ValueError("basis too ill-conditioned (a tiny singleton pivot)")
        self._coupling = square.take(single_rows, 0).take(rest_cols, 1)
        reduced = np.asfortranarray(square.take(rest_rows, 0).take(rest_cols, 1))
        self._lu, self._pivots = reduced, np.zeros(0, dtype=np.int32)
        if reduced.size:
            norm = float(np.max(np.sum(np.abs(reduced), axis=0)))
            self._lu, self._pivots, info = lapack.dgetrf(reduced, overwrite_a=True)
            if info != 0:
                raise ValueError("singular basis")
            rcond, info = lapack.dgecon(self._lu, norm, norm="1")
            if info != 0 or not rcond >= MIN_RCOND:
                raise ValueError(f"basis too ill-conditioned (rcond {rcond:.3g})")
        self._a_active_n = a.take(self._active, 0).take(self._nonbasic, 1)
        self._a_inactive = a.take(self._inactive, 0)

    def primal(
        self,
        row_lower: Array,
        row_upper: Array,
        lower: Array,
        upper: Array,
        tolerance: float,
    ) -> Array | None:
        """x of this basis for the row and column bounds, or None where it is not feasible
        (a bound or an inactive row violated by more than ``tolerance``) or not finite (a
        NaN passes every comparison: the solver decides such an LP)."""
        nonbasic = self._nonbasic
        x_n = np.where(self._at_upper, upper.take(nonbasic), lower.take(nonbasic))
        if not np.isfinite(x_n).all():
            return None
        x = np.empty(lower.size)
        x[nonbasic] = x_n
        basic = self._basic
        if basic.size:
            active = self._active
            rhs = (
                np.where(self._row_at_upper, row_upper.take(active), row_lower.take(active))
                - self._a_active_n @ x_n
            )
            x_b = np.empty(basic.size)
            x_rest = rhs.take(self._rest_rows)
            if x_rest.size:
                x_rest, info = lapack.dgetrs(self._lu, self._pivots, x_rest)
                if info != 0:
                    return None
            x_b[self._rest_cols] = x_rest
            x_b[self._single_cols] = (
                rhs.take(self._single_rows) - self._coupling @ x_rest
            ) / self._diagonal
            if (x_b < lower.take(basic) - tolerance).any() or (
                x_b > upper.take(basic) + tolerance
            ).any():
                return None
            x[basic] = x_b
        inactive = self._inactive
        if inactive.size:
            activity = self._a_inactive @ x
            if (activity > row_upper.take(inactive) + tolerance).any() or (
                activity < row_lower.take(inactive) - tolerance
            ).any():
                return None
        if not np.isfinite(x).all():
            return None
        return x


def from_basic_variables(
    a: Array,
    basic_variables: NDArray[np.int32],
    x: Array,
    lower: Array,
    upper: Array,
    row_lower: Array,
    row_upper: Array,
) -> OptimalBasis:
    """The basis a solver reports as its basic variables (column j as j, row i as −(i + 1),
    HiGHS's convention) at the optimum ``x``: each non-basic column, and each non-basic
    row's activity A_i x, sits at the bound it is nearer (an equality row's are one)."""
    rows, cols = a.shape
    basic_cols = np.zeros(cols, dtype=bool)
    basic_rows = np.zeros(rows, dtype=bool)
    basic_cols[basic_variables[basic_variables >= 0]] = True
    basic_rows[-1 - basic_variables[basic_variables < 0]] = True
    at_upper = np.abs(x - upper) < np.abs(x - lower)
    activity = a @ x
    row_at_upper = np.abs(activity - row_upper) <= np.abs(activity - row_lower)
    return OptimalBasis(a, basic_cols, at_upper, ~basic_rows, row_at_upper)
