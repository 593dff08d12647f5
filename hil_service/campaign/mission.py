"""One mission of a campaign: its plant, excitation and setpoint schedule, and the offline
yardsticks (reference only, the known-model oracle) on the same plant and disturbance.

The HIL run (``hil_run.py``) and the offline runs here step the same plant class from the
same seed, so they see the same disturbance; the setpoints come from the experiment's
``setpoint_schedule`` (a step every ``step_every`` samples after ``identify``).

Indexing follows the emulator: step k applies the excitation's value k until the service
commands, and the answer to sample k is applied at step k + 1 (docs/lockstep.md). The
offline reference-only run does the same. The oracle is the experiment's own
(``oracle_run``), which starts its excitation one step later; the difference is confined
to the identification phase, which no metric scores.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hil_service.campaign import SCENARIOS
from hil_service.experiment.closed_loop import (
    GLIDER_ORACLE,
    ClosedLoopSettings,
    known_plant,
    oracle_run,
    setpoint_schedule,
)
from hil_service.experiment.random_loop import TRIMS, channel_levels, oracle_settings_for
from plant_emulator.excitation import Excitation, build_channel_excitations
from plant_emulator.models import CHANNELS, DEFAULT_DESIGNS
from plant_emulator.plant import GliderPlant, PlantConfig
from plant_emulator.random_plants import RandomVehicle, RandomVehicleConfig, draw_family
from protocols.samples import TelemetrySample


class RandomPlant:
    """A ``RandomVehicle`` with what the emulator's ``Autopilot`` also asks of a plant."""

    def __init__(self, config: RandomVehicleConfig, system_id: int = 1):
        self.vehicle = RandomVehicle(config, system_id)
        self.config = config  # .period, as PlantConfig has
        self.loops = self.vehicle.loops
        self.actuators = self.vehicle.actuators

    @property
    def k(self) -> int:
        return self.vehicle.k

    @property
    def t(self) -> float:
        return self.vehicle.k * self.config.period

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample:
        return self.vehicle.step(u_depth, u_pitch)

    def applied_inputs(self) -> tuple[float, float]:
        return self.actuators["depth"].position, self.actuators["pitch"].position


Plant = GliderPlant | RandomPlant


@dataclass(frozen=True)
class Mission:
    scenario: str
    seed: int
    steps: int = 3600
    identify: int = 1000
    step_every: int = 400
    settle_band: float = 0.1

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario must be one of {SCENARIOS}, got {self.scenario!r}")
        # ClosedLoopSettings checks identify, steps and step_every and says what is wrong.
        self.settings()

    @property
    def run_id(self) -> str:
        return f"{self.scenario}-s{self.seed:04d}"

    def settings(self) -> ClosedLoopSettings:
        return ClosedLoopSettings(
            scenario="disturbed" if self.scenario == "random" else self.scenario,
            samples=self.steps,
            seed=self.seed,
            identify=self.identify,
            step_every=self.step_every,
            settle_band=self.settle_band,
        )

    def _random_config(self) -> RandomVehicleConfig:
        depth, pitch = draw_family(self.seed, 1)[0]
        return RandomVehicleConfig(depth=depth, pitch=pitch)

    def plant(self, system_id: int = 1) -> Plant:
        """A fresh plant at rest, with this mission's disturbance (seeded): a copy of one
        built once per process, because building one designs its inner loops (tens of ms)
        and a mission steps three (the HIL run's, the reference-only run's, the oracle's)."""
        return copy.deepcopy(_pristine_plant(self, system_id))

    @property
    def period(self) -> float:
        """s per step, from the plant's configuration: building the plant itself designs
        its inner loops (tens of ms), and scoring asks for the period several times."""
        if self.scenario == "random":
            return float(self._random_config().period)
        return float(PlantConfig(scenario=self.scenario, seed=self.seed).period)

    def trims(self) -> dict[str, float]:
        if self.scenario == "random":
            return dict(TRIMS)
        return {"depth": PlantConfig().trim_depth, "pitch": 0.0}

    def excitations(self) -> dict[str, Excitation]:
        return build_channel_excitations("steps", self.seed)

    def schedule(self) -> dict[str, np.ndarray]:
        """Setpoints per sample (NaN while identifying), as the experiment schedules them."""
        if self.scenario == "random":
            config = self._random_config()
            levels = {
                ch: channel_levels(config.spec(ch), config.input_limit, TRIMS[ch])
                for ch in CHANNELS
            }
            return setpoint_schedule(self.settings(), levels)
        return setpoint_schedule(self.settings())

    def reference_only(self) -> Callable[[int], tuple[float, float]]:
        """The input whose steady state is setpoint k (the plant's DC gain, pump inverted)."""
        schedule = self.schedule()
        trims = self.trims()
        if self.scenario == "random":
            config = self._random_config()
            plant = self.plant()
            knowns = {ch: known_plant(plant, ch, trims[ch]) for ch in CHANNELS}

            def random_reference(k: int) -> tuple[float, float]:
                out = [
                    knowns[ch].invert_pump(
                        (float(schedule[ch][k]) - trims[ch]) / config.spec(ch).dc_gain, 0.0
                    )
                    for ch in CHANNELS
                ]
                return out[0], out[1]

            return random_reference
        gains = {ch: DEFAULT_DESIGNS[ch].dc_gain for ch in CHANNELS}

        def glider_reference(k: int) -> tuple[float, float]:
            return (
                (float(schedule["depth"][k]) - trims["depth"]) / gains["depth"],
                float(schedule["pitch"][k]) / gains["pitch"],
            )

        return glider_reference


@functools.lru_cache(maxsize=8)
def _pristine_plant(mission: Mission, system_id: int) -> Plant:
    """The mission's plant at rest, never stepped: ``Mission.plant`` hands out copies."""
    if mission.scenario == "random":
        return RandomPlant(mission._random_config(), system_id)
    return GliderPlant(PlantConfig(scenario=mission.scenario, seed=mission.seed), system_id)


@dataclass
class Trace:
    """Outputs and applied inputs per step, one array per channel."""

    y: dict[str, np.ndarray]
    u: dict[str, np.ndarray]

    @classmethod
    def empty(cls, steps: int) -> Trace:
        return cls(
            y={ch: np.full(steps, np.nan) for ch in CHANNELS},
            u={ch: np.full(steps, np.nan) for ch in CHANNELS},
        )

    def record(self, k: int, sample: TelemetrySample) -> None:
        # Once per step of each of a mission's three runs: the fields, not a loop over
        # channels with ``sample.output``/``input`` calls.
        y, u = self.y, self.u
        y_depth = y["depth"]
        if 0 <= k < y_depth.size:
            y_depth[k] = sample.depth
            y["pitch"][k] = sample.pitch
            u["depth"][k] = sample.u_depth
            u["pitch"][k] = sample.u_pitch


def reference_only_trace(mission: Mission) -> Trace:
    """The plant driven by the reference alone, indexed as the emulator steps."""
    plant = mission.plant()
    excitation = mission.excitations()
    reference = mission.reference_only()
    trace = Trace.empty(mission.steps)
    for k in range(mission.steps):
        if k <= mission.identify:
            command = (excitation["depth"].value(k), excitation["pitch"].value(k))
        else:
            command = reference(k - 1)
        trace.record(k, plant.step(*command))
    return trace


def oracle_trace(mission: Mission) -> tuple[Trace, int]:
    """The known-model oracle on the same plant and setpoints; its LP failures."""
    plant = mission.plant()
    trims = mission.trims()
    if mission.scenario == "random":
        knowns = {ch: known_plant(plant, ch, trims[ch]) for ch in CHANNELS}
        settings = {ch: oracle_settings_for(knowns[ch]) for ch in CHANNELS}
    else:
        settings = GLIDER_ORACLE
    run, failures = oracle_run(mission.settings(), plant, mission.schedule(), settings, trims)
    return Trace(y=run.y, u=run.u), failures
