"""MAVLink 2 signing: the key file, frame verification, the emulator and the service."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

from hil_service.config import LinkSecurity, ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener, Notifier
from hil_service.mcap.reader import LogReader
from hil_service.mcap.recorder import McapRecorder
from hil_service.offline.replay import ReplayOptions, replay
from hil_service.service import HilService
from hil_service.umodel import build_model
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.signing import (
    FrameVerifier,
    SigningKeyError,
    load_key,
    signing_timestamp,
)
from tests.mavlink_peer import UdpPeer
from tests.test_emulator_process import acks, command, start_emulator, steps_by_time

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
MAPPING = TelemetryMapping()


def write_key(path: Path, data: bytes, mode: int = 0o600) -> Path:
    path.write_bytes(data)
    path.chmod(mode)
    return path


def heartbeat_frames(codec: MavlinkCodec, n: int = 1) -> list[bytes]:
    return [codec.pack(MAPPING.heartbeat(vehicle=True)) for _ in range(n)]


# ---- the key file ------------------------------------------------------------------------
def test_key_file_raw_or_hex(tmp_path):
    assert load_key(write_key(tmp_path / "raw.key", KEY)) == KEY
    assert load_key(write_key(tmp_path / "hex.key", KEY.hex().encode() + b"\n")) == KEY


@pytest.mark.parametrize("content", [b"short", bytes(33), b"zz" * 32])
def test_key_file_of_the_wrong_shape_is_refused_without_echoing_it(tmp_path, content):
    with pytest.raises(SigningKeyError, match="32 raw bytes or 64 hex digits") as error:
        load_key(write_key(tmp_path / "bad.key", content))
    assert content.hex() not in str(error.value)


@pytest.mark.skipif(os.name != "posix", reason="file modes are POSIX")
def test_key_file_readable_by_others_is_refused(tmp_path):
    with pytest.raises(SigningKeyError, match="chmod 600"):
        load_key(write_key(tmp_path / "open.key", KEY, mode=0o644))


def test_missing_key_file_is_a_clear_error(tmp_path):
    with pytest.raises(SigningKeyError, match="cannot read signing key"):
        load_key(tmp_path / "absent.key")


# ---- frame verification --------------------------------------------------------------------
def test_signed_frames_round_trip_and_are_counted():
    sender = MavlinkCodec(1, 1, signing_key=KEY)
    receiver = MavlinkCodec(255, 191, verifier=FrameVerifier(KEY))
    frames = heartbeat_frames(sender, 3)
    assert all(f[2] & 0x01 for f in frames), "signed flag not set"
    got = [m for f in frames for m in receiver.parse(f, datagram=True)]
    assert len(got) == 3
    assert receiver.verifier.counters.signed_accepted == 3
    assert receiver.verifier.counters.rejected == 0


def test_wrong_key_unsigned_and_replayed_frames_are_refused_and_counted():
    verifier = FrameVerifier(KEY)
    receiver = MavlinkCodec(255, 191, verifier=verifier)
    good = heartbeat_frames(MavlinkCodec(1, 1, signing_key=KEY))[0]
    forged = heartbeat_frames(MavlinkCodec(1, 1, signing_key=OTHER_KEY))[0]
    unsigned = heartbeat_frames(MavlinkCodec(1, 1))[0]
    assert receiver.parse(forged, datagram=True) == []
    assert receiver.parse(unsigned, datagram=True) == []
    assert len(receiver.parse(good, datagram=True)) == 1
    assert receiver.parse(good, datagram=True) == []  # the same frame again: a replay
    counters = verifier.counters
    assert (counters.bad_signature, counters.unsigned_rejected, counters.replayed) == (1, 1, 1)
    assert counters.signed_accepted == 1
    assert receiver.counters.frames == 1  # refused frames are not decoded further
    assert receiver.last_rejected == [good]


def test_a_forged_future_timestamp_does_not_lock_out_the_genuine_stream():
    """pymavlink's own check would record the forged timestamp before the signature."""
    verifier = FrameVerifier(KEY)
    receiver = MavlinkCodec(255, 191, verifier=verifier)
    genuine = MavlinkCodec(1, 1, signing_key=KEY)
    assert len(receiver.parse(heartbeat_frames(genuine)[0], datagram=True)) == 1
    attacker = MavlinkCodec(1, 1, signing_key=OTHER_KEY)
    attacker._packer.signing.timestamp = signing_timestamp() + 10**12
    assert receiver.parse(heartbeat_frames(attacker)[0], datagram=True) == []
    assert len(receiver.parse(heartbeat_frames(genuine)[0], datagram=True)) == 1
    assert verifier.counters.bad_signature == 1 and verifier.counters.replayed == 0


def test_a_new_stream_from_the_distant_past_is_refused():
    old = MavlinkCodec(1, 1, signing_key=KEY)
    frame = heartbeat_frames(old)[0]
    hours_later = signing_timestamp() / 100_000 + 1_420_070_400 + 3600

    live = FrameVerifier(KEY, clock=lambda: hours_later)
    assert not live.accept(frame) and live.counters.replayed == 1
    assert FrameVerifier(KEY).accept(frame)  # the same frame, now, is fine


def test_unsigned_non_commands_may_be_allowed_but_never_unsigned_commands():
    from plant_emulator.autopilot import COMMAND_MESSAGE_IDS

    verifier = FrameVerifier(KEY, accept_unsigned=True, always_signed=COMMAND_MESSAGE_IDS)
    plain = MavlinkCodec(255, 190)
    assert verifier.accept(heartbeat_frames(plain)[0])
    assert not verifier.accept(plain.pack(command(0.5, 0.0)))
    assert (verifier.counters.unsigned_accepted, verifier.counters.unsigned_rejected) == (1, 1)


# ---- the emulator as a process -------------------------------------------------------------
def _signed_peer(key: bytes | None) -> UdpPeer:
    peer = UdpPeer()
    peer.codec = MavlinkCodec(255, 190, signing_key=key)
    return peer


@pytest.mark.timeout(60)
def test_emulator_obeys_only_correctly_signed_commands(processes, tmp_path):
    key_file = write_key(tmp_path / "link.key", KEY)
    peer = _signed_peer(KEY)
    intruder = _signed_peer(OTHER_KEY)
    plain = _signed_peer(None)
    try:
        process = start_emulator(processes, peer, "--signing-key", str(key_file))
        first = peer.receive_until(lambda r: len(steps_by_time(r)) >= 3, timeout=15)
        assert all(r.message.get_msgbuf()[2] & 0x01 for r in first), "emulator must sign"
        intruder.remote = plain.remote = peer.remote
        intruder.send(command(0.9, 0.0))
        plain.send(command(-0.9, 0.0))
        quiet = peer.receive_for(1.0)
        assert not acks(quiet), "an unsigned or wrongly signed command was answered"
        reported = [
            r.message.actuator[0] for r in quiet if r.message.get_type() == "ACTUATOR_OUTPUT_STATUS"
        ]
        assert reported and all(abs(a) < 1e-6 for a in reported)  # excitation none: 0

        peer.send(command(0.5, 0.0))
        answered = peer.receive_until(lambda r: bool(acks(r)), timeout=5)
        assert acks(answered)[0].result == dialect.MAV_RESULT_ACCEPTED
        after = peer.receive_until(
            lambda r: any(
                m.message.get_type() == "ACTUATOR_OUTPUT_STATUS"
                and math.isclose(m.message.actuator[0], 0.5, abs_tol=1e-6)
                for m in r
            ),
            timeout=10,
        )
        assert after
        out, _ = processes.stop(process)
        stats = json.loads(out.strip().splitlines()[-1])["emulator"]
        assert stats["rx_signing_bad_signature"] == 1
        assert stats["rx_signing_unsigned_rejected"] == 1
        assert stats["commands_accepted"] == 1
    finally:
        for p in (peer, intruder, plain):
            p.close()


# ---- the service -------------------------------------------------------------------------
def _telemetry_frames(codec: MavlinkCodec, steps: int) -> list[bytes]:
    plant = GliderPlant(PlantConfig(seed=1))
    frames = []
    for _ in range(steps):
        sample = plant.step(0.3, -0.2)
        frames.append(b"".join(codec.pack(m) for m in MAPPING.encode_telemetry(sample)))
    return frames


def test_service_requires_signed_telemetry_counts_refusals_and_logs_them(tmp_path):
    recorder = McapRecorder(tmp_path, metadata={}).start()
    config = ServiceConfig(security=LinkSecurity(KEY))
    service = HilService(config, Listener(), Inbox(), recorder=recorder)
    signed = _telemetry_frames(MavlinkCodec(1, 1, signing_key=KEY), 20)
    unsigned = _telemetry_frames(MavlinkCodec(1, 1), 5)
    forged = _telemetry_frames(MavlinkCodec(1, 1, signing_key=OTHER_KEY), 5)
    for datagram in signed[:10] + unsigned + forged + signed[10:]:
        service.process_datagram(datagram)
    assert service.source.assembler.counters.samples == 20
    health = service.health(1)
    counters = health["link_wide"]  # the verifier sees frames, not vehicles
    assert counters["signing_signed_accepted"] == 80
    assert counters["signing_unsigned_rejected"] == 20
    assert counters["signing_bad_signature"] == 20
    assert health["signing"] == {
        "signed": True,
        "accept_unsigned": False,
        "rejected": 40,
        "last_rejection": "bad signature",
    }
    assert KEY.hex() not in json.dumps(config.to_json()) and KEY.hex() not in repr(config)
    recorder.close()
    [log] = tmp_path.glob("*.mcap")
    counts = {
        topic: sum(1 for _ in LogReader(log).messages({topic}))
        for topic in ("mavlink/raw/in", "mavlink/raw/rejected")
    }
    assert counts == {"mavlink/raw/in": 80, "mavlink/raw/rejected": 40}
    assert KEY not in log.read_bytes()


def test_service_may_accept_unsigned_telemetry_when_configured():
    config = ServiceConfig(security=LinkSecurity(KEY, accept_unsigned=True))
    service = HilService(config, Listener(), Inbox())
    for datagram in _telemetry_frames(MavlinkCodec(1, 1), 5):
        service.process_datagram(datagram)
    assert service.source.assembler.counters.samples == 5
    assert service.health(1)["link_wide"]["signing_unsigned_accepted"] == 20


def test_service_signs_the_commands_it_sends():
    """Through the service's own send path: signed telemetry in, control on, and every
    frame that reaches the vehicle's socket is a command signed with the link key."""
    from hil_service.pipeline import PipelineSettings
    from tests.test_safety_gate import BLOCKED, BURN_IN, SentFrames, plant_samples

    link = SentFrames()
    config = ServiceConfig(
        control_default=True,
        pipeline=PipelineSettings(burn_in=BURN_IN),
        security=LinkSecurity(KEY),
    )
    service = HilService(config, Listener(), Inbox(), link=link.link)
    service.inbox.set_setpoint(1, "depth", 16.0)
    vehicle = MavlinkCodec(1, 1, signing_key=KEY)
    try:
        # Until ten commands have gone out: the gate opens once burn-in and the horizon test
        # have passed, which is what the safety-gate tests measure; signing is what this checks.
        for sample, _ in plant_samples(BLOCKED + 2000):
            for message in MAPPING.encode_telemetry(sample):
                service.process_datagram(vehicle.pack(message))
            if service.vehicles[1].commands_sent >= 10:
                break
        frames = link.frames
    finally:
        link.close()
    assert len(frames) == 10 == service.vehicles[1].commands_sent
    genuine, other = FrameVerifier(KEY), FrameVerifier(OTHER_KEY)
    for frame in frames:
        assert frame[2] & 0x01, "signed flag not set"
        assert not other.accept(frame)
        assert genuine.accept(frame)  # each once: timestamps increase, no replay
    receiver = MavlinkCodec(255, 190, verifier=FrameVerifier(KEY))
    decoded = [m for frame in frames for m in receiver.parse(frame, datagram=True)]
    assert [m.get_type() for m in decoded] == ["COMMAND_LONG"] * 10


@pytest.mark.timeout(60)
def test_a_signed_log_replays_without_the_key_and_checks_bit_for_bit(tmp_path):
    config = ServiceConfig(security=LinkSecurity(KEY))
    recorder = McapRecorder(tmp_path, metadata=config.to_metadata()).start()
    service = HilService(config, Notifier(), Inbox(), recorder=recorder)
    for datagram in _telemetry_frames(MavlinkCodec(1, 1), 3):  # refused, logged apart
        service.process_datagram(datagram)
    for datagram in _telemetry_frames(MavlinkCodec(1, 1, signing_key=KEY), 50):
        service.process_datagram(datagram)
    recorder.close()
    [log] = tmp_path.glob("*.mcap")
    result = replay(log, ReplayOptions(check=True))
    assert result.mismatch is None
    assert result.samples == 50
    history = build_model("dynamic").history_length
    assert result.compared == 2 * (50 - history)  # both channels, after the history filled
