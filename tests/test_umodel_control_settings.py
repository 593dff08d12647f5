"""Control settings: no plant's horizon among them, and old logs' settings still load."""

from __future__ import annotations

import json

import pytest

from hil_service.pipeline import ControlSettings, PipelineSettings


def test_settings_survive_the_stored_configuration() -> None:
    settings = PipelineSettings(control=ControlSettings(max_blocks=5, refresh=20))
    again = PipelineSettings.from_json(json.loads(json.dumps(settings.to_json())))
    assert again.control == settings.control
    predictive = again.control.predictive()
    assert (predictive.max_blocks, predictive.refresh) == (5, 20)


def test_settings_recorded_by_the_old_controller_load_with_todays_defaults() -> None:
    old_control = {
        "horizon": {"depth": 150, "pitch": 3},
        "trajectory": {"pitch": 0.7},
        "mismatch_filter": 0.9,
        "reference_filter": 0.5,
        "rate_limit": 0.4,
    }
    old = {"control": old_control}
    control = PipelineSettings.from_json(old).control
    assert control.rate_limit == 0.4
    assert control == ControlSettings(rate_limit=0.4)


def test_invalid_predictive_constants_are_refused() -> None:
    with pytest.raises(ValueError):
        ControlSettings(max_blocks=1)
    with pytest.raises(ValueError):
        ControlSettings(min_horizon=1)
