"""``fleet`` and ``router`` refuse a number their flag cannot take before anything runs (one
line naming the flag, exit 2); ``emulate --vehicles N --latency-trace FILE`` refuses a FILE
that cannot be written before the run, and prints its summary even when writing the trace
fails after it; ``fleet`` that cannot declare its subscribers says so and closes its
session."""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import SimpleNamespace

import pytest

from hil_service.cli import main
from plant_emulator.fleet import write_latency_trace
from tests.refused_flags import must_not_run, refused_by_argparse

#: A fleet run short enough to end by itself: 1 s of plant time at 100x.
SHORT_FLEET = (
    "emulate", "--vehicles", "2", "--connect", "udpout:127.0.0.1:9", "--duration", "1",
    "--speed", "100",
)  # fmt: skip


# ---- fleet ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("flag", "value"),
    [
        ("--wait", "nan"),
        ("--wait", "-1"),
        ("--wait", "inf"),
        ("--period", "0"),
        ("--period", "-1"),
        ("--period", "nan"),
        ("--period", "inf"),
    ],
)
@pytest.mark.parametrize("json_output", [True, False])
def test_fleet_refuses_a_number_its_flag_cannot_take(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    flag: str,
    value: str,
    json_output: bool,
) -> None:
    monkeypatch.setattr("hil_service.cli.fleet.run", must_not_run)
    argv = ["fleet", *(["--json"] if json_output else []), flag, value]
    err = refused_by_argparse(capsys, argv)
    assert f"argument {flag}: expected" in err and repr(value) in err


def test_fleet_takes_a_zero_wait() -> None:
    from hil_service.cli import build_parser

    args = build_parser("fleet").parse_args(["fleet", "--json", "--wait", "0", "--period", "0.2"])
    assert (args.wait, args.period) == (0.0, 0.2)


# ---- router --------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["nan", "-1", "0", "inf"])
def test_router_refuses_a_duration_that_is_not_a_positive_number(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    monkeypatch.setattr("hil_service.cli.router.run", must_not_run)
    err = refused_by_argparse(capsys, ["router", "--duration", value])
    assert "argument --duration: expected" in err and repr(value) in err


# ---- emulate --latency-trace ---------------------------------------------------------------
@pytest.mark.parametrize("where", ["missing directory", "directory"])
def test_emulate_refuses_a_latency_trace_it_cannot_write_before_the_run(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    where: str,
) -> None:
    monkeypatch.setattr("plant_emulator.fleet._open_fleet", must_not_run)
    trace = tmp_path / "missing" / "trace.jsonl" if where == "missing directory" else tmp_path
    assert main([*SHORT_FLEET, "--latency-trace", str(trace)]) == 2
    err = capsys.readouterr().err
    assert f"--latency-trace {trace}:" in err and "Traceback" not in err
    assert not (tmp_path / "missing").exists()


def test_emulate_refuses_a_latency_trace_for_one_vehicle(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr("plant_emulator.cli._emulate", must_not_run)
    argv = ["emulate", "--latency-trace", str(tmp_path / "trace.jsonl"), *SHORT_FLEET[3:]]
    assert main(argv) == 2
    assert "--latency-trace measures a fleet" in capsys.readouterr().err


def test_emulate_writes_the_latency_trace_where_it_can(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    trace = tmp_path / "trace.jsonl"
    assert main([*SHORT_FLEET, "--latency-trace", str(trace)]) == 0
    assert json.loads(capsys.readouterr().out)["emulator"]["vehicles"] == 2
    assert trace.is_file()


def test_emulate_keeps_the_summary_when_the_latency_trace_cannot_be_written_after_the_run(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # As if the directory, there at the start, were removed during the run.
    monkeypatch.setattr("plant_emulator.fleet.check_latency_trace", lambda path: None)
    trace = tmp_path / "removed" / "trace.jsonl"
    assert main([*SHORT_FLEET, "--latency-trace", str(trace)]) == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out)["emulator"]["vehicles"] == 2
    assert f"--latency-trace {trace}: cannot write" in captured.err
    assert "Traceback" not in captured.err


def test_fleet_that_cannot_listen_says_why_and_closes_its_session(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A failure to declare the fleet's subscribers is one line and exit 2, with the Zenoh
    session closed (an open one would keep the interpreter from exiting)."""
    from hil_service.cli import fleet as fleet_cli
    from hil_service.listeners.zenoh_config import ZenohOptions, open_session
    from tests.conftest import free_tcp_port

    opened = []

    def open_on_loopback(options: ZenohOptions):  # the test's own endpoint, not the default
        opened.append(open_session(ZenohOptions(listen=(f"tcp/127.0.0.1:{free_tcp_port()}",))))
        return opened[-1]

    def refuse(*args: object) -> list[object]:
        raise RuntimeError("declaration refused")

    monkeypatch.setattr(fleet_cli, "open_session", open_on_loopback)
    monkeypatch.setattr(fleet_cli, "open_fleet", refuse)
    assert main(["fleet", "--json", "--wait", "0"]) == 2
    err = capsys.readouterr().err
    assert "glider-hil fleet: cannot listen for the fleet: declaration refused" in err
    assert len(opened) == 1 and opened[0].is_closed()


def test_emulate_does_not_wait_for_a_reader_of_a_latency_trace_pipe(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # Opening a named pipe for writing blocks until a process opens it for reading.
    pipe = tmp_path / "trace.pipe"
    os.mkfifo(pipe)
    assert main([*SHORT_FLEET, "--latency-trace", str(pipe)]) == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out)["emulator"]["vehicles"] == 2
    assert f"--latency-trace {pipe}: cannot write (a named pipe no process reads)" in captured.err


def test_the_latency_trace_goes_into_a_pipe_that_is_read(tmp_path: Path) -> None:
    pipe = tmp_path / "trace.pipe"
    os.mkfifo(pipe)
    reader = os.open(pipe, os.O_RDONLY | os.O_NONBLOCK)  # a reader there before the write
    vehicle = SimpleNamespace(vehicle=1007, sent_times=[1.5, 2.5], latencies=[0.001, 0.002])
    try:
        write_latency_trace(str(pipe), [vehicle])  # type: ignore[list-item]
        received = os.read(reader, 65536).decode()
    finally:
        os.close(reader)
    # One JSON array a line: [sent, vehicle, latency] (docs/fleet.md).
    assert [json.loads(line) for line in received.splitlines()] == [
        [1.5, 1007, 0.001],
        [2.5, 1007, 0.002],
    ]
