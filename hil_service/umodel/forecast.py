"""H-step-ahead forecast under a constant future input, for the inverse controller.

Why not the one-step inverse alone: both stabilised glider channels keep the plant's
non-minimum-phase zeros (depth: z = 1.0045; pitch: a pair of modulus 1.105 and z = −2.57),
and the exact one-step inverse of a non-minimum-phase model is unstable (its input grows
until it saturates). Holding the next input constant and asking the model where the output
will be ``horizon`` steps ahead turns that into a well-posed root-finding problem that
tends to the static inverse as the horizon grows and to the paper's one-step inverse as it
shrinks.

Timing: after ``step`` at sample k the model's history holds y(k) and u(k−1); u(k) has
already been applied (the vehicle reported it), so a command sent now acts from u(k+1) on.
The forecast therefore runs the model from k with u(k) = ``u_applied`` and
u(k+1 …) = u, and returns ŷ(k+H). Because every U-model in this package is affine in its
history, ŷ(k+H) = offset + gain_g·g(u) + gain_u·u, where g is the model's static input map
(RBF term plus polynomial); the affine coefficients come from one pass over the horizon and
Newton then needs only g and g′.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from .models import DynamicUModel, PaperUModel


class ForecastableModel(Protocol):
    def static_map(self, u: float) -> tuple[float, float]:
        """g(u) and g′(u): the part of ŷ that depends on u(t−1) through RBF and powers."""
        ...

    def affine_parts(self) -> tuple[float, list[float], list[float], list[float], list[float]]:
        """(bias, a, b, y_hist, u_hist): ŷ(t) = bias + Σa_i·y_hist_i + Σb_m·u_hist_m + g(u(t−1)).

        ``y_hist`` = y(t−1 …) in the units ``a`` multiplies, ``u_hist`` = u(t−2 …).
        """
        ...


@dataclass(frozen=True)
class Forecast:
    offset: float
    gain_g: float
    gain_u: float
    static_map: Callable[[float], tuple[float, float]]

    def value(self, u: float) -> float:
        return self.offset + self.gain_g * self.static_map(u)[0] + self.gain_u * u

    def derivative(self, u: float) -> float:
        return self.gain_g * self.static_map(u)[1] + self.gain_u


def forecast(model: ForecastableModel, u_applied: float, horizon: int) -> Forecast:
    """ŷ(k+horizon) as an affine function of g(u) and u; ``horizon`` ≥ 2."""
    if horizon < 2:
        raise ValueError("horizon must be >= 2: y(k+1) no longer depends on the command")
    bias, a, b, y_hist, u_hist = model.affine_parts()
    g_applied = model.static_map(u_applied)[0]
    # Each quantity is a triple (constant, coefficient of g(u), coefficient of u).
    ys: list[tuple[float, float, float]] = [(v, 0.0, 0.0) for v in y_hist]  # y(k), y(k−1)…
    us: list[tuple[float, float]] = [(v, 0.0) for v in u_hist]  # u(k−1), u(k−2)…: (const, coef u)
    result = (0.0, 0.0, 0.0)
    for j in range(1, horizon + 1):
        # predicting y(k+j): input u(k+j−1) drives g; older inputs are us[0], us[1], …
        if j == 1:
            const, cg, cu = bias + g_applied, 0.0, 0.0
        else:
            const, cg, cu = bias, 1.0, 0.0
        for coefficient, (yc, yg, yu) in zip(a, ys, strict=False):
            const += coefficient * yc
            cg += coefficient * yg
            cu += coefficient * yu
        for coefficient, (uc, uu) in zip(b, us, strict=False):
            const += coefficient * uc
            cu += coefficient * uu
        result = (const, cg, cu)
        if ys:
            ys = [result, *ys[:-1]]
        if us:
            newest = (u_applied, 0.0) if j == 1 else (0.0, 1.0)
            us = [newest, *us[:-1]]
    return Forecast(result[0], result[1], result[2], model.static_map)


class _UModelView:
    """Reads a paper or dynamic U-model's current parameters and history for ``forecast``.

    The layout is the one documented in :mod:`.models`: θ = [RBF weights, α₁..α_M, bias,
    a₁..a_na, b₂..b_nb] and the regressor tail [1, y(t−1..t−na)/y_scale, u(t−2..t−nb)].
    """

    def __init__(self, model: Any):
        self._model = model

    def static_map(self, u: float) -> tuple[float, float]:
        model = self._model
        value, slope = model._eval_both(u)
        return value - model._linear_const(), slope

    def affine_parts(self) -> tuple[float, list[float], list[float], list[float], list[float]]:
        model = self._model
        if not isinstance(model, DynamicUModel):
            return 0.0, [], [], [], []
        theta, phi, scale = model._theta, model._phi, model.y_scale
        i_y, i_u = model._i_y, model._i_u
        return (
            float(theta[i_y - 1]),
            [float(v) / scale for v in theta[i_y:i_u]],
            [float(v) for v in theta[i_u:]],
            [float(v) * scale for v in phi[i_y:i_u]],
            [float(v) for v in phi[i_u:]],
        )


def forecast_model(model: Any, u_applied: float, horizon: int) -> Forecast:
    """``forecast`` for the package's U-models (paper and dynamic)."""
    if not isinstance(model, PaperUModel | DynamicUModel):
        raise TypeError(f"no H-step forecast for {type(model).__name__}")
    return forecast(_UModelView(model), u_applied, horizon)
