"""``glider/{id}/health`` counts one vehicle's traffic, with what belongs to no one vehicle
named as link-wide: two vehicles and a stranger on one MAVLink link."""

from __future__ import annotations

import math

from protocols.mavlink_io import dialect
from protocols.schemas import validate
from tests.test_service_robustness import FakeVehicle, start_service
from tests.zenoh_peer import ZenohProbe


class CountingVehicle(FakeVehicle):
    """Counts the frames it sends; ``lose_frame`` uses up a sequence number unsent."""

    def __init__(self, port: int, system_id: int):
        super().__init__(port, system_id)
        self.sent = 0

    def raw(self, data: bytes) -> None:
        self.sent += 1
        super().raw(data)

    def lose_frame(self) -> None:
        self.codec.pack(dialect.MAVLink_heartbeat_message(0, 0, 0, 0, 0, 3))  # never sent


def test_health_counts_each_vehicle_on_a_shared_link_apart(processes, tmp_path):
    service, udp, endpoint = start_service(processes, tmp_path, "--sysid", "1", "--sysid", "2")
    probe = ZenohProbe(endpoint)
    first, second = CountingVehicle(udp, 1), CountingVehicle(udp, 2)
    stranger = FakeVehicle(udp, system_id=9)
    try:
        # Both vehicles step together on the one link; each has its own troubles.
        for k in range(20):
            first.step(k * 1000)
            if k < 10:
                second.step(k * 1000)
        second.lose_frame()  # vehicle 2: one frame lost
        first.step(20_000, depth=math.nan)  # vehicle 1: one invalid step
        first.step(5_000)  # vehicle 1: one step out of order
        second.step(10_000, depth=1e7)  # vehicle 2: two invalid steps
        second.step(11_000, depth=1e7)
        for k in range(21, 25):
            first.step(k * 1000)
        for k in range(12, 15):
            second.step(k * 1000)
        for k in range(5):  # vehicle 2 reboots: its clock starts again
            second.step(k * 1000)
        stranger.step(1000)  # a system not served
        stranger.raw(b"\x00\xffgarbage" * 20)  # bytes that are no frame
        expected = {
            1: {"samples": 24, "invalid": 1, "out_of_order": 1, "restarts": 0},
            2: {"samples": 10 + 3 + 3, "invalid": 2, "out_of_order": 2, "restarts": 1},
        }

        def health(system_id: int) -> dict:
            return probe.latest(f"glider/{system_id}/health", {})

        def settled() -> bool:
            return all(
                {k: health(i).get("counters", {}).get(k) for k in want} == want
                for i, want in expected.items()
            ) and health(1).get("link_wide") == health(2).get("link_wide")

        assert probe.wait_for(settled, 15), (health(1), health(2))
        one, two = health(1), health(2)
        for payload in (one, two):
            validate("health", payload)
        assert (one["samples"], two["samples"]) == (24, 16)
        assert one["malformed"] == 1 + 1 and two["malformed"] == 2 + 2
        # Link quality by sequence number, per vehicle.
        assert one["link"]["frames_received"] == first.sent
        assert two["link"]["frames_received"] == second.sent
        assert (one["link"]["frames_lost"], two["link"]["frames_lost"]) == (0, 1)
        assert one["packet_loss"] == 0.0 and two["packet_loss"] > 0.0
        # The identifier's step gaps: vehicle 1 skipped t = 20 s (invalid); vehicle 2 the
        # two invalid steps, then its reboot.
        assert one["counters"]["step_gaps"] == 1
        assert two["counters"]["step_gaps"] == 2
        # What belongs to no vehicle is named so, and is the same in both.
        wide = one["link_wide"]
        assert wide["unknown_system"] >= 3 and wide["bad_frames"] >= 1
        assert wide["frames"] >= first.sent + second.sent
        for counter in ("unknown_system", "bad_frames", "unknown_frames", "frames"):
            assert counter not in one["counters"]
        assert "setpoints_rejected" in one["service_wide"]
    finally:
        for vehicle in (first, second, stranger):
            vehicle.close()
        probe.close()
    _, err = processes.stop(service)
    assert service.returncode == 0, err
