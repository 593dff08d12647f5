"""ProfileAssembler: periodic TelemetrySamples per vehicle, implausible ones counted."""

from __future__ import annotations

import itertools

import pytest

from hil_service.sources.periodic_assembler import ProfileAssembler
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import load_profile

PROFILE = load_profile("ardusub")


def stream(system_id: int, seconds: float, depth: float = 12.0, pwm: int = 1700):
    """Decoded ArduSub-style messages of one vehicle, 10 Hz each, staggered."""
    codec, reader = MavlinkCodec(system_id, 1), MavlinkCodec(255, 0)
    out = []
    for k in range(int(seconds * 10)):
        ms = 1000 + k * 100
        servos = [1500] * 16
        servos[8], servos[9] = pwm, 1500
        for message in (
            dialect.MAVLink_attitude_message(ms, 0, 0.05, 0, 0, 0.01, 0),
            dialect.MAVLink_scaled_pressure2_message(
                ms + 20, PROFILE.pressure.pressure_hpa(depth), 0, 1500, 0
            ),
            dialect.MAVLink_vfr_hud_message(0, 0, 0, 0, -depth, 0.2),
            dialect.MAVLink_servo_output_raw_message((ms + 50) * 1000, 0, *servos),
        ):
            out += reader.parse(codec.pack(message), datagram=True)
    return out


def test_samples_per_vehicle_with_values_from_the_profile():
    assembler = ProfileAssembler(PROFILE)  # the profile's own period, 0.1 s
    samples = [s for m in stream(1, 5.0) + stream(2, 5.0) for s in assembler.add_all(m)]
    assert assembler.system_ids == [1, 2]
    ones = [s for s in samples if s.system_id == 1]
    assert len(ones) >= 45
    first = ones[0]
    assert first.depth == pytest.approx(12.0, abs=1e-3)
    assert (first.pitch, first.pitch_rate, first.climb) == pytest.approx((0.05, 0.01, 0.2))
    assert (first.u_depth, first.u_pitch) == pytest.approx((1.0, 0.0))
    steps = {b.time_boot_ms - a.time_boot_ms for a, b in itertools.pairwise(ones)}
    assert steps == {100}
    assert assembler.counters.as_dict()["samples"] == len(samples)


def test_allowed_vehicles_and_implausible_samples_are_counted():
    assembler = ProfileAssembler(PROFILE, 0.1, system_ids=[2])
    assert [s for m in stream(1, 1.0) for s in assembler.add_all(m)] == []
    assert assembler.counters.unknown_system > 0
    deep = [s for m in stream(2, 2.0, depth=20_000.0) for s in assembler.add_all(m)]
    assert deep == [] and assembler.counters.invalid > 0  # deeper than any ocean
    with pytest.raises(ValueError, match="no sample period"):
        ProfileAssembler(load_profile("glider"))
