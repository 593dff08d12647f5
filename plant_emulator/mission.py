"""The emulated vehicle's mission: the MAVLink mission protocol over a list of ballast setpoints.

What a glider mission means here (docs/mavlink.md, "Mission"): a list of ballast setpoints
for the depth and pitch channels, each held for a duration, that the emulator plays in place
of its own excitation whenever no companion commands it (and the vehicle is armed). Two
item commands, both in ``MAV_FRAME_MISSION``:

* the profile's ballast command sets a setpoint at once: ``MAV_CMD_DO_SET_ACTUATOR`` (glider:
  ``param1`` depth, ``param2`` pitch, −1..1, NaN keeps the channel) or
  ``MAV_CMD_DO_SET_SERVO`` (ardusub: ``param1`` a ballast servo, ``param2`` PWM µs);
* ``MAV_CMD_NAV_DELAY`` holds it for ``param1`` seconds of the vehicle's (simulated) time.

Played from ``MISSION_CURRENT`` to the end and then from the first item again, so an
uploaded mission is a repeating excitation. With ``home_item`` (the ardusub profile, as
ArduPilot) item 0 is the home position: whatever is uploaded there is kept but not played,
and a download returns the vehicle's home in it.

Protocol (https://mavlink.io/en/services/mission.html): upload ``MISSION_COUNT`` →
``MISSION_REQUEST_INT`` per item → ``MISSION_ITEM_INT`` → ``MISSION_ACK``; download
``MISSION_REQUEST_LIST`` → ``MISSION_COUNT`` → ``MISSION_REQUEST_INT`` (or the deprecated
``MISSION_REQUEST``) → ``MISSION_ITEM_INT``; ``MISSION_CLEAR_ALL`` → ``MISSION_ACK``;
``MISSION_SET_CURRENT`` (and ``MAV_CMD_DO_SET_MISSION_CURRENT``) → ``MISSION_CURRENT``. A bad
item ends the upload with the ``MAV_MISSION_RESULT`` that names what is wrong, and the
previous mission stays. Only ``MAV_MISSION_TYPE_MISSION``: a fence or rally upload is
refused ``MAV_MISSION_UNSUPPORTED`` and their download is empty.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from protocols.mavlink_io import MavMessage, dialect

MAX_ITEMS = 256
UPLOAD_TIMEOUT = 5.0  # wall s without an item before an upload is abandoned
MISSION = dialect.MAV_MISSION_TYPE_MISSION
DELAY = dialect.MAV_CMD_NAV_DELAY


@dataclass(frozen=True)
class Item:
    """One MISSION_ITEM_INT as stored (and sent back on download)."""

    command: int
    frame: int = dialect.MAV_FRAME_MISSION
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    x: int = 0
    y: int = 0
    z: float = 0.0
    autocontinue: int = 1

    @classmethod
    def of(cls, message: MavMessage) -> Item:
        return cls(
            int(message.command),
            int(message.frame),
            (
                float(message.param1),
                float(message.param2),
                float(message.param3),
                float(message.param4),
            ),
            int(message.x),
            int(message.y),
            float(message.z),
            int(message.autocontinue),
        )


class ItemRefused(ValueError):
    """An item the vehicle cannot fly; ``result`` is the MAV_MISSION_RESULT."""

    def __init__(self, result: int, reason: str):
        super().__init__(reason)
        self.result = result


#: Checks a setpoint item and returns its (depth, pitch) wire values −1..1 (NaN: keep).
SetpointReader = Callable[[Item], tuple[float, float]]


@dataclass
class MissionCounters:
    uploads: int = 0
    uploads_refused: int = 0
    downloads: int = 0
    clears: int = 0
    items_reached: int = 0
    results: dict[str, int] = field(default_factory=dict)  # MISSION_ACK sent, by result

    def as_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


@dataclass
class _Upload:
    peer: tuple[int, int]
    count: int
    items: list[Item] = field(default_factory=list)
    last: float = 0.0


class Mission:
    """The stored mission, its transfers, and where playing it has got to."""

    def __init__(
        self,
        send: Callable[[MavMessage], None],
        setpoint_command: int,
        read_setpoint: SetpointReader,
        clock: Callable[[], float],
        home: Callable[[], tuple[int, int, float]],
        home_item: bool = False,
    ):
        self.send = send
        self.setpoint_command = setpoint_command
        self.read_setpoint = read_setpoint
        self.clock = clock
        self.home = home
        self.home_item = home_item
        self.items: list[Item] = []
        self.current = 0
        self.counters = MissionCounters()
        self._upload: _Upload | None = None
        self._wires: list[tuple[float, float]] = []
        # Playing: the item being held since (simulated s), and the setpoint now in force.
        self._since: float | None = None
        self.setpoint = (math.nan, math.nan)

    def handlers(self) -> dict[str, Callable[[MavMessage], None]]:
        return {
            "MISSION_COUNT": self._count,
            "MISSION_ITEM_INT": self._item,
            "MISSION_ITEM": self._item_float,
            "MISSION_REQUEST_LIST": self._request_list,
            "MISSION_REQUEST_INT": self._request,
            "MISSION_REQUEST": self._request,
            "MISSION_CLEAR_ALL": self._clear,
            "MISSION_SET_CURRENT": self._set_current_message,
            "MISSION_ACK": lambda message: None,  # the end of a download
        }

    @property
    def uploading(self) -> bool:
        self._expire()
        return self._upload is not None

    # ---- upload ---------------------------------------------------------------------
    def _count(self, message: MavMessage) -> None:
        peer = (message.get_srcSystem(), message.get_srcComponent())
        if message.mission_type != MISSION:
            self._ack(peer, dialect.MAV_MISSION_UNSUPPORTED, message.mission_type)
            return
        if message.count > MAX_ITEMS:
            self.counters.uploads_refused += 1
            self._ack(peer, dialect.MAV_MISSION_NO_SPACE)
            return
        if message.count == 0:
            self._store([], peer)
            return
        self._upload = _Upload(peer, int(message.count), last=self.clock())
        self._request_item(peer, 0)

    def _item_float(self, message: MavMessage) -> None:
        peer = (message.get_srcSystem(), message.get_srcComponent())
        if self._upload is not None and message.mission_type == MISSION:
            self._upload = None
            self.counters.uploads_refused += 1
            self._ack(peer, dialect.MAV_MISSION_UNSUPPORTED_FRAME)  # MISSION_INT only

    def _item(self, message: MavMessage) -> None:
        self._expire()
        upload = self._upload
        peer = (message.get_srcSystem(), message.get_srcComponent())
        if upload is None or peer != upload.peer or message.mission_type != MISSION:
            return
        expected = len(upload.items)
        if message.seq != expected:
            self._request_item(peer, expected)  # a repeat or a skip: ask for the one wanted
            return
        upload.last = self.clock()
        item = Item.of(message)
        try:
            if not (self.home_item and message.seq == 0):
                self._check(item)
        except ItemRefused as refused:
            self._upload = None
            self.counters.uploads_refused += 1
            self._ack(peer, refused.result)
            return
        upload.items.append(item)
        if len(upload.items) < upload.count:
            self._request_item(peer, len(upload.items))
            return
        self._upload = None
        self._store(upload.items, peer)

    def _check(self, item: Item) -> tuple[float, float]:
        if item.command not in (self.setpoint_command, DELAY):
            raise ItemRefused(dialect.MAV_MISSION_UNSUPPORTED, f"command {item.command}")
        if item.frame != dialect.MAV_FRAME_MISSION:
            raise ItemRefused(dialect.MAV_MISSION_UNSUPPORTED_FRAME, f"frame {item.frame}")
        if item.command == DELAY:
            seconds = item.params[0]
            if not (math.isfinite(seconds) and 0 <= seconds <= 86400):
                raise ItemRefused(dialect.MAV_MISSION_INVALID_PARAM1, "delay 0..86400 s")
            return math.nan, math.nan
        return self.read_setpoint(item)

    def _store(self, items: list[Item], peer: tuple[int, int]) -> None:
        self.items = list(items)
        self._wires = [
            (math.nan, math.nan)
            if (self.home_item and i == 0) or item.command == DELAY
            else self.read_setpoint(item)
            for i, item in enumerate(self.items)
        ]
        self.counters.uploads += 1
        self.current = self.first
        self._since = None
        self.setpoint = (math.nan, math.nan)
        self._ack(peer, dialect.MAV_MISSION_ACCEPTED)
        self.send_current()

    def _request_item(self, peer: tuple[int, int], seq: int) -> None:
        self.send(dialect.MAVLink_mission_request_int_message(peer[0], peer[1], seq, MISSION))

    def _expire(self) -> None:
        if self._upload is not None and self.clock() - self._upload.last > UPLOAD_TIMEOUT:
            self._upload = None
            self.counters.uploads_refused += 1

    def _ack(self, peer: tuple[int, int], result: int, mission_type: int = MISSION) -> None:
        entry = dialect.enums["MAV_MISSION_RESULT"].get(result)
        name = entry.name if entry is not None else str(result)
        self.counters.results[name] = self.counters.results.get(name, 0) + 1
        self.send(dialect.MAVLink_mission_ack_message(peer[0], peer[1], result, mission_type))

    # ---- download, clear, current ---------------------------------------------------
    def _request_list(self, message: MavMessage) -> None:
        count = len(self.items) if message.mission_type == MISSION else 0
        if message.mission_type == MISSION:
            self.counters.downloads += 1
        self.send(
            dialect.MAVLink_mission_count_message(
                message.get_srcSystem(), message.get_srcComponent(), count, message.mission_type
            )
        )

    def _request(self, message: MavMessage) -> None:
        peer = (message.get_srcSystem(), message.get_srcComponent())
        if message.mission_type != MISSION or not 0 <= message.seq < len(self.items):
            self._ack(peer, dialect.MAV_MISSION_INVALID_SEQUENCE, message.mission_type)
            return
        item = self.items[message.seq]
        if self.home_item and message.seq == 0:
            lat, lon, alt = self.home()
            frame = dialect.MAV_FRAME_GLOBAL_INT
            item = Item(dialect.MAV_CMD_NAV_WAYPOINT, frame, x=lat, y=lon, z=alt)
        self.send(
            dialect.MAVLink_mission_item_int_message(
                peer[0],
                peer[1],
                message.seq,
                item.frame,
                item.command,
                int(message.seq == self.current),
                item.autocontinue,
                *item.params,
                item.x,
                item.y,
                item.z,
                MISSION,
            )
        )

    def _clear(self, message: MavMessage) -> None:
        peer = (message.get_srcSystem(), message.get_srcComponent())
        if message.mission_type not in (MISSION, dialect.MAV_MISSION_TYPE_ALL):
            self._ack(peer, dialect.MAV_MISSION_ACCEPTED, message.mission_type)
            return
        self.items, self._wires = [], []
        self.current, self._since = 0, None
        self.setpoint = (math.nan, math.nan)
        self.counters.clears += 1
        self._ack(peer, dialect.MAV_MISSION_ACCEPTED, message.mission_type)
        self.send_current()

    def _set_current_message(self, message: MavMessage) -> None:
        self.set_current(int(message.seq))

    def set_current(self, seq: int) -> bool:
        """Play from item ``seq`` next (False: no such item)."""
        if not self.first <= seq < len(self.items):
            return False
        self.current, self._since = seq, None
        self.send_current()
        return True

    @property
    def first(self) -> int:
        return 1 if self.home_item and self.items else 0

    @property
    def playable(self) -> bool:
        return len(self.items) > self.first

    def current_message(self) -> MavMessage:
        state = dialect.MISSION_STATE_ACTIVE if self.playable else dialect.MISSION_STATE_NO_MISSION
        return dialect.MAVLink_mission_current_message(self.current, len(self.items), state)

    def send_current(self) -> None:
        self.send(self.current_message())

    # ---- playing ----------------------------------------------------------------------
    def setpoints(self, t: float) -> tuple[float, float]:
        """The (depth, pitch) wire setpoints at simulated time ``t`` (NaN: keep the last);
        advances through the items, announcing each one reached."""
        if not self.playable:
            return math.nan, math.nan
        for _ in range(len(self.items) + 1):  # every item at most once per step
            seq = self.current
            item = self.items[seq]
            if self._since is None:
                self._since = t
            if item.command == DELAY and t - self._since < item.params[0]:
                break
            if item.command != DELAY:
                depth, pitch = self._wires[seq]
                self.setpoint = (
                    self.setpoint[0] if math.isnan(depth) else depth,
                    self.setpoint[1] if math.isnan(pitch) else pitch,
                )
            self.counters.items_reached += 1
            self.send(dialect.MAVLink_mission_item_reached_message(seq))
            self.current = seq + 1 if seq + 1 < len(self.items) else self.first
            self._since = t
            self.send_current()
        return self.setpoint
