"""The profile's ``[control]`` table: the safe input a tripped channel goes to, and the
probing excitation of a channel whose model does not pass the horizon test
(``hil_service/umodel/probe.py``, docs/control.md "Probing", docs/profiles.md)."""

from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import pytest

from hil_service.cli import build_parser
from hil_service.cli.serve import config_from_args
from hil_service.config import ServiceConfig
from hil_service.experiment.closed_loop import ClosedLoopSettings, inverse_run, setpoint_schedule
from hil_service.experiment.family_loop import levels
from hil_service.pipeline import ControlSettings, PipelineSettings
from hil_service.umodel.probe import LONGEST_HOLD, SHORTEST_HOLD, Probe
from plant_emulator.family import RATE_LIMIT, FamilyVehicle, draw_vehicle
from plant_emulator.models import CHANNELS
from protocols.profiles import ControlChoices, ProfileError, builtin_text, parse_profile


def test_a_probe_is_seeded_per_channel_and_steps_within_its_amplitude():
    def run(seed: int, channel: str) -> list[float]:
        probe = Probe(0.5, seed, channel)
        probe.start(0.4)
        return [probe.level() for _ in range(3000)]

    levels_ = run(3, "depth")
    assert levels_ == run(3, "depth")
    assert levels_ != run(3, "pitch") and levels_ != run(4, "depth")
    assert max(abs(v - 0.4) for v in levels_) <= 0.5
    assert max(levels_) - min(levels_) > 0.8  # the levels spread over the band
    holds = [len(list(run)) for _, run in itertools.groupby(levels_)][:-1]  # the last is cut
    assert min(holds) >= SHORTEST_HOLD and max(holds) <= LONGEST_HOLD


@pytest.mark.parametrize("amplitude", [-0.1, float("nan"), float("inf")])
def test_a_probe_amplitude_must_be_finite_and_not_negative(amplitude):
    with pytest.raises(ValueError, match="probe amplitude"):
        Probe(amplitude, 0, "depth")


@pytest.mark.parametrize("share", [-0.1, 1.5, float("nan")])
def test_control_settings_refuse_a_probe_outside_the_range(share):
    with pytest.raises(ValueError, match=r"probe must be 0\.\.1"):
        ControlSettings(probe=share)


def _unqualified_run(probe: float):
    """Seed 3's vehicle 20 (docs/control.md, "Probing"): its pitch model never passes the
    horizon test after the excitation ends at sample 800."""
    depth, pitch = draw_vehicle(3, 20)
    settings = ClosedLoopSettings(
        scenario="family", samples=1400, seed=3, identify=800, step_every=300,
        neutral_after_identify=True,
    )  # fmt: skip
    schedule = setpoint_schedule(
        settings, {ch: levels(spec) for ch, spec in zip(CHANNELS, (depth, pitch), strict=True)}
    )
    base = PipelineSettings(seed=3)
    pipeline = base.replace(control=dataclasses.replace(base.control, probe=probe))
    return settings, inverse_run(settings, FamilyVehicle(depth, pitch, 3), schedule, pipeline)


def test_a_channel_that_does_not_qualify_probes_only_where_its_settings_allow_it():
    settings, held = _unqualified_run(0.0)
    _, probing = _unqualified_run(0.25)
    after = slice(settings.identify, None)
    pitch_modes = {mode.split("/")[1] for mode in held.modes if mode}
    assert "probe" not in pitch_modes and held.supervision["pitch"]["commanded"] == 0
    assert np.all(held.trace.u["pitch"][after] == 0.0)  # held at neutral
    probed = [mode.split("/")[1] for mode in probing.modes if mode]
    assert probed.count("probe") > 400 and probing.supervision["pitch"]["commanded"] == 0
    u = probing.trace.u["pitch"][after]
    # About the input it held (the neutral input), within ± 0.25 of the range (2), at the
    # actuator's rate limit.
    assert np.max(np.abs(u)) <= 0.25 * ControlSettings().u_limit + 1e-12
    assert np.ptp(u) > 0.5
    assert np.max(np.abs(np.diff(u))) <= min(RATE_LIMIT, ControlSettings().rate_limit) + 1e-12


PROFILE = builtin_text("glider") + '\n[control]\nsafe_input = "release"\nprobe = 0.3\n'


def test_the_profile_chooses_the_safe_input_and_the_probe_and_serve_applies_them(tmp_path):
    assert parse_profile(builtin_text("glider")).control == ControlChoices("neutral", 0.0)
    assert parse_profile(PROFILE).control == ControlChoices("release", 0.3)
    path = tmp_path / "released.toml"
    path.write_text(PROFILE)
    args = build_parser().parse_args(["serve", "--profile", str(path), "--no-log"])
    config = config_from_args(args).service
    assert config.pipeline.control.safe_input == "release"
    assert config.pipeline.control.probe == 0.3
    stored = {name: json.loads(text) for name, text in config.to_metadata().items()}
    again = ServiceConfig.from_stored(stored)
    assert again is not None and again.pipeline.control == config.pipeline.control


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ('safe_input = "brake"', "'brake' is not one of hold, neutral, release"),
        ("probe = 1.5", "must be 0..1"),
        ('probe = "some"', "must be a number"),
        ("dither = 1", "unknown field"),
    ],
)
def test_a_bad_control_table_names_its_line(line, message):
    text = builtin_text("glider") + f"\n[control]\n{line}\n"
    with pytest.raises(ProfileError) as error:
        parse_profile(text, "bad.toml")
    assert f"bad.toml line {len(text.splitlines())}:" in str(error.value)
    assert message in str(error.value)
