"""`glider-hil emulate` as a real process, watched by a MAVLink peer on loopback UDP."""

from __future__ import annotations

import json
import math
from collections import defaultdict

import pytest

from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import dialect
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
    arrivals = [steps[t]["arrival"] for t in times[1:-1]]
    rate = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0])
    assert SPEED * 0.7 < rate < SPEED * 1.3, f"step rate {rate:.1f}/s, expected ~{SPEED}"

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
    peer.send_raw(b"\x00garbage\xfd\xfe" * 20)
    peer.send_raw(frame[: len(frame) // 2])  # truncated frame
    corrupted = bytearray(frame)
    corrupted[-3] ^= 0xFF
    peer.send_raw(bytes(corrupted))  # CRC failure
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
    assert stats["rx_bad_frames"] >= 2


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
