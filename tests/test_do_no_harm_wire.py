"""Do no harm on the wire: ``serve`` and an emulated vehicle in another process, over real
UDP in lockstep, setpoint and enable over Zenoh. The vehicle's pitch plant changes after
identification (``emulate --change``): its input's sign flips, or its gain grows fivefold.
The supervisor trips, the vehicle gets its safe input (neutral: 0), the trip is published
on ``glider/1/supervisor``, and the error at the end is no worse than 1.2 times the error
when control was enabled (docs/control.md, "Do no harm")."""

from __future__ import annotations

import itertools

import pytest

from protocols.schemas import validate
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

CHANGE_AT = 1200  # plant steps (1 s each): after identification, with control on
STEPS = 2000
SETPOINT = 0.1  # rad, from a trim of 0


@pytest.mark.wire
@pytest.mark.parametrize("change", ["flip", "gain5"])
def test_a_plant_change_on_the_wire_trips_the_supervisor_and_sends_the_safe_input(
    processes, change
):
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
        "--sysid", "1",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    try:
        probe.put("glider/1/setpoint/pitch", {"value": SETPOINT})
        probe.put("glider/1/control", {"enabled": True})
        emulator = processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--lockstep",
            "--duration", str(STEPS), "--scenario", "paper", "--lockstep-timeout", "30",
            "--change", change, "--change-channel", "pitch", "--change-at", str(CHANGE_AT),
        )  # fmt: skip
        _, err = emulator.communicate(timeout=600)
        assert emulator.returncode == 0, err
        assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > 0, 10)
        assert probe.wait_for(
            lambda: probe.latest("glider/1/health", {}).get("samples", 0) >= STEPS, 10
        ), probe.latest("glider/1/health")
        health = probe.latest("glider/1/health")
        events = probe.payloads("glider/1/supervisor")
        commands = probe.payloads("glider/1/command/ballast")
        telemetry = {round(s["t"]): s for s in probe.payloads("glider/1/telemetry")}
    finally:
        probe.close()
        processes.stop(service)

    commanded = [
        c
        for c in commands
        if c["u_pitch"] is not None and c["mode"].endswith(("newton", "fallback"))
    ]
    assert commanded and commanded[0]["t"] < CHANGE_AT, "control never ran before the change"
    trips = [e for e in events if e["event"] == "trip"]
    assert trips and trips[0]["channel"] == "pitch", events
    for event in events:
        validate("supervisor_event", event)
    first = trips[0]
    trip_t = first["time_boot_ms"] / 1000.0
    # Within four supervised segments of the change (docs/control.md: the change lands in
    # a segment, and shows only once the input moves), W = the horizon clamped to [10, 200].
    window = first["window"]
    assert CHANGE_AT < trip_t <= CHANGE_AT + 4 * window, (trip_t, window, first)
    assert first["safe_input"] == 0.0 and first["safe_mode"] == "neutral"
    assert health["identifier"]["pitch"]["supervisor"]["trips"] == len(trips)
    # From the trip until a re-arm: only the safe input, and the vehicle applies it.
    rearms = [e["time_boot_ms"] / 1000.0 for e in events if e["event"] == "rearm"]
    until = min([t for t in rearms if t > trip_t], default=float(STEPS))
    safe = [c for c in commands if trip_t <= c["t"] < until]
    assert safe and all(c["mode"].endswith("safe") for c in safe)
    # Toward the safe input at the rate limit (0.5 per step), then on it: 4 steps at most.
    steps = [abs(b["u_pitch"] - a["u_pitch"]) for a, b in itertools.pairwise(safe)]
    assert all(step <= 0.5 + 1e-6 for step in steps)
    assert all(c["u_pitch"] == 0.0 for c in safe[4:])
    applied = [
        telemetry[k]["u_pitch"] for k in range(int(trip_t) + 5, int(until)) if k in telemetry
    ]
    assert applied and all(abs(u) < 1e-6 for u in applied)
    # No worse at the end than when control was enabled (its first command).
    start = telemetry[round(commanded[0]["t"])]["pitch"]
    enabled_error = abs(start - SETPOINT)
    last = [telemetry[k]["pitch"] for k in range(STEPS - 50, STEPS) if k in telemetry]
    end_error = sum(abs(p - SETPOINT) for p in last) / len(last)
    print(
        f"{change}: trip {trip_t - CHANGE_AT:.0f} samples after the change (W {window}), "
        f"{len(trips)} trips; error at enable {enabled_error:.4f}, at the end {end_error:.4f}"
    )
    assert end_error <= 1.2 * enabled_error, (end_error, enabled_error, change)
