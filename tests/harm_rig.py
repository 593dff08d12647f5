"""In-process loops for the do-no-harm tests: a plant, its excitation while the pipeline
does not command, the pipeline's commands once it does (``tests/test_do_no_harm.py``)."""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field

from hil_service.experiment.closed_loop import ClosedLoopSettings
from hil_service.pipeline import PipelineSettings, VehiclePipeline
from plant_emulator.excitation import RandomSteps
from plant_emulator.random_plants import RandomPlantSpec, RandomVehicle, RandomVehicleConfig
from protocols.samples import TelemetrySample


def family_loop(seed: int, identify: int = 800) -> ClosedLoopSettings:
    """The family benchmark's run of a vehicle (``run_family_closed_loop``, docs/control.md,
    "The family benchmark"), without the oracle."""
    return ClosedLoopSettings(
        seed=seed, samples=2000, identify=identify, step_every=300, scenario="family",
        oracle=False, neutral_after_identify=True,
    )  # fmt: skip


def spec(
    poles: tuple[float, ...] = (0.8, 0.7),
    dc_gain: float = 1.0,
    period: float = 0.1,
    dead_zone: float = 0.0,
    cubic: float = 0.0,
    zero: float | None = None,
) -> RandomPlantSpec:
    return RandomPlantSpec(
        0, len(poles), tuple((p, 0.0) for p in poles), zero, dc_gain, dead_zone, cubic, period
    )


@dataclass
class Loop:
    """``steps`` samples: the vehicle's own excitation until the pipeline commands a
    channel, then the pipeline's commands (a NaN holds the channel's input)."""

    depth: RandomPlantSpec
    pitch: RandomPlantSpec
    settings: PipelineSettings = field(default_factory=PipelineSettings)
    #: Per sample index: a function of the effective input (the plant change under test).
    change: Callable[[int, float], float] | None = None
    #: Output disturbance added to depth, per sample index.
    disturbance: Callable[[int], float] | None = None
    scale: float = 1.0  # output units per plant unit (depth)
    offset: float = 15.0  # trim depth
    input_scale: float = 1.0  # vehicle input units per plant unit
    #: Share of ticks whose reading is served a tick early and then again on the next
    #: tick, as an asynchronous sampler does (``tests/test_umodel_repeats.py``).
    repeat_share: float = 0.0
    #: Share of ticks whose reading is lost on the link (independently): the vehicle goes
    #: on with its input, the pipeline hears nothing; recorded as NaN / "lost".
    loss_share: float = 0.0

    def __post_init__(self) -> None:
        self.vehicle = RandomVehicle(
            RandomVehicleConfig(depth=self.depth, pitch=self.pitch, trim_depth=0.0)
        )
        self.pipeline = VehiclePipeline(self.settings)
        self.excite = [RandomSteps(2.0, 5, 30, seed=11), RandomSteps(2.0, 5, 30, seed=12)]
        self.k = 0  # plant steps
        self.tick = 0  # samples served
        self._early: TelemetrySample | None = None
        self._rng = random.Random(13)
        self._loss_rng = random.Random(17)
        self.time_offset_ms = 0
        self.restart_mark = False  # the next sample is marked ``restarted``
        self.command = [0.0, 0.0]
        self.y: list[float] = []
        self.u: list[float] = []
        self.reasons: list[str] = []
        self.modes: list[str] = []
        self.events: list[dict] = []

    def _plant_step(self) -> TelemetrySample:
        vehicle = self.vehicle
        k = self.k
        out = {}
        applied = {}
        for i, ch in enumerate(("depth", "pitch")):
            actuator = vehicle.actuators[ch]
            effective = actuator.apply(self.command[i] / self.input_scale)
            if ch == "depth" and self.change is not None:
                effective = self.change(k, effective)
            applied[ch] = actuator.position * self.input_scale
            out[ch] = vehicle.loops[ch].step(effective)
        depth = out["depth"] + (self.disturbance(k) if self.disturbance else 0.0)
        self.k += 1
        t_ms = round(self.tick * self.depth.period * 1000.0) - self.time_offset_ms
        restarted, self.restart_mark = self.restart_mark, False
        return TelemetrySample(
            system_id=1,
            time_boot_ms=t_ms,
            depth=self.offset + self.scale * depth,
            pitch=out["pitch"],
            u_depth=applied["depth"],
            u_pitch=applied["pitch"],
            restarted=restarted,
        )

    def run(self, steps: int, setpoints: dict[str, float | None], enabled: bool = True) -> None:
        for _ in range(steps):
            k = self.tick
            if k > 0 and self.loss_share and self._loss_rng.random() < self.loss_share:
                self._lose_tick(k)
                continue
            if self._early is not None:
                sample, self._early = self._early, None  # the plant has not moved since
                period_ms = round(self.depth.period * 1000.0)
                sample = sample._replace(time_boot_ms=sample.time_boot_ms + period_ms)
            elif k > 0 and self.repeat_share and self._rng.random() < self.repeat_share:
                self._plant_step()  # this tick's reading is never served
                sample = self._early = self._plant_step()
            else:
                sample = self._plant_step()
            self.tick += 1
            self.pipeline.observe(sample, sampled=self.repeat_share > 0.0)
            decision = self.pipeline.decide(sample, setpoints, enabled)
            self.events += self.pipeline.take_events(sample.time_boot_ms)
            self.y.append(sample.depth)
            self.u.append(sample.u_depth)
            self.reasons.append(decision.reason)
            self.modes.append("" if decision.payload is None else decision.payload["mode"])
            for i, ch in enumerate(("depth", "pitch")):
                value = math.nan
                if decision.command is not None:
                    value = decision.command.u_depth if i == 0 else decision.command.u_pitch
                if math.isfinite(value):
                    self.command[i] = value
                elif not self._commanded(ch):
                    self.command[i] = self.excite[i].value(k) * self.input_scale

    def _lose_tick(self, k: int) -> None:
        """A tick whose reading never arrives: the plant steps, the vehicle keeps its input
        (or goes on with its own excitation), nothing is decided."""
        self._plant_step()
        self.tick += 1
        self.y.append(math.nan)
        self.u.append(math.nan)
        self.reasons.append("lost")
        self.modes.append("lost")
        for i, ch in enumerate(("depth", "pitch")):
            if not self._commanded(ch):
                self.command[i] = self.excite[i].value(k) * self.input_scale

    def _commanded(self, channel: str) -> bool:
        pipeline = self.pipeline.channels[channel]
        return pipeline.active or pipeline.tripped

    def restart_clock(self) -> None:
        """The vehicle's clock starts again from zero (a reboot) at the next sample."""
        self.time_offset_ms = round(self.tick * self.depth.period * 1000.0) - 1000

    def reboot_marked(self) -> None:
        """The vehicle reboots before the next sample, as a periodic source reports it: the
        time goes on, the sample is marked ``restarted``."""
        self.restart_mark = True
