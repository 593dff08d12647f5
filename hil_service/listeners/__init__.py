"""Everything that consumes the service's stream subscribes to one fan-out, as python-can's
``Notifier`` and ``Listener``.

The service tells its ``Notifier`` four things, and the notifier tells every listener:

* ``on_mavlink(direction, message, frame, t_ns)``: a MAVLink frame received (``in``: the
  decoded message; the frame is its own bytes), refused (``rejected``: the frame only) or
  sent (``out``: both);
* ``on_publish(key, payload, data, reliable)``: a publication under one of our Zenoh keys,
  ``data`` its JSON bytes (``payload_json``, encoded once for every listener);
* ``on_record(key, payload, direction)``: what only the log keeps (the decision inputs of a
  sample, received operator inputs);
* ``on_vehicle(system_id, state)``: a newly seen vehicle, with its state query.

Listeners: ``McapRecorder`` (the log), ``ZenohPublisher`` (``zenoh.py``: publications out,
operator inputs in), ``LiveView`` (the Foxglove live view), replay's ``Collector`` and any
test's own. A listener leaves out what it does not consume: the notifier calls only the
methods a listener defines (a subclass of ``Listener`` overrides them).

``Listener`` is in ``base.py`` (interpreted: anything may subclass it), ``Notifier`` in
``notifier.py`` (compiled: it is on the per-sample path).
"""

from __future__ import annotations

from hil_service.listeners.base import EVENTS, Listener
from hil_service.listeners.notifier import Notifier

__all__ = ["EVENTS", "Listener", "Notifier"]
