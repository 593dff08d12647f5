"""Do no harm: the horizon test that qualifies a model to command, and the closed-loop
supervisor that stops a loop making things worse (docs/control.md, "Do no harm").

Both are pure and scale-free: every threshold is a ratio of two errors measured on the
channel's own data, or a count of samples derived from the identified horizon.

**Horizon test.** Today's model, frozen, runs free on the applied inputs from the measured
outputs at segment starts k (the control horizon) apart, so each sample of a segment is
a j-step prediction, j = 1 … k. Beside it, the "hold" prediction is the output at the
segment's start, held. Over the last ``max(window, k)`` samples

    horizon fit = 100 · (1 − ‖y − ŷ_model‖ / ‖y − y_hold‖)   (%)

and against the mean ȳ of the outputs scored (the prediction "nothing but the level")

    mean fit = 100 · (1 − ‖y − ŷ_model‖ / ‖y − ȳ‖)   (%)

The model qualifies when at least k consecutive samples recorded since the last
disqualifying event (a trip, a vehicle restart, a divergence, a telemetry gap not bridged)
give a fit of at least ``threshold`` and, when a ``mean_threshold`` is set, a mean fit of
at least that: on a white-noise output, predicting the mean scores 29 % against holding
and 0 % against the mean. A bridged gap's samples are in the record as not
measured (``record_missing``): the model runs across them, no prediction is scored there.

**Supervisor.** While a channel commands, a second frozen copy of the model runs free on
the applied inputs over segments of ``window`` samples (the horizon, clamped), restarted
from the measured outputs. At each segment's end the segment is judged:

* ``against``: the output moved one way and the model predicted the other, both by more
  than the prediction's bound;
* ``saturated``: the command saturated the whole segment and the tracking error did not
  fall (the mean |error| over its last tenth against its first tenth, the start
  included), or saturated at least 90 % of it and the mean |tracking error| over it was
  not below the first tenth's;
* ``beyond``: the prediction error's RMS exceeded its bound and the tracking error grew
  (two segments running);
* ``oscillation``: the tracking error changed sign (by more than the bound each time) at
  least ``half_cycles`` times over the last three segments while the prediction did not;
* ``worse than not commanding``: two windows running (each ``compare_factor`` × the
  segment, at least the horizon), the realised mean |tracking error| exceeded
  ``1 + compare_margin`` times the mean |error| of the output the neutral input would
  have given: the measured output minus commanding's effect by the model's account
  (two frozen copies restarted from the measured history at the window's start, one fed
  the applied inputs, one an input going to 0 at the rate limit, or, where a trip releases
  the channel to the vehicle's own controller, to ``steady_input`` at the setpoint; the
  measured output carries the disturbance and the noise into both errors), and by more
  than a tenth of the bound;
* ``worse than trim``: the output settled (moved less than the bound over the segment) with
  a tracking error larger, by more than the bound, than the model's steady state at the
  neutral input would leave (a plan stalled where holding trim does better).

The bound is ``bound_factor`` × the RMS model error of the horizon test at arming (at
least ``hold_floor`` × the RMS hold error, so that a noise-free model still has one).

One module over 500 lines: the horizon test's verdict arms the supervisor and sets its
bounds, and both run the same frozen model over the same record; they are read together.
"""

from __future__ import annotations

import math
from collections import deque
from itertools import islice

from .dead_zone import narrow
from .dynamics import ModelDynamics
from .finite import finite

__all__ = ["HorizonTest", "Supervisor", "SupervisorSettings", "steady_input"]


def steady_input(dyn: ModelDynamics, level: float, lo: float, hi: float, points: int = 64) -> float:
    """The input in [lo, hi] whose steady state, by ``dyn``, is closest to ``level``: every
    input lag held at u, y = (bias + Σ_L P_L(u)) / (1 − Σ c_i). Scanned at ``points`` + 1
    inputs, then bisected between the first two neighbours that straddle ``level``; NaN
    when the model has no finite steady state (an integrator, non-finite coefficients)."""
    gain = dyn.ar_gain()
    if not (finite(gain) and abs(gain) > 1e-9 and finite(level)):
        return math.nan
    nb = len(dyn.lag_polys)

    def miss(u: float) -> float:
        acc = dyn.bias
        for lag in range(1, nb + 1):
            acc += dyn.lag_value(lag, u)
        return acc / gain - level

    step = (hi - lo) / points
    best_u, best = lo, abs(miss(lo))
    u_prev, m_prev = lo, miss(lo)
    for i in range(1, points + 1):
        u = lo + i * step
        m = miss(u)
        if not finite(m):
            return math.nan
        if abs(m) < best:
            best_u, best = u, abs(m)
        if (m_prev <= 0.0 <= m) or (m <= 0.0 <= m_prev):
            a, b, ma = u_prev, u, m_prev
            for _ in range(50):
                mid = 0.5 * (a + b)
                mm = miss(mid)
                if (ma <= 0.0) == (mm <= 0.0):
                    a, ma = mid, mm
                else:
                    b = mid
            return 0.5 * (a + b)
        u_prev, m_prev = u, m
    return best_u


def _percent(value: float, name: str) -> float:
    """A fit threshold: finite and below 100 % (a fit of 100 % is a perfect prediction)."""
    if not (finite(value) and value < 100.0):
        raise ValueError(f"{name} must be finite and below 100 %")
    return float(value)


class HorizonTest:
    """The current model against holding the output, over the controller's horizon, on
    the recent samples (see the module docstring).

    The samples are kept (``record``); ``evaluate`` runs today's model frozen from the
    measured outputs at segment starts k apart, newest segment ending at the newest
    sample, over the last ``max(window, k)`` samples: the verdict is on the model that
    would command, not on a copy frozen a horizon ago.
    """

    __slots__ = (
        "_inputs",
        "_measured",
        "_outputs",
        "_restart",
        "_runs",
        "evaluations",
        "fit",
        "full",
        "hold_rms",
        "horizon",
        "mean_fit",
        "mean_threshold",
        "minimum",
        "model_rms",
        "steps",
        "threshold",
        "window",
    )

    def __init__(
        self,
        threshold: float = 50.0,
        window: int = 500,
        capacity: int = 1100,
        minimum: int = 2,
        mean_threshold: float | None = None,
    ) -> None:
        self.threshold = _percent(threshold, "horizon threshold")
        self.mean_threshold = (
            None if mean_threshold is None else _percent(mean_threshold, "mean threshold")
        )
        if window < 2:
            raise ValueError("horizon window must be >= 2")
        self.window = int(window)
        size = max(capacity, window) + 16
        self._outputs: deque[float] = deque(maxlen=size)
        self._inputs: deque[float] = deque(maxlen=size)  # the input that produced each output
        #: Per sample: read (True), or lost and bridged with the model's prediction.
        self._measured: deque[bool] = deque(maxlen=size)
        #: Per sample, how many samples before it follow on without a restart
        #: (``restart_run``): a regressor may reach back that far.
        self._runs: deque[int] = deque(maxlen=size)
        self._restart = False  # the next sample starts a run
        #: The fewest prediction steps a verdict rests on while the record is shorter
        #: than the horizon (the pipeline's burn-in).
        self.minimum = max(int(minimum), 2)
        self.fit: float | None = None
        self.mean_fit: float | None = None
        self.steps = 0  # the prediction steps of the last evaluation's segments
        self.full = False  # they covered the whole horizon
        self.horizon = 0  # the horizon of the last evaluation
        self.evaluations = 0  # how many times ``evaluate`` has run
        self.model_rms = 0.0
        self.hold_rms = 0.0

    def break_record(self) -> None:
        """A hole in the samples (a telemetry gap): the record starts again, the last
        verdict stands."""
        self._outputs.clear()
        self._inputs.clear()
        self._measured.clear()
        self._runs.clear()
        self._restart = False

    def reset(self) -> None:
        """Forget every sample: the next verdict is on data recorded after this call."""
        self.break_record()
        self.fit = self.mean_fit = None
        self.steps = 0
        self.full = False
        self.model_rms = self.hold_rms = 0.0

    @property
    def count(self) -> int:
        return len(self._outputs)

    def samples(self) -> tuple[list[float], list[float]]:
        """The record, oldest first: the outputs and the input applied one step before each.
        A lost output (``record_missing``) is there as the model's prediction; its run is
        0 and the next sample starts a run, so no regression reaches across it."""
        return list(self._outputs), list(self._inputs)

    def runs(self) -> list[int]:
        """Per recorded sample, oldest first: how many samples before it follow on (its
        index, unless ``restart_run`` was called since the record began)."""
        return list(self._runs)

    def input_span(self, last: int) -> float:
        """How far the last ``last`` recorded inputs range (max − min; 0 for none)."""
        n = min(last, len(self._inputs))
        if n <= 0:
            return 0.0
        recent = list(islice(self._inputs, len(self._inputs) - n, None))
        return max(recent) - min(recent)

    def narrow_inputs(self, width: float) -> None:
        """The record's inputs beyond a dead zone of half-width ``width``, as the
        identifier sees them from now on (``ChannelPipeline``'s dead zone)."""
        narrowed = [narrow(u, width) for u in self._inputs]
        self._inputs.clear()
        self._inputs.extend(narrowed)

    def record(self, y: float, u_prev: float) -> None:
        """One consecutive sample: ``y`` and the input applied one step before it."""
        if finite(y) and finite(u_prev):
            self._runs.append(self._runs[-1] + 1 if self._runs and not self._restart else 0)
            self._restart = False
            self._outputs.append(y)
            self._inputs.append(u_prev)
            self._measured.append(True)
        else:
            self.break_record()  # consecutive samples only

    def record_missing(self, y_model: float, u_prev: float) -> None:
        """A lost sample bridged (``ChannelPipeline._bridge``): its input is known, its
        output is the model's prediction ``y_model``. The evaluation runs the model across
        it but scores no prediction there and starts no segment from it."""
        if not self._outputs:
            return  # nothing before it to bridge from
        if not (finite(y_model) and finite(u_prev)):
            self.break_record()
            return
        self._runs.append(0)
        self._restart = True
        self._outputs.append(y_model)
        self._inputs.append(u_prev)
        self._measured.append(False)

    def restart_run(self) -> None:
        """The newest sample is out of step (a reading served a tick early, or one whose
        input reading the next sample reuses): it starts no run of its own that a fit
        may train on (run 0), and the next sample starts a new run, so that the input
        lags' choice and its rebuilt identifier regress across neither."""
        if self._runs:
            self._runs[-1] = 0
        self._restart = True

    def evaluate(self, dyn: ModelDynamics, horizon: int) -> bool:
        """Score ``dyn`` over the record; True when it passes.

        Segments are ``horizon`` long, or as long as the record allows while it is shorter
        (at least ``minimum`` steps, and ``full`` is then False: the pipeline re-evaluates
        until a verdict covers the whole horizon)."""
        horizon = max(horizon, 1)
        self.horizon = horizon
        self.evaluations += 1
        history = max(len(dyn.ar), len(dyn.lag_polys), 1)
        n = len(self._outputs)
        span = max(self.window, horizon)
        first = max(history - 1, n - 1 - span)
        # ``model_rms`` and ``hold_rms`` stay those of the last evaluation that scored
        # (``reset`` clears them): a verdict that stands across a record too short to judge
        # (a telemetry gap) still arms the supervisor with the bounds it rests on.
        self.fit = self.mean_fit = None
        self.steps = max(0, min(horizon, n - 1 - first))
        self.full = self.steps >= horizon
        if self.steps < min(horizon, self.minimum):
            return False
        horizon = self.steps
        # Lists, not the deques (a deque's item access walks its blocks), of the part the
        # segments read: from ``history - 1`` samples before the first segment's start.
        skip = first - (history - 1)
        ys = list(islice(self._outputs, skip, None))
        us = list(islice(self._inputs, skip, None))
        measured = list(islice(self._measured, skip, None))
        n -= skip
        first -= skip
        na = len(dyn.ar)
        sum_m = sum_h = sum_y = sum_y2 = 0.0
        reference = ys[n - 1]
        count = 0
        end = n - 1
        while end - horizon >= first:
            s = end - horizon
            # A segment starts from measured outputs only: back over bridged samples.
            while s >= first and not all(measured[s - i] for i in range(max(na, 1))):
                s -= 1
            if s < first:
                break
            predictions = dyn.free_run(ys, us, s, end)
            y0 = ys[s]
            for j in range(s + 1, end + 1):
                y_model = predictions[j - s - 1]
                if not measured[j]:
                    continue
                y = ys[j]
                e = y - y_model
                if not (finite(e) and abs(e) < 1e100):
                    e = 1e100
                h = y - y0
                sum_m += e * e
                sum_h += h * h
                d = y - reference  # about the newest output: the sums stay well scaled
                sum_y += d
                sum_y2 += d * d
                count += 1
            end = s
        if count == 0 or not sum_h > 0.0 or not finite(sum_m / sum_h):
            return False
        self.fit = 100.0 * (1.0 - math.sqrt(sum_m / sum_h))
        self.model_rms = math.sqrt(sum_m / count)
        self.hold_rms = math.sqrt(sum_h / count)
        spread = sum_y2 - sum_y * sum_y / count
        if spread > 0.0 and finite(spread):
            self.mean_fit = 100.0 * (1.0 - math.sqrt(sum_m / spread))
        if self.mean_threshold is not None and not (
            self.mean_fit is not None and self.mean_fit >= self.mean_threshold
        ):
            return False
        return self.fit >= self.threshold


class SupervisorSettings:
    """Scale-free constants of the supervisor (counts, and ratios of measured errors)."""

    __slots__ = (
        "bound_factor",
        "compare_factor",
        "compare_margin",
        "half_cycles",
        "hold_floor",
        "holdoff_factor",
        "max_backoff",
        "max_trips",
        "max_window",
        "min_window",
    )

    def __init__(
        self,
        bound_factor: float = 3.0,
        hold_floor: float = 0.05,
        min_window: int = 10,
        max_window: int = 200,
        half_cycles: int = 6,
        max_backoff: int = 6,
        holdoff_factor: int = 4,
        max_trips: int = 3,
        compare_factor: int = 3,
        compare_margin: float = 0.1,
    ) -> None:
        if not (bound_factor > 0.0 and hold_floor >= 0.0):
            raise ValueError("bound_factor must be > 0 and hold_floor >= 0")
        if not 2 <= min_window <= max_window:
            raise ValueError("need 2 <= min_window <= max_window")
        self.bound_factor = float(bound_factor)
        self.hold_floor = float(hold_floor)
        self.min_window = int(min_window)
        self.max_window = int(max_window)
        self.half_cycles = int(half_cycles)
        self.max_backoff = int(max_backoff)
        #: The first hold-off after a trip, in horizons (or windows, the longer).
        self.holdoff_factor = int(holdoff_factor)
        #: Trips after which the channel stays off until control is disabled and enabled.
        self.max_trips = int(max_trips)
        #: The "worse than not commanding" window, in segments (at least the horizon), and
        #: the share by which the realised error must exceed the neutral input's predicted
        #: one to trip (the family target's 1.1 ×).
        if compare_factor < 1 or not compare_margin >= 0.0:
            raise ValueError("compare_factor must be >= 1 and compare_margin >= 0")
        self.compare_factor = int(compare_factor)
        self.compare_margin = float(compare_margin)


class Supervisor:
    """One channel's watchdog over its commanded loop; see the module docstring.

    The pipeline calls ``arm`` when the channel starts commanding, ``segment_sample`` with
    every commanded sample's output, prediction and tracking error, and reads ``reason``
    once it trips. ``holdoff`` (samples) grows twofold with every trip: trips and re-arms
    cannot chatter.
    """

    def __init__(self, settings: SupervisorSettings | None = None) -> None:
        self.settings = settings or SupervisorSettings()
        self.trips = 0
        self.strikes = 0  # trips since the operator last disabled control
        self.rearms = 0
        self.reason = ""
        self.window = self.settings.min_window
        self.bound = 0.0
        self.good_u = 0.0
        self._armed = False
        self._n = 0
        self._y0 = 0.0
        self._e0 = 0.0
        self._sq = 0.0
        self._sat = 0
        self._abs = 0.0
        self._head = 0.0
        self._tail: deque[float] = deque(maxlen=1)
        self._beyond_strikes = 0
        self._flips: deque[int] = deque()
        self._flips_pred: deque[int] = deque()
        self._sign = 0
        self._sign_pred = 0
        self._k = 0
        self._u0 = 0.0
        self._neutral_error = math.inf
        self.compare_window = 0
        self._cmp_n = 0
        self._cmp_real = 0.0
        self._cmp_alt = 0.0
        self._cmp_strikes = 0

    @property
    def armed(self) -> bool:
        return self._armed

    def window_for(self, horizon: int) -> int:
        s = self.settings
        return max(s.min_window, min(s.max_window, horizon))

    def holdoff(self, horizon: int) -> int:
        """Samples after a trip before a re-arm may be considered (twice as many after
        each trip since the operator last re-enabled control)."""
        s = self.settings
        doublings = min(max(self.strikes - 1, 0), s.max_backoff)
        return s.holdoff_factor * max(horizon, self.window_for(horizon)) * (1 << doublings)

    @property
    def latched(self) -> bool:
        """Tripped ``max_trips`` times since control was last enabled: no re-arm."""
        return self.strikes >= self.settings.max_trips

    def operator_reset(self) -> None:
        """Control disabled by the operator: the back-off and the latch start again."""
        self.strikes = 0

    def arm(self, model_rms: float, hold_rms: float, horizon: int, u: float) -> None:
        s = self.settings
        self.window = self.window_for(horizon)
        self.bound = s.bound_factor * max(model_rms, s.hold_floor * hold_rms)
        if not (finite(self.bound) and self.bound > 0.0):
            self.bound = math.inf  # nothing to judge by: only the saturation test acts
        self.good_u = u
        self.reason = ""
        self.compare_window = max(horizon, s.compare_factor * self.window)
        self.start_comparison()
        self._cmp_strikes = 0
        self._armed = True
        self._beyond_strikes = 0
        self._flips.clear()
        self._flips_pred.clear()
        self._sign = self._sign_pred = 0
        self._n = 0

    def disarm(self) -> None:
        self._armed = False

    def new_reference(self) -> None:
        """The setpoint changed: the tracking error's sign history starts again."""
        self._flips.clear()
        self._flips_pred.clear()
        self._sign = self._sign_pred = 0
        self._beyond_strikes = 0

    def start_segment(self, y: float, error: float, u: float) -> None:
        """A new segment from the measured output ``y`` (the prediction restarts there)."""
        self._n = 0
        self._y0 = y
        self._e0 = abs(error)
        self._sq = 0.0
        self._sat = 0
        self._abs = 0.0
        self._head = self._e0
        self._tail = deque(maxlen=self._ends())
        self._u0 = u
        self._neutral_error = math.inf

    def _ends(self) -> int:
        """Samples averaged at each end of a segment by the saturation test."""
        return max(1, self.window // 10)

    def neutral(self, error: float) -> None:
        """|r − the model's steady state at the neutral input| for this segment."""
        self._neutral_error = abs(error) if finite(error) else math.inf

    def segment_sample(
        self, y: float, y_pred: float, error: float, error_pred: float, saturated: bool
    ) -> str:
        """One commanded sample: ``error`` = y − r, ``error_pred`` = ŷ − r. Returns the trip
        reason ("" when none); the segment ends after ``window`` samples."""
        if not self._armed:
            return ""
        self._k += 1
        self._n += 1
        residual = y - y_pred
        self._sq += residual * residual
        if saturated:
            self._sat += 1
        self._abs += abs(error)
        ends = self._tail.maxlen or 1
        if self._n < ends:
            self._head += abs(error)
        self._tail.append(abs(error))
        self._note_flip(error, error_pred)
        reason = self._oscillation()
        if reason:
            return self._trip(reason)
        n = self._n
        moved, predicted = y - self._y0, y_pred - self._y0
        # The direction is judged from half a segment on: opposite moves, both beyond the
        # bound, are evidence enough.
        if (
            2 * n >= self.window
            and moved * predicted < 0.0
            and abs(moved) > self.bound
            and abs(predicted) > self.bound
        ):
            return self._trip(
                f"output moving against the predicted direction ({moved:+.3g} measured, "
                f"{predicted:+.3g} predicted over {n} samples)"
            )
        if n < self.window:
            return ""
        rms = math.sqrt(self._sq / n)
        growing = abs(error) > self._e0
        # Saturated against the predicted response: the error over the segment's last
        # tenth not below its first tenth's (the segment's start included; single samples
        # on a noisy plant differ either way), or, over a segment saturated for at least
        # 90 % of its samples (the rate limit's ramp into saturation takes a few), its mean
        # not below the first tenth's (an end alone can fall on a periodic disturbance's
        # favourable phase).
        start = self._head / ends
        end = 0.0
        for value in self._tail:
            end += value
        end /= ends
        held = self._sat >= n and end >= start
        if held or (10 * self._sat >= 9 * n and self._abs >= n * start):
            return self._trip(
                f"saturation held against the predicted response ({n} samples, "
                f"error {start:.3g} -> {end:.3g}, mean {self._abs / n:.3g})"
            )
        settled = abs(moved) < self.bound and abs(predicted) < self.bound
        if settled and abs(error) > self._neutral_error + self.bound:
            return self._trip(
                f"output settled worse than holding trim (error {abs(error):.3g}, "
                f"{self._neutral_error:.3g} at the neutral input)"
            )
        if rms > self.bound and growing:
            self._beyond_strikes += 1
            if self._beyond_strikes >= 2:
                return self._trip(
                    f"error growing beyond the prediction's bounds (RMS {rms:.3g} > "
                    f"{self.bound:.3g} over {2 * n} samples)"
                )
        else:
            self._beyond_strikes = 0
            self.good_u = self._u0  # the input this clean segment started from
        return ""

    def segment_done(self) -> bool:
        return self._n >= self.window

    def start_comparison(self) -> None:
        """A new "worse than not commanding" window (the neutral prediction restarts)."""
        self._cmp_n = 0
        self._cmp_real = self._cmp_alt = 0.0

    def comparison_done(self) -> bool:
        return self._cmp_n >= self.compare_window

    def compare_sample(
        self, error: float, error_neutral: float, alternative: str = "the neutral input"
    ) -> str:
        """One commanded sample: ``error`` = y − r, ``error_neutral`` = the output the
        channel's safe input (``alternative``: the neutral input, or the vehicle's own
        control) would have given − r. The trip reason at the end of the second window
        running that did worse ("" when none)."""
        if not self._armed:
            return ""
        if not finite(error_neutral):
            error_neutral = math.inf
        self._cmp_n += 1
        self._cmp_real += abs(error)
        self._cmp_alt += abs(error_neutral)
        if self._cmp_n < self.compare_window:
            return ""
        n = self._cmp_n
        real, alt = self._cmp_real / n, self._cmp_alt / n
        # Beyond the margin and by more than a tenth of the prediction's bound: below that
        # the two errors differ at the model's own resolution (a noise-free loop at its
        # setpoint has errors of 1e-10 on both sides).
        if real <= (1.0 + self.settings.compare_margin) * alt + 0.1 * self.bound:
            self._cmp_strikes = 0
            return ""
        self._cmp_strikes += 1
        if self._cmp_strikes < 2:
            return ""
        return self._trip(
            f"worse than not commanding (mean error {real:.3g} over {n} samples, "
            f"{alt:.3g} with {alternative} by the model's account; two windows running)"
        )

    def _note_flip(self, error: float, error_pred: float) -> None:
        bound = self.bound
        sign = 1 if error > bound else -1 if error < -bound else 0
        if sign and sign != self._sign:
            if self._sign:
                self._flips.append(self._k)
            self._sign = sign
        sign_pred = 1 if error_pred > bound else -1 if error_pred < -bound else 0
        if sign_pred and sign_pred != self._sign_pred:
            if self._sign_pred:
                self._flips_pred.append(self._k)
            self._sign_pred = sign_pred
        span = 3 * self.window
        while self._flips and self._flips[0] <= self._k - span:
            self._flips.popleft()
        while self._flips_pred and self._flips_pred[0] <= self._k - span:
            self._flips_pred.popleft()

    def _oscillation(self) -> str:
        flips = len(self._flips)
        if flips >= self.settings.half_cycles and len(self._flips_pred) * 2 < flips:
            return (
                f"unpredicted oscillation ({flips} half-cycles in {3 * self.window} samples, "
                f"{len(self._flips_pred)} predicted)"
            )
        return ""

    def _trip(self, reason: str) -> str:
        self.trips += 1
        self.strikes += 1
        self.reason = reason
        self._armed = False
        return reason
