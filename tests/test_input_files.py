"""A file a flag names (a signing key, a Zenoh configuration, a field mapping) that is
missing, a directory or a named pipe is refused in one line saying which, exit 2, before it
is opened: a pipe would block the open until a writer came (Zenoh's reader does so holding
the interpreter, where not even SIGTERM ends the process)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from hil_service.cli import main
from protocols.input_files import not_a_file
from tests.conftest import free_udp_port


@pytest.fixture
def paths(tmp_path: Path) -> dict[str, Path]:
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    return {"missing": tmp_path / "none", "directory": tmp_path, "pipe": pipe}


SAYS = {
    "missing": "no such",
    "directory": "a directory, not a",
    "pipe": "not a regular file (a pipe or a device: save it to a file)",
}


def _refused(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    (line,) = err.strip().splitlines()
    return line


def _zenoh_verbs(serve_flag: str, fleet_flag: str, router_flag: str) -> dict[str, list[str]]:
    """``serve``, ``fleet`` and ``router`` runs that would end by themselves, each ending in
    the flag given for it (its value to be appended)."""
    link = f"udpin:127.0.0.1:{free_udp_port()}"
    return {
        "serve": ["serve", "--mavlink", link, "--no-log", "--duration", "1", serve_flag],
        "fleet": ["fleet", "--json", "--wait", "1", fleet_flag],
        "router": ["router", "--duration", "1", router_flag],
    }


def test_a_regular_file_passes_and_the_rest_are_named(paths, tmp_path) -> None:
    regular = tmp_path / "key"
    regular.write_bytes(b"")
    assert not_a_file(regular, "key") == ""
    for kind, path in paths.items():
        assert not_a_file(path, "key").startswith(f"{path}: {SAYS[kind]}")


@pytest.mark.parametrize("kind", sorted(SAYS))
def test_serve_and_emulate_refuse_such_a_signing_key(capsys, paths, kind) -> None:
    key = str(paths[kind])
    link = f"udpin:127.0.0.1:{free_udp_port()}"
    serve = ["serve", "--mavlink", link, "--no-log", "--duration", "1", "--signing-key", key]
    line = _refused(capsys, serve)
    assert line.startswith(f"glider-hil serve: cannot read signing key {key}: {SAYS[kind]}")
    emulate = ["emulate", "--connect", "udpout:127.0.0.1:9", "--duration", "1", "--signing-key"]
    line = _refused(capsys, [*emulate, key])
    assert line.startswith(f"glider-hil emulate: cannot read signing key {key}: {SAYS[kind]}")


@pytest.mark.parametrize("kind", sorted(SAYS))
def test_serve_fleet_and_router_refuse_such_a_zenoh_configuration(capsys, paths, kind) -> None:
    config = str(paths[kind])
    argvs = _zenoh_verbs("--zenoh-config", "--zenoh-config", "--config")
    for verb, argv in argvs.items():
        line = _refused(capsys, [*argv, config])
        assert line.startswith(f"glider-hil {verb}: ")
        assert f"{argv[-1]} {config}: {SAYS[kind]}" in line, line


@pytest.mark.parametrize("kind", sorted(SAYS))
def test_import_refuses_such_a_mapping(capsys, paths, tmp_path, kind) -> None:
    data = tmp_path / "d.csv"
    data.write_text("t,depth\n1,2\n")
    mapping = str(paths[kind])
    argv = ["import", str(data), "--format", "csv", "--mapping", mapping]
    line = _refused(capsys, [*argv, "-o", str(tmp_path / "o.mcap")])
    assert line.startswith(f"glider-hil import: {mapping}: {SAYS[kind]}")


def test_zenoh_s_refusals_are_said_without_its_rust_source_paths(capsys, tmp_path) -> None:
    """A configuration file zenoh cannot parse is named with the flag and where it fails,
    and an endpoint in use is said as zenoh says it, neither with the ``at /root/.cargo/…
    lib.rs:1486`` the Rust error carries; the live view's address is HOST:PORT."""
    bad = tmp_path / "zenoh.json5"
    bad.write_text("{ not json5")
    link = f"udpin:127.0.0.1:{free_udp_port()}"
    serve = ["serve", "--mavlink", link, "--no-log", "--duration", "1"]
    argvs = _zenoh_verbs("--zenoh-config", "--zenoh-config", "--config")
    for verb, argv in argvs.items():
        argv.append(str(bad))
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"glider-hil {verb}: ") and f"{argv[-2]} {bad}: " in err, err
        assert "1 | { not json5" in err and ".rs:" not in err and "Traceback" not in err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["router", "--duration", "1", "--listen", f"tcp/127.0.0.1:{port}"]) == 2
        err = capsys.readouterr().err
        assert "Address already in use" in err and ".rs:" not in err, err
        assert main([*serve, "--zenoh-listen", f"tcp/127.0.0.1:{port}"]) == 2
        err = capsys.readouterr().err
        assert "cannot open Zenoh session" in err and "Address already in use" in err
        assert ".rs:" not in err
        assert main([*serve, "--foxglove", f"127.0.0.1:{port}"]) == 2
        err = capsys.readouterr().err
        assert f"cannot start the Foxglove server on 127.0.0.1:{port}: " in err, err


def test_an_endpoint_zenoh_refuses_is_said_with_its_flag_and_zenoh_s_own_words(capsys) -> None:
    """Not Rust's debug form of the error (``Json5Err(Message { msg: …, location: … })``)."""
    argvs = _zenoh_verbs("--zenoh-listen", "--zenoh-connect", "--listen")
    for verb, argv in argvs.items():
        line = _refused(capsys, [*argv, "nonsense"])
        assert line.startswith(f"glider-hil {verb}: ") and f"{argv[-1]}: Endpoints must be" in line
        assert line.endswith(": nonsense") and "Json5Err" not in line and ".rs:" not in line


def test_a_value_zenoh_refuses_in_a_configuration_file_is_said_with_its_line(
    capsys, tmp_path
) -> None:
    """A file that parses but holds a value zenoh refuses (a mode it has not): the file, the
    message and where it is, not ``JSON error: Message { msg: …, location: Some(…) }``."""
    config = tmp_path / "zenoh.json5"
    config.write_text('{\n  mode: "nonsense",\n}\n')
    for verb, argv in _zenoh_verbs("--zenoh-config", "--zenoh-config", "--config").items():
        line = _refused(capsys, [*argv, str(config)])
        assert line.startswith(f"glider-hil {verb}: ") and f"{argv[-1]} {config}: " in line
        assert "unknown variant `nonsense`" in line and "(line 2, column " in line, line
        assert "Message {" not in line and ".rs:" not in line
