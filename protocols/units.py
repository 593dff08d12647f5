"""Unit conversions shared by the emulator and the service (docs/mavlink.md).

The one home of the unit defaults (sea water, standard atmosphere, the paper's ±2 ballast
at wire ±1): the profiles' parser, the service's ``Units`` and the emulator take them from
these dataclasses."""

from __future__ import annotations

import math
from dataclasses import dataclass

STANDARD_GRAVITY = 9.80665  # m/s²


@dataclass(frozen=True)
class PressureDepth:
    """Absolute pressure (hPa) ↔ depth (m, positive down), ArduSub's Bar30 convention.

    depth = (press_abs − surface)·100 / (ρ·g). Defaults: sea water, standard atmosphere.
    """

    water_density: float = 1025.0  # kg/m³
    surface_hpa: float = 1013.25
    gravity: float = STANDARD_GRAVITY

    def __post_init__(self) -> None:
        if not (self.water_density > 0 and math.isfinite(self.water_density)):
            raise ValueError(f"water density must be positive, got {self.water_density}")
        if not (self.surface_hpa > 0 and math.isfinite(self.surface_hpa)):
            raise ValueError(f"surface pressure must be positive, got {self.surface_hpa}")

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
        if not (self.full_scale > 0 and math.isfinite(self.full_scale)):
            raise ValueError(f"full scale must be positive, got {self.full_scale}")

    def to_wire(self, model_units: float) -> float:
        return model_units / self.full_scale

    def to_model(self, wire: float) -> float:
        return wire * self.full_scale
