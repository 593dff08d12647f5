"""The live view queues no MAVLink message of an advertised type while no client watches a
MAVLink channel (the control path's cost of a viewer that watches telemetry only).
With a viewer subscribed to them, `tests/test_foxglove_live.py` receives and validates them."""

from __future__ import annotations

import time

from hil_service.live.address import LiveAddress
from hil_service.live.view import LiveView
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec
from tests.foxglove_stalled import StalledViewer


def test_an_unwatched_mavlink_type_is_advertised_once_then_not_queued() -> None:
    codec = MavlinkCodec(1, 1)
    [heartbeat] = codec.parse(codec.pack(TelemetryMapping().heartbeat(vehicle=True)), True)
    live = LiveView(LiveAddress("127.0.0.1", 0)).start()
    viewer = StalledViewer("127.0.0.1", live.port)  # reads advertisements, subscribes to none
    try:
        live.offer_mavlink("in", heartbeat, None, time.time_ns())
        assert live.unwatched == 0  # a new type: queued, so that its channels are advertised
        channel = viewer.wait_advertised("mavlink/json/in/HEARTBEAT")
        assert channel["schemaName"] == "mavlink.HEARTBEAT"
        assert viewer.wait_advertised("mavlink/raw/in")["encoding"] == "mavlink2"
        for _ in range(100):
            live.offer_mavlink("in", heartbeat, None, time.time_ns())
        assert live.unwatched == 100
        assert live.offered == 101 and live.dropped == 0
        live.offer_mavlink("out", heartbeat, None, time.time_ns())  # another direction: new
        assert live.unwatched == 100
        assert viewer.wait_advertised("mavlink/json/out/HEARTBEAT")["encoding"] == "json"
        assert live.sync(30)
        assert live.status()["pending"] == 0 and live.status()["sent"] == 0  # nobody watched
    finally:
        viewer.close()
        live.close()
