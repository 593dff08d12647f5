"""docs/ tells the truth: the documented keys are ``protocols/keys.py``'s, the documented MCAP
channels are what a recorded log holds, the MAVLink ids are the dialect's, and every table
renders."""

from __future__ import annotations

import re
import socket
import time
from pathlib import Path

import pytest

from hil_service.builder import open_recorder, wire
from hil_service.config import LinkSecurity, LogOptions, ServiceConfig
from hil_service.listeners.zenoh_config import ZenohOptions, open_session
from hil_service.mcap.reader import LogReader
from hil_service.pipeline import PipelineSettings
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols import keys
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import Link, MavlinkCodec, dialect
from protocols.schemas import load_schema
from tests.conftest import free_tcp_port
from tests.markdown_tables import misshapen_tables

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
DATA = Path(__file__).parent / "data"
KEY = bytes(range(32))
SYSTEM_ID = 7

FORMATTERS = {
    keys.TELEMETRY: keys.telemetry,
    keys.UMODEL: keys.umodel,
    keys.COMMAND_BALLAST: keys.command_ballast,
    keys.HEALTH: keys.health,
    keys.SUPERVISOR: keys.supervisor,
    keys.SETPOINT: keys.setpoint,
    keys.CONTROL: keys.control,
    keys.STATE: keys.state,
    keys.SERVICE: keys.service,
    keys.DECISION_INPUTS: keys.decision_inputs,
}


def table(path: Path, first_column: str) -> list[dict[str, str]]:
    """The rows of the Markdown table in ``path`` whose first header is ``first_column``."""
    lines = path.read_text().splitlines()
    starts = [n for n, line in enumerate(lines) if _cells(line)[:1] == [first_column]]
    assert starts, f"{path.name}: no table starting with column {first_column!r}"
    start = starts[0]
    header = _cells(lines[start])
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = _cells(line)
        assert len(cells) == len(header), f"{path.name}: {line!r}"
        rows.append(dict(zip(header, cells, strict=True)))
    assert rows, f"{path.name}: empty table {first_column!r}"
    return rows


def _cells(line: str) -> list[str]:
    if not line.startswith("|"):
        return []
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def code(cell: str) -> str | None:
    """The text of a cell that is one code span; None for "—"."""
    if cell == "—":
        return None
    match = re.fullmatch(r"`([^`]+)`", cell)
    assert match, f"expected one code span, got {cell!r}"
    return match.group(1)


def instances(pattern: str) -> list[str]:
    """A documented key pattern made concrete, once per channel where it has one."""
    channels = keys.CHANNELS if "{channel}" in pattern else ("",)
    return [pattern.format(id=SYSTEM_ID, channel=channel) for channel in channels]


# ---- docs/zenoh.md ------------------------------------------------------------------------
def test_the_documented_key_table_is_the_key_space_of_protocols_keys():
    documented = set()
    for row in table(DOCS / "zenoh.md", "key"):
        pattern = code(row["key"])
        assert pattern is not None
        for key in instances(pattern):
            parsed = keys.parse(key)
            assert parsed is not None, f"docs/zenoh.md: {key} is not a key of protocols/keys.py"
            assert parsed.system_id == SYSTEM_ID
            documented.add(parsed.kind)
            args = (SYSTEM_ID,) if parsed.channel is None else (SYSTEM_ID, parsed.channel)
            assert FORMATTERS[parsed.kind](*args) == key
            schema = code(row["schema"])
            assert schema == keys.SCHEMA_FOR_KIND.get(parsed.kind), key
            if schema is not None:  # the schema file names the same key
                assert load_schema(schema)["title"] == pattern
    assert documented == set(keys.ZENOH_KINDS)


def test_the_key_parser_refuses_what_is_not_a_key():
    for bad in (
        "glider/0/telemetry",  # system ids are 1..255
        "glider/256/telemetry",
        "glider/07/telemetry",
        "glider/x/control",
        "glider/1/setpoint",  # a channel is needed
        "glider/1/setpoint/roll",
        "glider/1/telemetry/depth",
        "glider/1/command",
        "glider/1/decision-inputs",  # a log channel, not a Zenoh key
        "glider-hil/1/telemetry",
        "mavlink/raw/in",
        "glider",
        "",
    ):
        assert keys.parse(bad) is None, bad
    assert keys.parse("glider/255/umodel/pitch") == keys.ParsedKey(255, keys.UMODEL, "pitch")
    assert keys.parse("glider-hil/3/decision-inputs") == keys.ParsedKey(3, keys.DECISION_INPUTS)


# ---- docs/mavlink.md ----------------------------------------------------------------------
def test_the_documented_mavlink_ids_are_the_dialects():
    text = (DOCS / "mavlink.md").read_text()
    pairs = re.findall(r"`([A-Z][A-Z0-9_]+)` \((\d+)\)", text)
    assert len(pairs) >= 10
    for name, number in pairs:
        value = getattr(dialect, f"MAVLINK_MSG_ID_{name}", None)
        if value is None:
            value = getattr(dialect, name)  # an enum entry: MAV_CMD_…, MAV_RESULT_…
        assert value == int(number), f"docs/mavlink.md: {name} is {value}, not {number}"


# ---- docs/mcap.md -------------------------------------------------------------------------
def _wait(condition, what: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def _telemetry(codec: MavlinkCodec, steps: int) -> list[bytes]:
    plant = GliderPlant(PlantConfig(scenario="disturbed", seed=0))
    excitation = build_channel_excitations("steps", 0)
    mapping = TelemetryMapping()
    datagrams = []
    for k in range(steps):
        sample = plant.step(excitation["depth"].value(k), excitation["pitch"].value(k))
        datagrams += [codec.pack(m) for m in mapping.encode_telemetry(sample)]
    return datagrams


@pytest.fixture(scope="module")
def recorded_log(tmp_path_factory) -> Path:
    """A short in-process run, every part real: a signed UDP link to a socket of ours, a Zenoh
    session on loopback with a second session putting setpoints and control, the recorder."""
    log_dir = tmp_path_factory.mktemp("logs")
    config = ServiceConfig(
        control_default=False,
        pipeline=PipelineSettings().replace(burn_in=50),
        security=LinkSecurity(KEY),
    )
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    link = Link(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}", 255, 191)
    session = open_session(ZenohOptions(listen=(endpoint,)))
    recorder = open_recorder(config, LogOptions(directory=str(log_dir)))
    wired = wire(config, session=session, link=link, recorder=recorder)
    operator = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        _wait(lambda: any(True for _ in operator.info.peers_zid()), "the Zenoh peer")

        def inputs_arrived() -> bool:
            operator.put(keys.control(SYSTEM_ID), b'{"enabled": true}')
            operator.put(keys.setpoint(SYSTEM_ID, "depth"), b'{"value": 12.0}')
            operator.put(keys.setpoint(SYSTEM_ID, "pitch"), b'{"value": 0.1}')
            time.sleep(0.05)
            current = wired.inbox.get(SYSTEM_ID)
            return current.enabled is True and None not in current.setpoints.values()

        _wait(inputs_arrived, "the operator's inputs")
        operator.put(keys.setpoint(SYSTEM_ID, "depth"), b'{"value": "deep"}')  # refused
        _wait(lambda: wired.inbox.rejected >= 1, "the refused input")
        codec = MavlinkCodec(SYSTEM_ID, 1, signing_key=KEY)
        for datagram in _telemetry(MavlinkCodec(SYSTEM_ID, 1), 2):  # unsigned: refused
            wired.service.process_datagram(datagram)
        for datagram in _telemetry(codec, 400):
            wired.service.process_datagram(datagram)
        wired.service.tick()
        vehicle.settimeout(5)
        command = vehicle.recv(65535)  # the first command the service sent
        for message in MavlinkCodec(SYSTEM_ID, 1, signing_key=KEY).parse(command, True):
            ack = TelemetryMapping().command_ack(message, accepted=True)
            wired.service.process_datagram(codec.pack(ack))
            break
    finally:
        operator.close()
        wired.close()
        vehicle.close()
    [log] = log_dir.glob("*.mcap")
    return log


def _channel_pattern(topic: str) -> re.Pattern[str]:
    escaped = re.escape(topic)
    parts = {"id": r"\d+", "channel": "|".join(keys.CHANNELS), "MESSAGE": "[A-Z0-9_]+"}
    for name, regex in parts.items():
        escaped = escaped.replace(re.escape("{" + name + "}"), f"(?P<{name}>{regex})")
    return re.compile(escaped + "$")


def test_the_documented_channels_are_what_a_recorded_log_holds(recorded_log):
    reader = LogReader(recorded_log)
    for _ in reader.messages():
        pass
    assert reader.report.complete
    recorded = reader.report.channels
    rows = table(DOCS / "mcap.md", "channel")
    unmatched = set(recorded)
    for row in rows:
        topic = code(row["channel"])
        assert topic is not None
        pattern = _channel_pattern(topic)
        matches = [name for name in recorded if pattern.match(name)]
        assert matches, f"docs/mcap.md: {topic} is not in the recorded log"
        for name in matches:
            channel = recorded[name]
            unmatched.discard(name)
            assert channel["encoding"] == code(row["encoding"]), name
            schema = code(row["schema"])
            if schema is not None:
                message = pattern.match(name).groupdict().get("MESSAGE")
                schema = schema.replace("{MESSAGE}", message or "")
                assert channel["schema_encoding"] == "jsonschema", name
            assert channel["schema"] == schema, name
            assert channel["metadata"]["direction"] == code(row["direction"]), name
        if "{id}" in topic and topic.startswith(("glider/", "glider-hil/")):
            for name in matches:  # the key space's own parser agrees
                assert keys.parse(name) is not None, name
    assert not unmatched, f"channels missing from docs/mcap.md: {sorted(unmatched)}"


def test_the_documented_stored_configuration_is_what_a_log_holds(recorded_log):
    reader = LogReader(recorded_log)
    for _ in reader.messages():
        pass
    stored = reader.config()
    rows = {code(row["key"]): row["JSON"] for row in table(DOCS / "mcap.md", "key")}
    assert set(rows) == set(stored)
    for part, cell in rows.items():
        documented = set(re.findall(r"`([a-z_]+)`", cell))
        assert set(stored[part]) <= documented, f"docs/mcap.md does not list {part} fields"
    config = ServiceConfig.from_stored(stored)
    assert config is not None
    again = config.stored()
    # The key is never stored, so what is read back has none; everything else round-trips.
    assert stored["service"].pop("signing") == {"signed": True, "accept_unsigned": False}
    assert again["service"].pop("signing") == {"signed": False, "accept_unsigned": False}
    assert again == stored


# A log recorded before the configuration module stored the setpoint limits: the replay
# fixtures are regenerated whenever the controller changes, so one old log is kept as it was.
@pytest.mark.parametrize("name", ["legacy-paper"])
def test_logs_written_before_the_config_module_still_read(name, capsys):
    import json

    from hil_service.cli import main

    reader = LogReader(DATA / f"{name}.mcap")
    for _ in reader.messages():
        pass
    config = ServiceConfig.from_stored(reader.config())
    assert config is not None
    assert ServiceConfig.from_stored(config.stored()) == config
    assert config.security.key is None  # never stored
    # info shows the configuration as read back, and says which fields the log lacked.
    assert main(["info", "--json", str(DATA / f"{name}.mcap")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["config"] == config.stored()
    # The log predates the stored profile too: it reads as the built-in glider profile.
    assert info["config_defaults"] == [
        "service.limits",
        "service.max_vehicles",
        "service.profile",
        "profile",
    ]
    assert config.profile.name == "glider"


def test_serve_flags_reach_replay_through_the_stored_configuration():
    """What ``serve`` is told is what the log stores and what ``replay`` rebuilds."""
    import json

    from hil_service.cli import build_parser
    from hil_service.cli.serve import config_from_args

    args = build_parser().parse_args(
        ["serve", "--sysid", "3", "--model", "paper", "--seed", "4", "--burn-in", "77",
         "--full-scale", "1.5", "--water-density", "1000", "--surface-pressure", "1010",
         "--min-depth", "2", "--max-depth", "40", "--max-pitch", "0.3", "--control"]
    )  # fmt: skip
    config = config_from_args(args).service
    stored = {name: json.loads(text) for name, text in config.to_metadata().items()}
    again = ServiceConfig.from_stored(stored)
    assert again is not None and again.stored() == config.stored() == stored
    assert (again.units, again.limits, again.system_ids) == (
        config.units,
        config.limits,
        config.system_ids,
    )
    assert again.mapping().inputs.full_scale == 1.5
    assert again.pipeline.model == "paper" and again.pipeline.burn_in == 77


def test_the_docs_index_lists_every_document():
    index = (DOCS / "README.md").read_text()
    for path in sorted(DOCS.rglob("*")):
        if path.is_file() and path.name != "README.md":
            name = path.relative_to(DOCS).as_posix()
            assert name in index, f"docs/README.md does not list {name}"


@pytest.mark.parametrize(
    "document",
    ["README.md", *sorted(p.relative_to(ROOT).as_posix() for p in DOCS.rglob("*.md"))],
)
def test_every_table_of_the_docs_renders(document):
    """Each Markdown table has as many cells in every row as in its header (an escaped
    ``\\|`` is a pipe inside a cell); one that does not is shown as text, or loses cells."""
    assert misshapen_tables((ROOT / document).read_text()) == []
