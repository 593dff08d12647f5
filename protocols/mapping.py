"""The MAVLink contract (docs/mavlink.md): which standard message carries what.

* depth: SCALED_PRESSURE2 (137) ``press_abs`` hPa, converted by ``PressureDepth``;
  also VFR_HUD (74) ``alt`` m (negative below the surface) and ``climb`` m/s.
* pitch: ATTITUDE (30) ``pitch`` rad, ``pitchspeed`` rad/s.
* applied inputs: ACTUATOR_OUTPUT_STATUS (375) ``actuator[0]`` depth channel,
  ``actuator[1]`` pitch channel, normalised −1..1 (``InputScale``).
* ballast command: COMMAND_LONG with MAV_CMD_DO_SET_ACTUATOR, ``param1`` depth,
  ``param2`` pitch, −1..1, NaN = leave unchanged; answered with COMMAND_ACK.

Both the emulator and the service build messages and read their fields only through this
module (the service's ``assembler`` groups messages by the step time read here, then builds
the sample with the readers below).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from protocols.mavlink_io import MavMessage, dialect
from protocols.samples import BallastCommand, TelemetrySample
from protocols.units import InputScale, PressureDepth

AUTOPILOT_COMPONENT = dialect.MAV_COMP_ID_AUTOPILOT1
SERVICE_COMPONENT = dialect.MAV_COMP_ID_ONBOARD_COMPUTER
MSG_ATTITUDE = "ATTITUDE"
MSG_PRESSURE = "SCALED_PRESSURE2"
MSG_HUD = "VFR_HUD"
MSG_ACTUATORS = "ACTUATOR_OUTPUT_STATUS"
MSG_ACK = "COMMAND_ACK"
TELEMETRY_TYPES = frozenset({MSG_ATTITUDE, MSG_PRESSURE, MSG_HUD, MSG_ACTUATORS})
DEPTH_ACTUATOR = 0
PITCH_ACTUATOR = 1
ACTUATOR_SLOTS = 32
WATER_TEMPERATURE_CDEG = 1500  # 15 °C, reported in SCALED_PRESSURE2


class CommandRejected(ValueError):
    """A ballast command the vehicle must refuse (answered with MAV_RESULT_DENIED)."""


@dataclass(frozen=True)
class TelemetryMapping:
    """Conversions between samples and MAVLink messages, shared by both ends of the link."""

    pressure: PressureDepth = field(default_factory=PressureDepth)
    inputs: InputScale = field(default_factory=InputScale)

    # ---- vehicle side -------------------------------------------------------------
    def heartbeat(
        self,
        vehicle: bool = True,
        autopilot: int = dialect.MAV_AUTOPILOT_GENERIC,
        base_mode: int = 0,
    ) -> MavMessage:
        """A vehicle's HEARTBEAT (``autopilot``, ``base_mode`` as given), or with
        ``vehicle=False`` an onboard controller's."""
        kind = dialect.MAV_TYPE_SUBMARINE if vehicle else dialect.MAV_TYPE_ONBOARD_CONTROLLER
        if not vehicle:
            autopilot, base_mode = dialect.MAV_AUTOPILOT_INVALID, 0
        return dialect.MAVLink_heartbeat_message(
            kind, autopilot, base_mode, 0, dialect.MAV_STATE_ACTIVE, 3
        )

    def encode_telemetry(self, sample: TelemetrySample) -> list[MavMessage]:
        """The four messages of one plant step, all stamped with the step's time."""
        ms = sample.time_boot_ms & 0xFFFFFFFF
        actuators = [0.0] * ACTUATOR_SLOTS
        actuators[DEPTH_ACTUATOR] = self.inputs.to_wire(sample.u_depth)
        actuators[PITCH_ACTUATOR] = self.inputs.to_wire(sample.u_pitch)
        return [
            dialect.MAVLink_attitude_message(
                ms, 0.0, sample.pitch, 0.0, 0.0, sample.pitch_rate, 0.0
            ),
            dialect.MAVLink_scaled_pressure2_message(
                ms, self.pressure.pressure_hpa(sample.depth), 0.0, WATER_TEMPERATURE_CDEG, 0
            ),
            dialect.MAVLink_vfr_hud_message(0.0, 0.0, 0, 0, -sample.depth, sample.climb),
            dialect.MAVLink_actuator_output_status_message(ms * 1000, 0b11, actuators),
        ]

    def status_text(self, text: str, severity: int = dialect.MAV_SEVERITY_NOTICE) -> MavMessage:
        return dialect.MAVLink_statustext_message(severity, text.encode()[:50], 0, 0)

    def parse_ballast_command(self, message: MavMessage) -> BallastCommand:
        """Read a DO_SET_ACTUATOR command; raise ``CommandRejected`` for bad values.

        NaN means "leave unchanged"; infinities, values outside −1..1 and a command with
        nothing to set (both NaN) are refused.
        """
        values = []
        for wire in (message.param1, message.param2):
            if math.isnan(wire):
                values.append(math.nan)
                continue
            if not math.isfinite(wire) or abs(wire) > 1.0:
                raise CommandRejected(f"actuator value {wire!r} outside -1..1")
            values.append(self.inputs.to_model(wire))
        if all(math.isnan(v) for v in values):
            raise CommandRejected("no actuator value given (both NaN)")
        return BallastCommand(u_depth=values[0], u_pitch=values[1])

    def command_ack(self, message: MavMessage, accepted: bool) -> MavMessage:
        result = dialect.MAV_RESULT_ACCEPTED if accepted else dialect.MAV_RESULT_DENIED
        return dialect.MAVLink_command_ack_message(
            message.command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent()
        )

    # ---- service side -------------------------------------------------------------
    def ballast_command(
        self, command: BallastCommand, target_system: int, confirmation: int = 0
    ) -> MavMessage:
        wire = [
            math.nan if math.isnan(u) else self.inputs.to_wire(u)
            for u in (command.u_depth, command.u_pitch)
        ]
        return dialect.MAVLink_command_long_message(
            target_system,
            AUTOPILOT_COMPONENT,
            dialect.MAV_CMD_DO_SET_ACTUATOR,
            confirmation,
            wire[0],
            wire[1],
            math.nan,
            math.nan,
            math.nan,
            math.nan,
            0.0,
        )

    def depth_from_pressure(self, message: MavMessage) -> float:
        """Depth (m) of a SCALED_PRESSURE2."""
        return self.pressure.depth_m(message.press_abs)

    def inputs_from_actuators(self, message: MavMessage) -> tuple[float, float]:
        """Applied (depth, pitch) inputs in model units of an ACTUATOR_OUTPUT_STATUS."""
        return (
            self.inputs.to_model(message.actuator[DEPTH_ACTUATOR]),
            self.inputs.to_model(message.actuator[PITCH_ACTUATOR]),
        )


def is_ballast_command(message: MavMessage) -> bool:
    return (
        message.get_type() == "COMMAND_LONG" and message.command == dialect.MAV_CMD_DO_SET_ACTUATOR
    )


def command_target_system(message: MavMessage) -> int:
    """The system a COMMAND_LONG is addressed to (0: every system)."""
    return int(message.target_system)


def step_time_ms(message: MavMessage, kind: str) -> int:
    """The plant step (ms since boot) of a telemetry message of type ``kind`` that carries
    one (ATTITUDE, SCALED_PRESSURE2, ACTUATOR_OUTPUT_STATUS); -1 for any other message."""
    if kind in (MSG_ATTITUDE, MSG_PRESSURE):
        return int(message.time_boot_ms)
    if kind == MSG_ACTUATORS:
        return int(message.time_usec) // 1000
    return -1


def pitch_from_attitude(message: MavMessage) -> float:
    """Pitch (rad) of an ATTITUDE."""
    return float(message.pitch)


def pitch_rate_from_attitude(message: MavMessage) -> float:
    """Pitch rate (rad/s) of an ATTITUDE."""
    return float(message.pitchspeed)


def ack_accepted(message: MavMessage) -> bool:
    """Whether a COMMAND_ACK accepts the command."""
    return bool(message.result == dialect.MAV_RESULT_ACCEPTED)
