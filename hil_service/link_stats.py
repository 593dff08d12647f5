"""Link quality from MAVLink sequence numbers, and sample rate over a sliding window."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

SEQ_MODULO = 256
#: A jump this large backwards is a sender restart or a reordered frame, not 200 lost frames.
MAX_FORWARD_GAP = 128


@dataclass
class LinkCounts:
    """Frames received, lost, duplicated and reordered, by sequence number."""

    received: int = 0
    lost: int = 0
    duplicates: int = 0
    reordered: int = 0

    @property
    def loss_fraction(self) -> float:
        expected = self.received - self.duplicates + self.lost
        return self.lost / expected if expected > 0 else 0.0

    def as_dict(self) -> dict[str, float | int]:
        return {
            "frames_received": self.received,
            "frames_lost": self.lost,
            "frames_duplicated": self.duplicates,
            "frames_reordered": self.reordered,
            "loss_fraction": self.loss_fraction,
        }


@dataclass
class SequenceTracker:
    """Counts frames lost, duplicated and reordered per sender (system, component).

    The 8-bit sequence number is unwrapped against the sender's latest frame. A forward gap
    marks the skipped numbers missing (counted as lost); a frame arriving behind the latest
    fills its hole if it was missing (reordered: no longer lost) and is a duplicate
    otherwise, so late copies are never mistaken for late originals and nothing is counted
    twice. Holes older than ``MAX_FORWARD_GAP`` frames stay lost.

    Counts are kept per system id (``for_system``: one vehicle's link quality, all its
    components together); ``total`` and the attributes below add up every system.
    """

    _systems: dict[int, LinkCounts] = field(default_factory=dict)
    #: Per sender, keyed system_id · 256 + component_id (both are bytes on the wire): an
    #: int key, not a tuple built and hashed for every frame.
    _last: dict[int, int] = field(default_factory=dict)
    _missing: dict[int, set[int]] = field(default_factory=dict)

    def observe(self, system_id: int, component_id: int, seq: int) -> None:
        counts = self._systems.get(system_id)
        if counts is None:
            counts = self._systems[system_id] = LinkCounts()
        counts.received += 1
        key = system_id * 256 + component_id
        last = self._last.get(key)
        if last is None:
            self._last[key] = seq
            self._missing[key] = set()
            return
        missing = self._missing[key]
        gap = (seq - last) % SEQ_MODULO
        if gap == 0:
            counts.duplicates += 1
        elif gap <= MAX_FORWARD_GAP:
            counts.lost += gap - 1
            for skipped in range(1, gap):
                missing.add((last + skipped) % SEQ_MODULO)
            self._last[key] = seq
            # Forget holes so old that their numbers will come round again (the set is
            # empty on a clean link, so this costs nothing per frame there).
            if missing:
                missing -= {m for m in missing if (seq - m) % SEQ_MODULO > MAX_FORWARD_GAP}
        elif seq in missing:
            missing.discard(seq)
            counts.reordered += 1
            counts.lost -= 1
        else:
            counts.duplicates += 1

    def for_system(self, system_id: int) -> LinkCounts:
        """One system's counts (all zero for a system not seen)."""
        counts = self._systems.get(system_id)
        return LinkCounts() if counts is None else counts

    @property
    def total(self) -> LinkCounts:
        """Every system on the link together."""
        total = LinkCounts()
        for counts in self._systems.values():
            total.received += counts.received
            total.lost += counts.lost
            total.duplicates += counts.duplicates
            total.reordered += counts.reordered
        return total

    @property
    def received(self) -> int:
        return self.total.received

    @property
    def lost(self) -> int:
        return self.total.lost

    @property
    def duplicates(self) -> int:
        return self.total.duplicates

    @property
    def reordered(self) -> int:
        return self.total.reordered

    @property
    def loss_fraction(self) -> float:
        return self.total.loss_fraction

    def as_dict(self) -> dict[str, float | int]:
        """The whole link's counts (every system)."""
        return self.total.as_dict()


@dataclass
class RateMeter:
    """Events per second over the last ``window`` seconds of the given clock."""

    window: float = 5.0
    _times: deque[float] = field(default_factory=deque)

    def tick(self, now: float) -> None:
        self._times.append(now)
        self._trim(now)

    def rate(self, now: float) -> float:
        self._trim(now)
        return len(self._times) / self.window

    def _trim(self, now: float) -> None:
        while self._times and self._times[0] < now - self.window:
            self._times.popleft()
