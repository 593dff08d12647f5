"""The Foxglove live view: ``serve --foxglove`` against the reference client from npm.

The node script (tests/foxglove_client/client.js, ``@foxglove/ws-protocol`` 0.8 with ``ws``
and ``ajv``, installed by ``make test`` from the lock file) connects with the subprotocol
``foxglove.sdk.v1``, subscribes to telemetry, estimates and commands and validates each
message against the JSON Schema the server advertised for its channel.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hil_service.cli.processes import wait_for_line
from hil_service.live.address import LiveAddress
from hil_service.live.server import channel_schema
from protocols.schemas import load_schema
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

CLIENT_DIR = Path(__file__).resolve().parent / "foxglove_client"
KINDS = ("telemetry", "umodel", "command/ballast")
#: The MAVLink channels of the log, streamed too (raw frames: schemaless ``mavlink2``).
MAVLINK_KINDS = ("mavlink/raw/in", "mavlink/raw/out", "mavlink/json/in", "mavlink/json/out")
BURN_IN = 200


def test_address_parsing() -> None:
    assert LiveAddress.parse("8765") == LiveAddress("127.0.0.1", 8765)
    assert LiveAddress.parse("0.0.0.0:9000") == LiveAddress("0.0.0.0", 9000)
    assert LiveAddress.parse("[::1]:9000") == LiveAddress("::1", 9000)
    for bad in ("", "host:", "x:70000", "port"):
        with pytest.raises(ValueError, match="--foxglove"):
            LiveAddress.parse(bad)


def test_channel_schemas_are_the_logs() -> None:
    schema = channel_schema("glider/7/telemetry")
    assert schema is not None and schema.name == "glider-hil.telemetry"
    assert json.loads(schema.data) == load_schema("telemetry")
    assert channel_schema("glider/7/umodel/depth").name == "glider-hil.umodel"
    assert channel_schema("glider-hil/7/decision-inputs").name == "glider-hil.decision_inputs"
    assert channel_schema("glider/7/service") is None  # a liveliness token: no payload


def _node_client() -> list[str]:
    node = shutil.which("node")
    if node is None or not (CLIENT_DIR / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.skip("node or the npm client is missing: run `make test` (npm ci) with node")
    return [node, str(CLIENT_DIR / "client.js")]


def test_reference_client_validates_live_messages(processes, tmp_path) -> None:
    client = _node_client()
    udp, zport, fox = free_udp_port(), free_tcp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
        "--burn-in", str(BURN_IN), "--control", "--foxglove", f"127.0.0.1:{fox}",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    try:
        probe.put("glider/1/setpoint/depth", {"value": 17.0})
        processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--speed", "50",
            "--duration", "100000", "--scenario", "paper", "--seed", "3",
        )  # fmt: skip
        # The service publishes commands once its identifier has converged.
        assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > 0, 60)
        result = subprocess.run(
            [*client, f"ws://127.0.0.1:{fox}", "50", "30", *KINDS, *MAVLINK_KINDS],
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        probe.close()
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["subprotocol"] == "foxglove.sdk.v1"
    assert summary["complete"], summary
    for kind in (*KINDS, *MAVLINK_KINDS):
        counts = summary["kinds"][kind]
        assert counts["valid"] >= 50 and counts["invalid"] == 0, (kind, summary["errors"])
    advertised = {c["topic"]: c for c in summary["advertised"]}
    for topic, schema in (
        ("glider/1/telemetry", "glider-hil.telemetry"),
        ("glider/1/umodel/depth", "glider-hil.umodel"),
        ("glider/1/umodel/pitch", "glider-hil.umodel"),
        ("glider/1/command/ballast", "glider-hil.command_ballast"),
        ("glider/1/setpoint/depth", "glider-hil.setpoint"),  # an input, streamed too
    ):
        assert advertised[topic]["encoding"] == "json"
        assert advertised[topic]["schemaName"] == schema
        assert advertised[topic]["schemaEncoding"] == "jsonschema"
    # The log's MAVLink channels: raw frames without a schema, each message type decoded
    # under its generated schema (docs/mcap.md), in and out.
    for direction in ("in", "out"):
        raw = advertised[f"mavlink/raw/{direction}"]
        assert raw["encoding"] == "mavlink2" and raw["schemaLength"] == 0, raw
    for topic, schema in (
        ("mavlink/json/in/ATTITUDE", "mavlink.ATTITUDE"),
        ("mavlink/json/in/SCALED_PRESSURE2", "mavlink.SCALED_PRESSURE2"),
        ("mavlink/json/out/COMMAND_LONG", "mavlink.COMMAND_LONG"),
    ):
        assert advertised[topic]["encoding"] == "json"
        assert advertised[topic]["schemaName"] == schema
        assert advertised[topic]["schemaEncoding"] == "jsonschema"
    assert not summary["errors"], summary["errors"]


def test_replay_streams_a_log_to_the_reference_client(processes) -> None:
    """``replay --foxglove``: the replayed service's publications, validated the same way."""
    client = _node_client()
    fox = free_tcp_port()
    log = Path(__file__).resolve().parent / "data" / "paper.mcap"
    # --loop: a loaded machine may start the node client after a single pass has ended (the
    # view closes with the replay: "closed: 1006" in one burner-loaded make test).
    replay = processes.start(
        "replay", str(log), "--speed", "100", "--loop", "--foxglove", f"127.0.0.1:{fox}"
    )
    wait_for_line(replay, "Foxglove live view on", 60)
    result = subprocess.run(
        [*client, f"ws://127.0.0.1:{fox}", "20", "30", "telemetry", "umodel"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["complete"], summary
    assert summary["kinds"]["umodel"]["invalid"] == 0 and not summary["errors"], summary


def test_verbs_without_a_live_view_do_not_load_the_sdk() -> None:
    code = (
        "import sys, hil_service.cli as c, hil_service.builder, hil_service.config; "
        "c.build_parser(); print('foxglove' in sys.modules)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.stdout.strip() == "False", result.stderr
