"""A loopback UDP relay that drops, duplicates and reorders datagrams, and says what it did.

Vehicle → service datagrams suffer the faults; service → vehicle datagrams pass untouched.
Decisions come from a seeded RNG; every delivered MAVLink 2 frame's sequence number and
message is logged so a test can compute exactly what a receiver should have counted.
"""

from __future__ import annotations

import random
import socket
import struct
import threading
from dataclasses import dataclass, field

#: Messages whose payload starts with the step's timestamp (message id → bytes, scale to ms).
_STAMPED = {30: ("<I", 1), 137: ("<I", 1), 375: ("<Q", 1000)}  # ATTITUDE, SCALED_PRESSURE2, AOS


@dataclass(frozen=True)
class Delivered:
    seq: int
    msg_id: int
    stamp_ms: int | None


@dataclass
class RelayLog:
    received: int = 0
    dropped: int = 0
    duplicated: int = 0
    reordered: int = 0
    delivered: list[Delivered] = field(default_factory=list)

    def expected_link_counters(self) -> dict[str, int]:
        """What a perfect sequence tracker must count from the delivered order."""
        seen: set[int] = set()
        lost = duplicates = reordered = 0
        highest: int | None = None
        for d in self.delivered:
            # Unwrap the 8-bit sequence against the highest seen (runs here stay short).
            if highest is None:
                value = d.seq
            else:
                delta = (d.seq - highest) % 256
                value = highest + delta if delta <= 128 else highest - (256 - delta)
            if value in seen:
                duplicates += 1
            elif highest is not None and value < highest:
                reordered += 1
                lost -= 1
            elif highest is not None:
                lost += value - highest - 1
            seen.add(value)
            highest = value if highest is None else max(highest, value)
        return {"lost": lost, "duplicates": duplicates, "reordered": reordered}

    def complete_steps(self, needed: frozenset[int] = frozenset(_STAMPED)) -> set[int]:
        """Timestamps (ms) of the steps whose every stamped message was delivered."""
        parts: dict[int, set[int]] = {}
        for d in self.delivered:
            if d.stamp_ms is not None:
                parts.setdefault(d.stamp_ms, set()).add(d.msg_id)
        return {stamp for stamp, ids in parts.items() if ids >= needed}


def _describe(frame: bytes) -> Delivered | None:
    if len(frame) < 12 or frame[0] != 0xFD:
        return None
    msg_id = frame[7] | frame[8] << 8 | frame[9] << 16
    stamp = None
    if msg_id in _STAMPED:
        fmt, divisor = _STAMPED[msg_id]
        size = struct.calcsize(fmt)
        payload = frame[10 : 10 + frame[1]].ljust(size, b"\0")  # MAVLink 2 trims zeros
        stamp = struct.unpack_from(fmt, payload)[0] // divisor
    return Delivered(frame[4], msg_id, stamp)


class FaultyRelay:
    """Forwards between a vehicle (whoever sends first) and ``target``, on its own thread."""

    def __init__(
        self,
        target: tuple[str, int],
        drop: float = 0.0,
        duplicate: float = 0.0,
        reorder: float = 0.0,
        seed: int = 0,
    ):
        self.target = target
        self.drop, self.duplicate, self.reorder = drop, duplicate, reorder
        self.log = RelayLog()
        self.paused = threading.Event()  # set: everything from the vehicle is dropped
        self._rng = random.Random(seed)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.1)
        self._vehicle: tuple[str, int] | None = None
        self._held: bytes | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="faulty-relay", daemon=True)

    @property
    def port(self) -> int:
        return self._sock.getsockname()[1]

    def start(self) -> FaultyRelay:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._sock.close()

    def snapshot(self) -> RelayLog:
        with self._lock:
            return RelayLog(
                self.log.received,
                self.log.dropped,
                self.log.duplicated,
                self.log.reordered,
                list(self.log.delivered),
            )

    def _forward(self, data: bytes) -> None:
        self._sock.sendto(data, self.target)
        described = _describe(data)
        if described is not None:
            self.log.delivered.append(described)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, source = self._sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            if source == self.target:
                if self._vehicle is not None:
                    self._sock.sendto(data, self._vehicle)
                continue
            self._vehicle = source
            with self._lock:
                self._from_vehicle(data)

    def _from_vehicle(self, data: bytes) -> None:
        log = self.log
        log.received += 1
        if self.paused.is_set():
            log.dropped += 1
            return
        draw = self._rng.random()
        if draw < self.drop:
            log.dropped += 1
            return
        if draw < self.drop + self.duplicate:
            log.duplicated += 1
            self._forward(data)
            self._forward(data)
        elif draw < self.drop + self.duplicate + self.reorder and self._held is None:
            log.reordered += 1
            self._held = data  # goes out right after the next forwarded datagram
            return
        else:
            self._forward(data)
        if self._held is not None:
            held, self._held = self._held, None
            self._forward(held)
