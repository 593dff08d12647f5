"""The served vehicles' companions, each polled only when it may have something to send.

A companion's ``poll`` sends nothing and changes nothing unless its heartbeat is due, a
stream request waits to go out, or the one in flight has timed out
(``Companion.next_poll`` says from when); only ``on_message`` changes that otherwise.
``CompanionSchedule.due`` therefore polls the companions whose time has come (a heap of
wake times) and those that heard a message since the last call (``heard``), and returns
what they send in the order the vehicles were first seen: the same messages, at the same
ticks, as polling every companion at every tick, at a cost that follows what is due rather
than the size of the fleet.
"""

from __future__ import annotations

import heapq
import math

from hil_service.sources.companion import Companion
from protocols.mavlink_io import MavMessage


class CompanionSchedule:
    def __init__(self) -> None:
        #: Each served vehicle's companion, in the order the vehicles were first seen.
        self.companions: dict[int, Companion] = {}
        self._order: dict[int, int] = {}  # system id → rank in ``companions``
        self._wakes: list[tuple[float, int]] = []  # heap of (wake time, system id)
        self._wake: dict[int, float] = {}  # each companion's current wake time
        self._heard: set[int] = set()  # companions that heard a message since ``due``

    def add(self, system_id: int, companion: Companion) -> None:
        """Serve ``companion`` (polled at the next ``due``); replaces one of the same id."""
        self.companions[system_id] = companion
        self._order.setdefault(system_id, len(self._order))
        self._heard.add(system_id)

    def heard(self, system_id: int) -> None:
        """``system_id``'s companion was shown a message: poll it at the next ``due``."""
        if system_id in self.companions:
            self._heard.add(system_id)

    def due(self, now: float) -> list[tuple[int, MavMessage]]:
        """What the companions have to send at ``now``: (system id, message)."""
        ready = self._heard
        self._heard = set()
        wakes, wake = self._wakes, self._wake
        while wakes and wakes[0][0] <= now:
            at, system_id = heapq.heappop(wakes)
            if wake.get(system_id) == at:  # not an entry a later poll superseded
                ready.add(system_id)
        if not ready:
            return []
        out: list[tuple[int, MavMessage]] = []
        order = self._order
        for system_id in sorted(ready, key=order.__getitem__):
            companion = self.companions[system_id]
            out.extend((system_id, message) for message in companion.poll(now))
            at = companion.next_poll(now)
            if at <= now:
                self._heard.add(system_id)  # more to send: the next tick
                at = math.inf
            if wake.get(system_id) != at:
                wake[system_id] = at
                if at < math.inf:
                    heapq.heappush(wakes, (at, system_id))
        return out
