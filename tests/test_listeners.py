"""The fan-out: every listener hears every event it consumes, in the order it was added."""

from __future__ import annotations

from typing import Any

import pytest

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener, Notifier
from hil_service.service import HilService
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols import payload_json
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec


class Tape(Listener):
    def __init__(self, name: str, heard: list[tuple[str, ...]]) -> None:
        self.name, self.heard = name, heard

    def on_mavlink(self, direction, message, frame, t_ns) -> None:
        self.heard.append((self.name, "mavlink", direction, message.get_type()))

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        assert data == payload_json.encode(payload)
        self.heard.append((self.name, "publish", key))


class PublicationsOnly(Listener):
    def __init__(self) -> None:
        self.data: list[bytes] = []

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        self.data.append(data)


def test_every_listener_hears_the_service_in_order_and_the_bytes_are_shared():
    heard: list[tuple[str, ...]] = []
    first, second, publications = Tape("a", heard), Tape("b", heard), PublicationsOnly()
    notifier = Notifier([first, second, publications])
    service = HilService(ServiceConfig(), notifier, Inbox())
    plant, codec = GliderPlant(PlantConfig(seed=1)), MavlinkCodec(1, 1)
    for message in TelemetryMapping().encode_telemetry(plant.step(0.0, 0.0)):
        service.process_datagram(codec.pack(message))
    mavlink = [h for h in heard if h[1] == "mavlink"]
    assert [h[0] for h in mavlink] == ["a", "b"] * 4  # each frame: a, then b
    published = [h for h in heard if h[1] == "publish"]
    assert published[0] == ("a", "publish", "glider/1/telemetry")
    assert [h[0] for h in published] == ["a", "b"] * (len(published) // 2)
    assert len(publications.data) == len(published) // 2 > 0
    notifier.remove_listener(second)
    assert notifier.listeners == [first, publications]


def test_an_object_that_listens_to_nothing_is_refused():
    class OldBus:
        def publish(self, key, payload, reliable=False) -> None:
            pass

    with pytest.raises(TypeError, match="listens to nothing"):
        Notifier([OldBus()])


def test_a_handler_set_on_the_instance_is_heard():
    """A listener may hand the notifier a handler of its own (a compiled one, as the Zenoh
    publisher does) by setting it on the instance rather than overriding the method."""
    heard: list[str] = []

    class Handed(Listener):
        def __init__(self) -> None:
            self.on_publish = lambda key, payload, data, reliable: heard.append(key)

    notifier = Notifier([Handed(), PublicationsOnly()])
    notifier.publish("glider/1/telemetry", {"t": 0.0})
    assert heard == ["glider/1/telemetry"]
    notifier.mavlink("in", None, b"", 0)  # the events it did not hand over stay unheard
