"""Seeded families of stable plants the controller was not tuned on (``--scenario random``).

Each plant is a discrete transfer function of order 2 or 3, strictly proper:

    G(z) = g · N(z) / D(z),   D with poles of modulus 0.5–0.995 (real, or a complex pair),
    N = 1, or (z − z₀) with a non-minimum-phase zero z₀ ∈ [1.05, 3],

scaled so that G(1), the drawn DC gain, is in 0.2–5 (log-uniform), behind the same kind
of ballast actuator as the glider's (amplitude and rate limits) with an optional pump map
(a dead zone and/or a cubic term). Sample periods differ between vehicles. A vehicle
carries two such plants, one on each telemetry channel, so the service's pipeline runs on
them unchanged; depth is reported around a trim depth as on the glider.

Units: on the depth channel the drawn gain is metres per unit of input, as the glider's.
On the pitch channel it is per unit of a scaled actuator, so that the plant is one a
vehicle could be: the strongest drawn gain (5) at the actuator's full effective output
(the pump map at the input limit) holds the vehicle at ``PITCH_FULL_SCALE`` rad, a weaker
one proportionally less. Taken in radians per unit of input, as the depth gain is, the
family's pitch plants reached 18 rad, which no vehicle does and the service refuses as
implausible (|pitch| ≤ π). The plant's true DC gain (``dc_gain``, output units per unit of
effective input) is the drawn gain times ``unit``; ``drawn_gain`` gives the drawn one back.

Everything is drawn from ``numpy.random.default_rng(seed)``: the same seed gives the same
family, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from plant_emulator.actuator import BallastActuator, PumpNonlinearity
from plant_emulator.models import CHANNELS, ClosedLoopChannel
from protocols.samples import TelemetrySample, new_sample

POLE_RANGE = (0.5, 0.995)
DC_GAIN_RANGE = (0.2, 5.0)
NMP_ZERO_RANGE = (1.05, 3.0)
DEAD_ZONE_RANGE = (0.05, 0.3)
CUBIC_RANGE = (0.02, 0.2)
PERIODS = (0.1, 0.2, 0.5, 1.0, 2.0)
#: Chance that a plant gets each optional feature.
P_NMP, P_DEAD_ZONE, P_CUBIC, P_COMPLEX = 0.3, 0.3, 0.3, 0.4
#: Largest pole angle of a complex pair (rad): a lightly oscillating, not a ringing, plant.
MAX_POLE_ANGLE = 0.5
#: The actuator's amplitude limit (model units), as the glider's ballast input.
INPUT_LIMIT = 2.0
#: The steady pitch (rad, about 46°) of the strongest drawn pitch plant at full actuator:
#: within what a glider pitches (gliders fly at 15–45°), well inside the service's ±π.
PITCH_FULL_SCALE = 0.8


@dataclass(frozen=True)
class RandomPlantSpec:
    """One drawn plant; ``poles`` as (real, imaginary) pairs, conjugates listed once each."""

    index: int
    order: int
    poles: tuple[tuple[float, float], ...]
    zero: float | None  # non-minimum-phase zero, or None
    dc_gain: float  # the plant's DC gain: output units (m, rad) per unit of effective input
    dead_zone: float
    cubic: float
    period: float
    #: Output units per unit of drawn gain: 1 on depth, ``pitch_unit(...)`` on pitch.
    unit: float = 1.0

    @property
    def drawn_gain(self) -> float:
        """The gain as drawn from ``DC_GAIN_RANGE`` (per unit of the scaled actuator)."""
        return self.dc_gain / self.unit

    def den(self) -> np.ndarray:
        roots: list[complex] = []
        for re, im in self.poles:
            roots.append(complex(re, im))
            if im != 0.0:
                roots.append(complex(re, -im))
        return np.real(np.poly(roots))

    def num(self) -> np.ndarray:
        """Numerator (descending powers, same length as ``den``, leading zero: strictly proper)."""
        den = self.den()
        shape = np.array([1.0]) if self.zero is None else np.array([1.0, -self.zero])
        gain = self.dc_gain * float(np.sum(den)) / float(np.sum(shape))
        num = np.zeros(den.size)
        num[-shape.size :] = gain * shape
        return num

    def pole_moduli(self) -> list[float]:
        return [math.hypot(re, im) for re, im in self.poles]

    def pump(self) -> PumpNonlinearity | None:
        if self.dead_zone == 0.0 and self.cubic == 0.0:
            return None
        return PumpNonlinearity(dead_zone=self.dead_zone, cubic=self.cubic)

    def describe(self) -> str:
        poles = ", ".join(
            f"{re:.3f}" if im == 0.0 else f"{math.hypot(re, im):.3f}∠±{math.atan2(im, re):.2f}"
            for re, im in self.poles
        )
        dc = f"DC {self.dc_gain:.2f}" if self.unit == 1.0 else f"DC {self.dc_gain:.3f}"
        parts = [f"order {self.order}", f"poles {poles}", dc]
        if self.zero is not None:
            parts.append(f"zero {self.zero:.2f}")
        if self.dead_zone:
            parts.append(f"dead zone {self.dead_zone:.2f}")
        if self.cubic:
            parts.append(f"cubic {self.cubic:.2f}")
        parts.append(f"T {self.period:g} s")
        return ", ".join(parts)

    def as_json(self) -> dict[str, object]:
        return {
            "index": self.index,
            "order": self.order,
            "poles": [list(p) for p in self.poles],
            "zero": self.zero,
            "dc_gain": self.dc_gain,
            "drawn_gain": self.drawn_gain,
            "unit": self.unit,
            "dead_zone": self.dead_zone,
            "cubic": self.cubic,
            "period": self.period,
        }

    def channel_model(self, channel: str) -> ClosedLoopChannel:
        """The plant as the emulator's channel type (controllable canonical form)."""
        den, num = self.den(), self.num()
        n = den.size - 1
        a = np.zeros((n, n))
        a[0, :] = -den[1:]
        a[1:, :-1] = np.eye(n - 1)
        b = np.zeros(n)
        b[0] = 1.0
        c = num[1:].astype(float)
        return ClosedLoopChannel(
            channel=channel,
            dt=self.period,
            a_cl=a,
            b_cl=b,
            c_cl=c,
            d_cl=0.0,
            gain_k=np.zeros(n),
            ref_gain=1.0,
        )


def _draw_poles(rng: np.random.Generator, order: int) -> tuple[tuple[float, float], ...]:
    lo, hi = POLE_RANGE
    poles: list[tuple[float, float]] = []
    remaining = order
    if rng.random() < P_COMPLEX:
        modulus = float(rng.uniform(lo, hi))
        angle = float(rng.uniform(0.05, MAX_POLE_ANGLE))
        poles.append((modulus * math.cos(angle), modulus * math.sin(angle)))
        remaining -= 2
    poles += [(float(rng.uniform(lo, hi)), 0.0) for _ in range(remaining)]
    return tuple(poles)


def pitch_unit(dead_zone: float, cubic: float, limit: float = INPUT_LIMIT) -> float:
    """Radians per unit of drawn gain on the pitch channel: the strongest drawn gain at the
    pump map's full output (its value at ``limit``) gives ``PITCH_FULL_SCALE``."""
    pump = PumpNonlinearity(dead_zone=dead_zone, cubic=cubic)
    full = pump(limit) if (dead_zone or cubic) else limit
    return PITCH_FULL_SCALE / (DC_GAIN_RANGE[1] * full)


def draw_plant(
    rng: np.random.Generator, index: int, period: float, channel: str = "depth"
) -> RandomPlantSpec:
    """One plant of the family for ``channel`` (the draws do not depend on it: only the
    pitch channel's unit does)."""
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")
    order = int(rng.integers(2, 4))
    poles = _draw_poles(rng, order)
    zero = float(rng.uniform(*NMP_ZERO_RANGE)) if rng.random() < P_NMP else None
    dc = float(math.exp(rng.uniform(math.log(DC_GAIN_RANGE[0]), math.log(DC_GAIN_RANGE[1]))))
    dead_zone = float(rng.uniform(*DEAD_ZONE_RANGE)) if rng.random() < P_DEAD_ZONE else 0.0
    cubic = float(rng.uniform(*CUBIC_RANGE)) if rng.random() < P_CUBIC else 0.0
    unit = pitch_unit(dead_zone, cubic) if channel == "pitch" else 1.0
    return RandomPlantSpec(index, order, poles, zero, dc * unit, dead_zone, cubic, period, unit)


def draw_family(seed: int, plants: int = 20) -> list[tuple[RandomPlantSpec, RandomPlantSpec]]:
    """``plants`` plants (rounded up to even) as (depth, pitch) pairs, one pair per vehicle."""
    if plants < 1:
        raise ValueError(f"plants must be at least 1, got {plants}")
    rng = np.random.default_rng(seed)
    pairs = []
    for v in range((plants + 1) // 2):
        period = float(PERIODS[int(rng.integers(len(PERIODS)))])
        depth = draw_plant(rng, 2 * v, period, "depth")
        pairs.append((depth, draw_plant(rng, 2 * v + 1, period, "pitch")))
    return pairs


@dataclass(frozen=True)
class RandomVehicleConfig:
    depth: RandomPlantSpec
    pitch: RandomPlantSpec
    trim_depth: float = 15.0
    input_limit: float = INPUT_LIMIT
    rate_limit: float = 0.5

    @property
    def period(self) -> float:
        return self.depth.period

    @property
    def scenario(self) -> str:
        return "random"

    def spec(self, channel: str) -> RandomPlantSpec:
        return self.depth if channel == "depth" else self.pitch


class RandomVehicle:
    """A vehicle with a random plant on each channel; the same stepping as ``GliderPlant``."""

    def __init__(self, config: RandomVehicleConfig, system_id: int = 1):
        if config.depth.period != config.pitch.period:
            raise ValueError("both channels of a vehicle share its sample period")
        self.config = config
        self.system_id = system_id
        self.loops = {ch: config.spec(ch).channel_model(ch) for ch in CHANNELS}
        self.actuators = {
            ch: BallastActuator(
                limit=config.input_limit,
                rate_limit=config.rate_limit,
                nonlinearity=config.spec(ch).pump(),
            )
            for ch in CHANNELS
        }
        self.k = 0

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample:
        """Apply the commanded inputs for one period (see ``GliderPlant.step``)."""
        actuators, loops = self.actuators, self.loops
        actuator = actuators["depth"]
        effective = actuator.apply(u_depth)
        u_depth_applied = actuator.position
        depth_out = loops["depth"].step(effective)
        actuator = actuators["pitch"]
        effective = actuator.apply(u_pitch)
        u_pitch_applied = actuator.position
        pitch = loops["pitch"].step(effective)
        config = self.config
        t = self.k * config.period
        self.k += 1
        return new_sample(
            self.system_id,
            round(t * 1000.0),
            config.trim_depth + depth_out,
            pitch,
            u_depth_applied,
            u_pitch_applied,
        )
