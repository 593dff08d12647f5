"""Logs we did not write: a stored configuration (``glider-hil.config``) of the wrong JSON
types, values that are not JSON, damaged decision-inputs records and publications, and raw
frames that decode to nothing. ``replay``, ``info`` and ``report`` refuse the configuration
in one line naming the log and the stored key (exit 2), and count and skip the records."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from mcap.writer import Writer

from hil_service.cli import main
from hil_service.config import ServiceConfig
from hil_service.mcap.recorder import CONFIG_METADATA
from hil_service.offline.field.report import field_section
from hil_service.offline.series import load_series
from protocols import keys
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec
from protocols.samples import TelemetrySample

SAMPLES = 5
RAW_IN = "mavlink/raw/in"


def _stored() -> dict[str, Any]:
    """The configuration a default service stores, decoded."""
    return ServiceConfig().stored()


def _metadata(cfg: dict[str, Any]) -> dict[str, str]:
    """A decoded configuration as the metadata record holds it (JSON strings)."""
    return {name: json.dumps(value) for name, value in cfg.items()}


def _frames() -> list[bytes]:
    """The raw frames of ``SAMPLES`` telemetry samples of vehicle 1, 1 s apart."""
    codec, mapping = MavlinkCodec(1, 1), TelemetryMapping()
    return [
        codec.pack(message)
        for k in range(SAMPLES)
        for message in mapping.encode_telemetry(TelemetrySample(1, 1000 * k, 15.0, 0.0, 0.1, -0.1))
    ]


def write_log(
    path: Path,
    metadata: dict[str, str],
    records: list[tuple[str, bytes]] | None = None,
    frames: list[bytes] | None = None,
) -> Path:
    """A log as the ``mcap`` package writes it: ``metadata`` as the stored configuration,
    ``records`` (topic, bytes) first, then the raw ``frames`` (default: ``_frames()``)."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="glider-hil", library="test")
        writer.add_metadata(CONFIG_METADATA, metadata)
        channels: dict[str, int] = {}
        log_ns = 1_700_000_000 * 10**9
        entries = [
            *(records or []),
            *((RAW_IN, f) for f in (_frames() if frames is None else frames)),
        ]
        for k, (topic, data) in enumerate(entries):
            if topic not in channels:
                encoding = "mavlink" if topic == RAW_IN else "json"
                channels[topic] = writer.register_channel(topic, encoding, 0)
            writer.add_message(channels[topic], log_ns + k, data, log_ns + k)
        writer.finish()
    return path


def _with(path: Path, change: str) -> Path:
    """A log whose stored configuration is the default one after ``change`` (Python over
    ``cfg``, the decoded configuration)."""
    cfg = _stored()
    exec(change, {"cfg": cfg})
    return write_log(path, _metadata(cfg))


def _one_line(err: str) -> str:
    assert "Traceback" not in err
    assert err.strip().count("\n") == 0, err
    return err.strip()


STALE_ABC = 'service.stale_timeout: expected a number, got "abc"'
#: (change to the stored configuration, the stored key the error names)
WRONG_TYPES = [
    ('cfg["service"]["stale_timeout"] = "abc"', STALE_ABC),
    ('cfg["service"]["limits"] = [1]', "service.limits: expected an object, got [1]"),
    ('cfg["profile"]["text"] = 5', "profile.text: expected a string or null, got 5"),
    (
        'cfg["service"]["pipeline"]["model_options"] = {"depth": "x"}',
        'service.pipeline.model_options.depth: expected an object, got "x"',
    ),
    ('del cfg["mapping"]["water_density"]', "mapping.water_density: missing"),
    ('cfg["service"]["max_vehicles"] = "x"', 'service.max_vehicles: expected an integer, got "x"'),
    ('cfg["service"]["pipeline"] = "bogus"', 'service.pipeline: expected an object, got "bogus"'),
    (
        'cfg["service"]["pipeline"]["burn_in"] = "abc"',
        'service.pipeline.burn_in: expected an integer, got "abc"',
    ),
    ('cfg["service"]["profile"] = "x"', 'service.profile: expected an object, got "x"'),
    ("cfg['service'] = 5", "service: expected an object, got 5"),
]


def _keys(cases: list[tuple[str, str]]) -> list[str]:
    """Each case's stored key, as its test id."""
    return [named.split(":")[0] for _, named in cases]


@pytest.mark.parametrize(("change", "named"), WRONG_TYPES, ids=_keys(WRONG_TYPES))
def test_replay_refuses_a_stored_value_of_the_wrong_type_naming_log_and_key(
    tmp_path, capsys, change, named
):
    log = _with(tmp_path / "bad.mcap", change)
    assert main(["replay", "--fast", str(log)]) == 2
    assert _one_line(capsys.readouterr().err) == f"glider-hil replay: {log}: stored config {named}"


@pytest.mark.parametrize(("change", "named"), WRONG_TYPES[:4], ids=_keys(WRONG_TYPES[:4]))
def test_info_shows_what_the_log_stores_and_names_the_unreadable_value(
    tmp_path, capsys, change, named
):
    log = _with(tmp_path / "bad.mcap", change)
    assert main(["info", "--json", str(log)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["config_error"] == f"{log}: stored config {named}"
    assert info["channels"][RAW_IN]["count"] == len(_frames())
    assert info["config"]["service"]["system_ids"] == []  # the rest, as stored
    assert main(["info", str(log)]) == 0
    assert f"configuration unreadable, shown as stored: {log}: stored config {named}" in (
        capsys.readouterr().out
    )


def test_a_stored_value_that_is_not_json_is_named_by_every_verb(tmp_path, capsys):
    metadata = _metadata(_stored())
    log = write_log(tmp_path / "raw.mcap", {**metadata, "service": "{not json"})
    named = f"{log}: stored config service: not JSON ("
    assert main(["replay", "--fast", str(log)]) == 2
    assert _one_line(capsys.readouterr().err).startswith(f"glider-hil replay: {named}")
    assert main(["report", str(log), "-o", str(tmp_path / "out")]) == 2
    assert _one_line(capsys.readouterr().err).startswith(f"glider-hil report: {named}")
    assert not (tmp_path / "out").exists()
    assert main(["info", "--json", str(log)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["config_error"].startswith(named)
    assert info["config"]["service"] == "{not json"  # shown as the text the log holds
    assert info["config"]["mapping"] == json.loads(metadata["mapping"])  # the rest, decoded


def _estimates(count: int, bad: dict[int, dict[str, Any]] | None = None) -> list[tuple[str, bytes]]:
    """Telemetry and a depth estimate per sample, as the service publishes them; ``bad``
    replaces fields of the k-th estimate."""
    records = []
    for k in range(count):
        t = float(k)
        telemetry = {"t": t, "depth": 15.0, "pitch": 0.0, "u_depth": 0.1, "u_pitch": -0.1}
        estimate = {"t": t, "y": 15.0 + k, "y_hat": 15.0, "baseline_y_hat": 15.0, "alpha": [1.0]}
        estimate.update((bad or {}).get(k, {}))
        records += [
            (keys.telemetry(1), json.dumps(telemetry).encode()),
            (keys.umodel(1, "depth"), json.dumps(estimate).encode()),
        ]
    return records


UNREADABLE_FOR_REPORT = [
    ('cfg["service"]["stale_timeout"] = "abc"', STALE_ABC),
    ('cfg["service"] = 5', "service: expected an object, got 5"),
]


@pytest.mark.parametrize(
    ("change", "named"), UNREADABLE_FOR_REPORT, ids=_keys(UNREADABLE_FOR_REPORT)
)
def test_report_refuses_an_unreadable_stored_configuration_rather_than_use_defaults(
    tmp_path, capsys, change, named
):
    cfg = _stored()
    cfg["service"]["pipeline"]["burn_in"] = 2  # readable, as everything but the change
    exec(change, {"cfg": cfg})
    metadata = _metadata(cfg)
    log = write_log(tmp_path / "bad.mcap", metadata, _estimates(10))
    assert main(["report", str(log), "-o", str(tmp_path / "out")]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err == f"glider-hil report: {log}: stored config {named}"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("ids", ["abc", [999], [0], [True]])
def test_stored_system_ids_outside_1_to_255_are_refused(tmp_path, capsys, ids):
    log = _with(tmp_path / "ids.mcap", f'cfg["service"]["system_ids"] = {ids!r}')
    assert main(["replay", "--fast", str(log)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err == (
        f"glider-hil replay: {log}: stored config service.system_ids: expected a list of "
        f"system ids 1..255, got {json.dumps(ids)}"
    )


#: (change, the message naming the stored key): ranges checked by ServiceConfig itself
OUT_OF_RANGE = [
    (
        'cfg["service"]["stale_timeout"] = -1',
        "service.stale_timeout: must be a positive finite number of s, got -1",
    ),
    (
        'cfg["service"]["limits"]["max_abs_pitch"] = -1',
        "service.limits.max_abs_pitch: is the largest |pitch|: it must be ≥ 0 rad, got -1",
    ),
    (
        'cfg["service"]["limits"].update(min_depth=5, max_depth=3)',
        "service.limits.min_depth: 5 m is deeper than service.limits.max_depth 3 m",
    ),
    ('cfg["service"]["vehicle_ids"] = "x"', "service.vehicle_ids: must be one of sysid, link"),
]


@pytest.mark.parametrize(("change", "named"), OUT_OF_RANGE, ids=_keys(OUT_OF_RANGE))
def test_an_out_of_range_stored_value_is_named_by_its_key_not_a_flag(
    tmp_path, capsys, change, named
):
    log = _with(tmp_path / "range.mcap", change)
    assert main(["replay", "--fast", str(log)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"glider-hil replay: {log}: stored config {named}")
    assert "--" not in err


def test_the_flag_wording_stays_for_a_flag():
    with pytest.raises(ValueError, match=r"^--stale-timeout must be a positive"):
        ServiceConfig(stale_timeout=-1)


def _inputs(time_boot_ms: Any = 0) -> bytes:
    event = {
        "time_boot_ms": time_boot_ms,
        "setpoints": {"depth": None, "pitch": None},
        "enabled": False,
        "reset": False,
    }
    return json.dumps(event).encode()


def test_damaged_decision_inputs_are_counted_skipped_and_the_first_named(tmp_path, capsys):
    topic = keys.decision_inputs(1)
    metadata = _metadata(_stored())
    records = [(topic, _inputs()), (topic, _inputs("x")), (topic, b"{not json")]
    log = write_log(tmp_path / "inputs.mcap", metadata, records)
    assert main(["replay", "--fast", "--json", str(log)]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert result["samples"] == SAMPLES and result["skipped_inputs"] == 2
    err = _one_line(captured.err)
    assert err.startswith(
        f"glider-hil replay: {log}: 2 decision-inputs record(s) could not be read and were "
        f"skipped; the first: {topic} at log time 2023-11-14T22:13:20+00:00: "
        'time_boot_ms: expected an integer ≥ 0, got "x"'
    )


def test_a_decision_inputs_record_that_is_not_json_is_named_as_such(tmp_path, capsys):
    topic = keys.decision_inputs(1)
    metadata = _metadata(_stored())
    log = write_log(tmp_path / "inputs.mcap", metadata, [(topic, b"{not json")])
    assert main(["replay", "--fast", str(log)]) == 0
    err = _one_line(capsys.readouterr().err)
    assert "1 decision-inputs record(s) could not be read" in err
    assert ": not JSON (" in err


def test_publications_with_wrong_typed_fields_are_counted_and_skipped(tmp_path):
    bad = {3: {"y": "abc", "y_hat": None}, 6: {"alpha": "12"}}
    records = _estimates(10, bad)
    telemetry_x = json.dumps({"t": "x", "u_depth": 0.1, "u_pitch": -0.1}).encode()
    records.insert(10, (keys.telemetry(1), telemetry_x))  # between samples 4 and 5
    metadata = _metadata(_stored())
    series = load_series(write_log(tmp_path / "pub.mcap", metadata, records))
    assert series.skipped == 3
    vehicle = series.vehicles[1]
    depth = vehicle.channels["depth"]
    assert depth.t == [0.0, 1.0, 2.0, 4.0, 5.0, 7.0, 8.0, 9.0]
    assert all(y == 15.0 + t for y, t in zip(depth.y, depth.t, strict=True))
    assert vehicle.telemetry_t == [float(k) for k in range(10)]
    assert vehicle.segment_starts == [0]  # no restart made up from the bad time


def test_a_field_import_whose_issues_or_grid_is_not_an_object_is_named(tmp_path):
    for name in ("issues", "grid"):
        field = {"format": "seaglider", "vehicle": "SG542", name: "many"}
        lines, figures, results = field_section(tmp_path / "x.mcap", {"field": field}, tmp_path)
        assert f"Not computed: the log's stored field.{name} is not an object" in "\n".join(lines)
        assert figures == [] and results == []


def test_replay_counts_the_frames_it_could_not_decode(tmp_path, capsys):
    metadata = _metadata(_stored())
    garbage = [bytes([0xFD, 9, 0, 0, 7]) + bytes(range(40)), b"\x00\x01junk", b""]
    log = write_log(tmp_path / "junk.mcap", metadata, frames=garbage)
    assert main(["replay", "--fast", "--json", str(log)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["samples"] == 0
    assert result["bad_frames"] > 0 and result["empty_frames"] == 1
    assert main(["replay", "--fast", str(log)]) == 0
    out = capsys.readouterr().out
    assert "replayed 0 samples (3 frames)" in out
    assert f"not decoded: {result['bad_frames']} bad frames" in out and "1 empty records" in out


def test_report_writes_nothing_for_a_log_with_nothing_to_report(tmp_path, capsys):
    metadata = _metadata(_stored())
    log = write_log(tmp_path / "junk.mcap", metadata, frames=[b"junk"])
    assert main(["report", str(log), "-o", str(tmp_path / "out")]) == 1
    assert _one_line(capsys.readouterr().err).endswith("holds no identifier publications")
    assert not (tmp_path / "out").exists()


def test_report_to_a_file_is_refused_as_not_a_directory(tmp_path, capsys):
    metadata = _metadata(_stored())
    log = write_log(tmp_path / "log.mcap", metadata, _estimates(10))
    afile = tmp_path / "afile"
    afile.write_text("kept")
    assert main(["report", str(log), "-o", str(afile)]) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"glider-hil report: {afile} is a file, not a directory"
    )
    assert afile.read_text() == "kept"


def test_a_stored_null_where_the_settings_take_none_is_read(tmp_path, capsys):
    change = (
        'cfg["service"]["pipeline"]["control"]["mean_fit"] = None; '
        'cfg["service"]["pipeline"]["choose_input_lags"] = None'
    )
    log = _with(tmp_path / "nulls.mcap", change)
    assert main(["replay", "--fast", str(log)]) == 0
    assert f"replayed {SAMPLES} samples" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("stored", "named"),
    [
        ({"field": {"format": "seaglider", "grid": {"period_s": "1 s"}}}, "field.grid.period_s"),
        ({"service": {"pipeline": {"burn_in": "x"}}}, "service.pipeline.burn_in"),
    ],
    ids=["grid-period", "pipeline"],
)
def test_experiment_on_a_log_names_an_unreadable_stored_value(tmp_path, capsys, stored, named):
    """``experiment --log`` reads the stored grid and pipeline as replay does: a value of the
    wrong type is one line naming the stored key, not a traceback."""
    log = write_log(tmp_path / "odd.mcap", _metadata(stored))
    code = main(["experiment", "--log", str(log)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert named in err and "Traceback" not in err
