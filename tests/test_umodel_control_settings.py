"""Control settings: no plant's horizon among them, and old logs' settings still load."""

from __future__ import annotations

import json

import pytest

from hil_service.pipeline import ControlSettings, PipelineSettings
from protocols.profiles import DEFAULT_PROFILE, load_profile

DEFAULT = load_profile(DEFAULT_PROFILE)  # serve's, with no --profile


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
    # Recorded before the disturbance was forecast, the horizon capped by the response's
    # arrival time and near pole-zero pairs let go: replayed without any of them.
    assert control == ControlSettings(
        rate_limit=0.4, disturbance_forecast=0.0, horizon_arrivals=0.0, cancel_near_pairs=False
    )


def test_invalid_predictive_constants_are_refused() -> None:
    with pytest.raises(ValueError):
        ControlSettings(max_blocks=1)
    with pytest.raises(ValueError):
        ControlSettings(min_horizon=1)


#: The control block of a stored configuration with every key a user or a log writes today,
#: none at its default.
STORED_CONTROL = {
    "u_limit": 1.5,
    "rate_limit": 0.25,
    "min_horizon": 7,
    "max_horizon": 600,
    "settle_band": 0.1,
    "max_blocks": 6,
    "move_weight": 0.05,
    "disturbance_share": 0.75,
    "refresh": 25,
    "cost_points": 90,
    "disturbance_forecast": 0.3,
    "horizon_arrivals": 6.0,
    "cancel_near_pairs": False,
    "horizon_fit": 60.0,
    "mean_fit": 30.0,
    "safe_input": "hold",
    "probe": 0.2,
}


def test_a_stored_configuration_with_every_control_key_loads_and_is_written_back_alike() -> None:
    settings = PipelineSettings.from_json({"control": dict(STORED_CONTROL)})
    control = settings.control
    predictive = control.predictive()
    assert (predictive.min_horizon, predictive.max_horizon, predictive.band) == (7, 600, 0.1)
    assert (predictive.max_blocks, predictive.move_weight) == (6, 0.05)
    assert (predictive.disturbance_share, predictive.refresh, predictive.cost_points) == (
        0.75,
        25,
        90,
    )
    assert predictive.disturbance_forecast == 0.3
    assert predictive.horizon_arrivals == 6.0
    assert predictive.cancel_near_pairs is False
    assert (control.u_limit, control.rate_limit) == (1.5, 0.25)
    assert (control.horizon_fit, control.mean_fit, control.safe_input) == (60.0, 30.0, "hold")
    assert control.probe == 0.2
    # The same flat keys, the same values, in what is stored again.
    assert settings.to_json()["control"] == STORED_CONTROL


def test_the_control_block_of_a_fixture_log_loads() -> None:
    """The control block the replay fixtures store (written before the horizon test's
    settings existed) reads with today's defaults for what it lacks."""
    from hil_service.mcap.reader import LogReader
    from tests.conftest import DATA

    reader = LogReader(DATA / "paper.mcap")
    for _ in reader.messages():
        pass
    stored = reader.config()["service"]["pipeline"]
    assert "settle_band" in stored["control"]
    control = PipelineSettings.from_json(stored).control
    for key, value in stored["control"].items():
        assert getattr(control, key) == value
    assert control.horizon_fit == ControlSettings().horizon_fit


def test_the_control_defaults_are_the_predictive_defaults() -> None:
    """ControlSettings carries the predictive inverse's constants for the stored
    configuration; its defaults are PredictiveSettings' own."""
    from hil_service.umodel.predictive import PredictiveSettings

    ours, theirs = ControlSettings().predictive(), PredictiveSettings()
    names = ("min_horizon", "max_horizon", "band", "max_blocks", "move_weight",
             "disturbance_share", "refresh", "cost_points")  # fmt: skip
    for name in names:
        assert getattr(ours, name) == getattr(theirs, name), name


def test_input_lags_reach_every_channels_identifier_and_the_stored_configuration() -> None:
    import argparse

    from hil_service.cli.serve import add_arguments, settings_from_args
    from hil_service.umodel import build_model

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    settings = settings_from_args(parser.parse_args(["--input-lags", "7"]), DEFAULT)
    assert settings.model_options == {"depth": {"nb": 7}, "pitch": {"nb": 7}}
    again = PipelineSettings.from_json(json.loads(json.dumps(settings.to_json())))
    assert again.options_for("pitch") == {"nb": 7}
    assert build_model("dynamic", **again.options_for("depth")).config()["nb"] == 7
    assert settings_from_args(parser.parse_args([]), DEFAULT).model_options is None


@pytest.mark.parametrize("lags", [0, -1, 2.5, True, 51])
def test_input_lags_out_of_range_are_refused(lags) -> None:
    with pytest.raises(ValueError, match="input lags must be an integer"):
        PipelineSettings().with_input_lags(lags)


def test_input_lags_are_the_dynamic_models_only() -> None:
    with pytest.raises(ValueError, match="not the paper model's"):
        PipelineSettings(model="paper").with_input_lags(6)


def test_input_lags_auto_chooses_them_from_the_record_and_is_stored() -> None:
    import argparse

    from hil_service.cli.serve import add_arguments, settings_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    settings = settings_from_args(parser.parse_args(["--input-lags", "auto"]), DEFAULT)
    assert settings.choose_input_lags and settings.model_options is None
    again = PipelineSettings.from_json(json.loads(json.dumps(settings.to_json())))
    assert again.choose_input_lags
    assert not PipelineSettings.from_json({"model": "dynamic"}).choose_input_lags  # old logs
    # The default for the dynamic model, the only one with input lags; given lags win.
    assert settings_from_args(parser.parse_args([]), DEFAULT).choose_input_lags
    assert not PipelineSettings(model="paper").choose_input_lags
    given = settings_from_args(parser.parse_args(["--input-lags", "4"]), DEFAULT)
    assert given.options_for("depth")["nb"] == 4
    with pytest.raises(ValueError, match="auto or an integer"):
        PipelineSettings().with_input_lag_choice("some")
    with pytest.raises(ValueError, match="not the paper model's"):
        PipelineSettings(model="paper").with_input_lag_choice("auto")


def test_bridge_gap_is_stored_and_old_logs_replay_without_it() -> None:
    import argparse

    from hil_service.cli.serve import add_arguments, settings_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert settings_from_args(parser.parse_args([]), DEFAULT).bridge_gap == 5
    settings = settings_from_args(parser.parse_args(["--bridge-gap", "0"]), DEFAULT)
    again = PipelineSettings.from_json(json.loads(json.dumps(settings.to_json())))
    assert again.bridge_gap == 0
    # A log recorded before gaps were bridged resynchronised after every one.
    assert PipelineSettings.from_json({"model": "dynamic"}).bridge_gap == 0
    with pytest.raises(ValueError, match="bridge_gap must be an integer"):
        PipelineSettings(bridge_gap=-1)
    with pytest.raises((TypeError, ValueError)):  # the compiled class checks the type first
        PipelineSettings(bridge_gap=2.5)  # type: ignore[arg-type]


def test_a_control_block_stored_without_the_mean_threshold_judges_against_holding_alone():
    """A log recorded before the horizon test asked for a fit against the mean replays
    with the test it was recorded under."""
    stored = {k: v for k, v in STORED_CONTROL.items() if k != "mean_fit"}
    control = PipelineSettings.from_json({"control": stored}).control
    assert control.mean_fit is None and control.horizon_fit == 60.0
    assert ControlSettings().mean_fit is not None
