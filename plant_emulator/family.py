"""A seeded family of vehicles the controller was not designed on (``--scenario family``).

Each plant (one per telemetry channel, two per vehicle sharing its sample period) is drawn
from ``numpy.random.default_rng([seed, vehicle])`` — the same seed and index give the same
plant bit for bit, whatever the family's size — as:

* **linear part**: order 1–4 (uniform), poles of modulus 0.3–0.98 (real, or one complex
  pair of angle ≤ 0.6 rad), with probability ``P_INTEGRATOR`` one of them an integrator
  (a pole at ``INTEGRATOR_POLE`` = 0.9995: a ramp over any run we make, yet a model the
  oracle's LP can hold), with probability ``P_NMP`` a non-minimum-phase zero in 1.05–3;
  DC gain log-uniform in 0.2–5 (an integrator's drawn gain is its gain over 100 samples);
* **input delay** of 0–5 samples (uniform), in the state (the oracle knows it);
* **static map** (``P_HAMMERSTEIN`` / ``P_WIENER`` / linear): Hammerstein on the input — a
  dead zone (0–0.3), a cubic term (0–0.2), an asymmetric saturation of the effective
  input at 40–100 % of the range on each side; or Wiener on the output — y + c·y³/A²
  (c 0.1–0.5, A the plant's authority), monotone;
* **disturbance** on the output, none / white / coloured (AR(1), pole 0.9–0.99) /
  periodic (period 20–400 samples), of an RMS (periodic: amplitude) up to the control
  authority A = |DC gain| × the map at full input (log-uniform share 0.01–1);
* **units**: output scale 10^U(−3, 3) (six decades) and offset 10^U(−1, 3) (signed on
  pitch), applied after everything; sample periods 0.01–2 s.

The actuator is the glider's (range ±2, rate 0.5 per sample) with the Hammerstein map as
its pump map. ``FamilyVehicle`` steps two such plants as ``GliderPlant`` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from plant_emulator.actuator import BallastActuator
from plant_emulator.models import CHANNELS, ClosedLoopChannel
from protocols.samples import TelemetrySample

ORDERS = (1, 2, 3, 4)
POLE_RANGE = (0.3, 0.98)
MAX_POLE_ANGLE = 0.6
INTEGRATOR_POLE = 0.9995
INTEGRATOR_SPAN = 100  # samples over which an integrator's drawn gain is reached
DC_GAIN_RANGE = (0.2, 5.0)
NMP_ZERO_RANGE = (1.05, 3.0)
DELAYS = (0, 1, 2, 3, 4, 5)
DEAD_ZONE_MAX = 0.3
CUBIC_MAX = 0.2
SATURATION_RANGE = (0.4, 1.0)  # shares of the input range, each side
WIENER_RANGE = (0.1, 0.5)
DISTURBANCES = ("none", "white", "coloured", "periodic")
DISTURBANCE_SHARE = (0.01, 1.0)  # of the authority, log-uniform
COLOURED_POLE = (0.9, 0.99)
PERIODIC_SAMPLES = (20, 400)
SCALE_DECADES = (-3.0, 3.0)
OFFSET_DECADES = (-1.0, 3.0)
PERIODS = (0.01, 0.1, 0.5, 1.0, 2.0)
P_COMPLEX, P_INTEGRATOR, P_NMP = 0.35, 0.1, 0.25
P_HAMMERSTEIN, P_WIENER = 0.45, 0.25
INPUT_LIMIT = 2.0
RATE_LIMIT = 0.5


@dataclass(frozen=True)
class InputMap:
    """Hammerstein map on the actuator position: dead zone, cubic, asymmetric saturation
    (monotone non-decreasing, so the oracle can invert it)."""

    dead_zone: float = 0.0
    cubic: float = 0.0
    upper: float = math.inf  # effective input saturates here …
    lower: float = -math.inf  # … and here

    def __call__(self, u: float) -> float:
        v = math.copysign(max(abs(u) - self.dead_zone, 0.0), u) + self.cubic * u**3
        return min(max(v, self.lower), self.upper)

    @property
    def identity(self) -> bool:
        return self.dead_zone == 0.0 and self.cubic == 0.0 and math.isinf(self.upper)


@dataclass(frozen=True)
class FamilyPlantSpec:
    vehicle: int
    channel: str
    order: int
    poles: tuple[tuple[float, float], ...]  # conjugates listed once
    integrator: bool
    zero: float | None
    dc_gain: float  # output units (before scale) per unit of effective input
    delay: int
    kind: str  # "hammerstein", "wiener" or "linear"
    input_map: InputMap
    wiener: float  # the Wiener term's c (0: none)
    disturbance: str
    disturbance_level: float  # RMS (amplitude if periodic), linear-output units
    disturbance_param: float  # AR pole (coloured) or period in samples (periodic)
    scale: float
    offset: float
    period: float

    def roots(self) -> list[complex]:
        roots: list[complex] = []
        for re, im in self.poles:
            roots.append(complex(re, im))
            if im != 0.0:
                roots.append(complex(re, -im))
        return roots

    def den(self) -> np.ndarray:
        return np.real(np.poly(self.roots()))

    def num(self) -> np.ndarray:
        den = self.den()
        shape = np.array([1.0]) if self.zero is None else np.array([1.0, -self.zero])
        gain = self.dc_gain * float(np.sum(den)) / float(np.sum(shape))
        num = np.zeros(den.size)
        num[-shape.size :] = gain * shape
        return num

    def authority(self) -> float:
        """|DC gain| × the map's largest effective input (linear-output units)."""
        full = max(abs(self.input_map(INPUT_LIMIT)), abs(self.input_map(-INPUT_LIMIT)))
        return abs(self.dc_gain) * full

    def wiener_map(self, w: float) -> float:
        if self.wiener == 0.0:
            return w
        a = self.authority()
        return w + self.wiener * w**3 / (a * a)

    def wiener_inverse(self, y: float) -> float:
        """The linear output whose Wiener map is ``y`` (monotone: bisection)."""
        if self.wiener == 0.0:
            return y
        lo, hi = -abs(y) - 1.0, abs(y) + 1.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if self.wiener_map(mid) < y:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def channel_model(self) -> ClosedLoopChannel:
        """Controllable canonical form with the input delay as a shift register before it."""
        den, num = self.den(), self.num()
        n = den.size - 1
        d = self.delay
        size = n + d
        a = np.zeros((size, size))
        a[0, :n] = -den[1:]
        a[1:n, : n - 1] = np.eye(n - 1)
        b = np.zeros(size)
        c = np.zeros(size)
        c[:n] = num[1:]
        if d == 0:
            b[0] = 1.0
        else:
            a[0, n + d - 1] = 1.0  # the oldest delayed input drives the dynamics
            for i in range(1, d):
                a[n + i, n + i - 1] = 1.0
            b[n] = 1.0
        return ClosedLoopChannel(
            channel=self.channel,
            dt=self.period,
            a_cl=a,
            b_cl=b,
            c_cl=c,
            d_cl=0.0,
            gain_k=np.zeros(size),
            ref_gain=1.0,
        )

    def describe(self) -> str:
        poles = ", ".join(
            f"{re:.3f}" if im == 0.0 else f"{math.hypot(re, im):.3f}∠±{math.atan2(im, re):.2f}"
            for re, im in self.poles
        )
        parts = [f"{self.kind} order {self.order}", f"poles {poles}", f"DC {self.dc_gain:.3g}"]
        if self.zero is not None:
            parts.append(f"zero {self.zero:.2f}")
        if self.delay:
            parts.append(f"delay {self.delay}")
        if self.disturbance != "none":
            parts.append(f"{self.disturbance} {self.disturbance_level / self.authority():.2f}·A")
        parts.append(f"scale {self.scale:.3g} offset {self.offset:.3g} T {self.period:g} s")
        return ", ".join(parts)

    def as_json(self) -> dict[str, object]:
        return {
            "vehicle": self.vehicle,
            "channel": self.channel,
            "kind": self.kind,
            "order": self.order,
            "poles": [list(p) for p in self.poles],
            "integrator": self.integrator,
            "zero": self.zero,
            "dc_gain": self.dc_gain,
            "delay": self.delay,
            "dead_zone": self.input_map.dead_zone,
            "cubic": self.input_map.cubic,
            "saturation": [self.input_map.lower, self.input_map.upper],
            "wiener": self.wiener,
            "disturbance": self.disturbance,
            "disturbance_share": self.disturbance_level / self.authority(),
            "scale": self.scale,
            "offset": self.offset,
            "period": self.period,
        }


def _poles(rng: np.random.Generator, order: int) -> tuple[list[tuple[float, float]], bool]:
    poles: list[tuple[float, float]] = []
    remaining = order
    integrator = rng.random() < P_INTEGRATOR
    if integrator:
        poles.append((INTEGRATOR_POLE, 0.0))
        remaining -= 1
    if remaining >= 2 and rng.random() < P_COMPLEX:
        modulus = float(rng.uniform(*POLE_RANGE))
        angle = float(rng.uniform(0.05, MAX_POLE_ANGLE))
        poles.append((modulus * math.cos(angle), modulus * math.sin(angle)))
        remaining -= 2
    poles += [(float(rng.uniform(*POLE_RANGE)), 0.0) for _ in range(remaining)]
    return poles, integrator


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw_plant(
    rng: np.random.Generator, vehicle: int, channel: str, period: float
) -> FamilyPlantSpec:
    order = int(rng.choice(ORDERS))
    poles, integrator = _poles(rng, order)
    zero = float(rng.uniform(*NMP_ZERO_RANGE)) if rng.random() < P_NMP else None
    dc = _log_uniform(rng, *DC_GAIN_RANGE)
    if integrator:  # its gain over INTEGRATOR_SPAN samples is the drawn one
        dc *= (1.0 - INTEGRATOR_POLE**INTEGRATOR_SPAN) ** -1
    delay = int(rng.choice(DELAYS))
    draw = rng.random()
    kind = (
        "hammerstein"
        if draw < P_HAMMERSTEIN
        else "wiener"
        if draw < P_HAMMERSTEIN + P_WIENER
        else "linear"
    )
    input_map, wiener = InputMap(), 0.0
    if kind == "hammerstein":
        dead = float(rng.uniform(0.0, DEAD_ZONE_MAX))
        cubic = float(rng.uniform(0.0, CUBIC_MAX))
        full = InputMap(dead, cubic)(INPUT_LIMIT)
        upper = full * float(rng.uniform(*SATURATION_RANGE))
        lower = -full * float(rng.uniform(*SATURATION_RANGE))
        input_map = InputMap(dead, cubic, upper, lower)
    elif kind == "wiener":
        wiener = float(rng.uniform(*WIENER_RANGE))
    disturbance = str(rng.choice(DISTURBANCES))
    share = _log_uniform(rng, *DISTURBANCE_SHARE)
    param = 0.0
    if disturbance == "coloured":
        param = float(rng.uniform(*COLOURED_POLE))
    elif disturbance == "periodic":
        param = float(rng.uniform(*PERIODIC_SAMPLES))
    scale = 10.0 ** float(rng.uniform(*SCALE_DECADES))
    offset = 10.0 ** float(rng.uniform(*OFFSET_DECADES))
    if channel == "pitch" and rng.random() < 0.5:
        offset = -offset
    spec = FamilyPlantSpec(
        vehicle, channel, order, tuple(poles), integrator, zero, dc, delay, kind, input_map,
        wiener, disturbance, 0.0, param, scale, offset, period,
    )  # fmt: skip
    level = 0.0 if disturbance == "none" else share * spec.authority()
    return FamilyPlantSpec(
        vehicle, channel, order, tuple(poles), integrator, zero, dc, delay, kind, input_map,
        wiener, disturbance, level, param, scale, offset, period,
    )  # fmt: skip


def draw_vehicle(seed: int, vehicle: int) -> tuple[FamilyPlantSpec, FamilyPlantSpec]:
    """Vehicle ``vehicle`` of the family of ``seed``: (depth, pitch) plants."""
    rng = np.random.default_rng([seed, vehicle])
    period = float(PERIODS[int(rng.integers(len(PERIODS)))])
    depth = draw_plant(rng, vehicle, "depth", period)
    return depth, draw_plant(rng, vehicle, "pitch", period)


def draw_family(seed: int, plants: int) -> list[tuple[FamilyPlantSpec, FamilyPlantSpec]]:
    """``plants`` plants (rounded up to even), two per vehicle."""
    if plants < 1:
        raise ValueError(f"plants must be at least 1, got {plants}")
    return [draw_vehicle(seed, v) for v in range((plants + 1) // 2)]


class Disturbance:
    """The plant's output disturbance, seeded by the plant (white, coloured, periodic)."""

    def __init__(self, spec: FamilyPlantSpec, seed: int) -> None:
        self.spec = spec
        self.rng = np.random.default_rng([seed, spec.vehicle, CHANNELS.index(spec.channel), 7])
        self.state = 0.0
        self.k = 0

    def next(self) -> float:
        spec = self.spec
        k = self.k
        self.k += 1
        if spec.disturbance == "white":
            return spec.disturbance_level * float(self.rng.standard_normal())
        if spec.disturbance == "coloured":
            pole = spec.disturbance_param
            gain = spec.disturbance_level * math.sqrt(1.0 - pole * pole)  # RMS = level
            self.state = pole * self.state + gain * float(self.rng.standard_normal())
            return self.state
        if spec.disturbance == "periodic":
            return spec.disturbance_level * math.sin(2.0 * math.pi * k / spec.disturbance_param)
        return 0.0


class FamilyVehicle:
    """Two family plants behind the glider's actuator; the same stepping as ``GliderPlant``."""

    def __init__(self, depth: FamilyPlantSpec, pitch: FamilyPlantSpec, seed: int = 0):
        if depth.period != pitch.period:
            raise ValueError("both channels of a vehicle share its sample period")
        self.specs = {"depth": depth, "pitch": pitch}
        self.period = depth.period
        self.loops = {ch: self.specs[ch].channel_model() for ch in CHANNELS}
        self.actuators = {ch: self._actuator(self.specs[ch]) for ch in CHANNELS}
        self.disturbances = {ch: Disturbance(self.specs[ch], seed) for ch in CHANNELS}
        self.k = 0

    @staticmethod
    def _actuator(spec: FamilyPlantSpec) -> BallastActuator:
        # The actuator calls its map on the position: any monotone callable serves.
        pump: Any = None if spec.input_map.identity else spec.input_map
        return BallastActuator(limit=INPUT_LIMIT, rate_limit=RATE_LIMIT, nonlinearity=pump)

    def output(self, channel: str, linear: float) -> float:
        spec = self.specs[channel]
        return spec.offset + spec.scale * spec.wiener_map(linear)

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample:
        outputs, applied = {}, {}
        for ch, command in (("depth", u_depth), ("pitch", u_pitch)):
            actuator = self.actuators[ch]
            effective = actuator.apply(command)
            applied[ch] = actuator.position
            linear = self.loops[ch].step(effective) + self.disturbances[ch].next()
            outputs[ch] = self.output(ch, linear)
        t = self.k * self.period
        self.k += 1
        return TelemetrySample(
            system_id=1,
            time_boot_ms=round(t * 1000.0),
            depth=outputs["depth"],
            pitch=outputs["pitch"],
            u_depth=applied["depth"],
            u_pitch=applied["pitch"],
        )
