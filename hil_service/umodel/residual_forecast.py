"""A forecast of the disturbance over the horizon, for the predictive inverse (opt-in).

The predictive inverse holds its disturbance estimate constant over the horizon: the
residual y − y_m of its internal model, low-passed (``PredictiveInverse.track``). A
disturbance that oscillates (a wave, a periodic current) or decays (a coloured one) is then
chased one lagged level at a time. Here the residual's departure from that level,
x = y − y_m − d̂, is fitted by an AR(2) model, x(t) = a₁·x(t−1) + a₂·x(t−2), by recursive
least squares with forgetting, and the plan is given d̂ + x̂(t+j) at each cost point j
instead of d̂. An AR(2) holds a sinusoid exactly (roots e^{±iω}) and a first-order decay,
and forecasts white noise as 0, where the level alone remains.

The forecast is used only while it has predicted the residual clearly better than the
level did: the mean square of its one-step errors below ``ratio`` times the level's
(both exponentially weighted over about ``1 / AVERAGING`` samples), after ``MIN_SAMPLES``
samples, with the fitted AR part's forecast not growing. Its prior is set from the first
deviations it sees, so that the fit does not depend on the output's units.

Pure arithmetic, no I/O; compiled with the controller (``protocols.compiled.HOT_PATH``).
"""

from __future__ import annotations

from .finite import finite

#: Samples of the residual before the forecast may be used.
MIN_SAMPLES = 200
#: The weight of a new one-step error in the two running mean squares (≈ 100 samples).
AVERAGING = 0.01
#: RLS forgetting factor (a memory of ≈ 200 samples).
FORGETTING = 0.995
#: The prior's weight against the first deviations' mean square: a weak prior.
PRIOR = 1e4
#: How far outside the unit circle's stability triangle the AR part may reach: a
#: sinusoid's roots lie on the circle (a₂ = −1), and its fit a rounding error either side.
#: A root of modulus 1 + 1e-6 grows a forecast by 0.1 % over the longest horizon (1,000).
STABILITY_MARGIN = 1e-6


class ResidualForecast:
    """AR(2) of the residual's departure from the disturbance level, by RLS."""

    __slots__ = ("_a1", "_a2", "_err_ar", "_err_level", "_n", "_p", "_seen", "_x1", "_x2")

    def __init__(self) -> None:
        self._a1 = 0.0
        self._a2 = 0.0
        self._p = [0.0, 0.0, 0.0]  # P (2 × 2, symmetric): p11, p12, p22
        self._x1 = 0.0  # x(t), x(t − 1)
        self._x2 = 0.0
        self._seen = 0  # deviations seen since the last reset (0, 1, 2: the history fills)
        self._n = 0  # RLS updates
        self._err_ar = 0.0
        self._err_level = 0.0

    def observe(self, deviation: float, level_error: float) -> None:
        """The newest residual's departure from the level ``deviation`` (x(t)), and the
        error with which the level held from the sample before predicted the residual."""
        if not (finite(deviation) and finite(level_error)):
            return
        if self._seen < 2:
            self._x2, self._x1 = self._x1, deviation
            self._seen += 1
            if self._seen == 2:
                scale = self._x1 * self._x1 + self._x2 * self._x2
                weight = PRIOR / scale if scale > 0.0 else PRIOR
                self._p = [weight, 0.0, weight]
            return
        x1, x2 = self._x1, self._x2
        error = deviation - (self._a1 * x1 + self._a2 * x2)
        self._err_ar += AVERAGING * (error * error - self._err_ar)
        self._err_level += AVERAGING * (level_error * level_error - self._err_level)
        p11, p12, p22 = self._p
        g1 = p11 * x1 + p12 * x2
        g2 = p12 * x1 + p22 * x2
        denominator = FORGETTING + x1 * g1 + x2 * g2
        if finite(denominator) and denominator > 0.0:
            k1, k2 = g1 / denominator, g2 / denominator
            a1, a2 = self._a1 + k1 * error, self._a2 + k2 * error
            q11 = (p11 - k1 * g1) / FORGETTING
            q12 = (p12 - k1 * g2) / FORGETTING
            q22 = (p22 - k2 * g2) / FORGETTING
            if finite(a1) and finite(a2) and finite(q11) and finite(q12) and finite(q22):
                self._a1, self._a2 = a1, a2
                self._p = [q11, q12, q22]
        self._n += 1
        self._x2, self._x1 = x1, deviation

    def stable(self) -> bool:
        """The AR part's roots inside or on the unit circle (the stability triangle): its
        forecast does not grow."""
        a1, a2 = self._a1, self._a2
        limit = 1.0 + STABILITY_MARGIN
        return abs(a2) <= limit and a1 + a2 <= limit and a2 - a1 <= limit

    def confident(self, ratio: float) -> bool:
        """Whether to plan with the forecast: enough samples, a stable AR part, and one-step
        errors whose mean square is below ``ratio`` times the level's."""
        return self._n >= MIN_SAMPLES and self.stable() and self._err_ar < ratio * self._err_level

    def forecast(self, level: float, points: list[int]) -> list[float]:
        """level + x̂(t + j) for each j of ``points`` (j ≥ 1, any order)."""
        last = 0
        for j in points:
            last = max(last, j)
        ahead = [0.0] * (last + 1)
        a1, a2 = self._a1, self._a2
        x1, x2 = self._x1, self._x2
        for j in range(1, last + 1):
            x = a1 * x1 + a2 * x2
            ahead[j] = x
            x2, x1 = x1, x
        return [level + ahead[j] for j in points]

    @property
    def coefficients(self) -> tuple[float, float]:
        return self._a1, self._a2
