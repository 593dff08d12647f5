"""A two-input U-model of a glider's depth: the buoyancy input and the measured pitch.

The single-input U-model of depth (``dynamic``) sees the buoyancy input u alone, while the
vertical speed of a glider depends as much on its pitch θ: in steady flight (the flight
model of :mod:`.steady_glide`, Graver 2005 ch. 3, Merckelbach et al. 2010)

    ż = −k · sign(b) · √|b| · |sin θ|^{3/2},   b = u − v₀ − c_p·z.

This model keeps the U-model's structure, a polynomial in its input whose coefficients
vary with time, and depth integrates with a unit coefficient on y(t−1). Its input is one
of two (``feature``):

* ``"buoyancy"``: the buoyancy input x = u / u_scale, the pitch setting the coefficients as
  the flight model does::

      y(t) = α₀(t) + Σ_{m=1..M} α_m(t) · x(t−1)^m,
      α_m(t) = β_m · s(t−1),                                 s = |sin θ|^{3/2},
      α₀(t) = y(t−1) + c + β₀ · s(t−1) + γ · s(t−1) · ζ(t−1),  ζ = y / y_scale.

  The polynomial β₀ + Σ β_m x^m stands for sign(b)·√|b| (the neutral volume v₀ in β₀ and the
  lower powers, the sign change and the square root in the odd and even powers), γ·ζ for
  the hull's compression with depth (c_p);

* ``"steady-glide"``: the flight model's own regressor g = sign(b)·√|b|·|sin θ|^{3/2},
  b = u − v₀ − c_p·y, with the neutral volume v₀ (input units) and c_p (per metre) given
  (the least-squares flight model's, :func:`.steady_glide.fit_steady_glide`, fitted on the
  same training samples before the model learns)::

      y(t) = α₀(t) + Σ_{m=1..M} α_m(t) · g(t−1)^m,   α_m = β_m,   α₀(t) = y(t−1) + c.

  Of degree 1 without the drift it is the flight model (β₁ = −k·Δt); the higher powers
  are how far the measured depth rate departs from the square-root law on this glider (a
  glide angle that is not the pitch, a drag coefficient that varies with speed, a buoyancy
  that varies with depth otherwise than linearly), learnt as the U-model learns its
  polynomial.

c, a steady vertical drift, only with ``drift=True`` (the default). The feature, the degree
M and the drift are the structure, chosen per data set on its training dives by
``offline/field/structure.py``. Depth is the integral of the vertical speed, so the output
enters as y(t−1) with a unit coefficient (an integrator from physics, not a fitted a₁ ≈ 1
whose error would grow over a thousand-metre free run). Every term is linear in the
parameters θ (``buoyancy``: [β₁..β_M, β₀, (c,) γ]; ``steady-glide``: [β₁..β_M, (c)]):
recursive least squares with forgetting (``ListRLS``, sums in a fixed order:
deterministic, no random initialisation).

Inputs: ``step(u_prev, y, pitch_prev)`` with u_prev = u(t−1), the buoyancy input applied
before y(t) was measured, and pitch_prev = θ(t−1) in radians, the pitch measured then
(see :mod:`.models` for the timing convention). A sample whose input, pitch or output is
non-finite or absurd (beyond the guard's limits; |θ| > π) is rejected without touching the
state, divergence is detected as in every other model (:mod:`.guards`), and ``predict``
never returns NaN.

Not a controller model: it has no multi-step map (``dynamics()``), since the pitch it needs
is a measurement, not a command the controller chooses. Pure numerics, no I/O.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

from .guards import DivergenceMonitor, GuardConfig
from .models import Estimate, Status
from .reproducible import dot
from .rls import ListRLS

__all__ = ["FEATURES", "GlideUModel", "glide_factor", "glide_regressor", "steady_glide_feature"]

_isfinite = math.isfinite

#: The model's input: the buoyancy input scaled by the pitch, or the flight model's regressor.
FEATURES = ("buoyancy", "steady-glide")


def glide_factor(pitch: float) -> float:
    """|sin θ|^{3/2}, the flight model's pitch dependence of the vertical speed."""
    return abs(math.sin(pitch)) ** 1.5


def steady_glide_feature(u: float, pitch: float, y: float, v0: float, c_p: float) -> float:
    """g = sign(b)·√|b|·|sin θ|^{3/2}, b = u − v₀ − c_p·y: the flight model's ż = −k·g."""
    b = u - v0 - c_p * y
    return math.copysign(math.sqrt(abs(b)), b) * glide_factor(pitch)


def glide_regressor(
    u: float,
    pitch: float,
    y: float,
    degree: int,
    u_scale: float,
    y_scale: float,
    drift: bool = True,
    feature: str = "buoyancy",
    v0: float = 0.0,
    c_p: float = 0.0,
) -> list[float]:
    """φ(t) of ŷ(t) − y(t−1) = θ·φ(t) from u = u(t−1), pitch = θ(t−1), y = y(t−1).

    ``feature="steady-glide"``: [g, g², …, g^M, (1)] with g = ``steady_glide_feature``
    (``u_scale`` and ``y_scale`` unused); else the buoyancy input's regressor."""
    if feature == "steady-glide":
        g = steady_glide_feature(u, pitch, y, v0, c_p)
        phi = []
        p = 1.0
        for _ in range(degree):
            p *= g
            phi.append(p)
        if drift:
            phi.append(1.0)
        return phi
    s = glide_factor(pitch)
    x = u / u_scale
    phi = []
    p = 1.0
    for _ in range(degree):
        p *= x
        phi.append(s * p)
    phi.append(s)
    if drift:
        phi.append(1.0)
    phi.append(s * y / y_scale)
    return phi


class GlideUModel:
    """Depth from the buoyancy input and the measured pitch (see the module)."""

    name: ClassVar[str] = "glide-u"

    def __init__(
        self,
        *,
        degree: int = 3,
        u_scale: float = 2.0,
        y_scale: float = 100.0,
        lam: float = 0.9999,
        p0: float = 1000.0,
        drift: bool = True,
        feature: str = "buoyancy",
        v0: float = 0.0,
        c_p: float = 0.0,
        guard: GuardConfig | dict[str, Any] | None = None,
    ) -> None:
        if int(degree) != degree or degree < 1:
            raise ValueError("degree M must be an integer >= 1")
        for label, value in (("u_scale", u_scale), ("y_scale", y_scale)):
            if not (isinstance(value, int | float) and _isfinite(value) and value > 0.0):
                raise ValueError(f"{label} must be finite and > 0, got {value!r}")
        if feature not in FEATURES:
            raise ValueError(f"feature must be one of {FEATURES}, got {feature!r}")
        for label, value in (("v0", v0), ("c_p", c_p)):
            if not (isinstance(value, int | float) and _isfinite(value)):
                raise ValueError(f"{label} must be finite, got {value!r}")
        self.guard = GuardConfig.coerce(guard)
        self.degree = int(degree)
        self.u_scale = float(u_scale)
        self.y_scale = float(y_scale)
        self.drift = bool(drift)
        self.feature = feature
        self.v0 = float(v0)
        self.c_p = float(c_p)
        if feature == "steady-glide":
            n = self.degree + (1 if self.drift else 0)
        else:
            n = self.degree + (3 if self.drift else 2)
        self.rls = ListRLS(n, lam, p0)
        self._monitor = DivergenceMonitor(self.guard)
        self._theta: list[float] = [0.0] * n
        self._phi: list[float] = [0.0] * n
        self._frozen = False
        self._primed = False
        self._y_last = 0.0
        self._u_last = 0.0
        self._pitch_last = 0.0
        self._n_accepted = 0
        self._n_rejected = 0

    # ---- the regressor -----------------------------------------------------------------
    def _regressor(self, u: float, pitch: float) -> list[float]:
        return glide_regressor(
            u,
            pitch,
            self._y_last,
            self.degree,
            self.u_scale,
            self.y_scale,
            self.drift,
            self.feature,
            self.v0,
            self.c_p,
        )

    def _valid(self, u: float, pitch: float) -> bool:
        return (
            _isfinite(u)
            and abs(u) <= self.guard.input_limit
            and _isfinite(pitch)
            and abs(pitch) <= math.pi
        )

    def _output_ok(self, y: float) -> bool:
        return _isfinite(y) and abs(y) <= self.guard.output_limit

    # ---- public API --------------------------------------------------------------------
    @property
    def history_length(self) -> int:
        """One sample: y(t−1) with u(t−1) and θ(t−1)."""
        return 1

    @property
    def frozen(self) -> bool:
        return self._frozen

    @property
    def parameters(self) -> tuple[float, ...]:
        """θ = (β₁..β_M, β₀, c, γ) (``buoyancy``) or (β₁..β_M, c) (``steady-glide``),
        without c when ``drift`` is off."""
        return tuple(self._theta)

    def predict(self, u_prev: float, pitch_prev: float) -> float:
        """A-priori ŷ(t); invalid inputs are replaced by the last accepted ones, a
        non-finite result by the last accepted output. No mutation."""
        if not self._valid(u_prev, pitch_prev):
            u_prev, pitch_prev = self._u_last, self._pitch_last
        if not self._primed:
            return self._y_last
        y_hat = self._y_last + dot(self._theta, self._regressor(u_prev, pitch_prev))
        return y_hat if _isfinite(y_hat) else self._y_last

    def observe_only(self, u_prev: float, y: float, pitch_prev: float) -> bool:
        """Advance the history by one sample without learning (after a gap, or a free run
        fed its own predictions); invalid values are ignored (False)."""
        if not (self._valid(u_prev, pitch_prev) and self._output_ok(y)):
            return False
        self._remember(u_prev, y, pitch_prev)
        return True

    def step(self, u_prev: float, y: float, pitch_prev: float) -> Estimate:
        """Predict ŷ(t) from u(t−1), θ(t−1) and y(t−1), then learn from y(t)."""
        if not (self._valid(u_prev, pitch_prev) and self._output_ok(y)):
            self._n_rejected += 1
            y_hat = self.predict(u_prev, pitch_prev)
            return Estimate(
                self.name,
                "rejected",
                y if _isfinite(y) else y_hat,
                y_hat,
                0.0,
                self._alpha(self._u_last, self._pitch_last, y_hat),
                tuple(self._theta),
            )
        if not self._primed:  # no y(t−1) yet: nothing to predict from
            self._remember(u_prev, y, pitch_prev)
            self._n_accepted += 1
            return Estimate(self.name, "ok", y, y, 0.0, (y,), tuple(self._theta))
        phi = self._regressor(u_prev, pitch_prev)
        y_hat = self._y_last + dot(self._theta, phi)
        status: Status = "frozen" if self._frozen else "ok"
        if not _isfinite(y_hat):
            y_hat = self._y_last
            self._diverged()
            status = "diverged"
        error = y - y_hat
        alpha = self._alpha(u_prev, pitch_prev, y_hat)
        weights = tuple(self._theta)
        if status == "ok" and not (self.rls.update(self._theta, phi, error) and self._params_ok()):
            self._diverged()
            status = "diverged"
        if status != "diverged" and self._monitor.observe(y, error):
            self._diverged()
            status = "diverged"
        self._remember(u_prev, y, pitch_prev)
        self._n_accepted += 1
        return Estimate(self.name, status, y, y_hat, error, alpha, weights)

    def unfreeze(self) -> None:
        self._frozen = False
        self._monitor.count = 0

    def reset(self) -> None:
        """Back to the freshly constructed state."""
        self._theta = [0.0] * len(self._theta)
        self.rls.reset()
        self._monitor.reset()
        self._frozen = False
        self._primed = False
        self._y_last = self._u_last = self._pitch_last = 0.0
        self._n_accepted = self._n_rejected = 0

    def config(self) -> dict[str, Any]:
        """JSON-serialisable construction parameters: ``GlideUModel(**cfg)`` minus the name
        rebuilds the same model."""
        return {
            "name": self.name,
            "degree": self.degree,
            "u_scale": self.u_scale,
            "y_scale": self.y_scale,
            "lam": self.rls.lam,
            "p0": self.rls.p0,
            "drift": self.drift,
            "feature": self.feature,
            "v0": self.v0,
            "c_p": self.c_p,
            "guard": self.guard.to_dict(),
        }

    def snapshot(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "theta": list(self._theta),
            "frozen": self._frozen,
            "y_last": self._y_last,
            "u_last": self._u_last,
            "pitch_last": self._pitch_last,
            "n_accepted": self._n_accepted,
            "n_rejected": self._n_rejected,
            "monitor": self._monitor.state(),
        }

    # ---- internals ---------------------------------------------------------------------
    def _alpha(self, u: float, pitch: float, y_hat: float) -> tuple[float, ...]:
        """(α₀, α₁..α_M) that produced ``y_hat``: y_hat = α₀ + Σ α_m w^m, w the input u
        (``buoyancy``) or g = ``steady_glide_feature`` of u, the pitch and y(t−1)
        (``steady-glide``)."""
        if self.feature == "steady-glide":
            w = steady_glide_feature(u, pitch, self._y_last, self.v0, self.c_p)
            poly = list(self._theta[: self.degree])
        else:
            w = u
            s = glide_factor(pitch)
            poly = [self._theta[m] * s / self.u_scale ** (m + 1) for m in range(self.degree)]
        a0 = y_hat
        p = 1.0
        for a in poly:
            p *= w
            a0 -= a * p
        return (a0, *poly)

    def _remember(self, u: float, y: float, pitch: float) -> None:
        self._primed = True
        self._y_last = y
        self._u_last = u
        self._pitch_last = pitch

    def _params_ok(self) -> bool:
        limit = self.guard.param_limit
        return dot(self._theta, self._theta) <= limit * limit

    def _diverged(self) -> None:
        mon = self._monitor
        mon.n_divergences += 1
        mon.count = 0
        if self.guard.on_divergence == "reset" or not self._params_ok():
            self._theta = [0.0] * len(self._theta)
            self.rls.reset()
        if self.guard.on_divergence == "freeze":
            self._frozen = True
