"""What a ground station shows besides the plant's own signals: position, battery, hull.

None of it feeds the plant or the service; it makes the emulated vehicle look whole to a
ground station (docs/mavlink.md, "What a ground station gets"):

* position, dead-reckoned from the home position (the dive's surfacing point) along a fixed
  heading at a fixed horizontal speed, with the plant's depth: ``GLOBAL_POSITION_INT``
  (``relative_alt`` = −depth, ``alt`` = home altitude − depth, ``hdg``), ``HOME_POSITION``;
* a battery that drains linearly over ``endurance`` simulated hours: ``SYS_STATUS``,
  ``BATTERY_STATUS``;
* the hull's internal barometer, ``SCALED_PRESSURE`` (surface pressure, dry air inside),
  as ArduSub reports its board barometer beside the Bar30's ``SCALED_PRESSURE2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocols.mapping import WATER_TEMPERATURE_CDEG
from protocols.mavlink_io import MavMessage, dialect
from protocols.samples import TelemetrySample

EARTH_RADIUS = 6_378_137.0  # m, WGS-84 equatorial
HULL_TEMPERATURE_CDEG = 2000  # 20 °C inside the hull
SENSORS = (
    dialect.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | dialect.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | dialect.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | dialect.MAV_SYS_STATUS_SENSOR_BATTERY
)
UINT16_MAX = 0xFFFF


@dataclass(frozen=True)
class NavigationConfig:
    home_lat: float = 43.0956  # deg: the dive's surfacing point (default: off Toulon)
    home_lon: float = 5.9282  # deg
    home_alt: float = 0.0  # m above mean sea level of the surface
    heading: float = 0.0  # deg true, the course dead reckoning follows (ATTITUDE yaw is 0)
    speed: float = 0.3  # m/s over ground, a glider's typical horizontal speed
    voltage: float = 14.8  # V at full charge
    current: float = 0.5  # A drawn
    capacity_mah: float = 50_000.0
    endurance: float = 100.0  # simulated hours from full to empty

    def __post_init__(self) -> None:
        if not (-90 <= self.home_lat <= 90 and -180 <= self.home_lon <= 180):
            raise ValueError("home latitude must be -90..90 and longitude -180..180")
        if not (self.speed >= 0 and self.endurance > 0):
            raise ValueError("speed must be >= 0 and endurance > 0")


class Navigation:
    """Dead reckoning and battery, advanced once per plant step."""

    def __init__(self, config: NavigationConfig | None = None):
        self.config = config or NavigationConfig()
        self.north = 0.0  # m from home
        self.east = 0.0
        self.t = 0.0  # simulated s of the last step
        self.sample: TelemetrySample | None = None
        # m/s north and east along the configured course, for every step's advance.
        heading = math.radians(self.config.heading)
        self._north_speed = self.config.speed * math.cos(heading)
        self._east_speed = self.config.speed * math.sin(heading)

    def advance(self, sample: TelemetrySample, period: float) -> None:
        self.north += self._north_speed * period
        self.east += self._east_speed * period
        self.t = sample.time_boot_ms / 1000.0
        self.sample = sample

    # ---- position -----------------------------------------------------------------------
    def lat_lon_e7(self) -> tuple[int, int]:
        c = self.config
        lat = c.home_lat + math.degrees(self.north / EARTH_RADIUS)
        lon = c.home_lon + math.degrees(
            self.east / (EARTH_RADIUS * max(math.cos(math.radians(c.home_lat)), 1e-6))
        )
        return round(lat * 1e7), round(lon * 1e7)

    def home_e7(self) -> tuple[int, int, float]:
        """Home as a mission item carries it: lat, lon (degE7), altitude (m)."""
        c = self.config
        return round(c.home_lat * 1e7), round(c.home_lon * 1e7), c.home_alt

    def global_position(self, ms: int) -> MavMessage:
        depth = self.sample.depth if self.sample is not None else 0.0
        climb = self.sample.climb if self.sample is not None else 0.0
        heading = math.radians(self.config.heading)
        lat, lon = self.lat_lon_e7()
        return dialect.MAVLink_global_position_int_message(
            ms & 0xFFFFFFFF,
            lat,
            lon,
            round((self.config.home_alt - depth) * 1000),
            round(-depth * 1000),
            round(self.config.speed * math.cos(heading) * 100),
            round(self.config.speed * math.sin(heading) * 100),
            round(-climb * 100),
            round(self.config.heading % 360 * 100),
        )

    def home_position(self) -> MavMessage:
        lat, lon, alt = self.home_e7()
        return dialect.MAVLink_home_position_message(
            lat, lon, round(alt * 1000), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0
        )

    # ---- battery, hull ------------------------------------------------------------------
    def remaining(self) -> int:
        """Battery left, % (0..100)."""
        return max(0, min(100, round(100.0 * (1.0 - self.t / (self.config.endurance * 3600)))))

    def sys_status(self) -> MavMessage:
        c = self.config
        return dialect.MAVLink_sys_status_message(
            SENSORS,
            SENSORS,
            SENSORS,
            100,  # load, per mille
            round(c.voltage * 1000),
            round(c.current * 100),
            self.remaining(),
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def battery_status(self) -> MavMessage:
        c = self.config
        voltages = [round(c.voltage * 1000)] + [UINT16_MAX] * 9
        consumed = round(c.capacity_mah * (100 - self.remaining()) / 100)
        return dialect.MAVLink_battery_status_message(
            0,
            dialect.MAV_BATTERY_FUNCTION_ALL,
            dialect.MAV_BATTERY_TYPE_LION,
            WATER_TEMPERATURE_CDEG,
            voltages,
            round(c.current * 100),
            consumed,
            -1,
            self.remaining(),
        )

    def hull_pressure(self, ms: int, surface_hpa: float) -> MavMessage:
        return dialect.MAVLink_scaled_pressure_message(
            ms & 0xFFFFFFFF, surface_hpa, 0.0, HULL_TEMPERATURE_CDEG
        )
