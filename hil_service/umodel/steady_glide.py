"""A first-principles baseline: the steady-glide flight model of a buoyancy-driven glider.

In steady, wings-level flight the net buoyancy is balanced by lift and drag (Graver 2005,
*Underwater gliders: dynamics, control and design*, PhD thesis, Princeton, ch. 3; the form
fitted to field data by Merckelbach, Smeed & Griffiths 2010, "Vertical water velocities from
underwater gliders", J. Atmos. Oceanic Technol. 27(3) 547-563, and Frajka-Williams et al.
2011, "Determining vertical water velocities from Seaglider", J. Atmos. Oceanic Technol.
28(12) 1641-1656). Along the glide path, drag ½ρ S C_D U² equals the buoyancy's component
F_B·sin γ; with the glide angle γ taken as the pitch θ (angle of attack neglected: a few
degrees in steady flight) the vertical speed is

    w = sign(F_B) · √(2 |F_B| |sin θ| / (ρ S C_D)) · |sin θ|.

The net buoyancy is F_B ∝ (v − v₀ − c_p·z): the buoyancy engine's volume v (its input
units) less the neutral volume v₀, less the hull's compression with depth z (c_p per m;
Merckelbach's ε term, linearised). With k = √(2 g/(S C_D)) and the constants absorbed,
the model of the depth rate (positive down) is

    ż = −k · sign(b) · √|b| · |sin θ|^{3/2},   b = v − v₀ − c_p·z,

three parameters (k, v₀, c_p), fitted by least squares on the training samples' measured
ż: k in closed form for given (v₀, c_p), those two by a grid then a shrinking pattern
search (deterministic). Depth is stepped forward with ż over the sample period.

The pitch is given, in equilibrium, by the moment balance of the moving mass against the
hull's metacentric righting moment (Graver ch. 3): linearised about level flight,
θ = a + b·m + c·v (m: the pitch input, v: the buoyancy input, which moves the centre of
gravity too); ``StaticPitch`` fits it by least squares.

Pure numerics: numpy only, no I/O, deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def glide_regressor_of(b: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """sign(b)·√|b|·|sin θ|^{3/2}: the regressor of k (the flight model's, by columns)."""
    return np.sign(b) * np.sqrt(np.abs(b)) * np.abs(np.sin(pitch)) ** 1.5


@dataclass(frozen=True)
class SteadyGlide:
    """ż = −k·sign(b)·√|b|·|sin θ|^{3/2}, b = v − v₀ − c_p·z (see the module)."""

    k: float
    v0: float
    c_p: float
    rms: float  # of the fit on its training samples, m/s
    samples: int

    def depth_rate(
        self, buoyancy: np.ndarray | float, pitch: np.ndarray | float, depth: np.ndarray | float
    ) -> np.ndarray:
        b = np.asarray(buoyancy, dtype=float) - self.v0 - self.c_p * np.asarray(depth, float)
        return -self.k * glide_regressor_of(b, np.asarray(pitch, dtype=float))

    def step(self, depth: float, buoyancy: float, pitch: float, dt: float) -> float:
        """The depth dt s after ``depth`` with the inputs held."""
        return depth + dt * float(self.depth_rate(buoyancy, pitch, depth))

    def as_dict(self) -> dict[str, float | int]:
        return {
            "k": self.k,
            "v0": self.v0,
            "c_p": self.c_p,
            "rms": self.rms,
            "samples": self.samples,
        }


def _best_k(rate: np.ndarray, shape: np.ndarray) -> tuple[float, float]:
    """(k, sum of squared residuals) of rate ≈ −k·shape by least squares."""
    denom = float(shape @ shape)
    if not denom > 0:
        return 0.0, float(rate @ rate)
    k = -float(shape @ rate) / denom
    residual = rate + k * shape
    return k, float(residual @ residual)


def fit_steady_glide(
    rate: np.ndarray,
    buoyancy: np.ndarray,
    pitch: np.ndarray,
    depth: np.ndarray,
    v0_range: tuple[float, float] | None = None,
) -> SteadyGlide:
    """Least squares of the measured depth rate ``rate`` (m/s, + down) on the model.

    ``v0_range``: where the neutral volume is looked for (default: the inputs' range).
    """
    arrays = [np.asarray(a, dtype=float).ravel() for a in (rate, buoyancy, pitch, depth)]
    ok = np.logical_and.reduce([np.isfinite(a) for a in arrays])
    rate, buoyancy, pitch, depth = (a[ok] for a in arrays)
    if rate.size < 3:
        raise ValueError(f"a steady-glide fit needs at least 3 samples, got {rate.size}")
    low, high = v0_range or (float(buoyancy.min()), float(buoyancy.max()))
    span = max(high - low, 1e-9)
    z_span = max(float(np.max(np.abs(depth))), 1.0)

    def cost(v0: float, c_p: float) -> tuple[float, float]:
        return _best_k(rate, glide_regressor_of(buoyancy - v0 - c_p * depth, pitch))

    best = (math.inf, 0.0, 0.0)
    for v0 in np.linspace(low, high, 41):
        for c_p in np.linspace(-span / z_span, span / z_span, 21):
            _, sse = cost(float(v0), float(c_p))
            if sse < best[0]:
                best = (sse, float(v0), float(c_p))
    sse, v0, c_p = best
    steps = [span / 40.0, span / z_span / 10.0]
    for _ in range(200):  # pattern search, halving the steps when no move helps
        moved = False
        for dv, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            trial = (v0 + dv * steps[0], c_p + dc * steps[1])
            _, value = cost(*trial)
            if value < sse:
                sse, (v0, c_p), moved = value, trial, True
        if not moved:
            steps = [s / 2.0 for s in steps]
            if steps[0] < span * 1e-6:
                break
    k, sse = cost(v0, c_p)
    return SteadyGlide(k, v0, c_p, math.sqrt(sse / rate.size), int(rate.size))


@dataclass(frozen=True)
class StaticPitch:
    """θ = a + b·m + c·v, the linearised moment balance (see the module)."""

    a: float
    b: float
    c: float
    rms: float
    samples: int

    def pitch(self, pitch_input: np.ndarray | float, buoyancy: np.ndarray | float) -> np.ndarray:
        return (
            self.a + self.b * np.asarray(pitch_input, float) + self.c * np.asarray(buoyancy, float)
        )

    def as_dict(self) -> dict[str, float | int]:
        return {"a": self.a, "b": self.b, "c": self.c, "rms": self.rms, "samples": self.samples}


def fit_static_pitch(
    pitch: np.ndarray, pitch_input: np.ndarray, buoyancy: np.ndarray
) -> StaticPitch:
    arrays = [np.asarray(a, dtype=float).ravel() for a in (pitch, pitch_input, buoyancy)]
    ok = np.logical_and.reduce([np.isfinite(a) for a in arrays])
    y, m, v = (a[ok] for a in arrays)
    if y.size < 3:
        raise ValueError(f"a static pitch fit needs at least 3 samples, got {y.size}")
    x = np.column_stack([np.ones(y.size), m, v])
    theta, *_ = np.linalg.lstsq(x, y, rcond=None)
    residual = y - x @ theta
    a, b, c = (float(value) for value in theta)
    return StaticPitch(a, b, c, float(np.sqrt(np.mean(residual**2))), int(y.size))
