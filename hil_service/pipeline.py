"""Per-vehicle identification and inverse control, with no I/O: the live service, replay
and the in-process experiment all feed it the same samples and get the same numbers.

Each channel (depth, pitch) has its identifier, a persistence baseline beside it, error
statistics, and an inverse controller that is allowed to act only once the identifier has
converged (``burn_in`` samples and a recent skill versus persistence of at least
``min_skill``) and has not diverged since.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from hil_service.umodel import (
    CommandShaper,
    Estimate,
    PersistenceModel,
    PredictiveModel,
    ReferenceFilter,
    build_model,
    solve_inverse,
)
from hil_service.umodel.forecast import forecast_model
from hil_service.umodel.scoring import ErrorStats
from protocols.samples import BallastCommand, TelemetrySample

CHANNELS = ("depth", "pitch")
MODEL_CHOICES = ("paper", "dynamic")

#: Model options per channel on top of each model's defaults. ``y_scale`` brings depth
#: (≈ 15 m) to O(1) in the dynamic model's regressor so it does not swamp the NLMS norm.
DEFAULT_MODEL_OPTIONS: dict[str, dict[str, dict[str, Any]]] = {
    "paper": {"depth": {}, "pitch": {}},
    "dynamic": {"depth": {"y_scale": 1.0}, "pitch": {"y_scale": 0.1}},
}


#: Before ``trajectory`` existed the controller aimed ŷ(k+H) at the setpoint itself: a log
#: recorded then carries no ``trajectory`` and replays with this one.
NO_TRAJECTORY: dict[str, float] = {"depth": 0.0, "pitch": 0.0}


@dataclass(frozen=True)
class ControlSettings:
    """Inverse-control settings; horizon and trajectory per channel.

    Why pitch looks 3 steps ahead on a trajectory (``experiment --closed-loop``): the
    identified pitch model's ŷ(k+H) under a held input is close to the plant's step response
    for H ≲ 5 and non-monotone in u for H ≳ 8 (its increment form integrates every small
    input-map error over the horizon), so at H = 20 a quarter of the solves had no root and
    the answer jumped to the map's extremum (overshoot 300–500 %). At H = 3 the map is
    monotone but aiming ŷ(k+3) at the setpoint is a deadbeat, high-gain demand; the
    reference trajectory (pole ``trajectory``) asks for a share 1 − λ^H of the remaining
    error instead. The trajectory starts at each sample from the measured output, so the
    setpoint filter is redundant and off by default. Depth keeps H = 150 and λ = 0: no
    trajectory or horizon we tried made its identified long-horizon map trustworthy.
    """

    horizon: dict[str, int] = field(default_factory=lambda: {"depth": 150, "pitch": 3})
    u_limit: float = 2.0  # model units, the actuator's range
    rate_limit: float = 0.5  # model units per step, as the vehicle's actuator
    reference_filter: float = 0.0  # first-order setpoint filter coefficient, 0..1
    mismatch_filter: float = 0.9  # first-order filter on the IMC mismatch y − ŷ, 0..1
    # Reference-trajectory pole per channel, 0..1: ŷ(k+H) is aimed at r − λ^H·(r − y(k));
    # 0 aims at the (filtered) setpoint r itself.
    trajectory: dict[str, float] = field(default_factory=lambda: {"depth": 0.0, "pitch": 0.7})

    def __post_init__(self) -> None:
        for ch, pole in self.trajectory.items():
            if not (math.isfinite(pole) and 0.0 <= pole < 1.0):
                raise ValueError(f"trajectory pole for {ch} must be in [0, 1), got {pole}")

    def remaining_share(self, channel: str) -> float:
        """λ^H: the share of the error r − y(k) the target still leaves at k + H.

        Repeated products, not ``**``: the same bits on every platform.
        """
        pole = self.trajectory.get(channel, 0.0)
        share = 1.0
        for _ in range(self.horizon[channel]):
            share *= pole
        return share


@dataclass(frozen=True)
class PipelineSettings:
    model: str = "dynamic"
    seed: int = 0
    model_options: dict[str, dict[str, Any]] | None = None
    burn_in: int = 300
    min_skill: float = 0.0
    window: int = 500
    control: ControlSettings = field(default_factory=ControlSettings)

    def __post_init__(self) -> None:
        if self.model not in MODEL_CHOICES:
            raise ValueError(f"model must be one of {MODEL_CHOICES}, got {self.model!r}")

    def replace(self, **changes: Any) -> PipelineSettings:
        return replace(self, **changes)

    def options_for(self, channel: str) -> dict[str, Any]:
        chosen = self.model_options or DEFAULT_MODEL_OPTIONS[self.model]
        return dict(chosen.get(channel, {}))

    def to_json(self) -> dict[str, Any]:
        data = asdict(self)
        data["model_options"] = {ch: self.options_for(ch) for ch in CHANNELS}
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PipelineSettings:
        data = dict(data)
        control_data = dict(data.pop("control", {}))
        control_data.setdefault("trajectory", dict(NO_TRAJECTORY))
        control = ControlSettings(**control_data)
        return cls(control=control, **data)


@dataclass
class StepContinuity:
    """Tells whether a sample directly follows the previous one.

    The plant period is learnt as the smallest positive timestamp step seen (the vehicle
    does not announce it); a step longer than ``tolerance`` periods means samples are
    missing in between.
    """

    tolerance: float = 1.5
    period_ms: int | None = None
    last_ms: int | None = None
    gaps: int = 0

    def follows(self, time_ms: int) -> bool:
        last, self.last_ms = self.last_ms, time_ms
        if last is None:
            return False
        step = time_ms - last
        if step <= 0:
            self.gaps += 1
            return False
        if self.period_ms is None or step < self.period_ms:
            self.period_ms = step
        if step > self.tolerance * self.period_ms:
            self.gaps += 1
            return False
        return True


@dataclass(frozen=True)
class Decision:
    command: BallastCommand | None
    payload: dict[str, Any] | None
    reason: str


class ChannelPipeline:
    def __init__(self, channel: str, settings: PipelineSettings, seed: int):
        self.channel = channel
        self.settings = settings
        options = settings.options_for(channel)
        model = build_model(settings.model, seed=seed, **options)
        assert isinstance(model, PredictiveModel)  # MODEL_CHOICES are the U-models
        self.model: PredictiveModel = model
        self.persistence = PersistenceModel()
        self.stats = ErrorStats(burn_in=settings.burn_in, window=settings.window)
        control = settings.control
        self.reference = ReferenceFilter(a=control.reference_filter)
        self.remaining = control.remaining_share(channel)
        self.shaper = CommandShaper(-control.u_limit, control.u_limit, control.rate_limit)
        self.u_prev: float | None = None
        self.last: Estimate | None = None
        self.converged = False
        self.divergences = 0
        self.rejected = 0
        self.active = False
        self.mismatch = 0.0
        self.resync = 0  # samples still to refill the model's history after a gap
        self.skipped = 0

    def config(self) -> dict[str, Any]:
        return self.model.config()

    def observe(
        self, t: float, y: float, u_now: float, follows_previous: bool = True
    ) -> dict[str, Any] | None:
        """Learn from one sample; None when the sample only refills the history.

        After a gap (``follows_previous`` False; also the very first sample) the input
        applied one step before ``y`` is unknown and the model's lags hold pre-gap values,
        so the next ``history_length`` samples enter the history without training the model
        (counted as ``skipped``): a missing step is skipped, never mis-aligned.
        """
        if not follows_previous or self.u_prev is None:
            self.resync = self.model.history_length
        if self.resync > 0:
            u_guess = u_now if self.u_prev is None else self.u_prev
            self.model.observe_only(u_guess, y)
            self.persistence.observe_only(u_guess, y)
            self.u_prev = u_now
            self.resync -= 1
            self.skipped += 1
            return None
        u_prev = self.u_prev
        assert u_prev is not None  # set by every sample, resynchronising ones included
        estimate = self.model.step(u_prev, y)
        baseline = self.persistence.step(u_prev, y)
        self.u_prev = u_now
        self.last = estimate
        if estimate.status == "rejected":
            self.rejected += 1
        elif estimate.status == "diverged":
            self.divergences += 1
            self.converged = False
        else:
            self.stats.add(y, estimate.error, baseline.error)
            if not self.converged and self.stats.count >= self.settings.burn_in:
                skill = self.stats.recent_skill()  # only needed until convergence
                if skill is not None and skill >= self.settings.min_skill:
                    self.converged = True
        return {
            "t": t,
            "y": estimate.y,
            "y_hat": estimate.y_hat,
            "error": estimate.error,
            "alpha": list(estimate.alpha),
            "weights": list(estimate.weights),
            "model": estimate.model,
            "status": estimate.status,
            "baseline_y_hat": baseline.y_hat,
        }

    def blocked_reason(self) -> str:
        if self.resync > 0 or self.last is None:
            return f"identifier resynchronising after a telemetry gap ({self.channel})"
        if self.last.status == "diverged":
            return f"identifier diverged ({self.channel})"
        if not self.converged:
            return (
                f"identifier not converged ({self.channel}: "
                f"{min(self.stats.count, self.settings.burn_in)}/{self.settings.burn_in} samples, "
                f"recent skill {self.stats.recent_skill()})"
            )
        return ""

    def solve(self, setpoint: float, y: float, u_applied: float) -> tuple[float, str, bool]:
        """One inverse-control step: (command, solver path, saturated)."""
        control = self.settings.control
        assert self.last is not None
        if not self.active:
            self.reference.reset()
            self.shaper.reset(u_applied)
            self.mismatch = 0.0
            self.active = True
        # IMC: aim the model off by the plant/model mismatch, low-passed so that one-step
        # prediction noise does not become input chatter.
        a = control.mismatch_filter
        self.mismatch = a * self.mismatch + (1.0 - a) * (y - self.last.y_hat)
        reference = self.reference.filter(setpoint, start=y)
        # Reference trajectory from the measured output: at k + H only a share λ^H of the
        # current error may remain (λ = 0: the setpoint itself).
        target = reference - self.remaining * (reference - y) - self.mismatch
        prediction = forecast_model(self.model, u_applied, control.horizon[self.channel])
        limit = control.u_limit
        result = solve_inverse(
            prediction.value,
            prediction.derivative,
            target,
            self.shaper.u,
            -limit,
            limit,
            f_vec=prediction.values,
            d2f=prediction.curvature,
        )
        shaped = self.shaper.shape(result.u)
        saturated = result.saturated or shaped.saturated or shaped.rate_limited
        return shaped.u, result.path, saturated

    def deactivate(self) -> None:
        self.active = False

    def health(self) -> dict[str, Any]:
        return {
            "model": self.model.config()["name"],
            "status": "none" if self.last is None else self.last.status,
            "converged": self.converged,
            "divergences": self.divergences,
            "rejected": self.rejected,
            "skipped": self.skipped,
            **self.stats.summary(),
        }


class VehiclePipeline:
    def __init__(self, settings: PipelineSettings | None = None):
        self.settings = settings or PipelineSettings()
        self.channels = {
            ch: ChannelPipeline(ch, self.settings, self.settings.seed * 2 + i)
            for i, ch in enumerate(CHANNELS)
        }
        self.gaps = StepContinuity()

    def observe(self, sample: TelemetrySample) -> dict[str, dict[str, Any]]:
        """Estimates per channel (a channel refilling its history after a gap has none)."""
        follows = self.gaps.follows(sample.time_boot_ms)
        estimates = {}
        for ch, pipeline in self.channels.items():
            estimate = pipeline.observe(sample.t, sample.output(ch), sample.input(ch), follows)
            if estimate is not None:
                estimates[ch] = estimate
        return estimates

    def decide(
        self, sample: TelemetrySample, setpoints: dict[str, float | None], enabled: bool
    ) -> Decision:
        """The command for this sample, or why there is none."""
        active = {ch: v for ch, v in setpoints.items() if v is not None and math.isfinite(v)}
        reason = ""
        if not enabled:
            reason = "control disabled"
        elif not active:
            reason = "no setpoint"
        else:
            reason = next((r for ch in active if (r := self.channels[ch].blocked_reason())), "")
        if reason:
            for pipeline in self.channels.values():
                pipeline.deactivate()
            return Decision(None, None, reason)
        values = {"depth": math.nan, "pitch": math.nan}
        paths, saturated = [], False
        for ch, pipeline in self.channels.items():
            if ch not in active:
                pipeline.deactivate()
                paths.append("-")
                continue
            u, path, sat = pipeline.solve(active[ch], sample.output(ch), sample.input(ch))
            values[ch] = u
            paths.append(path)
            saturated = saturated or sat
        payload = {
            "t": sample.t,
            "u_depth": None if math.isnan(values["depth"]) else values["depth"],
            "u_pitch": None if math.isnan(values["pitch"]) else values["pitch"],
            "setpoints": {ch: setpoints.get(ch) for ch in CHANNELS},
            "saturated": saturated,
            "mode": "/".join(paths),
        }
        return Decision(BallastCommand(values["depth"], values["pitch"]), payload, "")

    def mark_stale(self) -> None:
        for pipeline in self.channels.values():
            pipeline.deactivate()

    def identifier_health(self) -> dict[str, Any]:
        return {ch: pipeline.health() for ch, pipeline in self.channels.items()}

    def configs(self) -> dict[str, dict[str, Any]]:
        return {ch: pipeline.config() for ch, pipeline in self.channels.items()}

