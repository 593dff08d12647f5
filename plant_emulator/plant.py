"""The simulated glider: two stabilised channels, their actuators and disturbances.

Pure simulation (no sockets, no clock): the MAVLink autopilot and the in-process experiment
both step it. Time is simulated: step k is at t = k·period.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from plant_emulator.actuator import BallastActuator
from plant_emulator.disturbances import Disturbance
from plant_emulator.family import INPUT_LIMIT as FAMILY_INPUT_LIMIT
from plant_emulator.family import FamilyPlantSpec, FamilyVehicle, draw_vehicle
from plant_emulator.models import CHANNELS, ClosedLoopChannel, design_closed_loop
from plant_emulator.scenarios import build_actuator, build_disturbance, check_scenario
from protocols.samples import DEPTH_RANGE, TelemetrySample, new_sample


@dataclass(frozen=True)
class PlantConfig:
    scenario: str = "paper"
    period: float = 1.0  # s of simulated time per step; the paper does not give it
    seed: int = 0
    trim_depth: float = 15.0  # m; depth is reported as trim + model output
    input_limit: float = 2.0  # model units
    rate_limit: float = 0.5  # model units per step

    def __post_init__(self) -> None:
        check_scenario(self.scenario)
        if not (self.period > 0 and math.isfinite(self.period)):
            raise ValueError(f"period must be positive, got {self.period}")
        if not 0 <= self.trim_depth <= DEPTH_RANGE[1]:  # the deepest ocean
            raise ValueError(
                f"trim depth must be 0..{DEPTH_RANGE[1]:g} m below the surface, got "
                f"{self.trim_depth!r}"
            )


class GliderPlant:
    """Steps both channels once per call; reports what a vehicle's sensors would see."""

    def __init__(self, config: PlantConfig | None = None, system_id: int = 1):
        self.config = config or PlantConfig()
        self.system_id = system_id
        self.loops: dict[str, ClosedLoopChannel] = {
            ch: design_closed_loop(ch, self.config.period) for ch in CHANNELS
        }
        self.actuators: dict[str, BallastActuator] = {
            ch: build_actuator(
                self.config.scenario, self.config.input_limit, self.config.rate_limit
            )
            for ch in CHANNELS
        }
        self.disturbances: dict[str, Disturbance] = {
            ch: build_disturbance(self.config.scenario, ch, self.config.seed) for ch in CHANNELS
        }
        self.k = 0
        self._last_depth: float | None = None
        self._last_pitch: float | None = None

    @property
    def t(self) -> float:
        return self.k * self.config.period

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample:
        """Apply the commanded inputs for one period.

        The sample holds the outputs at the start of the step (they depend on the inputs of
        earlier steps only) and the inputs applied during it (actuator positions after rate
        limiting), so an identifier sees y(t) together with u(t) and uses u(t−1) from the
        previous sample.
        """
        config = self.config
        period = config.period
        t = self.k * period
        actuators, loops, disturbances = self.actuators, self.loops, self.disturbances
        # Depth, then pitch: each channel's actuator, loop and disturbance in this order.
        actuator = actuators["depth"]
        effective = actuator.apply(u_depth)
        u_depth_applied = actuator.position
        depth_out = loops["depth"].step(effective) + disturbances["depth"].sample(t)
        actuator = actuators["pitch"]
        effective = actuator.apply(u_pitch)
        u_pitch_applied = actuator.position
        pitch = loops["pitch"].step(effective) + disturbances["pitch"].sample(t)
        depth = config.trim_depth + depth_out
        last_depth, last_pitch = self._last_depth, self._last_pitch
        climb = 0.0 if last_depth is None else -(depth - last_depth) / period
        pitch_rate = 0.0 if last_pitch is None else (pitch - last_pitch) / period
        self._last_depth, self._last_pitch = depth, pitch
        self.k += 1
        return new_sample(
            self.system_id,
            round(t * 1000.0),
            depth,
            pitch,
            u_depth_applied,
            u_pitch_applied,
            pitch_rate,
            climb,
        )

    def applied_inputs(self) -> tuple[float, float]:
        return self.actuators["depth"].position, self.actuators["pitch"].position


class FamilyPlant:
    """Vehicle ``index`` of the seeded family of ``seed`` (``plant_emulator.family``) behind
    ``GliderPlant``'s interface, so the emulated autopilot serves it as it serves the glider
    (``glider-hil emulate --family SEED:INDEX``).

    ``period`` replaces the vehicle's drawn sample period: the plants are discrete, so the
    same vehicle runs at any rate, sample for sample the same. Depth and pitch are the
    family's outputs in their own units, sent as metres and radians: ``wire_bounds`` says
    whether they stay within what the glider's telemetry carries.
    """

    def __init__(self, seed: int, index: int, period: float | None = None, system_id: int = 1):
        if index < 0:
            raise ValueError(f"family vehicle index must be ≥ 0, got {index}")
        depth, pitch = draw_vehicle(seed, index)
        if period is not None:
            depth, pitch = replace(depth, period=period), replace(pitch, period=period)
        self.specs = {"depth": depth, "pitch": pitch}
        self.vehicle = FamilyVehicle(depth, pitch, seed)
        self.config = PlantConfig(period=depth.period, seed=seed, input_limit=FAMILY_INPUT_LIMIT)
        self.system_id = system_id
        self.actuators = self.vehicle.actuators
        self._last: TelemetrySample | None = None

    @property
    def k(self) -> int:
        return self.vehicle.k

    @property
    def t(self) -> float:
        return self.vehicle.k * self.config.period

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample:
        """One step, as ``GliderPlant.step``: the outputs at its start, the inputs during it."""
        sample = self.vehicle.step(u_depth, u_pitch)
        last, period = self._last, self.config.period
        sample = sample._replace(
            system_id=self.system_id,
            climb=0.0 if last is None else -(sample.depth - last.depth) / period,
            pitch_rate=0.0 if last is None else (sample.pitch - last.pitch) / period,
        )
        self._last = sample
        return sample

    def applied_inputs(self) -> tuple[float, float]:
        return self.actuators["depth"].position, self.actuators["pitch"].position


#: Margin on a family output's excursion from its offset (transients overshoot the steady
#: state; a complex pair of angle ≤ 0.6 rad overshoots by less than this).
EXCURSION_MARGIN = 2.0


def family_output_range(spec: FamilyPlantSpec) -> tuple[float, float]:
    """Where a family plant's output can go over a run: its offset ± the steady state at
    the input's extremes (through the Wiener map) and three times its disturbance, times
    ``EXCURSION_MARGIN``, in output units. Unbounded for an integrator (it ramps)."""
    if spec.integrator:
        return -math.inf, math.inf
    linear = spec.authority() + 3.0 * spec.disturbance_level
    excursion = EXCURSION_MARGIN * abs(spec.scale) * abs(spec.wiener_map(linear))
    return spec.offset - excursion, spec.offset + excursion


def wire_bounds(spec: FamilyPlantSpec) -> str:
    """Why the plant's output may leave what the glider's telemetry carries ("" if it
    stays within: depth in ``DEPTH_RANGE`` m, |pitch| ≤ π rad)."""
    lo, hi = family_output_range(spec)
    if spec.channel == "depth":
        low, high = DEPTH_RANGE
        if low <= lo and hi <= high:
            return ""
        return f"depth may reach {lo:.4g}..{hi:.4g} m, outside {low:g}..{high:g}"
    if -math.pi <= lo and hi <= math.pi:
        return ""
    return f"pitch may reach {lo:.4g}..{hi:.4g} rad, outside ±π"
