"""Unit conversions shared by the emulator and the service (docs/mavlink.md).

The one home of the unit defaults (sea water, standard atmosphere, the paper's ±2 ballast
at wire ±1): the profiles' parser, the service's ``Units`` and the emulator take them from
these dataclasses."""

from __future__ import annotations

from dataclasses import dataclass

STANDARD_GRAVITY = 9.80665  # m/s²
#: kg/m³: from water lighter than any lake's to brine heavier than the Dead Sea's.
WATER_DENSITY_RANGE = (500.0, 2000.0)
#: hPa at the water's surface: from a lake far above any on Earth to a pressurised tank.
SURFACE_PRESSURE_RANGE = (100.0, 10_000.0)
#: Model units at wire 1.0: wide enough for any actuator's units (the paper's ballast is
#: 2, a buoyancy engine's cc hundreds), narrow enough that every wire value, a model value
#: divided by it, stays a float32 (what MAVLink carries).
FULL_SCALE_RANGE = (1e-6, 1e6)


def range_problem(value: float, bounds: tuple[float, float], unit: str) -> str:
    """Why ``value`` lies outside ``bounds`` (NaN lies in no range), or "" when it lies in."""
    low, high = bounds
    if low <= value <= high:
        return ""
    return f"must be {low:g}..{high:g} {unit}, got {value!r}"


@dataclass(frozen=True)
class PressureDepth:
    """Absolute pressure (hPa) ↔ depth (m, positive down), ArduSub's Bar30 convention.

    depth = (press_abs − surface)·100 / (ρ·g). Defaults: sea water, standard atmosphere.
    """

    water_density: float = 1025.0  # kg/m³
    surface_hpa: float = 1013.25
    gravity: float = STANDARD_GRAVITY

    def __post_init__(self) -> None:
        problem = range_problem(self.water_density, WATER_DENSITY_RANGE, "kg/m³")
        if problem:
            raise ValueError(f"water density {problem}")
        problem = range_problem(self.surface_hpa, SURFACE_PRESSURE_RANGE, "hPa")
        if problem:
            raise ValueError(f"surface pressure {problem}")

    def depth_m(self, press_abs_hpa: float) -> float:
        return (press_abs_hpa - self.surface_hpa) * 100.0 / (self.water_density * self.gravity)

    def pressure_hpa(self, depth_m: float) -> float:
        return self.surface_hpa + depth_m * self.water_density * self.gravity / 100.0


@dataclass(frozen=True)
class InputScale:
    """Model units (the paper's −2..2 ballast input) ↔ the wire's normalised −1..1.

    ``full_scale`` model units map to 1.0 on the wire.
    """

    full_scale: float = 2.0

    def __post_init__(self) -> None:
        problem = range_problem(self.full_scale, FULL_SCALE_RANGE, "model units")
        if problem:
            raise ValueError(f"full scale {problem}")

    def to_wire(self, model_units: float) -> float:
        return model_units / self.full_scale

    def to_model(self, wire: float) -> float:
        return wire * self.full_scale
