"""Inverse-control settings: the reference trajectory's share and old logs' settings."""

from __future__ import annotations

import pytest

from hil_service.pipeline import ControlSettings, PipelineSettings


def test_remaining_share_is_the_pole_to_the_horizon() -> None:
    control = ControlSettings(horizon={"depth": 150, "pitch": 3}, trajectory={"pitch": 0.5})
    assert control.remaining_share("pitch") == 0.125
    assert control.remaining_share("depth") == 0.0  # no pole: aim at the setpoint


def test_trajectory_pole_must_be_below_one() -> None:
    with pytest.raises(ValueError, match="trajectory pole"):
        ControlSettings(trajectory={"depth": 0.0, "pitch": 1.0})


def test_settings_recorded_before_the_trajectory_replay_without_one() -> None:
    old = {"control": {"horizon": {"depth": 150, "pitch": 20}, "reference_filter": 0.5}}
    control = PipelineSettings.from_json(old).control
    assert control.remaining_share("depth") == 0.0
    assert control.remaining_share("pitch") == 0.0
    assert control.reference_filter == 0.5
    new = PipelineSettings()
    assert PipelineSettings.from_json(new.to_json()).control == new.control
