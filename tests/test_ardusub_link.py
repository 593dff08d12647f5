"""The service-side pieces (companion manners, periodic sampling, DO_SET_SERVO commands)
against `glider-hil emulate --profile ardusub` on loopback UDP, across a µs-clock wrap."""

from __future__ import annotations

import itertools

from hil_service.cli.processes import last_json
from hil_service.pipeline import PipelineSettings
from protocols.mavlink_io import dialect
from protocols.profiles import load_profile
from tests.ardusub_client import ArduSubClient

SPEED = 5.0
PERIOD = 0.1
US32_SPAN = (1 << 32) / 1e6
PROFILE = load_profile("ardusub")


def test_companion_samples_ardusub_streams_and_commands_servos_across_a_wrap(processes):
    client = ArduSubClient(PROFILE, PERIOD)
    peer = client.peer
    emulator = processes.start(
        "emulate",
        "--profile",
        "ardusub",
        "--connect",
        f"udpout:127.0.0.1:{client.port}",
        "--speed",
        str(SPEED),
        "--period",
        str(PERIOD),
        "--uptime",
        f"{US32_SPAN - 20:.3f}",
        "--duration",
        "600",
        "--excitation",
        "prbs",
        "--seed",
        "2",
        "--command-timeout",
        "1000",
    )
    try:
        # Until every stream runs at the sample rate (the vehicle accepted each request).
        client.run(30.0, lambda: set(client.companion.states.values()) == {"accepted"})
        assert set(client.companion.states.values()) == {"accepted"}
        assert client.companion.counters.acks == {"MAV_RESULT_ACCEPTED": 4}
        # Then 40 simulated seconds, across the wrap of SERVO_OUTPUT_RAW's µs clock.
        client.run(0.5)  # the new rates take effect within a message interval
        first_sample, first_usec = len(client.samples), len(client.servo_usec)
        for command in PROFILE.command_messages(1.0, -0.5, target_system=1):
            peer.send(command)
        client.run(40.0 / SPEED)
        samples = client.samples[first_sample:]
        usec = client.servo_usec[first_usec:]
        assert any(b < a for a, b in itertools.pairwise(usec)), "no µs wrap seen"
        expected = round((samples[-1].t - samples[0].t) / PERIOD) + 1
        ratio = len(samples) / expected
        print(
            f"\nardusub streams: {len(samples)} samples formed of {expected} expected "
            f"({100 * ratio:.1f} %), counters {client.assembler.counters.as_dict()}"
        )
        assert ratio >= 0.95
        times = [s.t for s in samples]
        assert all(b > a for a, b in itertools.pairwise(times))
        # DO_SET_SERVO, one per channel, accepted; the outputs read back what was commanded
        # (1700 µs = 1.0 model units, 1400 µs = −0.5) after the actuator's rate limit.
        servo_acks = [a for a in client.acks if a.command == dialect.MAV_CMD_DO_SET_SERVO]
        assert [a.result for a in servo_acks] == [dialect.MAV_RESULT_ACCEPTED] * 2
        assert abs(samples[-1].u_depth - 1.0) < 0.01 and abs(samples[-1].u_pitch + 0.5) < 0.01
        # The vehicle saw the companion's heartbeats, as an onboard controller's.
        out, _ = processes.stop(emulator)
        heartbeats = last_json(out, "emulator")["gcs"]["heartbeats"]
        assert heartbeats.get("MAV_TYPE_ONBOARD_CONTROLLER", 0) >= 5
    finally:
        client.close()


def test_identifies_and_controls_depth_and_pitch_through_do_set_servo(processes):
    """Identification on ArduSub-style streams sampled every 0.1 s, then inverse control
    of a depth and pitch step through DO_SET_SERVO, across a µs-clock wrap."""
    speed, identify, control = 10.0, 60.0, 150.0  # simulated s
    # Burn-in: half the identification phase (a repeated reading refills the history
    # without training, ~30 % of the samples at this rate on a loaded machine).
    client = ArduSubClient(PROFILE, PERIOD, PipelineSettings(burn_in=int(0.5 * identify / PERIOD)))
    emulator = processes.start(
        "emulate",
        "--profile",
        "ardusub",
        "--connect",
        f"udpout:127.0.0.1:{client.port}",
        "--speed",
        str(speed),
        "--period",
        str(PERIOD),
        "--uptime",
        f"{US32_SPAN - identify:.3f}",
        "--excitation",
        "prbs",
        "--seed",
        "1",
        "--command-timeout",
        "5",
        "--fallback",
        "hold",
        "--trim-depth",
        "15",
    )
    try:
        client.run(30.0, lambda: set(client.companion.states.values()) == {"accepted"})
        # By samples, not wall time: on a loaded machine the emulator runs behind its speed.
        goal = len(client.samples) + round(identify / PERIOD)
        client.run(6 * identify / speed, lambda: len(client.samples) >= goal)
        health = client.pipeline.identifier_health()
        print("\nidentified:", _gains(client))
        assert all(health[ch]["converged"] for ch in ("depth", "pitch")), health
        assert all(health[ch]["skill"] > 0.2 for ch in ("depth", "pitch")), health
        start = len(client.samples)
        client.setpoints = {"depth": 16.0, "pitch": 0.1}
        goal = start + round(control / PERIOD)
        client.run(6 * control / speed, lambda: len(client.samples) >= goal)
        usec = client.servo_usec
        assert any(b < a for a, b in itertools.pairwise(usec)), "no µs wrap seen"
        # Mean |y − setpoint| over the second half of the step.
        tail = client.samples[start + (len(client.samples) - start) // 2 :]
        depth_error = sum(abs(s.depth - 16.0) for s in tail) / len(tail)
        pitch_error = sum(abs(s.pitch - 0.1) for s in tail) / len(tail)
        print(
            f"\nardusub closed loop: skill depth {health['depth']['skill']}, pitch "
            f"{health['pitch']['skill']}; mean |error| depth {depth_error:.3f} m, "
            f"pitch {pitch_error:.5f} rad; {client.commands_sent} DO_SET_SERVO"
        )
        counts = {
            ch: {"repeats": p.repeats, "skipped": p.skipped, "input_reuses": p.input_reuses}
            for ch, p in client.pipeline.channels.items()
        }
        print("pipeline:", counts)
        # No control leaves the 1 m step's 1 m and the 0.1 rad step's 0.1 rad. Measured with
        # the predictive inverse since the ArduSub timing fixes (docs/control.md), machine
        # load 3-5: depth 0.000-0.127 m in 12 runs, pitch below 1e-5 rad.
        assert depth_error < 0.4 and pitch_error < 0.01
        # Stop commanding, then wait for the DO_SET_SERVO already sent to be answered, so
        # that a loaded machine's emulator is not stopped with several still unread.
        client.setpoints = {"depth": None, "pitch": None}
        client.run(30.0, lambda: _servo_acks(client) >= client.commands_sent)
        out, _ = processes.stop(emulator)
        summary = last_json(out, "emulator")
        # The last sample's DO_SET_SERVO, one per channel, may still be in flight when the
        # emulator is stopped.
        assert client.commands_sent - 2 <= summary["commands_accepted"] <= client.commands_sent
        assert client.commands_sent > 0
        assert summary["commands_rejected"] == 0
    finally:
        client.close()


def _gains(client):
    from hil_service.umodel.predictive import factorise, step_response

    out = {}
    for ch, p in client.pipeline.channels.items():
        dyn = p.dynamics
        if dyn is None:
            out[ch] = None
            continue
        f = factorise(dyn, -1.0, 1.0)
        if f is None:
            out[ch] = "no map"
            continue
        gains, smap = f
        r = step_response(dyn.ar, gains, 2000)
        slope = smap.value(0.5) - smap.value(-0.5)
        out[ch] = (
            f"dc {r[-1] * slope:.3g} at 100: {r[99] * slope:.3g} horizon "
            f"{p.controller.horizon} d {p.controller.disturbance:.3g}"
        )
    return out


def _servo_acks(client: ArduSubClient) -> int:
    return sum(1 for ack in client.acks if ack.command == dialect.MAV_CMD_DO_SET_SERVO)
