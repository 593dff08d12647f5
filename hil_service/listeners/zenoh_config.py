"""The one place that turns command-line flags into a Zenoh configuration.

Defaults are safe for a laptop and for parallel test runs: peer mode, multicast and gossip
scouting off, so a session talks only to the endpoints it is given. With ``--zenoh-config``
the file is the base and every flag given on the command line is applied over it, as
zenoh's own examples do: a flag the user typed always wins, a flag left out leaves the
file's value (the safe defaults fill in only what neither says).
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass, field

import zenoh

from hil_service.listeners.zenoh_shutdown import close_at_exit
from protocols.input_files import not_a_file
from protocols.link_address import address_problem

DEFAULT_MODE = "peer"


@dataclass(frozen=True)
class ZenohOptions:
    config_file: str | None = None
    mode: str | None = None  # None: the file's mode, or DEFAULT_MODE without a file
    listen: Sequence[str] = field(default_factory=tuple)
    connect: Sequence[str] = field(default_factory=tuple)

    def to_config(self) -> zenoh.Config:
        """A Zenoh config: the file's, if given, with every explicit flag on top (ValueError
        naming the flag for a file or a value zenoh refuses)."""
        if self.config_file:
            config = config_from_file(self.config_file, "--zenoh-config")
        else:
            config = unscouted_config(DEFAULT_MODE)
        if self.mode is not None:
            insert_flag(config, "mode", self.mode, "--zenoh-mode")
        if self.listen:
            insert_flag(config, "listen/endpoints", list(self.listen), "--zenoh-listen")
        if self.connect:
            insert_flag(config, "connect/endpoints", list(self.connect), "--zenoh-connect")
        if self.config_file:
            flagged = {"listen/endpoints": self.listen, "connect/endpoints": self.connect}
            replaced = {key for key, given in flagged.items() if given}
            check_file_endpoints(config, replaced, f"--zenoh-config {self.config_file}")
        return config


def unscouted_config(mode: str) -> zenoh.Config:
    """A configuration in ``mode`` with multicast and gossip scouting off: without a file,
    a session or router talks only to the endpoints it is given."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    return config


def config_from_file(path: str, flag: str) -> zenoh.Config:
    """The Zenoh configuration in ``path``; ValueError naming ``flag`` and the file when it
    is not a regular file (checked before zenoh opens it: a pipe would block) or zenoh
    cannot parse it."""
    problem = not_a_file(path, "Zenoh configuration file")
    if problem:
        raise ValueError(f"{flag} {problem}")
    try:
        return zenoh.Config.from_file(path)
    except zenoh.ZError as error:
        raise ValueError(f"{flag} {path}: {zenoh_error_text(error, in_file=True)}") from error


def insert_flag(config: zenoh.Config, key: str, value: object, flag: str) -> None:
    """``config[key] = value`` from ``flag``; ValueError naming the flag when zenoh refuses
    the value (an endpoint that is not ``<protocol>/<address>``) or when an endpoint's host
    is not an address (``endpoint_problem``)."""
    try:
        config.insert_json5(key, json.dumps(value))
    except zenoh.ZError as error:
        raise ValueError(f"{flag}: {zenoh_error_text(error)}") from error
    if key.endswith("/endpoints") and isinstance(value, list):
        _check_endpoints(value, flag)


ENDPOINT_KEYS = ("listen/endpoints", "connect/endpoints")


def check_file_endpoints(config: zenoh.Config, replaced: Collection[str], source: str) -> None:
    """ValueError naming ``source`` (the flag and the file), the key and the endpoint when
    an endpoint a configuration file gives under ``ENDPOINT_KEYS`` has a host that is not an
    address (``endpoint_problem``). Keys in ``replaced`` are skipped: a flag the user typed
    replaced the file's value, and was checked as it was inserted."""
    for key in ENDPOINT_KEYS:
        if key in replaced:
            continue
        given = json.loads(config.get_json(key))
        per_mode = given.values() if isinstance(given, dict) else [given]
        for endpoints in per_mode:
            listed = endpoints if isinstance(endpoints, list) else [endpoints]
            _check_endpoints(listed, f"{source}: {key}")


def _check_endpoints(endpoints: Iterable[object], where: str) -> None:
    """ValueError ``{where} {endpoint}: {why}`` for the first endpoint whose host is not an
    address."""
    for endpoint in endpoints:
        problem = endpoint_problem(str(endpoint))
        if problem:
            raise ValueError(f"{where} {endpoint}: {problem}")


#: Zenoh's protocols whose address is HOST:PORT (the others name a path or a device).
HOST_PORT_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})


def endpoint_problem(endpoint: str) -> str:
    """Why the host of a ``<protocol>/<host>:<port>`` endpoint (its metadata and config
    after ``?`` or ``#`` left out) cannot be an address, or "". Zenoh would say only
    "failed to lookup address information" when the session opens, naming no endpoint."""
    protocol, _, address = endpoint.partition("/")
    address = address.split("?", 1)[0].split("#", 1)[0]
    host, _, port = address.rpartition(":")
    if protocol.lower() not in HOST_PORT_PROTOCOLS or not host or not port.isdigit():
        return ""
    return address_problem(host, int(port))


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("Zenoh")
    group.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration file")
    group.add_argument(
        "--zenoh-mode",
        choices=("peer", "client"),
        default=None,
        help=f"default: the config file's mode, else {DEFAULT_MODE}",
    )
    group.add_argument(
        "--zenoh-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    group.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )


def options_from_args(args: argparse.Namespace) -> ZenohOptions:
    return ZenohOptions(
        config_file=args.zenoh_config,
        mode=args.zenoh_mode,
        listen=tuple(args.zenoh_listen),
        connect=tuple(args.zenoh_connect),
    )


#: Where in zenoh's Rust sources an error was raised, as its message ends: `` at
#: /root/.cargo/git/checkouts/…/lib.rs:1472.`` Nothing a user can act on.
_RUST_SOURCE = re.compile(r"\s+at \S+\.rs:\d+\.?")


#: A configuration value zenoh refused, in Rust's debug form of its JSON5 error:
#: ``Json5Err(Message { msg: "…", location: … })`` for a value, ``JSON error: Message { … }``
#: for a file; the message, and for a file its line and column, are what a user reads.
_JSON5_MESSAGE = re.compile(
    r'(?:Json5Err\(|JSON error: )Message \{ msg: "(.*?)", location: '
    r"(?:Some\(Location \{ line: (\d+), column: (\d+) \}\)|None) \}\)?",
    re.S,
)


def zenoh_error_text(error: BaseException, in_file: bool = False) -> str:
    """A Zenoh error's message without the Rust source locations and debug forms it
    carries; with ``in_file``, a JSON5 error's line and column in the file after it."""

    def message(match: re.Match[str]) -> str:
        line, column = match.group(2), match.group(3)
        where = f" (line {line}, column {column})" if in_file and line else ""
        return match.group(1) + where

    return _JSON5_MESSAGE.sub(message, _RUST_SOURCE.sub("", str(error))).strip()


def open_session(options: ZenohOptions) -> zenoh.Session:
    """A session for ``options``, closed at exit if nothing closes it (``zenoh_shutdown``).
    ValueError for a configuration zenoh refuses (``to_config``), OSError for a session it
    cannot open (an endpoint in use or unreachable), in messages that name no Rust source."""
    try:
        session = zenoh.open(options.to_config())
    except zenoh.ZError as error:
        raise OSError(zenoh_error_text(error)) from error
    return close_at_exit(session)
