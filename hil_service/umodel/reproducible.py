"""Arithmetic that gives the same bits on every x86-64 machine and every Python version.

``--check`` replays a log recorded on one computer on another and compares commands bit
for bit, so the inverse controller's grid path must not depend on the CPU it runs on.
numpy picks its ``exp`` and ``power`` kernels at run time (AVX-512, AVX2 or baseline) and
OpenBLAS does the same for a mat-vec, and these kernels round differently in the last
place. Element-wise ``+`` and ``*`` are exactly rounded IEEE operations and so do not
vary. This module uses those, plus ``math.exp`` (glibc) for values that are cached per grid,
and ``dot`` for scalar products (see there for why not ``sum``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

__all__ = ["dot", "gaussian_columns", "linear_combination", "power_columns", "row_sum"]


def power_columns(xs: np.ndarray, degree: int) -> list[np.ndarray]:
    """[x, x², …, x^degree] by repeated multiplication (``xs**3`` would call ``pow``)."""
    columns = []
    p = np.ones_like(xs, dtype=float)
    for _ in range(degree):
        p = p * xs
        columns.append(p)
    return columns


def gaussian_columns(us: np.ndarray, centres: Sequence[float], beta: float) -> list[np.ndarray]:
    """Φ_j(u) = exp(−(u − c_j)²/β²) for every grid point, one column per centre.

    Computed with the same scalar expression as the per-sample path
    (:meth:`GaussianRBF.values_list`), so that grid and Newton agree to the bit.
    """
    k = 1.0 / (beta * beta)
    exp = math.exp
    points = [float(u) for u in us]
    return [np.array([exp(-(u - c) * (u - c) * k) for u in points]) for c in centres]


def linear_combination(
    columns: Sequence[np.ndarray] | np.ndarray, coefficients: Sequence[float], start: float = 0.0
) -> np.ndarray:
    """start + Σ_j coefficients_j · columns_j, summed in column order (no BLAS)."""
    out = np.full(len(columns[0]), float(start)) if len(columns) else np.array([float(start)])
    for coefficient, column in zip(coefficients, columns, strict=True):
        out += coefficient * column
    return out


def row_sum(rows: np.ndarray) -> np.ndarray:
    """Σ_i rows[i] of a 2-D array by halving: rows[:h] + rows[h:2h], an odd last row into
    the first, until one row is left.

    Each level is one element-wise ``+`` on slices, so the order of the additions is fixed
    by the shape alone (no ``np.sum``, whose reduction order is numpy's business): the same
    bits on every machine, in log₂(rows) numpy calls instead of one per row.
    """
    n = rows.shape[0]
    if n == 0:
        return np.zeros(rows.shape[1:])
    if n == 1:
        return rows[0].copy()
    while n > 1:
        half = n // 2
        summed = rows[:half] + rows[half : 2 * half]
        if n % 2:
            summed[0] += rows[n - 1]
        rows, n = summed, half
    return rows[0]


def dot(a: Iterable[float], b: Iterable[float]) -> float:
    """Σ a_i·b_i added left to right, so the same bits on every Python version.

    Not ``sum``: from Python 3.12 ``sum`` of floats uses compensated summation, so a log
    recorded under 3.11 would not replay bit for bit under 3.12 (and the other way round).
    Not ``math.fsum`` either: exact, but the RBF terms span a hundred orders of magnitude
    and its partials make it about twice as slow on the identifier's regressors. A plain
    loop is what ``sum`` did before 3.12, and is no slower on 3.11.
    """
    total = 0.0
    if isinstance(a, list) and isinstance(b, list):
        # The identifiers' vectors: indexed (compiled, a C loop over the two lists), the
        # same products added in the same order as the loop below.
        xs: list[float] = a
        ys: list[float] = b
        for i in range(min(len(xs), len(ys))):
            total += xs[i] * ys[i]
        return total
    for x, y in zip(a, b):  # noqa: B905 - the shorter length, as map(mul, a, b) had
        total += x * y
    return total
