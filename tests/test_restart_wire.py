"""A vehicle on the periodic (ArduSub) profile reboots while ``serve`` commands it, over
real UDP with setpoints and enable over Zenoh (``emulate --profile ardusub --reboot-at``).

The service's sample time goes on across the reboot (the sampler keeps one time line), so
only the sampler can tell: its clock stepped back. ``health`` shows the reboot, commanding
stops on both channels, and resumes only once the model has passed the horizon test again
on data after the reboot (docs/profiles.md, "Reboots and outages")."""

from __future__ import annotations

import json

import pytest

from hil_service.pipeline import PipelineSettings
from plant_emulator.models import CHANNELS
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

PERIOD = 0.1  # s: the service's sample period and the vehicle's plant step
SPEED = 10
REBOOT_AT = 900  # plant steps: 600 after the burn-in, commanding
STEPS = 2400
SETPOINTS = {"depth": 16.0, "pitch": 0.1}  # trim depth 15 m, pitch 0


def _commanded(commands: list[dict], channel: str) -> list[dict]:
    slot = CHANNELS.index(channel)
    return [
        c for c in commands
        if c[f"u_{channel}"] is not None and c["mode"].split("/")[slot] not in ("-", "safe")
    ]  # fmt: skip


@pytest.mark.wire
@pytest.mark.timeout(300)
def test_a_reboot_on_the_periodic_profile_stops_commanding_until_a_new_horizon_pass(
    processes,
):
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
        "--profile", "ardusub", "--sample-period", str(PERIOD), "--sysid", "1",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    try:
        for channel, value in SETPOINTS.items():
            probe.put(f"glider/1/setpoint/{channel}", {"value": value})
        probe.put("glider/1/control", {"enabled": True})
        emulator = processes.start(
            "emulate", "--profile", "ardusub", "--connect", f"udpout:127.0.0.1:{udp}",
            "--speed", str(SPEED), "--period", str(PERIOD), "--excitation", "prbs",
            "--seed", "1", "--duration", f"{STEPS * PERIOD:g}", "--reboot-at", str(REBOOT_AT),
        )  # fmt: skip
        out, err = emulator.communicate(timeout=240)
        assert emulator.returncode == 0, err
        vehicle = json.loads(out.strip().splitlines()[-1])["emulator"]
        assert probe.wait_for(
            lambda: (
                probe.latest("glider/1/health", {}).get("identifier", {})
                and probe.latest("glider/1/health")["sampling"]["reboots"] >= 1
                and probe.latest("glider/1/telemetry")["t"] >= 0.9 * STEPS * PERIOD
            ),
            15,
        ), probe.latest("glider/1/health")
        health = probe.latest("glider/1/health")
        healths = probe.payloads("glider/1/health")
        commands = probe.payloads("glider/1/command/ballast")
    finally:
        probe.close()
        processes.stop(service)
    assert vehicle["reboot"]["at_step"] == REBOOT_AT and vehicle["reboot"]["clock_back_s"] > 80
    # health shows it: one reboot, told apart from outages (none unless a loaded machine
    # stalled the service for 2 s of the vehicle's clock), each channel restarted once.
    sampling = health["sampling"]
    assert sampling["reboots"] == 1
    assert health["counters"]["restarts"] == sampling["reboots"] + sampling["outages"]
    for channel in CHANNELS:
        assert health["identifier"][channel]["restarts"] == 1, health["identifier"][channel]
    # Before the reboot the sample time is the vehicle's uptime (no reboot yet): the
    # reboot falls at REBOOT_AT plant steps.
    reboot_t = REBOOT_AT * PERIOD
    burn_in = PipelineSettings().burn_in  # serve's, as started
    requalified = []
    for channel in CHANNELS:
        commanded = _commanded(commands, channel)
        before = [c["t"] for c in commanded if c["t"] <= reboot_t]
        after = [c["t"] for c in commanded if c["t"] > reboot_t]
        horizon = health["identifier"][channel]["multistep_horizon"]
        if not before:
            # A loaded machine can keep a channel's model from qualifying in the 600 samples
            # between the burn-in and the reboot. What it may still not do is command after
            # the reboot before the horizon test has a verdict on post-reboot data.
            wait = round((after[0] - reboot_t) / PERIOD) if after else None
            print(f"{channel}: never commanded before the reboot; first after it: {wait}")
            assert wait is None or wait >= min(horizon, burn_in), (channel, wait, horizon)
            continue
        supervisor = health["identifier"][channel]["supervisor"]
        if not after and supervisor["trips"]:
            # The supervisor tripped it before the reboot (a loaded machine stalling the
            # loop can): a tripped channel stays off through the reboot, its hold-off (at
            # least twice the horizon) outlasting the run.
            assert supervisor["state"] == "tripped", supervisor
            print(f"{channel}: tripped before the reboot ({supervisor['reason']}), stays off")
            continue
        assert after, (
            f"{channel} never commanded again after the reboot",
            health["control"],
            health["identifier"][channel],
            sampling,
        )
        # Not before the horizon test has a verdict on post-reboot data: at least the
        # horizon (or the burn-in, the least a verdict rests on) of samples after it.
        gap = round((after[0] - before[-1]) / PERIOD)
        print(
            f"{channel}: last command before the reboot at {before[-1]:.1f} s, first after "
            f"at {after[0]:.1f} s ({gap} samples; horizon {horizon})"
        )
        assert gap >= min(horizon, burn_in), (channel, gap, horizon)
        requalified.append(channel)
    assert requalified, "no channel commanded both before and after the reboot"
    if "depth" not in requalified:
        return
    blocked = [
        h["control"]["reason"] for h in healths
        if h.get("identifier", {}).get("depth", {}).get("restarts") == 1
        and "model does not predict over the horizon" in h["control"]["reason"]
    ]  # fmt: skip
    # Depth's wait (≥ the burn-in, 3 s of wall clock) spans health's 1 Hz: health says why.
    assert blocked, "no health said the horizon test blocks after the reboot"
    print(f"health during the re-qualification: {blocked[0]}")
