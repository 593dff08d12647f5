"""The smoothness prior on the dynamic U-model's input lags (``umodel.lag_prior``): what it
does to a noisy record's lags, why a record without noise does not get it, and the
pipeline's choice of it (docs/control.md, "A smoothness prior on the input lags")."""

from __future__ import annotations

import json
import random

import numpy as np
import pytest

from hil_service.experiment.closed_loop import inverse_run, setpoint_schedule
from hil_service.experiment.family_loop import levels, run_vehicle
from hil_service.pipeline import ChannelPipeline, PipelineSettings
from hil_service.umodel import DynamicUModel
from hil_service.umodel.lag_prior import (
    LAG_SMOOTHING_GAIN,
    NOISE_FLOOR,
    adds_a_slower_mode,
    chain_covariance,
    slowest_mode,
)
from hil_service.umodel.structure import choose_input_lags
from plant_emulator.family import FamilyVehicle, draw_vehicle
from protocols.profiles import DEFAULT_PROFILE, load_profile
from tests.harm_rig import Loop, family_loop, spec

DEFAULT = load_profile(DEFAULT_PROFILE)  # serve's, with no --profile


def _record(noise: float, n: int = 900, seed: int = 0, pole: float = 0.8, delay: int = 1):
    """y = pole·y(t−1) + 0.4·u(t−1−delay) + white noise, the input a random step every 25
    samples: (y[t], the input applied at t − 1), as the horizon test records them."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1.5, 1.5, n // 25 + 1), 25)[:n]
    x = np.zeros(n)
    for t in range(1 + delay, n):
        x[t] = pole * x[t - 1] + 0.4 * u[t - 1 - delay]
    y = x + noise * rng.standard_normal(n)
    return y[1:], u[:-1]


def _identified_lags(y, u, smoothing: float) -> np.ndarray:
    model = DynamicUModel(nb=6, lag_smoothing=smoothing, u_scale=2.0)
    for yt, ut in zip(y, u, strict=True):
        model.step(float(ut), float(yt))
    return np.array([poly[0] for poly in model.dynamics().lag_polys])


def test_the_chain_covariance_is_the_inverse_of_the_prior_information():
    length, p0, weight = 6, 1000.0, 3.0
    d = np.diff(np.eye(length), axis=0)
    information = np.eye(length) / p0 + weight * d.T @ d
    covariance = np.array(chain_covariance(length, p0, weight))
    assert np.allclose(covariance @ information, np.eye(length), atol=1e-9)
    assert np.array_equal(covariance, covariance.T)
    with pytest.raises(ValueError):
        chain_covariance(0, p0, weight)
    with pytest.raises(ValueError):
        DynamicUModel(lag_smoothing=-1.0)


def test_on_a_noisy_record_the_prior_stops_the_input_lags_alternating():
    y, u = _record(noise=0.3)
    plain = _identified_lags(y, u, 0.0)
    smooth = _identified_lags(y, u, 3.0)
    # Neighbouring lags' differences: the record hardly fixes them, the prior ties them.
    assert np.abs(np.diff(smooth)).sum() < 0.5 * np.abs(np.diff(plain)).sum(), (plain, smooth)
    # Their sum (the steady-state gain over the lags) is what the record does fix.
    assert smooth.sum() == pytest.approx(plain.sum(), rel=0.25)


def test_on_a_record_without_noise_the_prior_buys_smooth_lags_with_a_slower_mode():
    # A first-order plant without delay: its four input lags and four output lags can
    # carry a common factor at no cost, and the prior picks the one with smooth lags.
    y, u = _record(noise=0.0, pole=0.5, delay=0)
    fitted = {}
    for weight in (0.0, 3.0):
        model = DynamicUModel(nb=4, lag_smoothing=weight, u_scale=2.0)
        for yt, ut in zip(y, u, strict=True):
            model.step(float(ut), float(yt))
        fitted[weight] = model.dynamics().ar
    assert slowest_mode(fitted[0.0]) == pytest.approx(0.5, abs=1e-3)
    assert slowest_mode(fitted[3.0]) > 0.95
    assert adds_a_slower_mode(fitted[0.0], fitted[3.0]), fitted


def test_the_choice_weighs_the_prior_by_the_record_s_noise_in_any_unit():
    quiet = choose_input_lags(*_record(noise=0.0), u_scale=2.0, smoothing_gain=100.0)
    assert quiet is not None and quiet.smoothing == 0.0
    # Noise whose residual share is below the floor (as the glider's records): none.
    faint = choose_input_lags(*_record(noise=0.02), u_scale=2.0, smoothing_gain=100.0)
    assert faint is not None and 0.0 < faint.residual < NOISE_FLOOR and faint.smoothing == 0.0
    y, u = _record(noise=0.3)
    noisy = choose_input_lags(y, u, u_scale=2.0, smoothing_gain=100.0)
    assert noisy is not None and noisy.smoothing > 0.1
    scaled = choose_input_lags(1000.0 + 1e-3 * y, u, u_scale=2.0, smoothing_gain=100.0)
    assert scaled is not None and scaled.smoothing == pytest.approx(noisy.smoothing, rel=1e-6)
    off = choose_input_lags(y, u, u_scale=2.0)
    assert off is not None and off.smoothing == 0.0 and off.lags == noisy.lags


def test_the_gain_is_a_serve_flag_stored_and_a_log_from_before_replays_without_it():
    import argparse

    from hil_service.cli.serve import add_arguments, settings_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert (
        settings_from_args(parser.parse_args([]), DEFAULT).lag_smoothing_gain == LAG_SMOOTHING_GAIN
    )
    off = settings_from_args(parser.parse_args(["--lag-smoothing-gain", "0"]), DEFAULT)
    assert off.lag_smoothing_gain == 0.0
    data = json.loads(json.dumps(off.to_json()))
    assert PipelineSettings.from_json(data).lag_smoothing_gain == 0.0
    data = PipelineSettings().to_json()
    assert PipelineSettings.from_json(data).lag_smoothing_gain == LAG_SMOOTHING_GAIN
    assert PipelineSettings.from_json(data).rebuild_keeps_record
    del data["lag_smoothing_gain"], data["rebuild_keeps_record"]
    old = PipelineSettings.from_json(data)
    assert old.lag_smoothing_gain == 0.0 and not old.rebuild_keeps_record
    with pytest.raises(ValueError, match="lag_smoothing_gain"):
        PipelineSettings(lag_smoothing_gain=-1.0)


def _family_row(seed: int, vehicle: int, channel: str, settings: PipelineSettings):
    rows, _ = run_vehicle(family_loop(seed), *draw_vehicle(seed, vehicle), settings)
    return next(r for r in rows if r.spec.channel == channel)


@pytest.mark.parametrize(
    ("seed", "vehicle", "without"),
    [
        (11, 2, 2.0),  # a tuning plant: linear, fourth order, delay 2, white noise
        (4, 36, 1.5),  # a targets' plant, not looked at while the prior was chosen
    ],
)
def test_a_noisy_family_plant_whose_lags_alternated_tracks_as_reference_only(
    seed, vehicle, without
):
    # Without the prior the identified lags alternate in sign and the plan chatters.
    no_prior = PipelineSettings(seed=seed, lag_smoothing_gain=0.0)
    plain = _family_row(seed, vehicle, "depth", no_prior)
    smooth = _family_row(seed, vehicle, "depth", PipelineSettings(seed=seed))
    assert plain.reference_ratio > without
    assert smooth.reference_ratio < 1.1
    assert smooth.trips == 0 and smooth.commanded > 1000


def test_a_plant_without_noise_keeps_its_plain_identifier_and_commands():
    # Seed 13's vehicle 8 depth (a tuning plant): first order, delay 3, a dead zone, no
    # disturbance. Even the tiny weight its residual share (8·10⁻⁶) would give buys smooth
    # lags with an unstable common factor (a mode of 4.4, never qualified); below the noise
    # floor it gets none and commands with the plain identifier.
    settings = PipelineSettings(seed=13)
    row = _family_row(13, 8, "depth", settings)
    assert row.horizon_passed and row.commanded > 1000 and row.reference_ratio < 1.0
    depth, pitch = draw_vehicle(13, 8)
    loop = family_loop(13)
    schedule = setpoint_schedule(loop, {"depth": levels(depth), "pitch": levels(pitch)})
    health = inverse_run(loop, FamilyVehicle(depth, pitch, 13), schedule, settings).identifier
    choice = health["depth"]["input_lag_choice"]
    assert 0.0 < choice["residual"] < NOISE_FLOOR and choice["lag_smoothing"] == 0.0, choice


def test_an_identifier_rebuilt_with_other_lags_is_judged_on_its_record():
    # Seed 11's vehicle 12 pitch (first order, delay 5, no noise), asked to command after
    # 400 samples, chooses more input lags then; the rebuilt identifier passes the horizon
    # test on the record it was rebuilt from and commands from the first controlled sample,
    # where a record started afresh (as a log from before replays) must refill first, at
    # neutral meanwhile.
    loop = family_loop(11, identify=400)
    rows = {}
    for kept in (True, False):
        settings = PipelineSettings(seed=11, rebuild_keeps_record=kept)
        rows[kept] = run_vehicle(loop, *draw_vehicle(11, 12), settings)[0][1]
    assert rows[True].commanded == 1600 and rows[True].reference_ratio < 1.0
    assert rows[False].commanded < 1600 and rows[False].reference_ratio > 1.1


def _observed_channel(gain: float) -> ChannelPipeline:
    """A channel fed 900 samples of y = 0.5·y(t−1) + 0.4·u(t−1) + white noise (0.03) under
    a step every 25 samples: its input lags are chosen at 600."""
    rng = np.random.default_rng(0)
    steps = rng.uniform(-1.5, 1.5, 40)
    channel = ChannelPipeline("depth", PipelineSettings(lag_smoothing_gain=gain), 0)
    x = 0.0
    for k in range(900):
        u = float(steps[k // 25])
        channel.observe(float(k), x + 0.03 * float(rng.standard_normal()), u)
        x = 0.5 * x + 0.4 * u
    return channel


def test_the_channel_refuses_a_smoothed_identifier_with_a_slower_mode():
    # The record's noise is just above the floor (residual share 0.0014). At a gain of 30
    # the smoothed fit keeps the plant's mode and is taken; at the default 100 and above
    # its smooth lags come with a slower mode, and the channel keeps the plain identifier.
    taken = _observed_channel(30.0)
    assert taken.lag_choice is not None and not taken.lag_choice.smoothing_rejected
    assert taken.lag_choice.smoothing > 0.0
    assert taken.model.config()["lag_smoothing"] == taken.lag_choice.smoothing
    refused = _observed_channel(300.0)
    assert refused.lag_choice is not None and refused.lag_choice.smoothing_rejected
    assert refused.lag_choice.as_json()["lag_smoothing"] == 0.0
    assert refused.model.config()["lag_smoothing"] == 0.0
    assert slowest_mode(refused.model.dynamics().ar) < 0.5


def test_a_channel_commanding_when_its_lags_are_chosen_keeps_its_identifier():
    # A noisy plant whose record restarts (a reboot) while the channel commands: it
    # qualifies again and commands before its record is long enough to choose the lags,
    # so the choice comes under way. Rebuilding the identifier for the prior alone would
    # stop the channel for a verdict on a record the loop has held near its setpoint; the
    # prior is withheld and the channel commands on.
    rng = random.Random(5)
    loop = Loop(spec(), spec(), disturbance=lambda k: 0.1 * rng.gauss(0.0, 1.0))
    loop.run(60, {"depth": None, "pitch": None}, enabled=False)
    loop.run(150, {"depth": 15.5, "pitch": None})
    loop.restart_clock()
    loop.run(1200, {"depth": 15.5, "pitch": None})
    channel = loop.pipeline.channels["depth"]
    choice = channel.lag_choice
    assert choice is not None and choice.residual >= NOISE_FLOOR
    assert choice.smoothing_withheld and choice.smoothing == 0.0
    assert channel.config()["lag_smoothing"] == 0.0
    modes = [mode.split("/")[0] for mode in loop.modes]
    commanded = [k for k, mode in enumerate(modes) if mode not in ("", "-", "safe")]
    idle = [k for k in range(commanded[0], len(modes)) if modes[k] in ("", "-", "safe")]
    # Once commanding, the channel stops at most for one stretch, an early trip's
    # hold-off before the choice (none at all on this seed), never at the choice.
    trips = [e for e in loop.events if e["channel"] == "depth" and e["event"] == "trip"]
    assert len(trips) <= 1
    assert idle == (list(range(idle[0], idle[0] + len(idle))) if trips else []), idle
    assert len(commanded) > 1000
