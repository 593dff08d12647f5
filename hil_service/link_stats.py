"""Link quality from MAVLink sequence numbers, and sample rate over a sliding window."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

SEQ_MODULO = 256
#: A jump this large backwards is a sender restart or a reordered frame, not 200 lost frames.
MAX_FORWARD_GAP = 128


@dataclass
class SequenceTracker:
    """Counts frames lost per sender (system, component) from gaps in the 8-bit sequence.

    A duplicate (same seq again) or a frame that arrives behind the latest (reordering) is
    counted separately and does not count as loss; the duplicate's predecessor gap is not
    reopened either, so loss is never counted twice.
    """

    received: int = 0
    lost: int = 0
    duplicates: int = 0
    reordered: int = 0
    _last: dict[tuple[int, int], int] = field(default_factory=dict)

    def observe(self, system_id: int, component_id: int, seq: int) -> None:
        self.received += 1
        key = (system_id, component_id)
        last = self._last.get(key)
        if last is None:
            self._last[key] = seq
            return
        gap = (seq - last) % SEQ_MODULO
        if gap == 0:
            self.duplicates += 1
        elif gap <= MAX_FORWARD_GAP:
            self.lost += gap - 1
            self._last[key] = seq
        else:
            self.reordered += 1
            # a late frame fills a hole counted as lost before
            self.lost = max(self.lost - 1, 0)

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
