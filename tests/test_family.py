"""The do-no-harm benchmark's family (``plant_emulator/family.py``) and its closed loop
(``hil_service/experiment/family_loop.py``)."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from hil_service.experiment.closed_loop import ClosedLoopSettings
from hil_service.experiment.family_loop import levels, run_vehicle
from plant_emulator.family import FamilyVehicle, InputMap, draw_family, draw_vehicle
from tests.harm_rig import family_loop


def test_the_family_is_seeded_and_a_plant_does_not_depend_on_the_family_size():
    assert draw_family(3, 40) == draw_family(3, 40)
    assert draw_family(3, 40)[:5] == draw_family(3, 10)
    assert draw_family(3, 10) != draw_family(4, 10)
    assert draw_vehicle(3, 7) == draw_family(3, 16)[7]


def test_200_plants_cover_what_the_benchmark_promises():
    plants = [p for pair in draw_family(0, 200) for p in pair]
    assert len(plants) == 200
    assert {p.order for p in plants} == {1, 2, 3, 4}
    assert {p.delay for p in plants} == {0, 1, 2, 3, 4, 5}
    assert {p.kind for p in plants} == {"hammerstein", "wiener", "linear"}
    assert {p.disturbance for p in plants} == {"none", "white", "coloured", "periodic"}
    assert any(p.zero is not None for p in plants) and any(p.integrator for p in plants)
    hammerstein = [p for p in plants if p.kind == "hammerstein"]
    # Asymmetric saturation: below the unsaturated map's full output, unequal sides.
    full = [InputMap(p.input_map.dead_zone, p.input_map.cubic)(2.0) for p in hammerstein]
    assert all(p.input_map.upper < f for p, f in zip(hammerstein, full, strict=True))
    unequal = [abs(p.input_map.upper + p.input_map.lower) for p in hammerstein]
    assert max(u / f for u, f in zip(unequal, full, strict=True)) > 0.1
    scales = [math.log10(p.scale) for p in plants]
    assert max(scales) - min(scales) > 5.0  # six decades drawn, > 5 seen in 200
    shares = [p.disturbance_level / p.authority() for p in plants if p.disturbance != "none"]
    assert max(shares) > 0.7  # disturbances up to the control authority


def test_a_plant_answers_after_its_delay_through_its_maps():
    depth, pitch = next(
        (d, p) for d, p in draw_family(1, 200) if d.delay >= 2 and d.disturbance == "none"
    )
    vehicle = FamilyVehicle(depth, pitch)
    outputs = [vehicle.step(1.0, 0.0).depth for _ in range(depth.delay + depth.order + 3)]
    # The position moves at the first step; the output answers after the delay and the
    # plant's relative degree (the leading zeros of its numerator), not a sample sooner.
    relative_degree = int(np.argmax(np.abs(depth.num()) > 0))
    first = next(k for k, y in enumerate(outputs) if y != outputs[0])
    assert first == depth.delay + relative_degree
    for spec in (depth, pitch):
        ws = np.linspace(-3.0, 3.0, 61) * spec.authority()
        mapped = [spec.wiener_map(float(w)) for w in ws]
        assert all(b > a for a, b in itertools.pairwise(mapped))  # monotone
        assert spec.wiener_inverse(spec.wiener_map(0.37)) == pytest_approx(0.37)


def pytest_approx(value: float):
    import pytest

    return pytest.approx(value, rel=1e-9, abs=1e-12)


def test_a_vehicle_of_the_family_runs_the_three_loops():
    depth, pitch = draw_vehicle(0, 0)
    settings = ClosedLoopSettings(
        scenario="family", samples=900, identify=400, step_every=250, oracle=True,
        neutral_after_identify=True,
    )  # fmt: skip
    rows, failures = run_vehicle(settings, depth, pitch)
    assert [r.spec.channel for r in rows] == ["depth", "pitch"] and failures == 0
    assert [r.name() for r in rows] == ["seed 0 vehicle 0 depth", "seed 0 vehicle 0 pitch"]
    assert dataclasses.replace(rows[0], seed=None).name() == "seed ? vehicle 0 depth"
    for row in rows:
        assert math.isfinite(row.inverse_iae) and row.reference_iae > 0
        assert row.oracle_iae is None or row.oracle_iae > 0
        assert row.commanded == 0 or row.horizon_passed
        reachable = levels(row.spec)
        assert len(set(reachable)) == len(reachable)


def test_the_phases_add_up_and_a_released_channel_gets_the_vehicles_own_control():
    """The IAE split by phase sums to the run's IAE. With ``released="vehicle"`` a channel
    the service does not command gets the vehicle's own controller (reference-only): a
    channel that never commands then has reference-only's IAE exactly."""
    settings = ClosedLoopSettings(
        scenario="family", samples=900, identify=400, step_every=250,
        neutral_after_identify=True,
    )  # fmt: skip
    checked = 0
    for seed, vehicle in ((0, 0), (0, 1), (1, 2)):
        depth, pitch = draw_vehicle(seed, vehicle)
        held, _ = run_vehicle(settings, depth, pitch)
        released, _ = run_vehicle(settings, depth, pitch, released="vehicle")
        for row in (*held, *released):
            assert sum(row.phases.values()) == pytest_approx(row.inverse_iae)
        for row in released:
            if row.commanded == 0 and row.trips == 0:
                assert row.inverse_iae == pytest_approx(row.reference_iae)
                checked += 1
    assert checked >= 2, "no channel of these vehicles stayed uncommanded"
    try:
        run_vehicle(settings, depth, pitch, released="sometimes")
    except ValueError as error:
        assert "released must be one of" in str(error)
    else:
        raise AssertionError("an unknown released semantics was accepted")


def test_white_output_noise_is_averaged_not_chased():
    """A plant whose output disturbance is white: nothing can predict it, so reacting to it
    only adds the estimate's noise to the output's (E|c + d| ≥ E|d|). The pipeline's IAE
    stays within 2.5 % of reference-only's (the true plant's static inverse, no feedback);
    a disturbance estimate at the horizon's pace alone gave 1.07 and 1.04 here."""

    depth, pitch = draw_vehicle(0, 0)
    plain = {
        "order": 1, "poles": ((0.3, 0.0),), "integrator": False, "zero": None,
        "dc_gain": 1.0, "delay": 0, "kind": "linear", "input_map": InputMap(), "wiener": 0.0,
        "disturbance": "white", "disturbance_level": 0.2, "disturbance_param": 0.0,
        "scale": 1.0, "offset": 0.0, "period": 0.1,
    }  # fmt: skip
    depth = dataclasses.replace(depth, **plain)
    pitch = dataclasses.replace(pitch, **{**plain, "poles": ((0.6, 0.0),), "delay": 1})
    settings = ClosedLoopSettings(
        scenario="family", samples=2000, identify=800, step_every=300,
        neutral_after_identify=True,
    )  # fmt: skip
    rows, _ = run_vehicle(settings, depth, pitch)
    for row in rows:
        assert row.commanded > 1000 and row.trips == 0
        assert row.inverse_iae <= 1.025 * row.reference_iae, (row.spec.channel, row.reference_ratio)


def test_input_lags_that_cover_the_delay_bring_a_delayed_plant_back_to_reference_only():
    # Seed 11's vehicle 12 pitch: linear, first order (pole 0.506), an input delay of 5
    # samples, no disturbance. Four input lags cannot hold the delay (the loop ends at
    # 1.01 × reference-only); by default (``--input-lags auto``) the pipeline chooses more
    # from its record and reports the choice in health (0.96 ×), and a user who knows the
    # delay gives them.
    from hil_service.experiment.closed_loop import inverse_run, setpoint_schedule
    from hil_service.pipeline import PipelineSettings
    from plant_emulator.models import CHANNELS

    depth, pitch = draw_vehicle(11, 12)
    assert (pitch.delay, pitch.disturbance, pitch.order) == (5, "none", 1)
    settings = family_loop(11)
    auto = PipelineSettings(seed=11)
    four_lags = PipelineSettings(seed=11).with_input_lags(4)
    four = run_vehicle(settings, depth, pitch, four_lags)[0][1].reference_ratio
    chosen = run_vehicle(settings, depth, pitch)[0][1].reference_ratio
    given = run_vehicle(settings, depth, pitch, PipelineSettings(seed=11).with_input_lags(7))
    assert chosen < 1.0 and given[0][1].reference_ratio < 1.0 and chosen < four, (four, chosen)

    specs = {"depth": depth, "pitch": pitch}
    schedule = setpoint_schedule(settings, {ch: levels(specs[ch]) for ch in CHANNELS})
    health = inverse_run(settings, FamilyVehicle(depth, pitch, 11), schedule, auto).identifier
    assert health["pitch"]["input_lags"] in (6, 8), health["pitch"]["input_lag_choice"]
    fits = health["pitch"]["input_lag_choice"]["fits"]
    assert fits["4"] < fits[str(health["pitch"]["input_lags"])]


def test_an_identifier_with_an_unstable_ar_part_is_rebuilt_with_fewer_output_lags():
    # Seed 13's vehicle 9 depth: Hammerstein, second order (poles 0.41 ± 0.23j), a delay of
    # one sample, a dead zone of 0.14, no disturbance. With its four output lags the
    # identifier's AR part carries a root of modulus 4.1 (a common factor of an
    # over-parameterised fit that the dead zone tips): its steps never settle, the horizon
    # test is never passed and the channel sits at neutral, 26 × reference-only. The
    # choice of the lags rebuilds it with fewer output lags, stable, and it commands.
    from hil_service.experiment.closed_loop import inverse_run, setpoint_schedule
    from hil_service.pipeline import PipelineSettings
    from plant_emulator.models import CHANNELS

    depth, pitch = draw_vehicle(13, 9)
    assert (depth.kind, depth.order, depth.delay, depth.disturbance) == (
        "hammerstein", 2, 1, "none",
    )  # fmt: skip
    settings = family_loop(13)
    four = PipelineSettings(seed=13, model_options={"depth": {"na": 4}, "pitch": {}})
    given = run_vehicle(settings, depth, pitch, four)[0][0]
    assert not given.horizon_passed and given.reference_ratio > 5.0  # the options are kept

    specs = {"depth": depth, "pitch": pitch}
    schedule = setpoint_schedule(settings, {ch: levels(specs[ch]) for ch in CHANNELS})
    run = inverse_run(settings, FamilyVehicle(depth, pitch, 13), schedule, None)
    choice = run.identifier["depth"]["input_lag_choice"]
    assert choice["output_lags"] is not None and choice["output_lags"] < 4, choice
    assert run.supervision["depth"]["horizon_passed"]
    assert run.supervision["depth"]["commanded"] > 1000
    assert run.identifier["pitch"]["input_lag_choice"]["output_lags"] is None  # stable: kept
    rows = run_vehicle(settings, depth, pitch)[0]
    assert rows[0].reference_ratio < 1.2, rows[0].reference_ratio


@pytest.mark.parametrize(
    ("seed", "vehicle", "channel", "kind"),
    [(3, 26, "depth", "wiener"), (3, 14, "pitch", "linear")],
)
def test_the_input_map_is_the_models_steady_state_only_where_that_rises_over_more(
    seed: int, vehicle: int, channel: str, kind: str
) -> None:
    # Seed 3's vehicle 26 depth: a Wiener plant (first order, pole 0.84, delay 3, no
    # disturbance). Its U-model's lags differ in shape, and the best rank-one fit of their
    # coefficients falls over (−1, 1): planned on it, the input goes to +2 at the first
    # setpoint, the supervisor trips on the held saturation and the plant ends at 4.5 ×
    # reference-only. The model's steady-state map rises over more of the range and is
    # taken. Seed 3's vehicle 14 pitch: a linear plant (poles 0.31, 0.32) under a periodic
    # disturbance, whose model's AR part is near an integrator: its lags nearly cancel at
    # steady state, and planned on their sum (their noise) throughout it ends at 5.8 ×
    # reference-only; the rule keeps the rank-one map there.
    depth, pitch = draw_vehicle(seed, vehicle)
    spec = depth if channel == "depth" else pitch
    assert spec.kind == kind
    settings = family_loop(seed)
    row = next(r for r in run_vehicle(settings, depth, pitch)[0] if r.spec.channel == channel)
    assert row.trips == 0
    assert row.reference_ratio < 1.1, row.reference_ratio


def test_a_channel_never_commanded_sits_at_neutral_after_the_excitation():
    """The family's "hold" semantics: the excitation ends at the neutral input, reached
    through the actuator's rate limit by the first controlled sample, so a channel the
    service never commands stays at neutral, not wherever the excitation had got to."""
    from hil_service.experiment.closed_loop import _drive, setpoint_schedule
    from plant_emulator.excitation import build_channel_excitations
    from plant_emulator.family import RATE_LIMIT
    from plant_emulator.models import CHANNELS

    depth, pitch = draw_vehicle(0, 0)
    specs = {"depth": depth, "pitch": pitch}
    settings = ClosedLoopSettings(
        scenario="family", samples=700, identify=400, step_every=250,
        neutral_after_identify=True,
    )  # fmt: skip
    excitation = build_channel_excitations(settings.excitation, settings.seed)
    last = [abs(excitation[ch].value(settings.identify - 1)) for ch in CHANNELS]
    assert max(last) > RATE_LIMIT, "the excitation ends within one step of neutral"
    schedule = setpoint_schedule(settings, {ch: levels(specs[ch]) for ch in CHANNELS})
    trace = _drive(
        settings, FamilyVehicle(depth, pitch), schedule, lambda k, s: (math.nan, math.nan)
    )
    for ch in CHANNELS:
        assert np.all(trace.u[ch][settings.identify :] == 0.0), ch
        assert np.any(trace.u[ch][: settings.identify] != 0.0), ch


def test_dropping_a_disturbance_mode_the_record_contradicts_takes_its_plant_below_reference_only():
    # Seed 0's vehicle 26 pitch: Hammerstein, first order, delay 3, a periodic disturbance
    # (period 398 samples). The identifier fits the disturbance with a pole near 0.9995
    # beside a zero near 1.0018: the response arrives with the plant and then drifts to
    # the other sign, and a plan over the drift (1,000 samples) drives the input to the
    # wrong limit: 3.2 × reference-only. Once the record holds inputs held long enough to
    # show no such drift, the horizon is a few arrivals of the plant's own response.
    from hil_service.pipeline import ControlSettings, PipelineSettings

    depth, pitch = draw_vehicle(0, 26)
    assert (pitch.disturbance, pitch.order, pitch.delay) == ("periodic", 1, 3)
    settings = family_loop(0)
    kept = PipelineSettings(seed=0, control=ControlSettings(cancel_near_pairs=False))
    drifting = run_vehicle(settings, depth, pitch, kept)[0][1].reference_ratio
    cancelled = run_vehicle(settings, depth, pitch)[0][1].reference_ratio
    assert drifting > 2.0, drifting
    assert cancelled < 1.0, cancelled


def test_the_horizon_cap_helps_a_plant_whose_model_holds_a_periodic_disturbance():
    # Seed 2's vehicle 24 depth: linear, second order, no delay, a periodic disturbance of
    # 0.69 of the authority. The identifier puts the disturbance's oscillation in its AR
    # part, and the horizon is the ring's length, 1,000 samples, at most of the plan's
    # 40 derivations: 2.06 × reference-only. Where the response arrives within a few
    # samples the cap (four arrival times) plans over a few tens of samples instead (823 →
    # 20 at one derivation): 1.89 ×.
    from hil_service.pipeline import ControlSettings, PipelineSettings

    depth, pitch = draw_vehicle(2, 24)
    assert (depth.disturbance, depth.order, depth.delay) == ("periodic", 2, 0)
    settings = family_loop(2)
    uncapped = PipelineSettings(seed=2, control=ControlSettings(horizon_arrivals=0.0))
    stretched = run_vehicle(settings, depth, pitch, uncapped)[0][0].reference_ratio
    capped = run_vehicle(settings, depth, pitch)[0][0].reference_ratio
    assert capped < 0.95 * stretched, (capped, stretched)
