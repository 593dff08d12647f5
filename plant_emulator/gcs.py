"""An autopilot's manners towards a ground station: what it answers, and how.

A ground station (MAVProxy, QGroundControl) asks for parameters, the mission, the home
position, the autopilot's version, message rates and files, and repeats a request that gets
no answer (MAVProxy: every 2 s, forever). This module answers each of them as ArduPilot
does, for an emulator whose real settings are its parameters:

* every ``COMMAND_LONG`` gets a ``COMMAND_ACK``: ``UNSUPPORTED`` unless a handler takes it;
  ``COMMAND_INT`` too;
* ``PARAM_REQUEST_LIST``/``PARAM_REQUEST_READ``/``PARAM_SET`` over ``Parameter`` objects
  whose setter changes the emulator (a change takes effect; a read-only or refused value is
  answered with the value kept);
* ``MISSION_REQUEST_LIST`` → ``MISSION_COUNT`` 0 (an empty mission);
* ``REQUEST_MESSAGE``/``REQUEST_AUTOPILOT_CAPABILITIES`` → ``AUTOPILOT_VERSION``;
* ``GET_HOME_POSITION`` → ``COMMAND_ACK`` ``FAILED`` (no home: there is no GPS under water);
* MAVLink FTP → a NAK (no file system), so a GCS falls back to ``PARAM_REQUEST_LIST``;
* ``TIMESYNC`` requests are answered.

Heartbeats seen are counted by MAV_TYPE (the service's own, as an onboard controller) and by
sender (``"SYSID/COMPID"``: a companion speaks from its vehicle's system id, component 191).
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from protocols.mavlink_io import MavMessage, dialect

FTP_OPCODE_NAK = 129
FTP_ERROR_FAIL = 1
FTP_ERROR_FILE_NOT_FOUND = 10
FTP_OPEN_OPCODES = frozenset({3, 4, 6, 11, 13})  # list dir, open RO, create, open WO, rename
FTP_HEADER = struct.Struct("<HBBBBBBI")
FIRMWARE_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | 255  # 0.1.0 official
CAPABILITIES = (
    dialect.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | dialect.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
)


@dataclass
class Parameter:
    """One setting: ``get`` reads it live; ``set`` applies a value or raises ValueError."""

    name: str
    get: Callable[[], float]
    set: Callable[[float], None] | None = None  # None: read-only
    integer: bool = False

    @property
    def param_type(self) -> int:
        return dialect.MAV_PARAM_TYPE_INT32 if self.integer else dialect.MAV_PARAM_TYPE_REAL32


#: A COMMAND_LONG handler: returns a MAV_RESULT (and may send what the command asks for).
CommandHandler = Callable[[MavMessage], int]


@dataclass
class GcsCounters:
    param_lists: int = 0
    param_reads: int = 0
    param_sets: int = 0
    param_sets_refused: int = 0
    mission_lists: int = 0
    commands_unsupported: int = 0
    ftp_naks: int = 0
    timesyncs: int = 0
    heartbeats: dict[str, int] = field(default_factory=dict)  # by MAV_TYPE
    heartbeat_sources: dict[str, int] = field(default_factory=dict)  # by "SYSID/COMPID"

    def as_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


class GroundStationManners:
    """Answers a ground station's requests; ``send`` puts a message on the link."""

    def __init__(
        self,
        system_id: int,
        send: Callable[[MavMessage], None],
        parameters: list[Parameter] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.system_id = system_id
        self.send = send
        self.parameters: list[Parameter] = []
        self._by_name: dict[str, int] = {}
        self.handlers: dict[int, CommandHandler] = {
            dialect.MAV_CMD_REQUEST_MESSAGE: self._request_message,
            dialect.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._capabilities,
            dialect.MAV_CMD_GET_HOME_POSITION: lambda m: dialect.MAV_RESULT_FAILED,
        }
        #: message id → a function sending one of it now (REQUEST_MESSAGE)
        self.on_demand: dict[int, Callable[[], None]] = {
            dialect.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.send_version,
        }
        self.counters = GcsCounters()
        self.clock = clock
        for parameter in parameters or []:
            self.add_parameter(parameter)

    def add_parameter(self, parameter: Parameter) -> None:
        if len(parameter.name) > 16:
            raise ValueError(f"parameter name {parameter.name!r} longer than 16 characters")
        self._by_name[parameter.name] = len(self.parameters)
        self.parameters.append(parameter)

    # ---- dispatch ---------------------------------------------------------------------
    def handle(self, message: MavMessage) -> bool:
        """Answer ``message`` if it is a ground station's request; False if it is not."""
        kind = message.get_type()
        if kind == "HEARTBEAT":
            name = dialect.enums["MAV_TYPE"].get(message.type)
            label = name.name if name is not None else str(message.type)
            self.counters.heartbeats[label] = self.counters.heartbeats.get(label, 0) + 1
            count_heartbeat(self.counters.heartbeat_sources, message)
            return True
        target = getattr(message, "target_system", None)
        if target is not None and target not in (0, self.system_id):
            return False
        handler = {
            "COMMAND_LONG": self._command,
            "COMMAND_INT": self._command,
            "PARAM_REQUEST_LIST": self._param_list,
            "PARAM_REQUEST_READ": self._param_read,
            "PARAM_SET": self._param_set,
            "MISSION_REQUEST_LIST": self._mission_list,
            "FILE_TRANSFER_PROTOCOL": self._ftp,
            "TIMESYNC": self._timesync,
        }.get(kind)
        if handler is None:
            return False
        handler(message)
        return True

    def ack(self, message: MavMessage, result: int) -> None:
        self.send(
            dialect.MAVLink_command_ack_message(
                message.command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent()
            )
        )

    def _command(self, message: MavMessage) -> None:
        handler = self.handlers.get(message.command)
        if handler is None or message.get_type() == "COMMAND_INT":
            self.counters.commands_unsupported += 1
            self.ack(message, dialect.MAV_RESULT_UNSUPPORTED)
            return
        self.ack(message, handler(message))

    # ---- commands ---------------------------------------------------------------------
    def _request_message(self, message: MavMessage) -> int:
        wanted = message.param1
        sender = self.on_demand.get(int(wanted)) if math.isfinite(wanted) else None
        if sender is None:
            return dialect.MAV_RESULT_UNSUPPORTED
        sender()
        return dialect.MAV_RESULT_ACCEPTED

    def _capabilities(self, message: MavMessage) -> int:
        self.send_version()
        return dialect.MAV_RESULT_ACCEPTED

    def send_version(self) -> None:
        self.send(
            dialect.MAVLink_autopilot_version_message(
                CAPABILITIES,
                FIRMWARE_VERSION,
                0,
                0,
                0,
                b"glider-h",  # flight_custom_version: 8 bytes, the git hash slot
                b"\0" * 8,
                b"\0" * 8,
                0,
                0,
                0x6C6964657268 + self.system_id,  # uid: "hlider" + sysid, stable
            )
        )

    # ---- parameters -------------------------------------------------------------------
    def _param_value(self, index: int) -> MavMessage:
        parameter = self.parameters[index]
        return dialect.MAVLink_param_value_message(
            parameter.name.encode(),
            float(parameter.get()),
            parameter.param_type,
            len(self.parameters),
            index,
        )

    def _param_list(self, message: MavMessage) -> None:
        self.counters.param_lists += 1
        for index in range(len(self.parameters)):
            self.send(self._param_value(index))

    def _param_read(self, message: MavMessage) -> None:
        self.counters.param_reads += 1
        name = _text(message.param_id)
        index = message.param_index if message.param_index >= 0 else self._by_name.get(name)
        if index is not None and 0 <= index < len(self.parameters):
            self.send(self._param_value(index))

    def _param_set(self, message: MavMessage) -> None:
        index = self._by_name.get(_text(message.param_id))
        if index is None:
            self.counters.param_sets_refused += 1
            return  # as ArduPilot: an unknown name gets no PARAM_VALUE
        parameter = self.parameters[index]
        value = float(message.param_value)
        try:
            if parameter.set is None or not math.isfinite(value):
                raise ValueError("read-only or not finite")
            parameter.set(round(value) if parameter.integer else value)
            self.counters.param_sets += 1
        except ValueError:
            self.counters.param_sets_refused += 1
        self.send(self._param_value(index))  # the value now in force

    # ---- mission, files, time ---------------------------------------------------------
    def _mission_list(self, message: MavMessage) -> None:
        self.counters.mission_lists += 1
        self.send(
            dialect.MAVLink_mission_count_message(
                message.get_srcSystem(), message.get_srcComponent(), 0, message.mission_type
            )
        )

    def _ftp(self, message: MavMessage) -> None:
        payload = bytes(message.payload)
        if len(payload) < FTP_HEADER.size:
            return
        seq, session, opcode, _size, _req, _burst, _pad, offset = FTP_HEADER.unpack_from(payload)
        error = FTP_ERROR_FILE_NOT_FOUND if opcode in FTP_OPEN_OPCODES else FTP_ERROR_FAIL
        reply = FTP_HEADER.pack(
            (seq + 1) & 0xFFFF, session, FTP_OPCODE_NAK, 1, opcode, 0, 0, offset
        ) + bytes([error])
        reply += b"\0" * (251 - len(reply))
        self.counters.ftp_naks += 1
        self.send(
            dialect.MAVLink_file_transfer_protocol_message(
                0, message.get_srcSystem(), message.get_srcComponent(), list(reply)
            )
        )

    def _timesync(self, message: MavMessage) -> None:
        if message.tc1 != 0:
            return  # an answer, not a request
        self.counters.timesyncs += 1
        self.send(dialect.MAVLink_timesync_message(int(self.clock() * 1e9), message.ts1))


def count_heartbeat(sources: dict[str, int], message: MavMessage) -> None:
    """Count a HEARTBEAT under its sender, ``"SYSID/COMPID"``."""
    source = f"{message.get_srcSystem()}/{message.get_srcComponent()}"
    sources[source] = sources.get(source, 0) + 1


def _text(value: object) -> str:
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value).split("\0", 1)[0]
