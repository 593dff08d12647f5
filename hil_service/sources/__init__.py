"""Where samples come from: one ``SampleSource`` per profile mode, chosen by ``source_for``.

* ``LockstepSource`` (``lockstep.py``): every message of a plant step carries the step's
  timestamp (``glider``); ``lockstep_assembler`` groups them, ``lockstep_responder``
  releases each step once the service is done with it (docs/lockstep.md).
* ``PeriodicSource`` (``periodic.py``): a real autopilot's asynchronous streams, sampled every
  period of the vehicle's clock (``periodic_assembler``, ``sampler``), with the stream
  requests a companion computer makes (``companion``; docs/profiles.md).

Both answer the service's questions alike: the samples a message completes, what is due to
be sent, and their counters under the same names, so ``HilService`` never asks which one it
has.
"""

from __future__ import annotations

from collections.abc import Callable

from hil_service.config import ServiceConfig
from hil_service.sources.base import SampleSource, Send
from hil_service.sources.lockstep import LockstepSource
from hil_service.sources.periodic import PeriodicSource

__all__ = ["LockstepSource", "PeriodicSource", "SampleSource", "Send", "source_for"]


def source_for(
    config: ServiceConfig, send: Send | None, clock: Callable[[], float]
) -> SampleSource:
    """The source of ``config``'s profile; ``send`` None: nothing is sent (replay)."""
    profile = config.vehicle_profile()
    if config.periodic:
        return PeriodicSource(profile, config, clock)
    return LockstepSource(profile, config, send)
