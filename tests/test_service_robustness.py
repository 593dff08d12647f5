"""Bad input on the service's MAVLink port is counted, never fatal; a killed service's log reads."""

from __future__ import annotations

import math
import signal
import time

import pytest

from hil_service.mcap.reader import LogError, LogReader
from hil_service.umodel import build_model
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.samples import TelemetrySample
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

MAPPING = TelemetryMapping()


class FakeVehicle:
    """Sends hand-made telemetry to the service's UDP port."""

    def __init__(self, port: int, system_id: int = 1):
        import socket

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.address = ("127.0.0.1", port)
        self.codec = MavlinkCodec(system_id, 1)

    def step(self, time_ms: int, depth: float = 15.0, pitch: float = 0.0, u: float = 0.1):
        sample = TelemetrySample(1, time_ms, depth, pitch, u, -u)
        for message in MAPPING.encode_telemetry(sample):
            self.raw(self.codec.pack(message))

    def raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.address)

    def close(self) -> None:
        self.sock.close()


#: Samples the default identifier spends refilling its lags after the start or a gap.
HISTORY = build_model("dynamic").history_length


def start_service(processes, tmp_path, *extra: str):
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
        "--log-dir", str(tmp_path / "logs"), *extra,
    )  # fmt: skip
    return service, udp, endpoint


def test_bad_mavlink_input_is_counted_in_health(processes, tmp_path):
    service, udp, endpoint = start_service(processes, tmp_path, "--sysid", "1")
    probe = ZenohProbe(endpoint)
    vehicle, stranger = FakeVehicle(udp), FakeVehicle(udp, system_id=9)
    try:
        for k in range(20):  # good steps
            vehicle.step(k * 1000)
        vehicle.raw(b"\x00\xffgarbage" * 50)
        frame = vehicle.codec.pack(dialect.MAVLink_attitude_message(1, 0, 0.1, 0, 0, 0, 0))
        vehicle.raw(frame[:10])  # truncated
        vehicle.step(20_000, depth=math.nan)  # NaN depth
        vehicle.step(21_000, depth=1e7)  # absurd depth
        vehicle.step(5_000)  # timestamp going backwards
        stranger.step(22_000)  # unknown system id
        for k in range(23, 30):  # and good data again
            vehicle.step(k * 1000)

        def counters():
            health = probe.payloads("glider/1/health")
            return health[-1]["counters"] if health else {}

        assert probe.wait_for(lambda: counters().get("samples") == 27, 10), counters()
        c = counters()
        assert c["invalid"] == 2
        assert c["out_of_order"] == 1
        health = probe.payloads("glider/1/health")[-1]
        assert health["link_wide"]["unknown_system"] >= 3  # the link's, not vehicle 1's
        assert health["link_wide"]["bad_frames"] >= 1
        assert health["malformed"] == c["invalid"] + c["out_of_order"] + c["incomplete"] >= 3
        assert service.poll() is None
        # The bad samples never reached the identifier, and around the hole they left (t = 20,
        # 21, 22 s) it refilled its history instead of pairing y(23) with u(19).
        ys = [e["y"] for e in probe.payloads("glider/1/umodel/depth")]
        assert all(math.isfinite(y) and y < 100 for y in ys)
        assert len(ys) == 27 - 2 * HISTORY
        assert health["identifier"]["depth"]["skipped"] == 2 * HISTORY
        assert c["step_gaps"] == 1
    finally:
        vehicle.close()
        stranger.close()
        probe.close()
    _, err = processes.stop(service)
    assert service.returncode == 0, err


def test_log_of_a_killed_service_reads_up_to_the_last_flush(processes, tmp_path):
    service, udp, _ = start_service(processes, tmp_path)
    vehicle = FakeVehicle(udp)
    logs = tmp_path / "logs"

    def flushed_records() -> int:
        """Raw frames readable from the open log now (the recorder flushes every 0.5 s)."""
        files = list(logs.glob("*.mcap"))
        if not files:
            return 0
        try:
            return sum(1 for _ in LogReader(files[0]).messages({"mavlink/raw/in"}))
        except LogError:  # created, its magic not yet written
            return 0

    try:
        k = 0
        first_flush_at = None
        # Stream until the first records are on disk (however slow the start was), then one
        # more second: the kill must lose at most what came after the last flush.
        while first_flush_at is None or time.monotonic() < first_flush_at + 1.0:
            for _ in range(10):
                vehicle.step(k * 1000, depth=15.0 + 0.01 * k)
                k += 1
                time.sleep(0.01)
            if first_flush_at is None and flushed_records() > 0:
                first_flush_at = time.monotonic()
            assert k < 100_000, "the service never flushed a record"
        on_disk = flushed_records()
        service.send_signal(signal.SIGKILL)
        service.wait(5)
    finally:
        vehicle.close()
    files = list((tmp_path / "logs").glob("*.mcap"))
    assert len(files) == 1
    reader = LogReader(files[0])
    times = [m.log_time_ns for m in reader.messages() if m.topic == "mavlink/raw/in"]
    report = reader.report
    assert not report.complete
    assert "recovered" in report.describe()
    assert times, "nothing recovered"
    # Everything that was on disk before the kill reads back (what came after the last
    # flush may be lost; how much depends on the flush interval, not asserted in wall time).
    assert len(times) >= on_disk > 0


def test_vehicles_split_by_system_id_with_state_and_liveliness(processes, tmp_path):
    import json as _json

    service, udp, endpoint = start_service(processes, tmp_path)
    probe = ZenohProbe(endpoint)
    first, second = FakeVehicle(udp, system_id=1), FakeVehicle(udp, system_id=2)
    try:
        for k in range(30):
            first.step(k * 1000, depth=15.0 + 0.1 * k)
            second.step(k * 1000, depth=40.0 - 0.1 * k)
        assert probe.wait_for(
            lambda: (
                probe.count("glider/1/umodel/depth") == 30 - HISTORY
                and probe.count("glider/2/umodel/depth") == 30 - HISTORY
            ),
            10,
        )
        assert probe.payloads("glider/1/telemetry")[-1]["depth"] == pytest.approx(17.9, abs=1e-3)
        assert probe.payloads("glider/2/telemetry")[-1]["depth"] == pytest.approx(37.1, abs=1e-3)
        # Each vehicle's identifier saw only its own outputs.
        assert max(e["y"] for e in probe.payloads("glider/1/umodel/depth")) < 20
        assert min(e["y"] for e in probe.payloads("glider/2/umodel/depth")) > 30

        replies = list(probe.session.get("glider/2/state", timeout=5.0))
        state = _json.loads(replies[0].ok.payload.to_bytes())
        assert state["telemetry"]["depth"] == pytest.approx(37.1, abs=1e-3)
        assert set(state["umodel"]) == {"depth", "pitch"}
        assert state["control_reason"] == "control disabled"

        tokens = list(probe.session.liveliness().get("glider/*/service", timeout=5.0))
        assert {str(t.ok.key_expr) for t in tokens} == {"glider/1/service", "glider/2/service"}
    finally:
        first.close()
        second.close()
        probe.close()
    _, err = processes.stop(service)
    assert service.returncode == 0, err


def test_bad_config_file_and_connection_string_are_clear_errors(processes, tmp_path):
    bad = tmp_path / "zenoh.json5"
    bad.write_text("{ this is not json5 ")
    process = processes.start("serve", "--zenoh-config", str(bad), "--log-dir", str(tmp_path))
    _, err = process.communicate(timeout=30)
    assert process.returncode == 2
    assert "glider-hil serve:" in err and "Traceback" not in err
    process = processes.start("serve", "--mavlink", "udpin:nonsense", "--no-log")
    _, err = process.communicate(timeout=30)
    assert process.returncode == 2
    assert "--mavlink 'udpin:nonsense': udpin: wants HOST:PORT" in err and "Traceback" not in err


def test_health_turns_stale_exactly_after_the_timeout_on_the_service_clock():
    """Staleness on a simulated clock: fresh up to ``stale_timeout`` after the last sample,
    stale just after, and the controllers re-arm before the next decision."""
    from hil_service.config import ServiceConfig
    from hil_service.inputs import Inbox
    from hil_service.listeners import Listener
    from hil_service.service import HilService

    now = [50.0]
    config = ServiceConfig(stale_timeout=3.0)
    service = HilService(config, Listener(), Inbox(), clock=lambda: now[0])
    codec = MavlinkCodec(1, 1)
    for k in range(10):
        for message in MAPPING.encode_telemetry(TelemetrySample(1, k * 1000, 15.0, 0.0, 0.1, -0.1)):
            service.process_datagram(codec.pack(message))
    now[0] += 3.0
    health = service.health(1)
    assert health["control"]["reason"] == "control disabled"
    assert health["telemetry_age"] == 3.0
    assert service.vehicles[1].reset_pending is False
    now[0] += 1e-6
    health = service.health(1)
    assert health["control"]["reason"] == "telemetry stale"
    assert health["control"]["commanding"] is False
    assert service.vehicles[1].reset_pending is True
