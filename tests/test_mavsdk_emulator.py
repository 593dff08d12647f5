"""MAVSDK-Python (from PyPI, with the ``mavsdk_server`` its wheel bundles) as a ground-station
script against ``glider-hil emulate`` on both profiles, on loopback UDP: connection and
version, parameters by name (integers read back exactly, a change persists), a mission
uploaded, downloaded, played and cleared through ``mission_raw`` (a bad item refused), arm
and disarm in the HEARTBEAT, the telemetry a ground station shows, a stream rate, and the
profile's actuator or servo command (ArduPilot's refusal of a servo in use). pymavlink reads
the same integers with the encoding the vehicle advertises."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import struct
import subprocess
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

mavsdk = pytest.importorskip("mavsdk", reason="MAVSDK-Python is a test dependency ([dev])")
from mavsdk import System  # noqa: E402
from mavsdk.action import ActionError  # noqa: E402
from mavsdk.mission_raw import MissionItem, MissionRawError  # noqa: E402
from mavsdk.telemetry import TelemetryError  # noqa: E402

from hil_service.cli.processes import dies_with_parent, last_json  # noqa: E402
from protocols.mavlink_io import dialect  # noqa: E402
from tests.conftest import free_tcp_port, free_udp_port  # noqa: E402
from tests.mavlink_peer import UdpPeer  # noqa: E402
from tests.orphans import outlives_its_killed_parent  # noqa: E402

SERVER = Path(mavsdk.__file__).parent / "bin" / "mavsdk_server"
SERVER_LOG = "mavsdk_server.log"  # in the server's scratch directory
TIMEOUT = 20.0  # s for any one MAVSDK call
SPEED = 5.0
NAN = math.nan
MISSION_FRAME = dialect.MAV_FRAME_MISSION


def item(seq: int, command: int, *params: float, frame: int = MISSION_FRAME) -> MissionItem:
    p = [*params, *([0.0] * (4 - len(params)))]
    return MissionItem(seq, frame, command, int(seq == 0), 1, *p, 0, 0, 0.0, 0)


def missions(profile: str) -> tuple[list[MissionItem], list[MissionItem]]:
    """A good mission (a setpoint held 3 s, then another) and one with a bad item."""
    delay = dialect.MAV_CMD_NAV_DELAY
    if profile == "glider":
        setpoint = dialect.MAV_CMD_DO_SET_ACTUATOR
        good = [
            item(0, setpoint, 0.5, -0.25, NAN, NAN),
            item(1, delay, 3.0, -1, -1, -1),
            item(2, setpoint, -0.5, NAN, NAN, NAN),
            item(3, delay, 3.0, -1, -1, -1),
        ]
        bad = [item(0, setpoint, 1.5, 0.0, NAN, NAN)]  # outside -1..1
        return good, bad
    servo = dialect.MAV_CMD_DO_SET_SERVO
    home = item(0, dialect.MAV_CMD_NAV_WAYPOINT, frame=dialect.MAV_FRAME_GLOBAL_INT)
    good = [home, item(1, servo, 9, 1700), item(2, delay, 3.0, -1, -1, -1)]
    bad = [home, item(1, servo, 3, 1700)]  # a thruster, not a ballast servo
    return good, bad


def start_mavsdk_server(port: int, vehicle: str, scratch: Path) -> subprocess.Popen[bytes]:
    """The wheel's ``mavsdk_server`` on gRPC ``port`` for the vehicle at ``vehicle``, dying
    with this process, its temporary files and its log (``SERVER_LOG``) in ``scratch``."""
    with open(scratch / SERVER_LOG, "w") as log:
        return subprocess.Popen(
            dies_with_parent(
                [str(SERVER), "-p", str(port), "--sysid", "245", "--compid", "190", vehicle]
            ),
            env={**os.environ, "TMPDIR": str(scratch)},
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
        )


@contextlib.asynccontextmanager
async def connected(udp_port: int) -> AsyncIterator[System]:
    """MAVSDK's own server (the wheel's binary) on a free port, connected to the vehicle.

    Started here rather than by ``System``, as the project starts every peer: it dies with
    the test run even when that is SIGKILLed (``dies_with_parent``), and the files it keeps
    in the temporary directory (downloaded component metadata) go to one that is removed
    with it."""
    port = free_tcp_port()
    with tempfile.TemporaryDirectory(prefix="mavsdk-server-") as scratch:
        log_path = Path(scratch) / SERVER_LOG
        server = start_mavsdk_server(port, f"udpin://127.0.0.1:{udp_port}", Path(scratch))
        try:
            drone = System(mavsdk_server_address="127.0.0.1", port=port)

            async def wait_connected() -> None:
                await drone.connect()  # returns once the server's gRPC port answers
                async for state in drone.core.connection_state():
                    if state.is_connected:
                        return

            try:
                await asyncio.wait_for(wait_connected(), TIMEOUT)
            except TimeoutError as timeout:
                tail = log_path.read_text(errors="replace")[-2000:]
                raise AssertionError(
                    f"mavsdk_server did not connect; its log ends:\n{tail}"
                ) from timeout
            yield drone
        finally:
            server.kill()
            server.wait()


async def first(stream, predicate=lambda value: True):
    async def take():
        async for value in stream:
            if predicate(value):
                return value
        return None

    return await asyncio.wait_for(take(), TIMEOUT)


def fields(m: MissionItem) -> tuple:
    """What a mission item says, NaN read as None (so that equal items compare equal)."""
    params = tuple(None if math.isnan(p) else p for p in (m.param1, m.param2, m.param3, m.param4))
    return (m.seq, m.frame, m.command, *params)


def call(awaitable):
    return asyncio.wait_for(awaitable, TIMEOUT)


async def exercise(drone: System, profile: str) -> dict:
    found: dict = {}
    version = await call(drone.info.get_version())
    found["version"] = (version.flight_sw_major, version.flight_sw_minor)
    # Parameters: integers exactly (1, not its float's bits 1065353216), a change that persists.
    found["SYSID_THISMAV"] = await call(drone.param.get_param_int("SYSID_THISMAV"))
    found["CMD_TIMEOUT"] = await call(drone.param.get_param_float("CMD_TIMEOUT"))
    await call(drone.param.set_param_int("CMD_FALLBACK", 1))
    found["CMD_FALLBACK"] = await call(drone.param.get_param_int("CMD_FALLBACK"))
    await call(drone.param.set_param_int("CMD_FALLBACK", 0))
    if profile == "ardusub":
        found["SERVO9_TRIM"] = await call(drone.param.get_param_int("SERVO9_TRIM"))
        found["SERVO3_FUNCTION"] = await call(drone.param.get_param_int("SERVO3_FUNCTION"))
    every = await call(drone.param.get_all_params())
    found["all_ints"] = {p.name: p.value for p in every.int_params}
    # Mission: a bad item is refused (the old mission stays), a good one goes up, comes
    # back item for item, is played, and is cleared.
    good, bad = missions(profile)
    try:
        await call(drone.mission_raw.upload_mission(bad))
        found["bad_upload"] = "accepted"
    except MissionRawError as error:
        found["bad_upload"] = error._result.result.name
    await call(drone.mission_raw.upload_mission(good))
    down = await call(drone.mission_raw.download_mission())
    found["downloaded"] = [fields(m) for m in down]
    found["uploaded"] = [fields(m) for m in good]
    found["progress"] = await first(
        drone.mission_raw.mission_progress(), lambda p: p.current >= len(good) - 1
    )
    if profile == "glider":  # the readback follows the mission's setpoints
        found["actuator"] = await first(
            drone.telemetry.actuator_output_status(),
            lambda a: abs(a.actuator[0] - 0.5) < 1e-6 or abs(a.actuator[0] + 0.5) < 1e-6,
        )
    await call(drone.mission_raw.clear_mission())
    found["after_clear"] = len(await call(drone.mission_raw.download_mission()))
    # Arming, as the HEARTBEAT's base_mode says it.
    await call(drone.action.disarm())
    found["disarmed"] = await first(drone.telemetry.armed(), lambda armed: not armed)
    await call(drone.action.arm())
    found["armed"] = await first(drone.telemetry.armed(), lambda armed: armed)
    # What a ground station shows.
    found["position"] = await first(drone.telemetry.position())
    found["home"] = await first(drone.telemetry.home())
    found["heading"] = await first(drone.telemetry.heading())
    found["battery"] = await first(drone.telemetry.battery())
    found["pressure"] = await first(drone.telemetry.scaled_pressure())
    await call(drone.telemetry.set_rate_position(2.0))
    found["position_again"] = await first(drone.telemetry.position())
    await call(drone.telemetry.set_rate_attitude_euler(1.0))
    try:
        await call(drone.telemetry.set_rate_attitude_euler(10.0))
        found["attitude_10hz"] = "accepted"
    except TelemetryError as error:
        found["attitude_10hz"] = error._result.result.name
    # The profile's ballast command through MAVSDK's set_actuator (DO_SET_SERVO on ArduPilot).
    if profile == "glider":
        await call(drone.action.set_actuator(1, 0.25))
        found["servo_in_use"] = None
    else:
        await call(drone.action.set_actuator(9, 1600))
        try:
            await call(drone.action.set_actuator(3, 1600))
            found["servo_in_use"] = "accepted"
        except ActionError as error:
            found["servo_in_use"] = error._result.result.name
    return found


@pytest.mark.timeout(240)
@pytest.mark.parametrize("profile", ["glider", "ardusub"])
def test_mavsdk_scripts_the_emulator(processes, profile):
    assert SERVER.exists(), f"MAVSDK-Python's wheel bundles mavsdk_server: no {SERVER}"
    udp = free_udp_port()
    emulator = processes.start(
        "emulate", "--profile", profile, "--connect", f"udpout:127.0.0.1:{udp}",
        "--speed", str(SPEED), "--command-timeout", "1000",
    )  # fmt: skip

    async def run() -> dict:
        async with connected(udp) as drone:
            return await exercise(drone, profile)

    found = asyncio.run(run())
    out, _ = processes.stop(emulator)
    summary = last_json(out, "emulator")
    assert found["version"] == (0, 1)
    assert found["SYSID_THISMAV"] == 1
    assert found["CMD_TIMEOUT"] == 1000.0
    assert found["CMD_FALLBACK"] == 1
    assert found["all_ints"]["SYSID_THISMAV"] == 1 and found["all_ints"]["CMD_FALLBACK"] == 0
    if profile == "ardusub":
        assert found["SERVO9_TRIM"] == 1500 and found["SERVO3_FUNCTION"] == 35
        assert found["all_ints"]["SERVO10_MAX"] == 1900
    assert found["bad_upload"] == "INVALID_ARGUMENT"  # MAVSDK's name for INVALID_PARAMn
    assert found["downloaded"][1:] == found["uploaded"][1:]
    if profile == "glider":
        assert found["downloaded"][0] == found["uploaded"][0]
        assert found["actuator"] is not None
    assert found["after_clear"] in (0, 1)  # ArduPilot keeps home as item 0
    assert found["disarmed"] is False and found["armed"] is True
    position = found["position"]
    assert -60 < position.relative_altitude_m < 0  # -depth, a dive of a few tens of metres
    assert abs(position.latitude_deg - found["home"].latitude_deg) < 0.01
    assert found["home"].relative_altitude_m == 0.0
    assert found["heading"].heading_deg == 0.0
    assert 0 < found["battery"].remaining_percent <= 100
    assert found["pressure"].absolute_pressure_hpa == pytest.approx(1013.25)
    assert found["position_again"] is not None
    if profile == "glider":  # ATTITUDE goes with each 1 s plant step, no faster
        assert found["attitude_10hz"] == "COMMAND_DENIED"
        assert found["servo_in_use"] is None
    else:
        assert found["attitude_10hz"] == "accepted"
        assert found["servo_in_use"] == "FAILED"
    mission = summary["mission"]
    assert mission["uploads_refused"] == 1
    assert mission["results"]["MAV_MISSION_INVALID_PARAM1"] == 1
    assert mission["items_reached"] >= 1  # played: MISSION_CURRENT moved on
    assert summary["arms"] == 1 and summary["disarms"] == 1
    assert summary["commands_accepted"] >= 1
    assert summary["gcs"]["commands_unsupported"] == 0, summary["gcs"]


def _decode(value: float, encoding: int) -> int:
    if encoding & dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST:
        return int(value)
    return struct.unpack("<i", struct.pack("<f", value))[0]


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("profile", "autopilot"),
    [("glider", dialect.MAV_AUTOPILOT_GENERIC), ("ardusub", dialect.MAV_AUTOPILOT_ARDUPILOTMEGA)],
)
def test_pymavlink_reads_integers_with_the_advertised_encoding(processes, profile, autopilot):
    peer = UdpPeer()
    try:
        emulator = processes.start(
            "emulate", "--profile", profile, "--connect", f"udpout:127.0.0.1:{peer.port}",
            "--speed", str(SPEED),
        )  # fmt: skip
        got = peer.receive_until(lambda r: any(m.message.get_type() == "HEARTBEAT" for m in r), 20)
        beat = next(m.message for m in got if m.message.get_type() == "HEARTBEAT")
        assert beat.autopilot == autopilot
        peer.send(
            dialect.MAVLink_command_long_message(
                1, 1, dialect.MAV_CMD_REQUEST_MESSAGE, 0,
                dialect.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0,
            )
        )  # fmt: skip
        got = peer.receive_until(
            lambda r: any(m.message.get_type() == "AUTOPILOT_VERSION" for m in r), 20
        )
        capabilities = next(
            m.message for m in got if m.message.get_type() == "AUTOPILOT_VERSION"
        ).capabilities
        encodings = capabilities & (
            dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
            | dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        )
        assert encodings in (
            dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST,
            dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE,
        )  # exactly one
        assert capabilities & dialect.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        peer.send(dialect.MAVLink_param_request_list_message(1, 1))
        got = peer.receive_until(
            lambda r: (
                {"SYSID_THISMAV", "CMD_FALLBACK"}
                <= {m.message.param_id for m in r if m.message.get_type() == "PARAM_VALUE"}
            ),
            20,
        )
        values = {
            m.message.param_id: _decode(m.message.param_value, encodings)
            for m in got
            if m.message.get_type() == "PARAM_VALUE"
            and m.message.param_type == dialect.MAV_PARAM_TYPE_INT32
        }
        assert values["SYSID_THISMAV"] == 1 and values["CMD_FALLBACK"] == 0
        # A PARAM_SET in the same encoding is applied and announced with PARAM_VALUE.
        wire = (
            1.0
            if encodings & dialect.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
            else (struct.unpack("<f", struct.pack("<i", 1))[0])
        )
        peer.send(
            dialect.MAVLink_param_set_message(
                1, 1, b"CMD_FALLBACK", wire, dialect.MAV_PARAM_TYPE_INT32
            )
        )
        got = peer.receive_until(
            lambda r: any(
                m.message.get_type() == "PARAM_VALUE"
                and m.message.param_id == "CMD_FALLBACK"
                and _decode(m.message.param_value, encodings) == 1
                for m in r
            ),
            20,
        )
        assert got
        out, _ = processes.stop(emulator)
        assert last_json(out, "emulator")["gcs"]["param_sets"] == 1
    finally:
        peer.close()


def _command(peer: UdpPeer, command: int, *params: float):
    values = [*params, *([0.0] * (7 - len(params)))]
    peer.send(dialect.MAVLink_command_long_message(1, 1, command, 0, *values))
    got = peer.receive_until(
        lambda r: any(
            m.message.get_type() == "COMMAND_ACK" and m.message.command == command for m in r
        ),
        20,
    )
    ack = [m.message for m in got if m.message.get_type() == "COMMAND_ACK"][-1]
    return ack.result, [m.message for m in got]


REQUESTABLE = (
    "HEARTBEAT", "SYS_STATUS", "BATTERY_STATUS", "GLOBAL_POSITION_INT", "SCALED_PRESSURE",
    "HOME_POSITION", "MISSION_CURRENT", "FLIGHT_INFORMATION", "AUTOPILOT_VERSION",
    "ATTITUDE", "SCALED_PRESSURE2", "VFR_HUD",
)  # fmt: skip


@pytest.mark.timeout(120)
@pytest.mark.parametrize("profile", ["glider", "ardusub"])
def test_every_message_is_requestable_and_its_rate_changes(processes, profile):
    peer = UdpPeer()
    try:
        emulator = processes.start(
            "emulate", "--profile", profile, "--connect", f"udpout:127.0.0.1:{peer.port}",
            "--speed", str(SPEED),
        )  # fmt: skip
        peer.receive_until(lambda r: any(m.message.get_type() == "ATTITUDE" for m in r), 20)
        readback = "ACTUATOR_OUTPUT_STATUS" if profile == "glider" else "SERVO_OUTPUT_RAW"
        for name in (*REQUESTABLE, readback):
            msg_id = getattr(dialect, f"MAVLINK_MSG_ID_{name}")
            result, got = _command(peer, dialect.MAV_CMD_REQUEST_MESSAGE, msg_id)
            assert result == dialect.MAV_RESULT_ACCEPTED, name
            assert name in {m.get_type() for m in got}, name
        # PROTOCOL_VERSION (id 300) is acknowledged and sent; pymavlink's common cannot
        # decode it, so the peer's codec counts it as an unknown frame.
        unknown = peer.codec.counters.unknown_frames
        result, _ = _command(peer, dialect.MAV_CMD_REQUEST_PROTOCOL_VERSION)
        assert result == dialect.MAV_RESULT_ACCEPTED
        peer.receive_for(0.3)
        assert peer.codec.counters.unknown_frames > unknown
        # A ground station changes a stream's rate and reads it back.
        position = dialect.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
        result, _ = _command(peer, dialect.MAV_CMD_SET_MESSAGE_INTERVAL, position, 200_000)
        assert result == dialect.MAV_RESULT_ACCEPTED
        result, got = _command(peer, dialect.MAV_CMD_GET_MESSAGE_INTERVAL, position)
        intervals = [m for m in got if m.get_type() == "MESSAGE_INTERVAL"]
        assert result == dialect.MAV_RESULT_ACCEPTED and intervals[-1].interval_us == 200_000
        got = peer.receive_for(2.0)  # 2 wall s at 5x: 10 simulated s, 50 at 5 Hz
        count = sum(m.message.get_type() == "GLOBAL_POSITION_INT" for m in got)
        assert count >= 25, count
        # Arming is refused, with the reason, while a mission upload is in progress.
        peer.send(dialect.MAVLink_mission_count_message(1, 1, 2, 0))
        peer.receive_until(
            lambda r: any(m.message.get_type() == "MISSION_REQUEST_INT" for m in r), 20
        )
        result, got = _command(peer, dialect.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert result == dialect.MAV_RESULT_FAILED
        assert "PreArm: mission upload in progress" in [
            m.text for m in got if m.get_type() == "STATUSTEXT"
        ]
        result, got = _command(peer, dialect.MAV_CMD_COMPONENT_ARM_DISARM, 0)
        assert result == dialect.MAV_RESULT_ACCEPTED
        beats = peer.receive_until(
            lambda r: any(
                m.message.get_type() == "HEARTBEAT"
                and not m.message.base_mode & dialect.MAV_MODE_FLAG_SAFETY_ARMED
                for m in r
            ),
            5,
        )
        assert any(
            m.message.get_type() == "HEARTBEAT"
            and not m.message.base_mode & dialect.MAV_MODE_FLAG_SAFETY_ARMED
            for m in beats
        )
        out, _ = processes.stop(emulator)
        summary = last_json(out, "emulator")
        assert summary["arms_refused"] == 1 and summary["disarms"] == 1
    finally:
        peer.close()


def test_mavsdk_server_dies_with_a_parent_that_is_sigkilled(tmp_path):
    """A test run SIGKILLed while MAVSDK is connected leaves no ``mavsdk_server`` behind:
    the parent here is a plain Python process that starts it as ``connected`` does."""
    code = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from tests.test_mavsdk_emulator import start_mavsdk_server\n"
        f"server = start_mavsdk_server({free_tcp_port()}, "
        f"'udpin://127.0.0.1:{free_udp_port()}', Path({str(tmp_path)!r}))\n"
        "print(server.pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    assert not outlives_its_killed_parent(code), "mavsdk_server outlived its killed parent"
