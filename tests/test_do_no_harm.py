"""Do no harm (docs/control.md): the horizon test keeps a model that cannot predict over
its horizon from commanding, the supervisor stops a loop that a plant change has made
harmful and sends the safe input, a vehicle restart re-qualifies the model, and the
figures do not depend on the units of the output or the input. In process, on the
plants of ``tests/harm_rig.py``."""

from __future__ import annotations

import dataclasses
import math

import pytest

from hil_service.pipeline import PipelineSettings
from plant_emulator.actuator import PumpNonlinearity
from tests.harm_rig import Loop, spec

IDENTIFY = 1500
CHANGE = 1900  # the plant changes here, 400 samples into control
SETPOINT = 15.8  # trim 15, 0.8 above


def _tripped_loop(change, settings: PipelineSettings | None = None) -> Loop:
    loop = Loop(spec(), spec(), change=change, settings=settings or PipelineSettings())
    loop.run(IDENTIFY, {"depth": None, "pitch": None})
    loop.run(2000, {"depth": SETPOINT, "pitch": None})
    return loop


def _first_trip(loop: Loop) -> int:
    return next(k for k, m in enumerate(loop.modes) if m.startswith("safe"))


@pytest.mark.parametrize(
    "change",
    [lambda k, u: -u if k >= CHANGE else u, lambda k, u: 5.0 * u if k >= CHANGE else u],
    ids=["sign-flip", "gain-x5"],
)
def test_a_plant_change_trips_the_supervisor_and_the_safe_input_holds(change):
    loop = _tripped_loop(change)
    depth = loop.pipeline.channels["depth"]
    window = depth.supervisor.window
    trip = _first_trip(loop)
    # Clean control before the change, a trip within two supervised segments after it
    # (the change can fall anywhere in a segment; the next one is judged whole).
    assert all(m.startswith(("newton", "fallback")) for m in loop.modes[IDENTIFY + 1 : CHANGE])
    assert CHANGE < trip <= CHANGE + 2 * window, (trip, window)
    assert loop.reasons[trip].startswith("supervisor: ") and loop.reasons[trip].endswith("(depth)")
    # The safe input (neutral by default) is what the vehicle applies from then on.
    assert depth.safe_u == 0.0
    rearm = next(
        (k for k, m in enumerate(loop.modes) if k > trip and not m.startswith("safe")), None
    )
    held = loop.u[trip + 6 : rearm]  # the actuator's rate limit: at 0 within 4 samples
    trips = [e for e in loop.events if e["event"] == "trip"]
    # The hold-off counts in the windows of the trip (each arming derives its own).
    assert len(held) >= 3 * trips[0]["window"]
    assert all(u == 0.0 for u in held)
    assert trips and trips[0]["channel"] == "depth" and trips[0]["safe_input"] == 0.0
    assert depth.health()["supervisor"]["trips"] == len(trips) >= 1
    # No worse at the end than when control was enabled (the target: 1.2 times).
    enabled_error = abs(loop.y[IDENTIFY] - SETPOINT)
    end_error = sum(abs(y - SETPOINT) for y in loop.y[-100:]) / 100
    assert end_error <= 1.2 * enabled_error, (end_error, enabled_error)


SLOW_CHANGE = 2900  # 400 samples into control on the slow plant below


@pytest.mark.parametrize(
    "change",
    [
        lambda k, u: -u if k >= SLOW_CHANGE else u,
        lambda k, u: 5.0 * u if k >= SLOW_CHANGE else u,
    ],
    ids=["sign-flip", "gain-x5"],
)
def test_the_supervisor_trips_when_an_asynchronous_sampler_repeats_readings(change):
    # A slow plant (supervised windows of 100-175 samples) read by an asynchronous
    # sampler: 6.5 % of the readings are served a tick early and again on the next tick
    # (about the ArduSub profile's share), so repeats fall inside every window. The runs
    # the supervisor judges by go on across them; a loop that restarted its judgement at
    # each repeat would never finish a window and command into the changed plant.
    identify = 2500
    loop = Loop(spec(poles=(0.98, 0.95)), spec(), change=change, repeat_share=0.065)
    loop.run(identify, {"depth": None, "pitch": None})
    loop.run(3000, {"depth": SETPOINT, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    assert depth.repeats > 100
    assert all(m.startswith(("newton", "fallback")) for m in loop.modes[identify:SLOW_CHANGE])
    trip = _first_trip(loop)
    assert SLOW_CHANGE < trip <= SLOW_CHANGE + 2 * depth.supervisor.window, trip
    assert loop.reasons[trip].startswith("supervisor: ")
    enabled_error = abs(loop.y[identify] - SETPOINT)
    end_error = sum(abs(y - SETPOINT) for y in loop.y[-100:]) / 100
    assert end_error <= 1.2 * enabled_error, (end_error, enabled_error)


def test_trips_and_rearms_are_rate_limited():
    """After a trip the channel re-arms only once its hold-off has passed and its model
    passed the horizon test on data after the trip, in which the input moved (here its
    profile allows probing: a tripped channel probes once its hold-off has passed); the
    hold-off doubles with each."""
    settings = PipelineSettings()
    probing = settings.replace(control=dataclasses.replace(settings.control, probe=0.25))
    loop = _tripped_loop(lambda k, u: -u if k >= CHANGE else u, probing)
    loop.run(6000, {"depth": SETPOINT, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    times = [(e["event"], e["time_boot_ms"] // 100) for e in loop.events]  # samples (0.1 s)
    trips = [t for kind, t in times if kind == "trip"]
    assert trips, times
    assert any(kind == "rearm" for kind, _ in times), times
    for event in loop.events:
        if event["event"] == "rearm":
            t = event["time_boot_ms"] // 100
            previous_trip = max(x for x in trips if x < t)
            n = trips.index(previous_trip) + 1
            h = event["horizon"]  # the hold-off is counted in the horizon at the re-arm
            assert event["holdoff"] == 4 * max(h, min(max(h, 10), 200)) * (1 << (n - 1))
            assert t - previous_trip >= event["holdoff"] - 1, times
    # Three trips at most, then off until the operator disables and enables control.
    assert len(trips) <= 3, times
    if len(trips) == 3:
        assert depth.supervisor.latched
        assert "off until control is re-enabled" in loop.reasons[-1]
        loop.run(1, {"depth": SETPOINT, "pitch": None}, enabled=False)
        assert not depth.supervisor.latched


def _issue_vehicle(settings: PipelineSettings) -> Loop:
    """The issue's vehicle: 100 Hz, second order, a dead zone and a cubic pump, a periodic
    disturbance as large as the control authority."""
    authority = PumpNonlinearity(dead_zone=0.3, cubic=0.1)(2.0)

    def disturbance(k: int) -> float:
        return authority * math.sin(2.0 * math.pi * k / 200)

    return Loop(
        spec((0.8, 0.8), period=0.01, dead_zone=0.3, cubic=0.1),
        spec(period=0.01),
        settings=settings,
        disturbance=disturbance,
    )


def test_a_model_that_does_not_predict_over_the_horizon_does_not_command():
    """The issue's vehicle, identified as the issue found it (a cubic input map, no dead
    zone chosen): one-step skill is excellent; over the horizon the model is worse than
    holding the output, and the channel does not command while the horizon test says so
    (identification goes on, on the vehicle's excitation). When a later model passes it
    and the loop then does worse than not commanding, the supervisor trips (on this plant,
    "saturation held against the predicted response", about 1,000 samples after its first
    command; the neutral-input comparison, whose counterfactual rests on the model's input
    response, does not see it)."""
    loop = _issue_vehicle(PipelineSettings(choose_dead_zone=False))
    loop.run(IDENTIFY, {"depth": None, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    assert depth.stats.recent_skill() > 0.9  # the one-step skill the issue saw
    health = depth.health()
    assert health["horizon_qualified"] is False and health["horizon_fit"] < 50.0
    loop.run(2500, {"depth": 15.5, "pitch": None})
    first = next(k for k, m in enumerate(loop.modes) if m)
    assert first > IDENTIFY + 50, "commanded on the verdict of enable"
    before = loop.reasons[IDENTIFY:first]
    assert all(r.startswith("model does not predict over the horizon (depth: ") for r in before)
    assert all(m == "" for m in loop.modes[IDENTIFY:first])
    assert depth.health()["samples"] >= IDENTIFY + 2490  # identification goes on
    trips = [e for e in loop.events if e["event"] == "trip"]
    assert trips, "the supervisor never tripped"
    assert trips[0]["time_boot_ms"] // 10 - first <= 2 * depth.supervisor.compare_window
    enabled_error = abs(loop.y[IDENTIFY] - 15.5)
    end_error = sum(abs(y - 15.5) for y in loop.y[-300:]) / 300
    assert end_error <= 1.2 * enabled_error, (end_error, enabled_error)


def test_the_issue_vehicle_with_its_dead_zone_found_trips_and_does_not_rearm_at_rest():
    """By default the dead zone is found (0.3, exactly) and the model with it predicts over
    the horizon: the channel commands, the loop still does worse than not commanding (the
    disturbance is as large as the authority), and the supervisor trips. At the neutral
    input the record since the trip shows no input moving, so the channel does not re-arm
    on it; the error at the end is no worse than 1.2 × the error at enable."""
    loop = _issue_vehicle(PipelineSettings())
    loop.run(IDENTIFY, {"depth": None, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    assert depth.dead_zone == pytest.approx(0.3)
    loop.run(2500, {"depth": 15.5, "pitch": None})
    first = next(k for k, m in enumerate(loop.modes) if m)
    trips = [e for e in loop.events if e["event"] == "trip"]
    assert trips, "the supervisor never tripped"
    assert trips[0]["time_boot_ms"] // 10 - first <= 2 * depth.supervisor.compare_window
    assert not [e for e in loop.events if e["event"] == "rearm"], loop.events
    trip = trips[0]["time_boot_ms"] // 10
    assert all(m.startswith("safe") for m in loop.modes[trip + 1 :])
    enabled_error = abs(loop.y[IDENTIFY] - 15.5)
    end_error = sum(abs(y - 15.5) for y in loop.y[-300:]) / 300
    assert end_error <= 1.2 * enabled_error, (end_error, enabled_error)


def test_a_restart_while_commanding_stops_until_the_horizon_test_passes_again():
    loop = Loop(spec(), spec())
    loop.run(IDENTIFY, {"depth": None, "pitch": None})
    loop.run(300, {"depth": SETPOINT, "pitch": None})
    assert loop.modes[-1].startswith(("newton", "fallback"))
    loop.restart_clock()
    loop.run(600, {"depth": SETPOINT, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    after = loop.modes[IDENTIFY + 300 :]
    resumed = next(i for i, m in enumerate(after) if m)
    # Not before the model has a burn-in's worth of post-restart data over its horizon.
    assert resumed >= min(depth.settings.burn_in, depth.controller.horizon), resumed
    assert "model does not predict over the horizon (depth" in loop.reasons[IDENTIFY + 320]
    assert loop.pipeline.gaps.restarts == 1 and depth.restarts == 1
    assert after[-1].startswith(("newton", "fallback"))


def _iae(output_scale: float, offset: float, input_scale: float) -> tuple[float, float]:
    settings = PipelineSettings()
    control = dataclasses.replace(
        settings.control,
        u_limit=settings.control.u_limit * input_scale,
        rate_limit=settings.control.rate_limit * input_scale,
    )
    loop = Loop(
        spec((0.9, 0.6), dc_gain=1.7, dead_zone=0.1, cubic=0.05),
        spec(),
        settings=settings.replace(control=control),
        scale=output_scale,
        offset=offset,
        input_scale=input_scale,
    )
    loop.run(IDENTIFY, {"depth": None, "pitch": None})
    target = offset + 0.7 * output_scale
    loop.run(1000, {"depth": target, "pitch": None})
    loop.run(1000, {"depth": offset - 0.5 * output_scale, "pitch": None})
    y = loop.y[IDENTIFY:]
    targets = [target] * 1000 + [offset - 0.5 * output_scale] * 1000
    iae = sum(abs(a - b) for a, b in zip(y, targets, strict=True)) / output_scale
    reference = sum(abs(b - y[0]) for b in targets) / output_scale  # holding the output
    return iae, reference


@pytest.mark.parametrize(
    ("output_scale", "offset", "input_scale"),
    [
        (1e3, 1000.0, 1.0),
        (1.0, 1000.0, 1e-3),
        (1.0, 15.0, 1e3),
        (1e3, 15.0, 1e-3),
        (1e-3, 15.0, 1.0),
        (1e-3, 1000.0, 1e3),
        (1e-3, 0.0, 1.0),
    ],
)
def test_the_figures_do_not_depend_on_units(output_scale, offset, input_scale):
    base, base_ref = _iae(1.0, 15.0, 1.0)
    assert base < 0.2 * base_ref  # it controls
    scaled, scaled_ref = _iae(output_scale, offset, input_scale)
    assert scaled / scaled_ref == pytest.approx(base / base_ref, rel=0.01)


def test_worse_than_not_commanding_compares_with_what_the_safe_input_gives():
    """The trip's counterfactual is the channel's alternative: the neutral input, or where a
    trip releases the channel to the vehicle's own controller, the input at which that
    controller holds the setpoint (by the model: its steady state there is the setpoint)."""
    for safe in ("neutral", "release"):
        settings = PipelineSettings()
        settings = settings.replace(control=dataclasses.replace(settings.control, safe_input=safe))
        loop = Loop(spec(dc_gain=2.0), spec(), settings)
        loop.run(800, {"depth": None, "pitch": None}, enabled=False)
        depth = loop.pipeline.channels["depth"]
        dyn = depth.model.dynamics()
        u = depth._counterfactual_input(dyn, 16.0)
        if safe == "neutral":
            assert u == 0.0
            continue
        gain = 1.0 - sum(dyn.ar)
        steady = dyn.bias + sum(dyn.lag_value(L, u) for L in range(1, len(dyn.lag_polys) + 1))
        assert steady / gain == pytest.approx(16.0, abs=1e-6)
        assert u == pytest.approx(0.5, abs=0.05)  # the plant's: 15 + 2·u = 16
