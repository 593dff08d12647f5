"""`glider-hil emulate` as a real process, watched by a MAVLink peer on loopback UDP."""

from __future__ import annotations

import json
import math
from collections import defaultdict

import pytest

from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, dialect
from tests.mavlink_peer import Received, UdpPeer

SPEED = 20.0
MAPPING = TelemetryMapping()


def steps_by_time(received: list[Received]) -> dict[int, dict[str, object]]:
    """Group telemetry by its timestamp; VFR_HUD (no timestamp) joins the step before it."""
    steps: dict[int, dict[str, object]] = defaultdict(dict)
    current = None
    for item in received:
        message = item.message
        kind = message.get_type()
        if kind in ("ATTITUDE", "SCALED_PRESSURE2"):
            current = message.time_boot_ms
            steps[current][kind] = message
            steps[current].setdefault("arrival", item.arrival)
        elif kind == "ACTUATOR_OUTPUT_STATUS":
            current = message.time_usec // 1000
            steps[current][kind] = message
        elif kind == "VFR_HUD" and current is not None:
            steps[current][kind] = message
    return dict(steps)


def command(u_depth_wire: float, u_pitch_wire: float, target: int = 1):
    return dialect.MAVLink_command_long_message(
        target, 1, dialect.MAV_CMD_DO_SET_ACTUATOR, 0,
        u_depth_wire, u_pitch_wire, math.nan, math.nan, math.nan, math.nan, 0.0,
    )  # fmt: skip


def acks(received: list[Received]) -> list:
    return [r.message for r in received if r.message.get_type() == "COMMAND_ACK"]


@pytest.fixture
def peer():
    p = UdpPeer()
    yield p
    p.close()


def start_emulator(processes, peer, *extra: str):
    return processes.start(
        "emulate", "--connect", f"udpout:127.0.0.1:{peer.port}", "--speed", str(SPEED),
        "--duration", "400", "--excitation", "none", "--seed", "3",
        "--command-timeout", "1000", *extra,
    )  # fmt: skip


def test_heartbeat_telemetry_commands_and_model(processes, peer):
    process = start_emulator(processes, peer)
    first = peer.receive_until(lambda r: len(steps_by_time(r)) >= 12, timeout=15)

    heartbeats = [r.message for r in first if r.message.get_type() == "HEARTBEAT"]
    assert heartbeats, "no HEARTBEAT"
    assert heartbeats[0].type == dialect.MAV_TYPE_SUBMARINE
    assert heartbeats[0].get_srcSystem() == 1
    assert heartbeats[0].get_srcComponent() == dialect.MAV_COMP_ID_AUTOPILOT1
    assert all(r.message.get_header().mlen is not None for r in first)
    assert all(r.message.get_msgbuf()[0] == 0xFD for r in first), "not MAVLink 2"

    steps = steps_by_time(first)
    times = sorted(steps)
    assert times[:3] == [0, 1000, 2000]
    for t in times[:-1]:
        step = steps[t]
        assert {"ATTITUDE", "SCALED_PRESSURE2", "VFR_HUD", "ACTUATOR_OUTPUT_STATUS"} <= set(step)
        depth = MAPPING.depth_from_pressure(step["SCALED_PRESSURE2"])
        assert step["VFR_HUD"].alt == pytest.approx(-depth, abs=1e-3)
    # Every plant step, none skipped, on the simulated clock (1 s per step).
    assert times == list(range(0, 1000 * len(times), 1000))
    # Paced to absolute deadlines, never ahead of them (a loaded machine only makes it
    # later, so this bound cannot fail for want of CPU).
    arrivals = [steps[t]["arrival"] for t in times[1:-1]]
    assert arrivals[-1] - arrivals[0] >= 0.9 * (len(arrivals) - 1) / SPEED

    # A command is acknowledged and reported back on the next step.
    peer.send(command(0.25, 0.25))
    after = peer.receive_until(lambda r: len(steps_by_time(r)) >= 60, timeout=15)
    assert [a.result for a in acks(after)] == [dialect.MAV_RESULT_ACCEPTED]
    ack_index = next(i for i, r in enumerate(after) if r.message.get_type() == "COMMAND_ACK")
    later = steps_by_time(after[ack_index:])
    next_step = later[min(later)]
    assert list(next_step["ACTUATOR_OUTPUT_STATUS"].actuator[:2]) == pytest.approx([0.25, 0.25])

    # Outputs follow the model: a twin plant fed the reported inputs gives the same outputs.
    all_steps = steps_by_time(first + after)
    twin = GliderPlant(PlantConfig(scenario="paper", seed=3))
    for t in sorted(all_steps)[:-1]:
        step = all_steps[t]
        u_depth, u_pitch = MAPPING.inputs_from_actuators(step["ACTUATOR_OUTPUT_STATUS"])
        expected = twin.step(u_depth, u_pitch)
        assert expected.time_boot_ms == t
        assert MAPPING.depth_from_pressure(step["SCALED_PRESSURE2"]) == pytest.approx(
            expected.depth, abs=1e-3
        )
        assert step["ATTITUDE"].pitch == pytest.approx(expected.pitch, abs=1e-5)
    # The step moves pitch toward its DC gain (0.2 rad per unit × 0.5 units = +0.1 rad).
    last = all_steps[sorted(all_steps)[-2]]
    assert last["ATTITUDE"].pitch == pytest.approx(0.1, abs=0.03)

    # Non-finite or out-of-range commands are refused with a failure result.
    for bad in ((math.nan, math.nan), (math.inf, 0.0), (1.5, 0.0)):
        peer.send(command(*bad))
    refused = peer.receive_until(lambda r: len(acks(r)) >= 3, timeout=10)
    assert [a.result for a in acks(refused)] == [dialect.MAV_RESULT_DENIED] * 3
    tail = steps_by_time(peer.receive_for(0.5))
    assert all(
        list(s["ACTUATOR_OUTPUT_STATUS"].actuator[:2]) == pytest.approx([0.25, 0.25])
        for s in tail.values()
        if "ACTUATOR_OUTPUT_STATUS" in s
    ), "a refused command changed the inputs"

    out, err = processes.stop(process)
    assert process.returncode == 0, err
    stats = json.loads(out.strip().splitlines()[-1])["emulator"]
    assert stats["commands_accepted"] == 1
    assert stats["commands_rejected"] == 3


def test_bad_input_is_counted_not_fatal(processes, peer):
    process = start_emulator(processes, peer)
    peer.receive_until(lambda r: len(steps_by_time(r)) >= 3, timeout=15)
    frame = peer.codec.pack(command(0.1, 0.1))
    corrupted = bytearray(frame)
    corrupted[-3] ^= 0xFF
    bad = [
        b"\x00garbage\xfd\xfe" * 20,
        frame[: len(frame) // 2],  # truncated frame
        bytes(corrupted),  # CRC failure
    ]
    for datagram in bad:
        peer.send_raw(datagram)
    peer.send(command(0.1, 0.1, target=7))  # another vehicle's command
    peer.send(command(0.1, 0.1))  # still works after all that
    received = peer.receive_until(lambda r: len(acks(r)) >= 1, timeout=10)
    assert [a.result for a in acks(received)] == [dialect.MAV_RESULT_ACCEPTED]
    assert process.poll() is None, "emulator died on bad input"

    out, err = processes.stop(process)
    assert process.returncode == 0, err
    stats = json.loads(out.strip().splitlines()[-1])["emulator"]
    assert stats["commands_accepted"] == 1
    assert stats["commands_for_other_systems"] == 1
    # Each bad datagram counted, as the codec counts it (the garbage holds two frame starts).
    reference = MavlinkCodec(1, 1)
    per_datagram = []
    for datagram in bad:
        before = reference.counters.bad_frames
        reference.parse(datagram, datagram=True)
        per_datagram.append(reference.counters.bad_frames - before)
    assert per_datagram == [2, 1, 1]
    assert stats["rx_bad_frames"] == sum(per_datagram)


def status_texts(received: list[Received]) -> list[str]:
    return [r.message.text for r in received if r.message.get_type() == "STATUSTEXT"]


def test_hold_fallback_after_command_timeout(processes, peer):
    process = start_emulator(processes, peer, "--command-timeout", "5", "--fallback", "hold")
    peer.receive_until(lambda r: len(steps_by_time(r)) >= 2, timeout=15)
    peer.send(command(0.5, 0.5))
    received = peer.receive_until(
        lambda r: any("no command" in text for text in status_texts(r)), timeout=10
    )
    texts = status_texts(received)
    assert any("external control" in text for text in texts)
    assert any("no command for 5s, hold" in text for text in texts)
    tail = steps_by_time(peer.receive_for(1.0))
    positions = [
        step["ACTUATOR_OUTPUT_STATUS"].actuator[0]
        for step in tail.values()
        if "ACTUATOR_OUTPUT_STATUS" in step
    ]
    assert positions, "no telemetry after the fallback"
    assert positions[-1] == pytest.approx(0.0), "hold must return the ballast to neutral"
    processes.stop(process)


def test_excitation_fallback_after_command_timeout():
    """The default fallback: once commands stop for ``command_timeout`` simulated seconds,
    the emulator says so and drives its excitation again (in process, simulated time)."""
    import socket

    from plant_emulator.autopilot import Autopilot, AutopilotConfig
    from protocols.mavlink_io import Link, MavlinkCodec

    class Level:
        def __init__(self, value: float) -> None:
            self.level = value

        def value(self, k: int) -> float:
            return self.level

    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    link = Link(f"udpout:127.0.0.1:{sink.getsockname()[1]}")
    try:
        autopilot = Autopilot(
            GliderPlant(PlantConfig(seed=3)),
            link,
            {"depth": Level(0.8), "pitch": Level(-0.6)},
            AutopilotConfig(command_timeout=5.0),
        )
        applied = [autopilot.step().u_depth for _ in range(5)]
        assert applied[-1] == pytest.approx(0.8)  # excitation before any command
        autopilot.handle_bytes(MavlinkCodec(255, 190).pack(command(0.25, 0.25)))  # 0.5 units
        during = [autopilot.step() for _ in range(6)]
        after = [autopilot.step() for _ in range(10)]
    finally:
        link.close()
        texts = []
        sink.setblocking(False)
        reader = MavlinkCodec(1, 1)
        while True:
            try:
                data = sink.recv(65536)
            except BlockingIOError:
                break
            texts += [
                m.text for m in reader.parse(data, datagram=True) if m.get_type() == "STATUSTEXT"
            ]
        sink.close()
    # Commanded for 5 simulated seconds after the command (t = 5 … 10), then the fallback.
    assert [s.u_depth for s in during] == pytest.approx([0.5] * 6)
    assert autopilot.stats.fallbacks == 1
    assert "ballast: no command for 5s, excitation" in texts
    assert after[-1].u_depth == pytest.approx(0.8) and after[-1].u_pitch == pytest.approx(-0.6)
    # The first step past the timeout (t = 11 s) is already the excitation's, through the
    # actuator's rate limit (0.5 units per step): pitch 0.5 → 0.0 on the way to −0.6.
    assert after[0].time_boot_ms == 11_000
    assert (after[0].u_depth, after[0].u_pitch) == pytest.approx((0.8, 0.0))
