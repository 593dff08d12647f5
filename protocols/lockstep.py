"""The lockstep handshake on the wire (docs/lockstep.md): which standard messages carry it.

Both ends import this module only, so the handshake is defined once, next to the rest of
the MAVLink contract:

* the vehicle announces lockstep with ``MAV_MODE_FLAG_HIL_ENABLED`` in its ``HEARTBEAT``
  ``base_mode`` (a simulated vehicle; a real one never sets it);
* the service releases step k, once it has finished with it, with its ballast command
  (``COMMAND_LONG``, as PX4's simulator is released by ``HIL_ACTUATOR_CONTROLS``) or, when it
  sends none, with ``SYSTEM_TIME`` whose ``time_boot_ms`` is the step's own timestamp and
  whose ``time_unix_usec`` is 0 ("unknown": the wall clock stays out of the handshake, so
  two runs send the same bytes).

``BatchedLink`` holds what one side sends during its turn and sends it as one datagram (a
datagram of whole MAVLink frames, which every parser of this project takes): a lockstep
turn then costs one wake-up of the other side instead of one per message.
"""

from __future__ import annotations

from protocols.mavlink_io import Link, MavMessage, dialect, type_of

#: The ``HEARTBEAT.base_mode`` bit a lockstep vehicle sets (``MAV_MODE_FLAG_HIL_ENABLED``).
LOCKSTEP_FLAG = int(dialect.MAV_MODE_FLAG_HIL_ENABLED)
#: The message type of a release.
RELEASE = "SYSTEM_TIME"
_MS_MASK = 0xFFFFFFFF


def lockstep_heartbeat() -> MavMessage:
    """The vehicle's heartbeat in lockstep: a submarine with the HIL flag set."""
    return dialect.MAVLink_heartbeat_message(
        dialect.MAV_TYPE_SUBMARINE,
        dialect.MAV_AUTOPILOT_GENERIC,
        LOCKSTEP_FLAG,
        0,
        dialect.MAV_STATE_ACTIVE,
        3,
    )


def announces_lockstep(message: MavMessage) -> bool:
    """A vehicle heartbeat that announces lockstep."""
    return (
        type_of(message) == "HEARTBEAT"
        and message.type != dialect.MAV_TYPE_GCS
        and message.type != dialect.MAV_TYPE_ONBOARD_CONTROLLER
        and bool(message.base_mode & LOCKSTEP_FLAG)
    )


def release(time_boot_ms: int) -> MavMessage:
    """The service's word that it has finished with the step stamped ``time_boot_ms``."""
    return dialect.MAVLink_system_time_message(0, time_boot_ms & _MS_MASK)


def released_time(message: MavMessage) -> int | None:
    """The step time a release names, or None when ``message`` is no release."""
    if type_of(message) != RELEASE:
        return None
    return int(message.time_boot_ms)


def step_time(time_boot_ms: int) -> int:
    """A step's time as a release carries it (uint32 ms, wrapping after 49.7 days)."""
    return time_boot_ms & _MS_MASK


class BatchedLink:
    """A ``Link`` whose sends are held until ``flush`` and then go as one datagram."""

    def __init__(self, link: Link):
        self.link = link
        self.datagram = link.datagram
        self._held: list[bytes] = []

    def send(self, frame: bytes) -> None:
        self._held.append(frame)

    def flush(self) -> None:
        if self._held:
            self.link.send(b"".join(self._held))
            self._held.clear()

    def wait(self, timeout: float) -> bool:
        return self.link.wait(timeout)

    def recv(self) -> bytes:
        return self.link.recv()

    def fileno(self) -> int:
        return self.link.fileno()

    def close(self) -> None:
        self.flush()
        self.link.close()
