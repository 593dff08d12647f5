"""An autopilot's manners towards a ground station: what it answers, and how.

A ground station (MAVProxy, QGroundControl, a MAVSDK script) asks for parameters, the mission,
the home position, the autopilot's version, message rates and files, and repeats a request
that gets no answer (MAVProxy: every 2 s, forever; MAVSDK: until it times out). This module
answers each of them, for an emulator whose real settings are its parameters
(docs/mavlink.md, "What a ground station gets", lists every request and its answer):

* every ``COMMAND_LONG``/``COMMAND_INT`` addressed to the autopilot gets a ``COMMAND_ACK``,
  ``UNSUPPORTED`` unless a handler takes it;
* ``PARAM_REQUEST_LIST``/``PARAM_REQUEST_READ``/``PARAM_SET`` over ``Parameter`` objects
  whose setter changes the emulator (a change takes effect for the run and is announced with
  ``PARAM_VALUE``; a read-only or refused value is answered with the value kept). Integers
  ride in the float field with the ``Identity``'s one encoding, advertised in
  ``AUTOPILOT_VERSION.capabilities``: C-cast as ArduPilot (``MAV_AUTOPILOT_ARDUPILOTMEGA``),
  byte-wise for the generic autopilot (MAVSDK decodes byte-wise unless the HEARTBEAT says
  ArduPilot, so the two must agree);
* the mission protocol is ``plant_emulator.mission``'s;
* ``REQUEST_MESSAGE`` for every message the vehicle sends on its own (``on_demand``),
  ``REQUEST_AUTOPILOT_CAPABILITIES`` → ``AUTOPILOT_VERSION``, ``REQUEST_PROTOCOL_VERSION`` →
  ``PROTOCOL_VERSION``, ``GET_HOME_POSITION`` → ``HOME_POSITION``;
* MAVLink FTP → a NAK (no file system), so a GCS falls back to ``PARAM_REQUEST_LIST``;
* ``TIMESYNC`` requests are answered.

A message whose ``target_system``/``target_component`` names someone else (a command to the
companion, component 191) is not answered. Heartbeats seen are counted by MAV_TYPE (the
service's own, as an onboard controller) and by sender (``"SYSID/COMPID"``: a companion
speaks from its vehicle's system id, component 191).
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from protocols.mavlink_io import MavMessage, dialect
from protocols.protocol_version import MSG_ID_PROTOCOL_VERSION, ProtocolVersionMessage

FTP_OPCODE_NAK = 129
FTP_ERROR_FAIL = 1
FTP_ERROR_FILE_NOT_FOUND = 10
FTP_OPEN_OPCODES = frozenset({3, 4, 6, 11, 13})  # list dir, open RO, create, open WO, rename
FTP_HEADER = struct.Struct("<HBBBBBBI")
FIRMWARE_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | 255  # 0.1.0 official
#: What both profiles support: MAVLink 2, the mission protocol with MISSION_ITEM_INT, and
#: COMMAND_INT for the commands a handler takes.
BASE_CAPABILITIES = (
    dialect.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | dialect.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | dialect.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
)
PARAM_ENCODINGS = {
    "bytewise": dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE,
    "c_cast": dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST,
}
AUTOPILOT_COMPONENT = dialect.MAV_COMP_ID_AUTOPILOT1
PROTOCOL_VERSION = 200  # MAVLink 2.0
_INT32 = struct.Struct("<i")
_FLOAT = struct.Struct("<f")


@dataclass(frozen=True)
class Identity:
    """Who the vehicle says it is: HEARTBEAT's autopilot and how its integers are encoded.

    The two go together: MAVSDK picks C-cast only for ArduPilot, and MAVProxy and QGC read
    ArduPilot's parameters as C-cast; the encoding is also advertised in
    ``AUTOPILOT_VERSION.capabilities`` for clients that read it.
    """

    autopilot: int = dialect.MAV_AUTOPILOT_GENERIC
    param_encoding: str = "bytewise"
    #: HEARTBEAT base_mode bits always set (ArduPilot: MAV_MODE_FLAG_CUSTOM_MODE_ENABLED).
    base_mode: int = 0

    def __post_init__(self) -> None:
        if self.param_encoding not in PARAM_ENCODINGS:
            raise ValueError(f"param encoding is one of {', '.join(PARAM_ENCODINGS)}")

    @property
    def capabilities(self) -> int:
        return BASE_CAPABILITIES | PARAM_ENCODINGS[self.param_encoding]

    def encode(self, value: float, integer: bool) -> float:
        """A parameter's value as it rides in ``param_value``."""
        if not integer:
            return float(value)
        if self.param_encoding == "c_cast":
            return float(int(value))
        return float(_FLOAT.unpack(_INT32.pack(int(value)))[0])

    def decode(self, wire: float, integer: bool) -> float:
        """The value a ``PARAM_SET`` carries (NaN when it does not decode)."""
        if not integer:
            return float(wire)
        if self.param_encoding == "c_cast":
            return float(round(wire)) if math.isfinite(wire) else math.nan
        try:
            return float(_INT32.unpack(_FLOAT.pack(wire))[0])
        except (OverflowError, struct.error):
            return math.nan


GENERIC = Identity()
ARDUPILOT = Identity(
    dialect.MAV_AUTOPILOT_ARDUPILOTMEGA,
    "c_cast",
    int(dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
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
    commands_unsupported: int = 0
    not_addressed_to_us: int = 0
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
        identity: Identity = GENERIC,
    ):
        self.system_id = system_id
        self.send = send
        self.identity = identity
        #: Other handlers of a ground station's messages (the mission): type → handler.
        self.message_handlers: dict[str, Callable[[MavMessage], None]] = {}
        self.parameters: list[Parameter] = []
        self._by_name: dict[str, int] = {}
        self.handlers: dict[int, CommandHandler] = {
            dialect.MAV_CMD_REQUEST_MESSAGE: self._request_message,
            dialect.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._capabilities,
            dialect.MAV_CMD_REQUEST_PROTOCOL_VERSION: self._protocol_version,
        }
        #: message id → a function sending one of it now (REQUEST_MESSAGE)
        self.on_demand: dict[int, Callable[[], None]] = {
            dialect.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.send_version,
            MSG_ID_PROTOCOL_VERSION: self.send_protocol_version,
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
        if not self.addressed_to_us(message):
            self.counters.not_addressed_to_us += 1
            return True
        handler = self.message_handlers.get(kind) or {
            "COMMAND_LONG": self._command,
            "COMMAND_INT": self._command,
            "PARAM_REQUEST_LIST": self._param_list,
            "PARAM_REQUEST_READ": self._param_read,
            "PARAM_SET": self._param_set,
            "FILE_TRANSFER_PROTOCOL": self._ftp,
            "TIMESYNC": self._timesync,
        }.get(kind)
        if handler is None:
            return False
        handler(message)
        return True

    def addressed_to_us(self, message: MavMessage) -> bool:
        """Whether a message is for this autopilot (or every system / component)."""
        target = getattr(message, "target_system", None)
        if target is not None and target not in (0, self.system_id):
            return False
        component = getattr(message, "target_component", None)
        return component is None or component in (0, AUTOPILOT_COMPONENT)

    def ack(self, message: MavMessage, result: int) -> None:
        self.send(
            dialect.MAVLink_command_ack_message(
                message.command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent()
            )
        )

    def _command(self, message: MavMessage) -> None:
        handler = self.handlers.get(message.command)
        if handler is None:
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

    def _protocol_version(self, message: MavMessage) -> int:
        self.send_protocol_version()
        return dialect.MAV_RESULT_ACCEPTED

    def send_protocol_version(self) -> None:
        self.send(ProtocolVersionMessage(PROTOCOL_VERSION, 100, PROTOCOL_VERSION))

    def send_version(self) -> None:
        self.send(
            dialect.MAVLink_autopilot_version_message(
                self.identity.capabilities,
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
            self.identity.encode(parameter.get(), parameter.integer),
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
        value = self.identity.decode(float(message.param_value), parameter.integer)
        try:
            if parameter.set is None or not math.isfinite(value):
                raise ValueError("read-only or not finite")
            parameter.set(round(value) if parameter.integer else value)
            self.counters.param_sets += 1
        except ValueError:
            self.counters.param_sets_refused += 1
        self.send(self._param_value(index))  # the value now in force, to every listener

    # ---- files, time ---------------------------------------------------------------
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
