"""A user's own lockstep profile is honoured: samples are assembled as its TOML says.

The profile below moves depth to SCALED_PRESSURE (29) in fresh water, and reads the ballast
with another full scale: a service that ignored it (the built-in glider contract) would
assemble nothing from these messages.
"""

from __future__ import annotations

import json

import pytest

from hil_service.cli import build_parser
from hil_service.cli.serve import config_from_args
from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from hil_service.service import HilService
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import load_profile

PROFILE = """
[profile]
name = "fresh-water-glider"

[sampling]
mode = "lockstep"

[units]
water_density = 997.0
surface_pressure_hpa = 1000.0

[[signals.depth]]
message = "SCALED_PRESSURE"
field = "press_abs"
convert = "pressure_to_depth"

[[signals.pitch]]
message = "ATTITUDE"
field = "pitch"

[[signals.pitch_rate]]
message = "ATTITUDE"
field = "pitchspeed"

[ballast]
readback = "ACTUATOR_OUTPUT_STATUS"
command = "DO_SET_ACTUATOR"
full_scale = 1.5
"""


def _step(profile, ms: int, depth: float, pitch: float, wires: tuple[float, float]):
    actuators = [0.0] * 32
    actuators[0], actuators[1] = wires
    return [
        dialect.MAVLink_attitude_message(ms, 0.0, pitch, 0.0, 0.0, 0.01, 0.0),
        dialect.MAVLink_scaled_pressure_message(
            ms, profile.pressure.pressure_hpa(depth), 0.0, 1500
        ),
        dialect.MAVLink_actuator_output_status_message(ms * 1000, 0b11, actuators),
    ]


@pytest.fixture
def profile_file(tmp_path):
    path = tmp_path / "fresh.toml"
    path.write_text(PROFILE)
    return path


def test_serve_keeps_a_lockstep_profile_file(profile_file):
    args = build_parser().parse_args(["serve", "--profile", str(profile_file), "--no-log"])
    config = config_from_args(args).service
    assert config.profile is not None and config.profile.name == "fresh-water-glider"
    stored = {name: json.loads(text) for name, text in config.to_metadata().items()}
    again = ServiceConfig.from_stored(stored)
    assert again is not None and again.profile is not None
    assert again.profile.name == "fresh-water-glider"
    assert again.stored() == config.stored()


def test_a_lockstep_profile_file_decides_how_samples_are_assembled(profile_file):
    args = build_parser().parse_args(["serve", "--profile", str(profile_file), "--no-log"])
    config = config_from_args(args).service
    service = HilService(config, Listener(), Inbox())
    profile = load_profile(profile_file)
    codec = MavlinkCodec(1, 1)
    samples = []
    for k in range(5):
        for message in _step(profile, 100 * (k + 1), 10.0 + k, 0.1, (0.5, -0.2)):
            samples.extend(service.process_datagram(codec.pack(message)))
    assert [s.time_boot_ms for s in samples] == [100, 200, 300, 400, 500]
    assert [s.depth for s in samples] == pytest.approx([10.0, 11.0, 12.0, 13.0, 14.0])
    assert samples[0].u_depth == pytest.approx(0.75)  # wire 0.5 at full scale 1.5
    assert samples[0].u_pitch == pytest.approx(-0.3)
    assert samples[0].pitch_rate == pytest.approx(0.01)
