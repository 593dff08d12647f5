"""The service's side of lockstep (docs/lockstep.md): release each step once it is decided.

One ``LockstepResponder`` per vehicle in lockstep: active from the start with
``serve --lockstep`` (``ServiceConfig.lockstep``), or from the vehicle's own heartbeat that
announces lockstep (``MAV_MODE_FLAG_HIL_ENABLED``); ``LockstepSource`` keeps them and sends
a vehicle without one nothing. Once active, every sample the service has finished with
(identified, decided) is released: by its command, which the vehicle takes as the release,
or, when the service sends none, by ``SYSTEM_TIME`` carrying the sample's timestamp. A
complete step whose sample the service refuses (implausible or invalid telemetry, counted
by the assembler) is finished with too, and released by ``SYSTEM_TIME``
(``released_refused``). Nothing else in the service changes: the identifier and the
controller see the samples they always see.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from protocols.lockstep import announces_lockstep, release
from protocols.mavlink_io import MavMessage
from protocols.samples import TelemetrySample


class LockstepResponder:
    def __init__(self, forced: bool = False) -> None:
        self.active = forced
        self.announced = False  # the vehicle's heartbeat announced lockstep
        self.releases = 0  # SYSTEM_TIME sent
        self.released_by_command = 0
        #: Of ``releases``: steps whose sample the service refused (implausible, invalid).
        self.released_refused = 0

    def observe(self, message: MavMessage) -> None:
        """Look for the announcement in a message of this vehicle's."""
        if announces_lockstep(message):
            self.announce()

    def announce(self) -> None:
        """The vehicle's heartbeat announced lockstep: release its steps from now on."""
        self.announced = True
        self.active = True

    @property
    def has_released(self) -> bool:
        """Whether a step of this vehicle's has been released (by either means)."""
        return self.releases > 0 or self.released_by_command > 0

    def after_sample(
        self, sample: TelemetrySample, commanded: bool, send: Callable[[MavMessage], None]
    ) -> None:
        """The service has finished with ``sample``: release its step (when active) unless
        the command it has just sent for it does."""
        if self.active:
            if commanded:
                self.released_by_command += 1
            else:
                send(release(sample.time_boot_ms))
                self.releases += 1

    def after_refused(self, time_boot_ms: int, send: Callable[[MavMessage], None]) -> None:
        """The service refused the step stamped ``time_boot_ms`` (a complete step whose
        sample is implausible or invalid, counted by the assembler): refusing it is finishing
        with it, so it is released (when active) with ``SYSTEM_TIME``, as a step the service
        sends no command for. Without this the vehicle would wait for its timeout."""
        if self.active:
            send(release(time_boot_ms))
            self.releases += 1
            self.released_refused += 1

    def as_dict(self) -> dict[str, object]:
        return {
            "active": self.active,
            "announced": self.announced,
            "releases": self.releases,
            "released_by_command": self.released_by_command,
            "released_refused": self.released_refused,
        }


def combined(responders: Iterable[LockstepResponder], forced: bool) -> dict[str, object]:
    """Several vehicles' lockstep as one ``as_dict``: the counts summed, ``active`` and
    ``announced`` when true of any (``active`` always with ``serve --lockstep``)."""
    total = LockstepResponder(forced)
    for responder in responders:
        total.active = total.active or responder.active
        total.announced = total.announced or responder.announced
        total.releases += responder.releases
        total.released_by_command += responder.released_by_command
        total.released_refused += responder.released_refused
    return total.as_dict()
