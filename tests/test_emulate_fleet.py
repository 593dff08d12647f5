"""``emulate --vehicles N``: N gliders in one process, ids from --sysid, independent seeds."""

from __future__ import annotations

from plant_emulator.fleet import connection_for
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe


def test_vehicles_split_in_contiguous_blocks() -> None:
    links = ["a", "b"]
    assert [connection_for(i, 4, links) for i in range(4)] == ["a", "a", "b", "b"]
    assert [connection_for(i, 5, links) for i in range(5)] == ["a", "a", "a", "b", "b"]
    assert {connection_for(i, 3, ["only"]) for i in range(3)} == {"only"}


def test_three_gliders_in_one_process(processes) -> None:
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    try:
        emulator = processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--vehicles", "3",
            "--sysid", "5", "--speed", "20", "--duration", "60", "--seed", "4",
        )  # fmt: skip
        ids = (5, 6, 7)
        assert probe.wait_for(
            lambda: all(probe.count(f"glider/{i}/telemetry") >= 30 for i in ids), 90
        ), {i: probe.count(f"glider/{i}/telemetry") for i in ids}
        assert probe.count("glider/4/telemetry") == probe.count("glider/8/telemetry") == 0
        # Independent seeds: the excitations differ, so the applied inputs do too.
        inputs = {
            i: [s["u_pitch"] for s in probe.payloads(f"glider/{i}/telemetry")[:30]] for i in ids
        }
        assert inputs[5] != inputs[6] != inputs[7] != inputs[5]
    finally:
        probe.close()
    out, _ = processes.stop(emulator)
    assert '"vehicles": 3' in out
