"""Zenoh flags given on the command line win over ``--zenoh-config``."""

from __future__ import annotations

import argparse
import json
import threading

import pytest
import zenoh

from hil_service.listeners.zenoh_config import (
    ZenohOptions,
    add_zenoh_arguments,
    open_session,
    options_from_args,
)
from tests.conftest import free_tcp_port


def _parse(*argv: str) -> ZenohOptions:
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    return options_from_args(parser.parse_args(list(argv)))


def _file(tmp_path, nowhere: str) -> str:
    """A client that must reach a router at ``nowhere`` (nothing listens there)."""
    path = tmp_path / "client.json5"
    path.write_text(
        "{ mode: 'client',"
        f"  connect: {{ endpoints: ['{nowhere}'] }},"
        "  scouting: { multicast: { enabled: false }, gossip: { enabled: false } } }"
    )
    return str(path)


def _get(config: zenoh.Config, key: str) -> object:
    return json.loads(config.get_json(key))


def test_flags_are_applied_over_the_config_file(tmp_path):
    nowhere = f"tcp/127.0.0.1:{free_tcp_port()}"
    listen = f"tcp/127.0.0.1:{free_tcp_port()}"
    config_file = _file(tmp_path, nowhere)
    config = _parse(
        "--zenoh-config", config_file, "--zenoh-mode", "peer", "--zenoh-listen", listen
    ).to_config()
    assert _get(config, "mode") == "peer"
    assert _get(config, "listen/endpoints") == [listen]
    assert _get(config, "connect/endpoints") == [nowhere]  # the file's, no flag given
    assert _get(config, "scouting/multicast/enabled") is False


def test_file_without_flags_keeps_its_mode(tmp_path):
    nowhere = f"tcp/127.0.0.1:{free_tcp_port()}"
    config = _parse("--zenoh-config", _file(tmp_path, nowhere)).to_config()
    assert _get(config, "mode") == "client"
    defaults = _parse().to_config()
    assert _get(defaults, "mode") == "peer"
    assert _get(defaults, "scouting/multicast/enabled") is False


def test_a_session_from_file_and_flags_listens_on_the_flags_endpoint(tmp_path):
    """The file alone is a client with no router (it cannot open); the flags make it a peer
    listening on an endpoint of its own, which another session reaches."""
    nowhere = f"tcp/127.0.0.1:{free_tcp_port()}"
    listen = f"tcp/127.0.0.1:{free_tcp_port()}"
    options = _parse(
        "--zenoh-config", _file(tmp_path, nowhere), "--zenoh-mode", "peer",
        "--zenoh-listen", listen,
    )  # fmt: skip
    session = open_session(options)
    other = None
    try:
        received = threading.Event()
        subscriber = session.declare_subscriber("test/flags", lambda _s: received.set())
        other = open_session(ZenohOptions(connect=(listen,)))
        publisher = other.declare_publisher("test/flags")
        for _ in range(50):  # until the subscription has propagated (5 s at most)
            publisher.put(b"hello")
            if received.wait(0.1):
                break
        assert received.is_set(), "nothing arrived on the flag's endpoint"
        publisher.undeclare()
        subscriber.undeclare()
    finally:
        if other is not None:
            other.close()
        session.close()


@pytest.mark.parametrize(
    ("endpoint", "bad_host"),
    [
        ("tcp/127.0.0.1:7447", None),
        ("tcp/[::1]:7447", None),
        ("tcp/127.0.0.1:7447?iface=lo", None),  # metadata after the address
        ("unixsock-stream//tmp/zenoh.sock", None),  # a path, no host
        ("tcp/999.1.1.1:7447", "999.1.1.1"),
        ("udp/10.0.0.300:7447#rel=1", "10.0.0.300"),
        ("tcp/[zz::1]:7447", "zz::1"),
    ],
)
def test_an_endpoint_whose_host_is_no_address_is_named(endpoint, bad_host):
    """Zenoh says only "failed to lookup address information" when the session opens, and
    names no endpoint; the check names the flag, the endpoint and the host. Only numeric
    hosts here: a name would be looked up."""
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    options = options_from_args(parser.parse_args(["--zenoh-connect", endpoint]))
    if bad_host is None:
        options.to_config()
        return
    with pytest.raises(ValueError) as refused:
        options.to_config()
    assert str(refused.value).startswith(f"--zenoh-connect {endpoint}: host {bad_host!r}")


def test_serve_and_the_router_name_an_endpoint_whose_host_is_no_address(processes):
    """Each in a process of its own, as a user starts it: the router installs its signal
    handlers before it opens its session, and must not leave them in the test run."""
    for verb, flag in (("router", "--listen"), ("serve", "--zenoh-listen")):
        extra = ("--mavlink", "udpin:127.0.0.1:0", "--no-log") if verb == "serve" else ()
        process = processes.start(verb, flag, "tcp/999.0.0.1:7447", *extra)
        _, err = process.communicate(timeout=60)
        assert process.returncode == 2, err
        assert f"glider-hil {verb}: {flag} tcp/999.0.0.1:7447: host '999.0.0.1'" in err


def _file_with(tmp_path, listen: object, connect: object) -> str:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        json.dumps(
            {
                "mode": "peer",
                "listen": {"endpoints": listen},
                "connect": {"endpoints": connect},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            }
        )
    )
    return str(path)


def test_an_endpoint_of_the_config_file_whose_host_is_no_address_is_named(tmp_path):
    """The file's endpoints are checked like the flags' (a list, or one list per mode),
    naming the file, the key and the endpoint; a flag that replaces the key wins."""
    good = f"tcp/127.0.0.1:{free_tcp_port()}"
    per_mode = {"router": [], "peer": ["tcp/999.2.2.2:7447"]}
    config_file = _file_with(tmp_path, [good], per_mode)
    with pytest.raises(ValueError) as refused:
        _parse("--zenoh-config", config_file).to_config()
    assert str(refused.value).startswith(
        f"--zenoh-config {config_file}: connect/endpoints tcp/999.2.2.2:7447: host '999.2.2.2'"
    )
    _parse("--zenoh-config", config_file, "--zenoh-connect", good).to_config()

    listening = _file_with(tmp_path, ["udp/10.0.0.300:7447"], [])
    with pytest.raises(ValueError, match=r"listen/endpoints udp/10\.0\.0\.300:7447: host"):
        _parse("--zenoh-config", listening).to_config()
    _parse("--zenoh-config", listening, "--zenoh-listen", good).to_config()
    _parse("--zenoh-config", _file_with(tmp_path, ["tcp/[::]:0"], [good])).to_config()


def test_the_router_names_an_endpoint_of_its_config_file_whose_host_is_no_address(tmp_path):
    from hil_service.cli.router import router_config

    config_file = _file_with(tmp_path, ["tcp/999.3.3.3:7447"], [])
    refusal = r"--config .*listen/endpoints tcp/999\.3\.3\.3:7447: host"
    with pytest.raises(ValueError, match=refusal):
        router_config(config_file, [])
    router_config(config_file, [f"tcp/127.0.0.1:{free_tcp_port()}"])
