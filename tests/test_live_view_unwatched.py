"""The live view queues no MAVLink message of an advertised type while no client watches a
MAVLink channel (issue 17: the control path's cost of a viewer that watches telemetry only).
With a viewer subscribed to them, `tests/test_foxglove_live.py` receives and validates them."""

from __future__ import annotations

import time

from hil_service.live.address import LiveAddress
from hil_service.live.view import LiveView
from protocols.mapping import TelemetryMapping


def test_an_unwatched_mavlink_type_is_advertised_once_then_not_queued() -> None:
    live = LiveView(LiveAddress("127.0.0.1", 0)).start()
    try:
        heartbeat = TelemetryMapping().heartbeat(vehicle=True)
        live.offer_mavlink("in", heartbeat, None, time.time_ns())
        assert live.unwatched == 0  # a new type: queued, so that its channels are advertised
        deadline = time.monotonic() + 30
        while ("in", "HEARTBEAT") not in live._known:
            assert time.monotonic() < deadline, "the sender thread never took the message"
            time.sleep(0.01)
        assert "mavlink/json/in/HEARTBEAT" in live._channels
        for _ in range(100):
            live.offer_mavlink("in", heartbeat, None, time.time_ns())
        assert live.unwatched == 100
        assert live.offered == 101 and live.dropped == 0
        live.offer_mavlink("out", heartbeat, None, time.time_ns())  # another direction: new
        assert live.unwatched == 100
    finally:
        live.close()
