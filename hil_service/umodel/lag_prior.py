"""A smoothness prior on the dynamic U-model's input lags.

The identifier regresses the output on the input at lags 1 … nb. An excitation of steps
10–40 samples long moves neighbouring lags together: the record fixes their sum well and
their differences hardly at all, so on a noisy record least squares leaves the single lags
free to alternate in sign (+0.7, −0.5, +0.5, … where the plant's response is smooth), and
a controller that plans with them one by one chatters. The prior says neighbouring lags of
the same power are alike: the information the covariance P starts from is

    P₀⁻¹ = I/p0 + w · DᵀD   on each power's lags 1 … nb,   I/p0 elsewhere,

D the first-difference matrix and w the weight, in the regression's normalised units
(inputs over their scale, outputs over the output scale), so that it means the same on
every vehicle. With forgetting this slow (λ = 0.9999) the prior acts as the penalty
w·Σ(b_k − b_{k+1})² of a batch least-squares fit.

It is not the identifier's default: on a record without noise the regression's output and
input lags can trade a common factor at no cost, and the prior then prefers smooth input
lags bought with a wild (even unstable) common factor. So w follows the record's noise
(``LAG_SMOOTHING_GAIN`` times its one-step residual share, none below ``NOISE_FLOOR``:
``structure``), and the channel keeps a smoothed identifier only when
``adds_a_slower_mode`` says it did not buy its lags that way (``hil_service.pipeline``).

Pure, no I/O: the prior in plain float lists and fixed-order sums (it starts the RLS, whose
figures replay bit for bit); the modes by ``numpy.roots``, a yes/no verdict.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "LAG_SMOOTHING_GAIN",
    "NOISE_FLOOR",
    "adds_a_slower_mode",
    "chain_covariance",
    "slowest_mode",
    "smooth_lag_prior",
]

#: The prior's weight per unit of the record's one-step residual share (the residual's
#: variance over the output's, ``structure``): a Gaussian prior on the lags' differences
#: with a standard deviation of a tenth of the output's.
LAG_SMOOTHING_GAIN = 100.0
#: The residual share below which a record gets no prior: its noise is too small for the
#: lags to alternate, and a prior could only choose among common factors.
NOISE_FLOOR = 1e-3
#: How much slower than the plain fit's slowest mode the smoothed fit's may be.
MODE_MARGIN = 0.02


def chain_covariance(length: int, p0: float, weight: float) -> list[list[float]]:
    """(I/p0 + weight·DᵀD)⁻¹ for a chain of ``length`` neighbours (Gauss–Jordan on a
    symmetric positive-definite tridiagonal matrix: no pivoting needed)."""
    if length < 1:
        raise ValueError("a chain needs at least one element")
    if not (p0 > 0.0 and weight >= 0.0):
        raise ValueError("p0 must be > 0 and the weight >= 0")
    n = length
    a = [[0.0] * n for _ in range(n)]
    for i in range(n):
        a[i][i] = 1.0 / p0
    for i in range(n - 1):
        a[i][i] += weight
        a[i + 1][i + 1] += weight
        a[i][i + 1] -= weight
        a[i + 1][i] -= weight
    inv = [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]
    for col in range(n):
        pivot = a[col][col]
        for j in range(n):
            a[col][j] /= pivot
            inv[col][j] /= pivot
        for row in range(n):
            if row != col:
                f = a[row][col]
                if f != 0.0:
                    for j in range(n):
                        a[row][j] -= f * a[col][j]
                        inv[row][j] -= f * inv[col][j]
    # Exactly symmetric (the elimination's round-off is not).
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (inv[i][j] + inv[j][i])
            inv[i][j] = v
            inv[j][i] = v
    return inv


def smooth_lag_prior(
    n: int, p0: float, weight: float, chains: list[list[int]]
) -> list[list[float]]:
    """The n × n prior covariance: p0·I, with each chain's indices (one power's lags
    1 … nb, in lag order) tied to their neighbours by ``chain_covariance``."""
    p = [[p0 if i == j else 0.0 for j in range(n)] for i in range(n)]
    for chain in chains:
        block = chain_covariance(len(chain), p0, weight)
        for bi, i in enumerate(chain):
            for bj, j in enumerate(chain):
                p[i][j] = block[bi][bj]
    return p


def slowest_mode(ar: list[float]) -> float:
    """The largest modulus among the roots of zⁿ − a₁zⁿ⁻¹ − … − aₙ (∞ when not finite)."""
    if not ar:
        return 0.0
    coefficients = np.array([1.0, *(-a for a in ar)], dtype=float)
    if not np.all(np.isfinite(coefficients)):
        return float("inf")
    roots = np.roots(coefficients)
    return float(np.max(np.abs(roots))) if roots.size else 0.0


def adds_a_slower_mode(plain_ar: list[float], smooth_ar: list[float]) -> bool:
    """Whether the smoothed fit bought its smooth lags with a common factor of the output
    and input lags slower than any mode of the plain fit (an unstable one, on a record
    without noise): its free run then drifts where the plain fit's does not."""
    return slowest_mode(smooth_ar) > slowest_mode(plain_ar) + MODE_MARGIN
