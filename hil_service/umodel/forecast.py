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
The forecast runs the model from k with u(k) = ``u_applied`` and u(k+1 …) = u, and returns
ŷ(k+H). Every U-model here is linear in its past outputs and a sum of static maps of each
input lag, so ŷ(k+H) = offset + Σ_m gain_m·map_m(u): two linear filter runs give the offset and
gains, and Newton then needs only the maps and their analytic derivatives.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.signal import lfilter, lfiltic

from .models import DynamicUModel, PaperUModel

InputMap = Callable[[float], tuple[float, float]]


@dataclass
class Forecast:
    offset: float
    gains: tuple[float, ...]  # one per input lag 1..nb
    maps: tuple[InputMap, ...]
    grid_maps: Callable[[np.ndarray], list[np.ndarray]] | None = None
    _last: tuple[float, float, float] | None = field(default=None, repr=False)

    def _evaluate(self, u: float) -> tuple[float, float]:
        # Newton asks for the value and the slope at the same u: evaluate the maps once.
        last = self._last
        if last is not None and last[0] == u:
            return last[1], last[2]
        total, slope = self.offset, 0.0
        for gain, input_map in zip(self.gains, self.maps, strict=True):
            if gain:
                value, derivative = input_map(u)
                total += gain * value
                slope += gain * derivative
        self._last = (u, total, slope)
        return total, slope

    def value(self, u: float) -> float:
        return self._evaluate(u)[0]

    def derivative(self, u: float) -> float:
        return self._evaluate(u)[1]

    def values(self, us: np.ndarray) -> np.ndarray:
        """``value`` on an array at once (the inverse solver's fallback grid)."""
        if self.grid_maps is None:
            return np.array([self.value(float(u)) for u in us])
        total = np.full(len(us), self.offset)
        for gain, column in zip(self.gains, self.grid_maps(us), strict=True):
            if gain:
                total += gain * column
        return total


def forecast_linear(
    bias: float,
    ar: Sequence[float],
    outputs: Sequence[float],
    maps: Sequence[InputMap],
    past_inputs: Sequence[float],
    u_applied: float,
    horizon: int,
) -> Forecast:
    """ŷ(k+horizon) for ŷ(t) = bias + Σ ar_i·y(t−i) + Σ_m map_m(u(t−m)).

    ``outputs`` = y(k), y(k−1), …; ``past_inputs`` = u(k−1), u(k−2), …; u(k) = ``u_applied``
    and every later input is the unknown u. The recursion is linear, so the answer is the
    response to the known forcing and initial outputs plus, for each input lag L, the sum
    of the first H−L impulse-response samples times map_L(u): two IIR filter runs.
    """
    if horizon < 2:
        raise ValueError("horizon must be >= 2: y(k+1) no longer depends on the command")
    known_inputs = [u_applied, *past_inputs]  # u(k), u(k−1), …
    forcing = np.full(horizon, float(bias))
    for lag, input_map in enumerate(maps, start=1):
        for j in range(1, min(lag, horizon) + 1):  # steps where lag L still sees a known input
            back = lag - j  # 0 → u(k), 1 → u(k−1), …
            if back < len(known_inputs):
                forcing[j - 1] += input_map(known_inputs[back])[0]
    denominator = np.concatenate(([1.0], -np.asarray(ar, dtype=float)))
    n_state = len(denominator) - 1
    if n_state:
        initial = lfiltic([1.0], denominator, y=list(outputs)[:n_state])
        known = lfilter([1.0], denominator, forcing, zi=initial)[0]
    else:
        known = forcing
    impulse = np.zeros(horizon)
    impulse[0] = 1.0
    cumulative = np.cumsum(lfilter([1.0], denominator, impulse))
    gains = tuple(
        float(cumulative[horizon - lag - 1]) if horizon - lag - 1 >= 0 else 0.0
        for lag in range(1, len(maps) + 1)
    )
    return Forecast(float(known[-1]), gains, tuple(maps))


def forecast_model(model: Any, u_applied: float, horizon: int) -> Forecast:
    """``forecast_linear`` for the package's U-models (paper and dynamic)."""
    if isinstance(model, DynamicUModel):
        theta = model._theta

        def static(u: float) -> tuple[float, float]:
            value, slope = model._eval_both(u)
            return value - model._linear_const(), slope

        maps: list[InputMap] = [static]
        maps += [(lambda u, lag=lag: model.lag_map(lag, u)) for lag in range(2, model.nb + 1)]

        def grid(us: np.ndarray) -> list[np.ndarray]:
            static_values = model.output_given_inputs(us) - model._linear_const()
            return [static_values, *model.lag_maps_on_grid(us)]

        result = forecast_linear(
            bias=theta[model._np],
            ar=model.ar_coefficients(),
            outputs=model._levels,
            maps=maps,
            past_inputs=model._inputs,
            u_applied=u_applied,
            horizon=horizon,
        )
        return replace(result, grid_maps=grid)
    if isinstance(model, PaperUModel):
        result = forecast_linear(0.0, [], [], [model._eval_both], [], u_applied, horizon)
        return replace(result, grid_maps=lambda us: [model.output_given_inputs(us)])
    raise TypeError(f"no H-step forecast for {type(model).__name__}")
