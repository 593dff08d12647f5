"""Lockstep HIL (docs/lockstep.md): the handshake on the wire, and same seed, same run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil_service.campaign.hil_run import run_hil
from hil_service.campaign.mission import Mission
from hil_service.cli import main
from hil_service.cli.processes import last_json
from hil_service.mcap.reader import LogReader
from hil_service.sources.lockstep_responder import LockstepResponder
from plant_emulator.autopilot import GCS_RATES_HZ, Autopilot, AutopilotConfig
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.lockstep import LockstepRunner
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.lockstep import announces_lockstep, lockstep_heartbeat, release, released_time
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import Link
from protocols.samples import TelemetrySample
from tests.conftest import free_tcp_port, free_udp_port

pytestmark = pytest.mark.wire

#: Short, but long enough for the identifier to converge and the controller to command.
MISSION = Mission("disturbed", seed=3, steps=600, identify=350, step_every=80)


def test_wire_messages_are_the_standard_ones() -> None:
    assert announces_lockstep(lockstep_heartbeat())
    assert not announces_lockstep(TelemetryMapping().heartbeat(vehicle=True))
    message = release(1_234_000)
    assert message.get_type() == "SYSTEM_TIME"
    assert message.time_unix_usec == 0
    assert released_time(message) == 1_234_000
    assert released_time(lockstep_heartbeat()) is None


#: Topics paced by the wall clock: the health, and the heartbeats of both sides with the
#: ground-station streams a lockstep vehicle sends beside its own (1 Hz wall clock), so
#: that how many there are depends on how long the run took.
WALL_CLOCK_TOPICS = ("/health", "/HEARTBEAT", *(f"/{name}" for name in GCS_RATES_HZ))


def _payloads(path: str) -> dict[str, list[object]]:
    """What a run decided, by channel, without wall-clock content (``WALL_CLOCK_TOPICS``)
    and without the MAVLink sequence numbers (they count the wall-clock messages). Raw
    frames carry the sequence number and a checksum over it, so the frames are compared
    decoded (every field)."""
    channels: dict[str, list[object]] = {}
    for message in LogReader(path).messages():
        topic = message.topic
        if topic.endswith(WALL_CLOCK_TOPICS) or topic.startswith("mavlink/raw/"):
            continue
        if topic.startswith("mavlink/json/"):
            payload = json.loads(message.data)
            payload["_header"].pop("seq")
            channels.setdefault(topic, []).append(payload)
        else:
            channels.setdefault(topic, []).append(message.data)
    return channels


def test_two_lockstep_runs_with_the_same_seed_are_the_same_bit_for_bit(tmp_path: Path) -> None:
    first = run_hil(MISSION, tmp_path / "a")
    second = run_hil(MISSION, tmp_path / "b")
    for outcome in (first, second):
        assert outcome.failure is None
        commands = outcome.service["vehicles"]["1"]["commands_sent"]
        assert commands > 100
        # Every step released: by its command when the service sent one, else SYSTEM_TIME.
        assert outcome.lockstep == {
            "released": 600 - commands, "released_by_command": commands,
            "timeouts": 0, "stale_releases": 0,
        }  # fmt: skip
        assert outcome.service["lockstep"]["releases"] == 600 - commands
    assert first.log_path is not None and second.log_path is not None
    a, b = _payloads(first.log_path), _payloads(second.log_path)
    for topic in ("glider/1/telemetry", "glider/1/umodel/depth", "glider/1/command/ballast"):
        assert len(a[topic]) > 100, topic
    assert a.keys() == b.keys()
    assert {"mavlink/json/out/COMMAND_LONG", "mavlink/json/out/SYSTEM_TIME"} <= a.keys()
    for topic in a:
        assert a[topic] == b[topic], f"{topic} differs between the two runs"
    for channel in ("depth", "pitch"):
        assert (first.trace.y[channel] == second.trace.y[channel]).all()
    # The service saw every step the vehicle computed, once, in order: nothing was skipped
    # or waited out, and pitch (a float on the wire as in the plant) is the plant's own.
    telemetry = [json.loads(data) for data in a["glider/1/telemetry"]]  # type: ignore[arg-type]
    assert [p["t"] for p in telemetry] == [float(k) for k in range(600)]
    assert [p["pitch"] for p in telemetry] == pytest.approx(list(first.trace.y["pitch"]), abs=1e-6)


@pytest.mark.parametrize(
    "spin", [(), ("--spin-wait", "200")], ids=["sleeping", "spinning"]
)  # docs/lockstep.md, "Two cores"
def test_emulate_lockstep_with_serve_announced_automatically(processes, spin) -> None:
    udp, zport = free_udp_port(), free_tcp_port()
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", f"tcp/127.0.0.1:{zport}",
        "--no-log", *spin,
    )  # fmt: skip
    emulator = processes.start(
        "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--lockstep", *spin,
        "--duration", "300", "--scenario", "disturbed", "--lockstep-timeout", "30",
    )  # fmt: skip
    out, err = emulator.communicate(timeout=120)
    assert emulator.returncode == 0, err
    emulated = last_json(out, "emulator")
    assert emulated["steps"] == 300
    # Every step waited for its release; none had to time out (30 s: a loaded machine).
    assert emulated["lockstep"] == {
        "released": 300, "released_by_command": 0, "timeouts": 0, "stale_releases": 0,
    }  # fmt: skip
    served = last_json(processes.stop(service)[0], "service")
    assert served["lockstep"] == {
        "active": True, "announced": True, "releases": 300, "released_by_command": 0,
        "released_refused": 0,
    }  # fmt: skip


def test_without_a_service_each_step_times_out_and_the_emulator_goes_on() -> None:
    link = Link(f"udpout:127.0.0.1:{free_udp_port()}", source_system=1, source_component=1)
    plant = GliderPlant(PlantConfig(scenario="paper"))
    autopilot = Autopilot(
        plant, link, build_channel_excitations("steps", 0), AutopilotConfig(duration=3.0)
    )
    runner = LockstepRunner(autopilot, timeout=0.05)
    try:
        stats = runner.run()
    finally:
        link.close()
    assert stats.steps == 3
    assert runner.stats.as_dict() == {
        "released": 0, "released_by_command": 0, "timeouts": 3, "stale_releases": 0,
    }  # fmt: skip


def test_lockstep_refuses_what_it_cannot_do(capsys) -> None:
    assert main(["emulate", "--lockstep", "--profile", "ardusub"]) == 2
    assert "--lockstep needs the glider profile" in capsys.readouterr().err
    assert main(["emulate", "--lockstep", "--vehicles", "3"]) == 2
    assert "--lockstep runs one vehicle" in capsys.readouterr().err


def test_the_service_side_releases_only_when_active_and_not_commanded() -> None:
    sample = TelemetrySample(1, 5000, 15.0, 0.0, 0.0, 0.0)
    sent: list[object] = []
    idle = LockstepResponder()
    idle.observe(TelemetryMapping().heartbeat(vehicle=True))  # no flag: stays off
    idle.after_sample(sample, False, sent.append)
    idle.after_refused(5000, sent.append)
    assert not idle.active and sent == []
    idle.observe(lockstep_heartbeat())
    assert idle.active and idle.announced
    idle.after_refused(5000, sent.append)  # active now: a refused step is released too
    assert [released_time(m) for m in sent] == [5000]  # type: ignore[arg-type]
    assert idle.as_dict()["released_refused"] == 1
    sent.clear()
    forced = LockstepResponder(forced=True)  # serve --lockstep
    forced.after_sample(sample, True, sent.append)  # the command released it
    forced.after_sample(sample, False, sent.append)
    assert [released_time(m) for m in sent] == [5000]  # type: ignore[arg-type]
    assert forced.as_dict() == {
        "active": True, "announced": False, "releases": 1, "released_by_command": 1,
        "released_refused": 0,
    }  # fmt: skip


class _TumblingPlant(GliderPlant):
    """A glider whose reported pitch is beyond ±π on some steps: implausible telemetry."""

    def __init__(self, tumbling: frozenset[int]):
        super().__init__(PlantConfig(scenario="paper"))
        self.tumbling = tumbling

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample:
        k = self.k
        sample = super().step(u_depth, u_pitch)
        return sample._replace(pitch=4.0) if k in self.tumbling else sample


def test_a_refused_sample_releases_its_step_and_lockstep_goes_on(processes) -> None:
    udp, zport = free_udp_port(), free_tcp_port()
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", f"tcp/127.0.0.1:{zport}",
        "--no-log", "--lockstep",
    )  # fmt: skip
    tumbling = frozenset(range(20, 60, 3))  # 14 implausible steps among 100
    link = Link(f"udpout:127.0.0.1:{udp}", source_system=1, source_component=1)
    autopilot = Autopilot(
        _TumblingPlant(tumbling), link, build_channel_excitations("steps", 0),
        AutopilotConfig(duration=100.0),
    )  # fmt: skip
    # 30 s: a loaded machine; a step the service did not release would wait all of it.
    runner = LockstepRunner(autopilot, timeout=30.0)
    try:
        stats = runner.run()
    finally:
        link.close()
    assert stats.steps == 100
    assert runner.stats.as_dict() == {
        "released": 100, "released_by_command": 0, "timeouts": 0, "stale_releases": 0,
    }  # fmt: skip
    served = last_json(processes.stop(service)[0], "service")
    assert served["lockstep"] == {
        "active": True, "announced": True, "releases": 100, "released_by_command": 0,
        "released_refused": len(tumbling),
    }  # fmt: skip
    assert served["counters"]["invalid"] == len(tumbling)
    assert served["counters"]["samples"] == 100 - len(tumbling)
