"""A forecast of the disturbance over the horizon, for the predictive inverse.

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
samples, with the fitted AR part's forecast not growing; and over the horizon only as far
as it has predicted there: at leads 2, 4, 8, … and the plan's last cost point
(``hold``) the forecasts made that many samples before are compared with the
residual, and the plan is given the forecast up to the longest lead below which every
checked lead's mean square error is smaller than the level's (held from then), and the
level beyond it. One-step skill alone is not enough: a smooth residual is fitted with
roots near 1 (a₁ ≈ 2, a₂ ≈ −1 extrapolates its slope, a₁ + a₂ ≈ 1 its momentum), which
predicts the next sample well and the horizon's end badly. Its prior is set from the first
deviations it sees, so that the fit does not depend on the output's units.

The coefficients the forecasts use are held from one derivation of the plan to the next
(``hold``), as the plan's model is, so that the plan's projections of them are fixed in
between and a sample costs two numbers per block; the fit itself goes on every sample.

Pure arithmetic, no I/O; compiled with the controller (``protocols.compiled.HOT_PATH``).
"""

from __future__ import annotations

import math

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


class _LeadCheck:
    """The forecasts made ``lead`` samples ago, and how well they and the level held from
    then have predicted the residual since (exponentially weighted mean squares)."""

    __slots__ = ("checked", "err_forecast", "err_level", "lead", "level", "made", "predicted")

    def __init__(self, lead: int) -> None:
        self.lead = lead
        self.predicted = [0.0] * lead  # ring: the forecast of the residual at its slot's time
        self.level = [0.0] * lead  # ring: the level when that forecast was made
        self.made = 0  # forecasts made
        self.checked = 0  # forecasts compared with the residual they forecast
        self.err_forecast = 0.0
        self.err_level = 0.0

    def compare(self, residual: float) -> None:
        """The residual that the forecast made ``lead`` samples ago was for."""
        if self.made < self.lead:
            return
        slot = self.made % self.lead
        if not finite(self.predicted[slot]):
            return  # no forecast was made then
        forecast_error = residual - self.predicted[slot]
        level_error = residual - self.level[slot]
        self.err_forecast += AVERAGING * (forecast_error * forecast_error - self.err_forecast)
        self.err_level += AVERAGING * (level_error * level_error - self.err_level)
        self.checked += 1

    def keep(self, predicted: float, level: float) -> None:
        slot = self.made % self.lead
        self.predicted[slot] = predicted
        self.level[slot] = level
        self.made += 1

    def passed(self) -> bool:
        return self.checked >= MIN_SAMPLES and self.err_forecast < self.err_level


class ResidualForecast:
    """AR(2) of the residual's departure from the disturbance level, by RLS."""

    __slots__ = (
        "_a1",
        "_a2",
        "_checks",
        "_err_ar",
        "_err_level",
        "_held_stable",
        "_n",
        "_p",
        "_refill",
        "_seen",
        "_u",
        "_v",
        "_x1",
        "_x2",
    )

    def __init__(self) -> None:
        self._a1 = 0.0
        self._a2 = 0.0
        self._p = [0.0, 0.0, 0.0]  # P (2 × 2, symmetric): p11, p12, p22
        self._x1 = 0.0  # x(t), x(t − 1)
        self._x2 = 0.0
        self._seen = 0  # deviations seen since the last reset (0, 1, 2: the history fills)
        self._refill = 0  # samples until the history is whole again after a lost one
        self._n = 0  # RLS updates
        self._err_ar = 0.0
        self._err_level = 0.0
        self._checks: list[_LeadCheck] = []
        # The held forecast: x̂(t + j) = u[j]·x(t) + v[j]·x(t − 1) (``hold``).
        self._u: list[float] = []
        self._v: list[float] = []
        self._held_stable = False

    def hold(self, points: list[int]) -> None:
        """Hold today's coefficients for the forecasts until the next call (the plan's
        derivation: its model is held as long), and check them at leads 2, 4, 8, … below
        the plan's last cost point and at that point (``points``: j ≥ 1); leads already
        checked keep their record."""
        last = 0
        for j in points:
            last = max(last, j)
        a1, a2 = self._a1, self._a2
        u = [1.0, a1]
        v = [0.0, a2]
        for j in range(2, last + 1):
            u.append(a1 * u[j - 1] + a2 * u[j - 2])
            v.append(a1 * v[j - 1] + a2 * v[j - 2])
        self._u, self._v = u, v
        self._held_stable = self.stable()
        leads = []
        lead = 2
        while lead < last:
            leads.append(lead)
            lead *= 2
        if last > 1:
            leads.append(last)
        if [c.lead for c in self._checks] != leads:
            kept = {c.lead: c for c in self._checks}
            self._checks = [kept.get(lead) or _LeadCheck(lead) for lead in leads]

    def observe(self, residual: float, level: float, previous_level: float) -> None:
        """The newest residual y − y_m, the level estimated with it and the level before it."""
        deviation = residual - level
        level_error = residual - previous_level
        if not (finite(deviation) and finite(level_error)):
            self.skip()
            return
        for check in self._checks:
            check.compare(residual)
        if self._seen < 2:
            self._x2, self._x1 = self._x1, deviation
            self._seen += 1
            if self._seen == 2:
                scale = self._x1 * self._x1 + self._x2 * self._x2
                weight = PRIOR / scale if scale > 0.0 else PRIOR
                self._p = [weight, 0.0, weight]
            return
        if self._refill > 0:
            # After a lost sample: the history fills again before the fit learns from it
            # or forecasts from it (x(t − 1) would be the sample before the loss).
            self._x2, self._x1 = self._x1, deviation
            self._refill -= 1
            self._keep_forecasts(level, math.nan if self._refill else deviation, self._x2)
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
        self._keep_forecasts(level, deviation, x1)

    def _keep_forecasts(self, level: float, x1: float, x2: float) -> None:
        """Each lead check's forecast from the departures ``x1`` = x(t), ``x2`` = x(t − 1)
        (NaN: none). Only a forecast that could be planned with is judged: a growing AR
        part's is not."""
        stable = self._held_stable and finite(x1)
        u, v = self._u, self._v
        for check in self._checks:
            ahead = u[check.lead] * x1 + v[check.lead] * x2 if stable else math.nan
            check.keep(level + ahead, level)

    def skip(self) -> None:
        """A sample without a residual (its output lost, or not finite): every lead check
        moves on by one sample, comparing nothing and forecasting nothing from it, so that
        each goes on comparing a forecast with the residual of the sample it was made for;
        and the fit waits for two samples in a row again before it learns or forecasts
        (while its history is first filling, the fill starts again)."""
        for check in self._checks:
            check.keep(math.nan, math.nan)
        if self._seen >= 2:
            self._refill = 2
        else:
            self._seen = 0

    def stable(self) -> bool:
        """The AR part's roots inside or on the unit circle (the stability triangle): its
        forecast does not grow."""
        a1, a2 = self._a1, self._a2
        limit = 1.0 + STABILITY_MARGIN
        return abs(a2) <= limit and a1 + a2 <= limit and a2 - a1 <= limit

    def confident(self, ratio: float) -> bool:
        """Whether to plan with the forecast: enough samples, held coefficients whose
        forecast does not grow, and one-step errors whose mean square is below ``ratio``
        times the level's."""
        return (
            self._n >= MIN_SAMPLES and self._held_stable and self._err_ar < ratio * self._err_level
        )

    def trusted_lead(self) -> int:
        """The longest lead up to which every checked lead's forecast has beaten the level
        (1 where the first has not: the one-step test's; the longest point where nothing is
        checked)."""
        trusted = 1
        for check in self._checks:
            if not check.passed():
                return trusted
            trusted = check.lead
        return trusted if self._checks else 1 << 30

    def weights(self, points: list[int], trusted: int) -> tuple[list[float], list[float]]:
        """(u, v) at each of ``points`` (held ones): x̂(t + j) = u·x(t) + v·x(t − 1) up to the
        lead ``trusted``, 0 beyond it (the level alone)."""
        u, v = self._u, self._v
        us: list[float] = []
        vs: list[float] = []
        for j in points:
            inside = j <= trusted and j < len(u)
            us.append(u[j] if inside else 0.0)
            vs.append(v[j] if inside else 0.0)
        return us, vs

    def state(self) -> tuple[float, float]:
        """(x(t), x(t − 1)): the newest departures from the level."""
        return self._x1, self._x2

    @property
    def coefficients(self) -> tuple[float, float]:
        return self._a1, self._a2
