"""Near pole–zero cancellations in the identified linear part G(q) = B(q)/A(q).

An ARX identifier under a slow or periodic output disturbance puts the disturbance's
dynamics in its AR part A(q), and, since the input does not excite them, B(q) gets a zero
next to each such pole. The pair nearly cancels over the samples the plant's own response
takes, but not in the long run: a pole at 0.9995 beside a zero at 1.0018 multiplies G's
steady state by (1 − 1.0018) / (1 − 0.9995) = −3.6, so the step response arrives within a
few samples and then drifts, over thousands, to a level of the wrong sign. Its arrival
time, and the horizon taken from it, are then the drift's, not the plant's.

``reduced_model`` is G without such pairs: those that stay hidden until its step response
has arrived (each pair's factor (1 − z q⁻¹) / (1 − p q⁻¹) moves a unit step by at most
|p − z| per sample, so by less than the settle band over that arrival time). The shape
alone cannot say whether a pair is a disturbance's or the plant's: the glider's depth has
a slow mode beside its non-minimum-phase zero of the same shape. ``record_prefers`` asks
the record: which input path, with the pair or without it, simulates the recorded outputs
better from the recorded inputs alone. Pure arithmetic (numpy's companion-matrix roots,
scipy's linear filter), no I/O; docs/control.md, "Near pole–zero cancellations".
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from librt.vecs import vec
from scipy.signal import lfilter

from .dynamics import StaticMap
from .horizon import arrival_time, step_response

__all__ = ["Reduced", "mapped_inputs", "record_prefers", "reduced_model"]

#: Farthest apart a pole and a zero may be to be tried as a pair (the horizon then
#: decides); keeps the search to near neighbours.
WIDEST_PAIR = 0.05


class Reduced(NamedTuple):
    """G without its near pole–zero pairs: ar and gains as ``reduced_model`` takes them,
    and the step response (``hi`` samples) that judged them hidden."""

    ar: list[float]
    gains: list[float]
    response: vec[float]


def _pairs(poles: np.ndarray, zeros: np.ndarray) -> list[tuple[int, int, float]]:
    """Each pole's nearest unused zero within ``WIDEST_PAIR``, closest pairs first:
    (pole index, zero index, distance). A complex pole pairs with a complex zero on its own
    side of the real axis (its conjugate pairs with the zero's conjugate)."""
    candidates = []
    for i, p in enumerate(poles):
        if p.imag < 0.0:
            continue  # taken with its conjugate
        for j, z in enumerate(zeros):
            if z.imag < 0.0 or (p.imag > 0.0) != (z.imag > 0.0):
                continue
            distance = float(abs(p - z))
            if distance <= WIDEST_PAIR:
                candidates.append((distance, i, j))
    candidates.sort()
    used_p: set[int] = set()
    used_z: set[int] = set()
    pairs = []
    for distance, i, j in candidates:
        if i in used_p or j in used_z:
            continue
        used_p.add(i)
        used_z.add(j)
        pairs.append((i, j, distance))
    return pairs


def _without(roots: np.ndarray, dropped: set[int]) -> np.ndarray:
    """``roots`` without the indices in ``dropped`` and their complex conjugates."""
    keep = []
    taken = set(dropped)
    for i in sorted(dropped):
        r = roots[i]
        if r.imag > 0.0:
            mirror = [
                k
                for k in range(len(roots))
                if k not in taken and abs(roots[k] - np.conj(r)) < 1e-9 * (1.0 + abs(r))
            ]
            if mirror:
                taken.add(mirror[0])
    for k in range(len(roots)):
        if k not in taken:
            keep.append(roots[k])
    return np.array(keep, dtype=complex)


def _model(
    poles: np.ndarray, zeros: np.ndarray, lead: float, delay: int
) -> tuple[list[float], list[float]] | None:
    """ar and gains of lead · q^−(1+delay) · Π(1 − z q⁻¹) / Π(1 − p q⁻¹)."""
    a = np.real(np.poly(poles)) if len(poles) else np.ones(1)
    b = lead * (np.real(np.poly(zeros)) if len(zeros) else np.ones(1))
    ar = [float(-c) for c in a[1:]]
    gains = [0.0] * delay + [float(c) for c in b]
    if not all(np.isfinite(ar)) or not all(np.isfinite(gains)):
        return None
    return ar, gains


def reduced_model(
    ar: list[float], gains: list[float], band: float, lo: int, hi: int
) -> Reduced | None:
    """G without the pole–zero pairs that stay within ``band`` until its step response
    has arrived (ar and gains as given), or None when there is no such pair (or the
    coefficients are not finite). ``lo``, ``hi``: the response's length and the arrival
    time's clamp, as ``arrival_time``'s.

    ``ar``: c_i of y(t) = Σ c_i y(t−i) + …; ``gains``: g_L of Σ_L g_L w(t−L), L = 1 … nb.
    """
    if not ar or len(gains) < 2:
        return None
    if not (np.all(np.isfinite(ar)) and np.all(np.isfinite(gains))):
        return None
    # Leading lags without a gain of their own (an input delay; the factorisation leaves
    # rounding there, not exact zeros).
    floor = 1e-12 * max(abs(g) for g in gains)
    delay = 0
    while delay < len(gains) and abs(gains[delay]) <= floor:
        delay += 1
    numerator = gains[delay:]
    if len(numerator) < 2:
        return None
    poles = np.roots(np.array([1.0] + [-c for c in ar]))
    zeros = np.roots(np.array(numerator))
    pairs = _pairs(poles, zeros)
    # Closest first (``_pairs``' order): give up the widest pair until the rest stay
    # hidden for as long as the response without them takes to arrive.
    while pairs:
        dropped_p = {i for i, _, _ in pairs}
        dropped_z = {j for _, j, _ in pairs}
        model = _model(_without(poles, dropped_p), _without(zeros, dropped_z), numerator[0], delay)
        if model is None:
            return None
        response = step_response(model[0], model[1], hi)
        if pairs[-1][2] * arrival_time(response, band, lo, hi) <= band:
            return Reduced(model[0], model[1], response)
        pairs.pop()
    return None


def mapped_inputs(shape: StaticMap, inputs: list[float]) -> np.ndarray:
    """N(u) of each input (``StaticMap.evaluate``'s value): the polynomial by numpy over
    the whole record at once, an RBF term sample by sample."""
    u = np.asarray(inputs, dtype=float)
    if shape.rbf is not None:
        return np.array([shape.evaluate(float(v))[0] for v in u])
    x = u * shape.scale
    value = np.zeros_like(x)
    for p in reversed(shape.poly):
        value = value * x + p
    return value * x


def _misfit(ar: list[float], gains: list[float], w: np.ndarray, y: np.ndarray) -> float:
    """Sum of squares of y − (G·w from rest), about its mean."""
    simulated = lfilter(np.array([0.0, *gains]), np.array([1.0, *(-c for c in ar)]), w)
    residual = y - simulated
    return float(np.sum((residual - residual.mean()) ** 2))


def record_prefers(
    full: tuple[list[float], list[float]],
    reduced: tuple[list[float], list[float]],
    w: list[float] | np.ndarray,
    y: list[float] | np.ndarray,
) -> bool:
    """Whether the record's outputs ``y`` are simulated better from its inputs alone
    (``w``: N of the input applied one sample before each output) by the reduced input
    path than by the full one, each from rest with its own offset: an output-error check
    of the pairs' long-run effect, which a record of held inputs shows and a record of
    fast steps hardly does (a tie keeps the full path)."""
    if len(w) != len(y) or len(y) < 2:
        return False
    wa, ya = np.asarray(w, dtype=float), np.asarray(y, dtype=float)
    if not (np.all(np.isfinite(wa)) and np.all(np.isfinite(ya))):
        return False
    kept = _misfit(full[0], full[1], wa, ya)
    cancelled = _misfit(reduced[0], reduced[1], wa, ya)
    return bool(np.isfinite(kept) and np.isfinite(cancelled) and cancelled < kept)
