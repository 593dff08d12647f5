"""The emulator's side of lockstep (docs/lockstep.md): step k+1 waits for the service.

``LockstepRunner.run`` replaces ``Autopilot.run``'s wall-clock schedule: it computes a plant
step, sends its telemetry (one datagram with the acknowledgement of the last command,
``BatchedLink``), then reads the link until the
service releases that step, with a ballast command or, when it sends none, ``SYSTEM_TIME``
carrying the step's timestamp, or until ``timeout`` wall-clock seconds have passed, which is
counted and the run goes on. A command is handled as always (``Autopilot.handle_message``),
so the next step is computed with it: the vehicle applies the service's answer to step k at
step k+1, exactly as the in-process experiment does.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

from plant_emulator.autopilot import Autopilot, AutopilotStats, run_steps
from protocols.lockstep import LOCKSTEP_FLAG, BatchedLink, released_time, step_time
from protocols.mapping import command_target_system, is_ballast_command
from protocols.mavlink_io import MavMessage

DEFAULT_TIMEOUT = 1.0  # wall s a step waits for its release


@dataclass
class LockstepStats:
    """What the handshake did: releases on time, timeouts, releases of other steps."""

    released: int = 0  # by SYSTEM_TIME
    released_by_command: int = 0
    timeouts: int = 0
    #: Releases naming a step other than the one waited for (late, after a timeout).
    stale_releases: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class LockstepRunner:
    """Runs an ``Autopilot`` in lockstep with the service on its link."""

    def __init__(
        self,
        autopilot: Autopilot,
        timeout: float = DEFAULT_TIMEOUT,
        clock: Callable[[], float] = time.monotonic,
    ):
        if not (timeout > 0 and math.isfinite(timeout)):
            raise ValueError(f"lockstep timeout must be positive, got {timeout}")
        self.autopilot = autopilot
        self.timeout = timeout
        self.clock = clock
        self.stats = LockstepStats()
        self._waiting: int | None = None  # the step time awaiting its release
        self._released = False
        self.link = BatchedLink(autopilot.link)  # type: ignore[arg-type]
        autopilot.link = self.link  # type: ignore[assignment]
        autopilot.lockstep = self
        autopilot.heartbeat_flags |= LOCKSTEP_FLAG

    def offer(self, message: MavMessage) -> bool:
        """Take ``message`` if it is a ``SYSTEM_TIME`` release (True); a ballast command for
        this vehicle releases the step too, and is left to the autopilot (False)."""
        released = released_time(message)
        if released is None:
            if (
                self._waiting is not None
                and not self._released
                and is_ballast_command(message)
                and command_target_system(message) in (0, self.autopilot.config.system_id)
            ):
                self._released = True
                self.stats.released_by_command += 1
            return False
        if self._waiting is not None and released == self._waiting and not self._released:
            self._released = True
            self.stats.released += 1
        else:
            self.stats.stale_releases += 1
        return True

    def run(self, stop: threading.Event | None = None) -> AutopilotStats:
        """Step until ``duration`` simulated seconds have passed or ``stop`` is set."""
        stop = stop or threading.Event()
        autopilot = self.autopilot
        link = self.link
        total_steps = run_steps(autopilot.config.duration, autopilot.plant.config.period)
        # Looked up once: every step calls them.
        stopped, clock, timeout = stop.is_set, self.clock, self.timeout
        wait, recv, handle_bytes = link.wait, link.recv, autopilot.handle_bytes
        stats = autopilot.stats
        while not stopped():
            if total_steps is not None and stats.steps >= total_steps:
                break
            # The heartbeat (1 Hz wall clock, as always; it carries the flag), and with it
            # the ground-station streams.
            autopilot.send_periodic(clock())
            sample = autopilot.step()
            link.flush()
            self._waiting = step_time(sample.time_boot_ms)
            self._released = False
            deadline = clock() + timeout
            while not self._released and not stopped():
                remaining = deadline - clock()
                if remaining <= 0:
                    self.stats.timeouts += 1
                    break
                if wait(remaining if remaining < 0.2 else 0.2):
                    data = recv()
                    if data:
                        # Its acknowledgement goes with the next step's telemetry: the same
                        # order, one datagram (and one wake-up of the service) less per step.
                        handle_bytes(data)
            self._waiting = None
        link.flush()
        return autopilot.stats
