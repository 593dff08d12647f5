"""The predictive inverse's plan, from the identified linear part: its horizon, input
blocks and cost points, and the fixed matrices of the QP over them (see :mod:`.predictive`).

Pure functions of the step response (and the AR part for the free response); they change
as slowly as the model does, and ``PredictiveInverse`` derives them again every
``refresh`` samples. The long series (a response runs to ``max_horizon``) and the
matrices are ``vec[float]`` (``librt``, mypyc's runtime library; matrices row-major):
compiled, their elements are C doubles, where a list boxes and unboxes each one read; sizes
and indices are ``i64``, machine integers.
"""

from __future__ import annotations

import math

from librt.vecs import vec
from mypy_extensions import i64

from .finite import finite

__all__ = [
    "LinearTerm",
    "add_move_penalty",
    "arrival_time",
    "block_starts",
    "cost_points",
    "cost_start",
    "free_response_terms",
    "lead_of",
    "plan_matrices",
    "project",
    "settling_horizon",
    "step_response",
]


def block_starts(horizon: int, max_blocks: int) -> list[int]:
    """First samples of the input blocks: 1 (the command), then geometrically spaced up to
    the horizon (ratio 2, or larger so that there are at most ``max_blocks``): fine where
    the plan is applied next, coarse where only its level matters."""
    ratio = 2.0
    if max_blocks > 2:
        ratio = max(ratio, math.exp(math.log(max(horizon, 2)) / (max_blocks - 1)))
    starts = [1]
    edge = 1.0
    while True:
        edge *= ratio
        start = round(edge)
        if start >= horizon:
            break
        if start > starts[-1]:
            starts.append(start)
    if len(starts) == 1 and horizon > 1:
        starts.append(2)
    return starts


def cost_points(
    horizon: int, stride: int, starts: list[int], first: int = 1
) -> tuple[list[int], list[float]]:
    """The samples j of the horizon whose predicted error enters the cost, newest first,
    and each one's weight (the samples it stands for, in strides).

    Every ``stride``-th sample from the horizon down, and every sample while the input
    blocks are shorter than a stride: a block's level moves the output at once (on the
    ArduSub depth channel by −2.1 m per unit within one sample, a wrong-way response that
    lasts as long as the block), so a block between two cost points could pulse unseen.
    The plan then kept an unseen pulse in its second block and the applied first block
    near the held input, every sample again (a stall 0.8 m short for 450 samples;
    docs/control.md, "Blocks the cost does not see"). A point stands for the samples down
    to the next one, so the sum stays a consistent approximation of the whole horizon's.
    """
    dense = 0
    for b in range(len(starts)):
        end = starts[b + 1] if b + 1 < len(starts) else horizon
        if end - starts[b] >= stride:
            break
        dense = end
    dense = min(dense, horizon)
    first = max(1, min(first, horizon))
    points = list(range(horizon, max(dense, first - 1), -stride))
    points += list(range(min(dense, points[-1] - 1 if points else horizon), first - 1, -1))
    weights: list[float] = []
    for p in range(len(points)):
        below = points[p + 1] if p + 1 < len(points) else first - 1
        weights.append(1.0 if points[p] - below >= stride else (points[p] - below) / stride)
    return points, weights


def cost_start(response: vec[float], horizon: int) -> int:
    """The first sample of the horizon whose error enters the cost (GPC's minimum costing
    horizon N1): 1, or the sample m at which the step response peaks the wrong way (5 on
    ArduSub and glider depth: −2.13 after one sample, −2.44 after five).

    Before it the output moves the wrong way whatever the plan does now. The first
    block acts from sample 2, so its own wrong-way peak is at m + 1 and its jump is seen at
    one point of the cost: a partial charge. Measured both ways (docs/control.md, "Blocks
    the cost does not see"): from m + 1 (the jump never charged) the plan was bolder and
    disturbed glider depth 3.8 % (5,000 samples) and 7.3 % (20,000) worse; from m, 1.9 %
    and 2.6 %; a cost from sample 1 holds the steady-state input and never kicks (paper
    depth 33 % worse)."""
    final = response[len(response) - 1] if len(response) else 0.0
    if not (finite(final) and final != 0.0):
        return 1
    worst = 0.0
    at = 0
    for m in range(min(horizon, len(response))):
        wrong = -response[m] if final > 0.0 else response[m]
        if wrong > worst:
            worst, at = wrong, m
    return at if at > 0 else 1


def step_response(ar: list[float], gains: list[float], n: int) -> vec[float]:
    """s(0 … n−1): the output j samples after w steps from 0 to 1 (s(0) = 0: no
    feedthrough), for y(t) = Σ c_i y(t−i) + Σ_L g_L w(t−L)."""
    na: i64 = len(ar)
    nb: i64 = len(gains)
    count: i64 = n
    c = vec[float](ar)
    out = vec[float]([0.0] * count)
    forcing = 0.0
    for j in range(count):
        if 1 <= j <= nb:
            forcing += gains[j - 1]
        acc = forcing
        for i in range(na):
            if j - 1 - i >= 0:
                acc += c[i] * out[j - 1 - i]
        out[j] = acc
    return out


def plan_matrices(
    response: vec[float], starts: list[int], points: list[int], weights: list[float]
) -> tuple[vec[float], list[float], vec[float]]:
    """Per cost point, each block's weighted effect on ŷ(k+j) (the columns, points ×
    blocks row-major) and the held input's step s(j − 1) (the onset); and the output
    cost's Hessian Σ_p w_p·col·colᵀ (blocks × blocks row-major)."""
    nblocks: i64 = len(starts)
    npoints: i64 = len(points)
    begins = vec[i64]([i64(start) for start in starts])
    columns = vec[float]([0.0] * (npoints * nblocks))
    onset: list[float] = []
    hessian = vec[float]([0.0] * (nblocks * nblocks))
    col = vec[float]([0.0] * nblocks)
    for p in range(npoints):
        j: i64 = points[p]
        weight = weights[p]
        # Block b's level acts on ŷ(k+j) through s(j − start_b) − s(j − start_{b+1})
        # (s(m) = 0 for m ≤ 0: an input acts one sample later).
        for b in range(nblocks):
            first = j - begins[b]
            on = response[first] if first > 0 else 0.0
            off = 0.0
            if b + 1 < nblocks:
                after = j - begins[b + 1]
                off = response[after] if after > 0 else 0.0
            col[b] = on - off
        # Stored weighted: the QP's linear term is Σ_p weight·col·residual.
        base = p * nblocks
        for b in range(nblocks):
            columns[base + b] = weight * col[b]
        first0 = j - begins[0]
        onset.append(response[first0] if first0 > 0 else 0.0)
        for a in range(nblocks):
            wa = weight * col[a]
            row = a * nblocks
            for b in range(nblocks):
                hessian[row + b] += wa * col[b]
    return columns, onset, hessian


def add_move_penalty(hessian: vec[float], nblocks: i64, move_weight: float) -> float:
    """Add the move penalty ρ Σ (W_b − W_{b−1})² (W_{−1} = the applied input's level) to
    ``hessian`` (``nblocks`` square, row-major) in place, ρ scaled to the output cost's
    size; returns ρ."""
    trace = 0.0
    for b in range(nblocks):
        trace += hessian[b * nblocks + b]
    rho = move_weight * (trace / float(nblocks) + 1e-12)
    for b in range(nblocks):
        hessian[b * nblocks + b] += rho if b + 1 == nblocks else 2.0 * rho
        if b + 1 < nblocks:
            hessian[b * nblocks + b + 1] -= rho
            hessian[(b + 1) * nblocks + b] -= rho
    return rho


def free_response_terms(
    ar: list[float], lags: int, n: int, points: list[int]
) -> tuple[list[float], list[list[float]]]:
    """1/A(q) at the cost points, for the free response in closed form
    (``PredictiveInverse._forcing``): S_A(j), the running sum of the impulse response
    h_A, and h_A(j − l) for l = 1 … L, L = max(na, lags − 1, 1)."""
    na: i64 = len(ar)
    lead = max(len(ar), lags - 1, 1)
    count: i64 = n
    c = vec[float](ar)
    impulse = vec[float]([0.0] * count)
    for m in range(count):
        acc = 1.0 if m == 0 else 0.0
        for i in range(na):
            if m - 1 - i >= 0:
                acc += c[i] * impulse[m - 1 - i]
        impulse[m] = acc
    running = vec[float]([0.0] * (count + 1))
    for m in range(count):
        running[m + 1] = running[m] + impulse[m]
    step = [running[j] for j in points]
    impulses = [[impulse[j - d] if j - d >= 0 else 0.0 for d in range(1, lead + 1)] for j in points]
    return step, impulses


def lead_of(impulses: list[list[float]]) -> int:
    """L, the free response's number of departures (``free_response_terms``)."""
    return len(impulses[0]) if impulses else 0


def project(columns: vec[float], nblocks: i64, values: list[float]) -> list[float]:
    """Σ_p columns[p][b]·values[p] per block b (``columns`` points × ``nblocks``,
    row-major): a per-point vector seen by the blocks."""
    out = vec[float]([0.0] * nblocks)
    npoints: i64 = len(values)
    for p in range(npoints):
        value = values[p]
        base = p * nblocks
        for b in range(nblocks):
            out[b] += columns[base + b] * value
    return list(out)


class LinearTerm:
    """The QP's linear term, in parts fixed between two derivations of the plan: the
    block columns projected on S_A(j), on each h_A(j − l), on 1 and on the onset
    (``PredictiveInverse._linear_term`` weighs them with the sample's E, d(l), disturbance
    − setpoint and applied level)."""

    __slots__ = ("impulses", "ones", "onset", "step")

    def __init__(
        self, step: list[float], impulses: list[list[float]], ones: list[float], onset: list[float]
    ) -> None:
        self.step = step
        self.impulses = impulses
        self.ones = ones
        self.onset = onset


def _final_band(response: vec[float], band: float) -> tuple[float, float] | None:
    """The step response's final value and ``band`` × its size; None when the final value
    is zero or not finite (there is no level to come within)."""
    final = response[len(response) - 1]
    if not finite(final) or final == 0.0:
        return None
    return final, band * abs(final)


def _clamp(j: int, lo: int, hi: int) -> int:
    return lo if j < lo else hi if j > hi else j


def settling_horizon(response: vec[float], band: float, lo: int, hi: int) -> int:
    """The first sample after which the step response stays within ``band`` of its last
    value (the response is ``hi`` long), clamped to [lo, hi]; ``hi`` when it does not
    settle or is not finite."""
    n: i64 = len(response)
    if n == 0:
        return lo
    level = _final_band(response, band)
    if level is None:
        return hi
    final, tol = level
    # Not settled if it still moves at the end: compare with the value a tenth earlier.
    if abs(response[n - 1 - n // 10] - final) > tol:
        return hi
    last = 0
    for j in range(n):
        if abs(response[j] - final) > tol:
            last = j + 1
    return _clamp(last, lo, hi)


def arrival_time(response: vec[float], band: float, lo: int, hi: int) -> int:
    """The first sample at which the step response comes within ``band`` of its last
    value, clamped to [lo, hi]; ``hi`` when it never does or is not finite.

    Shorter than the settling time on a lightly damped response: the output reaches its
    new level early and rings about it. The pace at which a level of the residual can be
    told from the model's own transient is set by this time, not by the ringing's decay.
    """
    if len(response) == 0:
        return lo
    level = _final_band(response, band)
    if level is None:
        return hi
    final, tol = level
    for j in range(len(response)):
        if abs(response[j] - final) <= tol:
            return _clamp(j, lo, hi)
    return hi
