"""MAVSDK-Python as the ground station of a vehicle whose companion is `glider-hil serve`:
`emulate --profile ardusub` on MAVProxy's master link, `serve --profile ardusub` and MAVSDK's
server each on an `--out` of it (MAVProxy sends no stream requests of its own here), Zenoh on
a loopback endpoint. MAVSDK reads integer parameters and commands servos through the router;
the vehicle's acknowledgements to it reach the service too, which counts them as not its
own (no command sent, none counted); MAVSDK lowering ATTITUDE below the rate the service
asked for is noticed and asked for again."""

from __future__ import annotations

import asyncio
import json

import pytest

pytest.importorskip("mavsdk", reason="MAVSDK-Python is a test dependency ([dev])")
from mavsdk.action import ActionError

from hil_service.sources.companion import ack_is_ours, addressed_to_companion
from protocols.mavlink_io import MavlinkCodec, dialect
from tests.conftest import free_tcp_port, free_udp_port
from tests.test_mavproxy_router import MAVPROXY, _mavproxy, _stop_mavproxy
from tests.test_mavsdk_emulator import SERVER, call, connected
from tests.zenoh_peer import ZenohProbe

PERIOD = 0.1
STREAMS = {"SCALED_PRESSURE2", "VFR_HUD", "ATTITUDE", "SERVO_OUTPUT_RAW"}


def _ack(target_system: int, target_component: int, command: int):
    """A COMMAND_ACK from vehicle 1's autopilot, decoded as the service sees it."""
    vehicle = MavlinkCodec(1, 1)
    frame = vehicle.pack(
        dialect.MAVLink_command_ack_message(command, 0, 0, 0, target_system, target_component)
    )
    return MavlinkCodec(255, 0).parse(frame, datagram=True)[0]


def test_only_acks_addressed_to_the_companion_count():
    servo = dialect.MAV_CMD_DO_SET_SERVO
    assert ack_is_ours(_ack(1, 191, servo))
    assert not ack_is_ours(_ack(245, 190, servo))  # to MAVSDK
    assert not ack_is_ours(_ack(255, 0, servo))  # to MAVProxy
    assert not ack_is_ours(_ack(1, 191, dialect.MAV_CMD_REQUEST_MESSAGE))  # not a command of ours
    assert addressed_to_companion(_ack(1, 191, dialect.MAV_CMD_SET_MESSAGE_INTERVAL))
    assert not addressed_to_companion(_ack(0, 0, servo))  # no target: a MAVLink 1-style ack


@pytest.mark.timeout(300)
def test_mavsdk_beside_serve_as_the_companion(processes, tmp_path):
    assert MAVPROXY.exists(), f"MAVProxy is a test dependency: no {MAVPROXY}"
    assert SERVER.exists(), f"MAVSDK-Python's wheel bundles mavsdk_server: no {SERVER}"
    master, service_port, gcs_port = free_udp_port(), free_udp_port(), free_udp_port()
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    router, console = _mavproxy(
        tmp_path, master, service_port, tmp_path / "router.tlog",
        f"--out=udpout:127.0.0.1:{gcs_port}", "--streamrate=-1",
    )  # fmt: skip
    probe = None
    try:
        service = processes.start_service(
            "--mavlink", f"udpin:127.0.0.1:{service_port}", "--zenoh-listen", endpoint,
            "--log-dir", str(tmp_path / "logs"), "--profile", "ardusub",
            "--sample-period", str(PERIOD), "--sysid", "1",
        )  # fmt: skip
        probe = ZenohProbe(endpoint)
        emulator = processes.start(
            "emulate", "--profile", "ardusub", "--connect", f"udpout:127.0.0.1:{master}",
            "--speed", "2", "--period", str(PERIOD),
        )  # fmt: skip

        def companion() -> dict:
            return (probe.latest("glider/1/health") or {}).get("companion") or {}

        def settled() -> bool:
            requests = companion().get("stream_requests") or {}
            return set(requests) == STREAMS and set(requests.values()) == {"accepted"}

        assert probe.wait_for(settled, 90), companion()

        async def script() -> dict:
            found: dict = {}
            async with connected(gcs_port) as drone:
                found["SYSID_THISMAV"] = await call(drone.param.get_param_int("SYSID_THISMAV"))
                found["SERVO9_TRIM"] = await call(drone.param.get_param_int("SERVO9_TRIM"))
                await call(drone.action.set_actuator(11, 1600))  # a free servo: accepted
                try:
                    await call(drone.action.set_actuator(3, 1600))  # a thruster: refused
                    found["thruster"] = "accepted"
                except ActionError as error:
                    found["thruster"] = error._result.result.name
                # A ground station slowing a stream the companion needs at 10 Hz.
                await call(drone.telemetry.set_rate_attitude_euler(1.0))
                found["rerequested"] = await asyncio.to_thread(
                    probe.wait_for,
                    lambda: companion().get("slow_streams", {}).get("ATTITUDE", 0) >= 1,
                    60,
                )
            return found

        found = asyncio.run(script())
        assert probe.wait_for(settled, 60), companion()  # asked again, and accepted
        final = companion()
    finally:
        if probe is not None:
            probe.close()
        _stop_mavproxy(router, console)
    processes.stop(emulator)
    out, err = processes.stop(service)
    assert service.returncode == 0, err
    served = json.loads(out.strip().splitlines()[-1])["service"]
    vehicle = served["vehicles"]["1"]
    assert found["SYSID_THISMAV"] == 1 and found["SERVO9_TRIM"] == 1500
    assert found["thruster"] == "FAILED"
    assert found["rerequested"], final
    assert final["rerequests"].get("rate", 0) >= 1
    # The vehicle's answers to MAVSDK reached the service and were not taken for its own.
    assert vehicle["commands_sent"] == 0
    assert vehicle["acks"]["accepted"] == vehicle["acks"]["refused"] == 0
    assert vehicle["acks"]["not_ours"] >= 2, vehicle["acks"]
    assert served["companions"]["1"]["not_ours"] > 0
