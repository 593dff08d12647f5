"""Who the service hears on its link: a system id sent from two hosts, and acknowledgements
of commands it never sent (docs/mavlink.md, "Whose message is it")."""

from __future__ import annotations

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from hil_service.mcap.reader import LogReader
from hil_service.service import HilService
from protocols.mavlink_io import MavlinkCodec, dialect
from tests.conftest import DATA

HOST_A = ("127.0.0.1", 40001)
HOST_B = ("127.0.0.1", 40002)


def _vehicle_datagrams(count: int) -> list[bytes]:
    """The first ``count`` datagrams a recorded glider (system 1) sent."""
    messages = LogReader(DATA / "disturbed.mcap").messages({"mavlink/raw/in"})
    return [message.data for _, message in zip(range(count), messages, strict=False)]


def _service(control: bool = False) -> HilService:
    return HilService(ServiceConfig(control_default=control), Listener(), Inbox())


def test_one_system_id_heard_from_two_hosts_is_counted_in_health_and_summary():
    """Two vehicles left at system id 1 on one link: their frames alternate between two
    addresses, and each move is counted for system 1."""
    service = _service()
    datagrams = _vehicle_datagrams(200)
    for k, data in enumerate(datagrams):
        service.process_datagram(data, source=HOST_A if k % 2 == 0 else HOST_B)
    changes = service.summary()["vehicles"]["1"]["address_changes"]
    assert changes == len(datagrams) - 1
    assert service.health(1)["counters"]["address_changes"] == changes


def test_a_vehicle_heard_from_one_address_counts_no_change():
    service = _service()
    for data in _vehicle_datagrams(200):
        service.process_datagram(data, source=HOST_A)
    assert service.summary()["vehicles"]["1"]["address_changes"] == 0
    assert service.health(1)["counters"]["address_changes"] == 0


def _ack_to_companion() -> bytes:
    """The vehicle (1, 1) acknowledging a ballast command to its companion (1, 191)."""
    ack = dialect.MAVLink_command_ack_message(
        dialect.MAV_CMD_DO_SET_ACTUATOR,
        dialect.MAV_RESULT_ACCEPTED,
        target_system=1,
        target_component=dialect.MAV_COMP_ID_ONBOARD_COMPUTER,
    )
    return MavlinkCodec(1, 1).pack(ack)


def test_an_acknowledgement_of_no_command_sent_is_unsolicited_not_accepted():
    service = _service(control=False)
    for data in _vehicle_datagrams(40):
        service.process_datagram(data)
    assert service.vehicles[1].commands_sent == 0
    service.process_datagram(_ack_to_companion())
    acks = service.summary()["vehicles"]["1"]["acks"]
    assert acks["accepted"] == 0 and acks["unsolicited"] == 1
    counters = service.health(1)["counters"]
    assert counters["acks_accepted"] == 0 and counters["acks_unsolicited"] == 1
