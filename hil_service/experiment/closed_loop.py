"""Closed-loop experiment: setpoint steps tracked by the inverse controller.

Three runs on identical plants (same scenario and seed, so the same disturbance): the
service's pipeline (``dynamic`` U-model identified online, then IMC inverse control), the
stabilised plant driven by its reference alone (the ballast input set to the setpoint
divided by the inner loop's DC gain), and the oracle (``oracle.py``: a constrained
receding-horizon controller that knows the plant's model, the yardstick the others are
divided by). All start from the same excitation phase, so the identifier has something to
learn from before control starts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import control
import numpy as np

from hil_service.experiment.oracle import KnownPlant, OracleController, OracleSettings, identity
from hil_service.pipeline import NOT_FROM_THE_PLAN, PipelineSettings, VehiclePipeline
from plant_emulator.actuator import BallastActuator
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.models import CHANNELS, DEFAULT_DESIGNS, ClosedLoopChannel, open_loop_plant
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.samples import TelemetrySample

#: The oracle's settings on the emulator's channels, tuned on seed 0 (``docs/control.md``):
#: depth looks 400 samples ahead (its non-minimum-phase zero at z = 1.0045 has a time scale
#: of ~220 samples) with single-sample moves at first, growing to 32, and the error costed
#: on every sample over the short moves (a stride longer than the shortest block lets the
#: plan wiggle between the costed samples), every 4th beyond; on paper each step then
#: realises the full-resolution LP optimum (no better causal plan exists without preview).
#: It estimates the disturbance slowly. Pitch is fast and needs no blocking; its disturbance
#: is extrapolated along its low-passed slope.
GLIDER_ORACLE: dict[str, OracleSettings] = {
    "depth": OracleSettings(
        horizon=400,
        blocks=(1,) * 8 + (2,) * 8 + (4,) * 8 + (8,) * 8 + (16,) * 4 + (32,) * 4,
        disturbance_tau=5000.0,
        cost_stride=4,
        stride_from=60,  # every sample while the moves are finer than 8 samples
        terminal=True,
    ),
    "pitch": OracleSettings(
        horizon=30, blocks=(1,) * 14 + (16,), disturbance_tau=1.0, disturbance_trend=30.0
    ),
}

#: Setpoint sequences cycled through, one step every ``step_every`` samples. Depth in
#: metres (the trim depth is 15 m), pitch in radians.
DEPTH_SETPOINTS = (17.0, 14.0, 16.0, 15.0)
PITCH_SETPOINTS = (0.15, -0.1, 0.0, 0.1)


@dataclass(frozen=True)
class ClosedLoopSettings:
    scenario: str = "disturbed"
    samples: int = 5000
    seed: int = 0
    identify: int = 1500  # samples of open-loop excitation before control starts
    step_every: int = 800
    settle_band: float = 0.1  # settled once |error| stays within this share of the step
    excitation: str = "steps"
    # Also run the known-model yardstick (an LP per sample: slow). The CLI turns it on;
    # off by default here so that library callers and tests pay for it only when asked.
    oracle: bool = False
    #: The excitation ends at the neutral input (0), reached through the actuators' rate
    #: limits by the first controlled sample: a controller that does not command leaves
    #: the vehicle at neutral, not wherever the excitation was.
    neutral_after_identify: bool = False

    def __post_init__(self) -> None:
        if self.identify < 1 or self.samples <= self.identify + 1:
            raise ValueError(
                f"need 1 <= identify < samples - 1, got identify={self.identify}, "
                f"samples={self.samples}"
            )
        if self.step_every < 2:
            raise ValueError(f"step_every must be at least 2, got {self.step_every}")


@dataclass
class StepMetrics:
    """Tracking of one channel over the controlled part of a run."""

    iae: float  # Σ|y − r|·period over the controlled samples, unit·s
    overshoot: float | None  # worst overshoot over the steps, % of the step size
    settling_median: float | None  # s, over the steps that settled
    settled: int
    steps: int
    step_total: float  # Σ|step size| over the steps, unit

    def as_json(self) -> dict[str, Any]:
        return {
            "iae": round(self.iae, 4),
            "overshoot_pct": None if self.overshoot is None else round(self.overshoot, 2),
            "settling_s": None if self.settling_median is None else round(self.settling_median, 1),
            "settled_steps": self.settled,
            "steps": self.steps,
            "step_total": round(self.step_total, 4),
        }


@dataclass
class RunTrace:
    """One run's time series (outputs, setpoints, inputs) over the whole experiment."""

    y: dict[str, np.ndarray]
    setpoint: dict[str, np.ndarray]
    u: dict[str, np.ndarray]
    metrics: dict[str, StepMetrics] = field(default_factory=dict)
    #: Per channel, commands with a NaN or infinite value (the channel held its position).
    non_finite_commands: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CHANNELS, 0))


@dataclass
class ClosedLoopResult:
    settings: ClosedLoopSettings
    inverse: RunTrace
    reference_only: RunTrace
    solver_paths: dict[str, int]
    blocked: int
    divergences: dict[str, int]
    nmp_bound: dict[str, float | None]
    identifier: dict[str, Any]
    oracle: RunTrace | None = None
    oracle_failures: int = 0  # LP solves that did not return an optimum (input held)

    def oracle_ratio(self, channel: str, run: str) -> float | None:
        """IAE of ``run`` ("inverse" or "reference_only") over the oracle's, or None."""
        if self.oracle is None:
            return None
        base = self.oracle.metrics[channel].iae
        trace = self.inverse if run == "inverse" else self.reference_only
        return round(trace.metrics[channel].iae / base, 4) if base > 0 else None

    def iae_lower_bound(self, channel: str) -> float | None:
        """The least IAE any causal controller could reach on the inverse run's steps."""
        per_unit = self.nmp_bound[channel]
        if per_unit is None:
            return None
        return _round(per_unit * self.inverse.metrics[channel].step_total)

    def as_json(self) -> dict[str, Any]:
        channels = {}
        for ch in CHANNELS:
            inv = self.inverse.metrics[ch]
            ref = self.reference_only.metrics[ch]
            channels[ch] = {
                "inverse": inv.as_json(),
                "reference_only": ref.as_json(),
                "oracle": None if self.oracle is None else self.oracle.metrics[ch].as_json(),
                "iae_ratio": round(inv.iae / ref.iae, 4) if ref.iae > 0 else None,
                "oracle_ratio": {
                    "inverse": self.oracle_ratio(ch, "inverse"),
                    "reference_only": self.oracle_ratio(ch, "reference_only"),
                },
                "iae_lower_bound": self.iae_lower_bound(ch),
                "iae_bound_per_unit_step": _round(self.nmp_bound[ch]),
            }
        return {
            "scenario": self.settings.scenario,
            "samples": self.settings.samples,
            "seed": self.settings.seed,
            "identify": self.settings.identify,
            "channels": channels,
            "solver_paths": self.solver_paths,
            "blocked_steps": self.blocked,
            "divergences": self.divergences,
            "non_finite_commands": self.inverse.non_finite_commands,
            "oracle_failures": self.oracle_failures,
            "identifier": self.identifier,
        }


def _round(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(value, digits)


def setpoint_schedule(
    settings: ClosedLoopSettings, levels_by_channel: dict[str, tuple[float, ...]] | None = None
) -> dict[str, np.ndarray]:
    """Setpoints per sample: NaN while identifying, then a step every ``step_every``."""
    schedules = {}
    chosen = levels_by_channel or {"depth": DEPTH_SETPOINTS, "pitch": PITCH_SETPOINTS}
    for ch, levels in chosen.items():
        values = np.full(settings.samples, np.nan)
        for k in range(settings.identify, settings.samples):
            index = (k - settings.identify) // settings.step_every
            values[k] = levels[index % len(levels)]
        schedules[ch] = values
    return schedules


def nmp_iae_bound(channel: str, period: float = 1.0) -> float | None:
    """Lower bound on IAE per unit step for *any* stabilising controller, or None.

    A real plant zero z₀ > 1 stays a zero of every closed loop (no stable controller can
    cancel it), so E(z₀) = R(z₀) = z₀/(z₀ − 1) for a unit step, and since z₀⁻ᵏ ≤ 1,
    Σ|e(k)| ≥ |Σ e(k) z₀⁻ᵏ| = z₀/(z₀ − 1). The nearest such zero to 1 gives the bound
    (unit·samples; multiplied by the period for unit·s).
    """
    zeros = np.asarray(control.zeros(open_loop_plant(channel, period)), dtype=complex)
    real = [z.real for z in zeros if abs(z.imag) < 1e-9 and z.real > 1.0]
    if not real:
        return None
    z0 = min(real)
    return z0 / (z0 - 1.0) * period


def step_metrics(
    y: np.ndarray, setpoint: np.ndarray, start: int, band: float, period: float
) -> StepMetrics:
    """IAE, worst overshoot and median settling time over the steps after ``start``."""
    iae = float(np.sum(np.abs(y[start:] - setpoint[start:]))) * period
    changes = [k for k in range(start + 1, y.size) if setpoint[k] != setpoint[k - 1]]
    overshoots: list[float] = []
    settling: list[float] = []
    step_total = 0.0
    # The first segment starts from wherever identification left the output.
    starts = [start, *changes]
    ends = [*changes, y.size]
    for k0, k1 in zip(starts, ends, strict=True):
        target = setpoint[k0]
        # A step's size is the setpoint change; the first one starts from the output.
        before = setpoint[k0 - 1] if k0 > 0 else math.nan
        initial = before if math.isfinite(before) else (y[k0 - 1] if k0 > 0 else y[k0])
        size = target - initial
        if abs(size) < 1e-9:
            continue
        step_total += abs(size)
        segment = y[k0:k1]
        beyond = (segment - target) * math.copysign(1.0, size)
        overshoots.append(max(0.0, float(np.max(beyond))) / abs(size) * 100.0)
        outside = np.flatnonzero(np.abs(segment - target) > band * abs(size))
        if outside.size == 0:
            settling.append(0.0)
        elif outside[-1] < segment.size - 1:
            settling.append(float(outside[-1] + 1) * period)
    return StepMetrics(
        iae=iae,
        overshoot=max(overshoots) if overshoots else None,
        settling_median=float(np.median(settling)) if settling else None,
        settled=len(settling),
        steps=len(overshoots),
        step_total=step_total,
    )


#: Given the step index and the sample, the command for the next step, or None to hold.
Controller = Callable[[int, TelemetrySample], tuple[float, float] | None]


class SteppedPlant(Protocol):
    """What a closed-loop run steps: ``GliderPlant`` or ``RandomVehicle``."""

    loops: dict[str, ClosedLoopChannel]
    actuators: dict[str, BallastActuator]

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample: ...


def _drive(
    settings: ClosedLoopSettings,
    plant: SteppedPlant,
    schedule: dict[str, np.ndarray],
    controller: Controller,
) -> RunTrace:
    """Run one plant: its excitation while identifying, then the controller's commands.

    The controller sees every sample, identification phase included (so an identifier can
    learn from it); its answer is used from ``settings.identify`` on. A command with a
    non-finite value is counted and that channel holds its position (the actuator ignores
    it, as the emulator's does).
    """
    n = settings.samples
    trace = RunTrace(
        y={ch: np.empty(n) for ch in CHANNELS},
        setpoint=schedule,
        u={ch: np.empty(n) for ch in CHANNELS},
    )
    excitation = build_channel_excitations(settings.excitation, settings.seed)
    # Commands sent from here on take the actuators from anywhere in their range to 0.
    to_neutral = settings.identify - (
        _steps_to_neutral(plant) if settings.neutral_after_identify else 0
    )
    command = (0.0, 0.0)
    for k in range(n):
        sample = plant.step(*command)
        for ch in CHANNELS:
            trace.y[ch][k] = sample.output(ch)
            trace.u[ch][k] = sample.input(ch)
        requested = controller(k, sample)
        if k < settings.identify:
            command = (excitation["depth"].value(k), excitation["pitch"].value(k))
            if k >= to_neutral:
                command = (0.0, 0.0)
        elif requested is not None:
            for ch, value in zip(CHANNELS, requested, strict=True):
                if not math.isfinite(value):
                    trace.non_finite_commands[ch] += 1
            command = requested
    return trace


def _steps_to_neutral(plant: SteppedPlant) -> int:
    """Steps in which every actuator reaches 0 from its limit at its rate limit."""
    return max(
        math.ceil(actuator.limit / actuator.rate_limit) for actuator in plant.actuators.values()
    )


def known_plant(plant: SteppedPlant, channel: str, trim: float) -> KnownPlant:
    """The oracle's knowledge of one channel: its model, actuator limits and pump map."""
    loop, actuator = plant.loops[channel], plant.actuators[channel]
    return KnownPlant(
        a=np.array(loop.a_cl, dtype=float),
        b=np.array(loop.b_cl, dtype=float),
        c=np.array(loop.c_cl, dtype=float),
        d=float(loop.d_cl),
        trim=trim,
        pump=actuator.nonlinearity or identity,
        u_limit=actuator.limit,
        rate_limit=actuator.rate_limit,
    )


def oracle_run(
    settings: ClosedLoopSettings,
    plant: SteppedPlant,
    schedule: dict[str, np.ndarray],
    oracle_settings: dict[str, OracleSettings],
    trims: dict[str, float],
) -> tuple[RunTrace, int]:
    """The oracle on ``plant`` (fresh, at rest): its trace and the LP solves that failed."""
    oracles = {
        ch: OracleController(known_plant(plant, ch, trims[ch]), oracle_settings[ch])
        for ch in CHANNELS
    }

    def control(k: int, sample: TelemetrySample) -> tuple[float, float] | None:
        for ch in CHANNELS:
            oracles[ch].observe(sample.output(ch), sample.input(ch))
        if k < settings.identify:
            return None
        return (
            oracles["depth"].command(float(schedule["depth"][k]), sample.u_depth),
            oracles["pitch"].command(float(schedule["pitch"][k]), sample.u_pitch),
        )

    trace = _drive(settings, plant, schedule, control)
    return trace, sum(o.failures for o in oracles.values())


@dataclass
class InverseRun:
    trace: RunTrace
    paths: dict[str, int]
    blocked: int
    divergences: dict[str, int]
    identifier: dict[str, Any]
    #: Per channel: supervisor trips, whether the horizon test ever passed, and the
    #: samples the channel commanded (its safe input not counted).
    supervision: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Per controlled sample, the decision's ``mode`` ("" when nothing was sent).
    modes: list[str] = field(default_factory=list)


def inverse_run(
    settings: ClosedLoopSettings,
    plant: SteppedPlant,
    schedule: dict[str, np.ndarray],
    pipeline_settings: PipelineSettings | None,
    released: Controller | None = None,
) -> InverseRun:
    """The service's pipeline (identifier + inverse controller) on ``plant``.

    ``released``: what the vehicle's own controller commands on a channel the service
    does not command (no decision, or a NaN for that channel); None: the vehicle holds
    its input, as on a silent link."""
    pipeline = VehiclePipeline(pipeline_settings or PipelineSettings(seed=settings.seed))
    paths: dict[str, int] = {}
    modes: list[str] = []
    blocked = 0

    def own(
        k: int, sample: TelemetrySample, values: tuple[float, float] | None
    ) -> tuple[float, float] | None:
        if released is None:
            return values
        fallback = released(k, sample)
        if values is None or fallback is None:
            return fallback if values is None else values
        depth, pitch = values
        return (
            fallback[0] if math.isnan(depth) else depth,
            fallback[1] if math.isnan(pitch) else pitch,
        )

    def inverse_control(k: int, sample: TelemetrySample) -> tuple[float, float] | None:
        nonlocal blocked
        pipeline.observe(sample)
        if k < settings.identify:
            return None
        setpoints: dict[str, float | None] = {ch: float(schedule[ch][k]) for ch in CHANNELS}
        decision = pipeline.decide(sample, setpoints, True)
        if decision.command is None or decision.payload is None:
            blocked += 1  # the vehicle holds its last input, as it would on a silent link
            modes.append("")
            return own(k, sample, None)
        mode = decision.payload["mode"]
        modes.append(mode)
        paths[mode] = paths.get(mode, 0) + 1
        return own(k, sample, (decision.command.u_depth, decision.command.u_pitch))

    trace = _drive(settings, plant, schedule, inverse_control)
    supervision = {}
    for i, (ch, channel) in enumerate(pipeline.channels.items()):
        commanded = sum(
            n for mode, n in paths.items() if mode.split("/")[i] not in NOT_FROM_THE_PLAN
        )
        supervision[ch] = {
            "trips": channel.supervisor.trips,
            "horizon_passed": channel.ever_qualified,
            "commanded": commanded,
        }
    return InverseRun(
        trace=trace,
        paths=paths,
        blocked=blocked,
        divergences={ch: p.divergences for ch, p in pipeline.channels.items()},
        identifier=pipeline.identifier_health(),
        supervision=supervision,
        modes=modes,
    )


def score(trace: RunTrace, settings: ClosedLoopSettings, period: float) -> None:
    for ch in CHANNELS:
        trace.metrics[ch] = step_metrics(
            trace.y[ch], trace.setpoint[ch], settings.identify, settings.settle_band, period
        )


def run_closed_loop(
    settings: ClosedLoopSettings,
    pipeline_settings: PipelineSettings | None = None,
    oracle_settings: dict[str, OracleSettings] | None = None,
) -> ClosedLoopResult:
    schedule = setpoint_schedule(settings)
    plant_config = PlantConfig(scenario=settings.scenario, seed=settings.seed)
    period = plant_config.period
    trim = plant_config.trim_depth
    gains = {ch: DEFAULT_DESIGNS[ch].dc_gain for ch in CHANNELS}

    def reference_only_control(k: int, sample: TelemetrySample) -> tuple[float, float]:
        return (
            (float(schedule["depth"][k]) - trim) / gains["depth"],
            float(schedule["pitch"][k]) / gains["pitch"],
        )

    inverse = inverse_run(settings, GliderPlant(plant_config), schedule, pipeline_settings)
    reference_only = _drive(settings, GliderPlant(plant_config), schedule, reference_only_control)
    oracle: RunTrace | None = None
    failures = 0
    if settings.oracle:
        oracle, failures = oracle_run(
            settings,
            GliderPlant(plant_config),
            schedule,
            oracle_settings or GLIDER_ORACLE,
            {"depth": trim, "pitch": 0.0},
        )
    for run in (inverse.trace, reference_only, oracle):
        if run is not None:
            score(run, settings, period)
    return ClosedLoopResult(
        settings=settings,
        inverse=inverse.trace,
        reference_only=reference_only,
        solver_paths=inverse.paths,
        blocked=inverse.blocked,
        divergences=inverse.divergences,
        nmp_bound={ch: nmp_iae_bound(ch, period) for ch in CHANNELS},
        identifier=inverse.identifier,
        oracle=oracle,
        oracle_failures=failures,
    )
