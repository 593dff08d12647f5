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
from collections.abc import Sequence
from dataclasses import dataclass, field

import zenoh

from hil_service.listeners.zenoh_shutdown import close_at_exit
from protocols.input_files import not_a_file

DEFAULT_MODE = "peer"


@dataclass(frozen=True)
class ZenohOptions:
    config_file: str | None = None
    mode: str | None = None  # None: the file's mode, or DEFAULT_MODE without a file
    listen: Sequence[str] = field(default_factory=tuple)
    connect: Sequence[str] = field(default_factory=tuple)

    def to_config(self) -> zenoh.Config:
        """A Zenoh config: the file's, if given, with every explicit flag on top."""
        if self.config_file:
            problem = not_a_file(self.config_file, "Zenoh configuration file")
            if problem:
                raise ValueError(f"--zenoh-config {problem}")
            try:
                config = zenoh.Config.from_file(self.config_file)
            except zenoh.ZError as error:
                raise ValueError(
                    f"--zenoh-config {self.config_file}: {zenoh_error_text(error)}"
                ) from error
        else:
            config = zenoh.Config()
            config.insert_json5("mode", json.dumps(DEFAULT_MODE))
            config.insert_json5("scouting/multicast/enabled", "false")
            config.insert_json5("scouting/gossip/enabled", "false")
        flags = (
            ("mode", "--zenoh-mode", self.mode),
            ("listen/endpoints", "--zenoh-listen", list(self.listen) or None),
            ("connect/endpoints", "--zenoh-connect", list(self.connect) or None),
        )
        for key, flag, value in flags:
            if value is None:
                continue
            try:
                config.insert_json5(key, json.dumps(value))
            except zenoh.ZError as error:
                raise ValueError(f"{flag}: {zenoh_error_text(error)}") from error
        return config


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


#: A configuration value zenoh refused, as Rust's debug form of its JSON5 error:
#: ``Json5Err(Message { msg: "…", location: … })``; the message is what a user reads.
_JSON5_MESSAGE = re.compile(r'Json5Err\(Message \{ msg: "(.*?)", location: .*\}\)$', re.S)


def zenoh_error_text(error: BaseException) -> str:
    """A Zenoh error's message without the Rust source locations and debug forms it
    carries."""
    text = _RUST_SOURCE.sub("", str(error)).strip()
    json5 = _JSON5_MESSAGE.search(text)
    return text if json5 is None else text[: json5.start()] + json5.group(1)


def open_session(options: ZenohOptions) -> zenoh.Session:
    """A session for ``options``, closed at exit if nothing closes it (``zenoh_shutdown``).
    ValueError for a configuration file that is not one (``to_config``), OSError for what
    zenoh refuses (a file it cannot parse, an endpoint in use or unreachable), in a message
    that names no Rust source."""
    try:
        session = zenoh.open(options.to_config())
    except zenoh.ZError as error:
        raise OSError(zenoh_error_text(error)) from error
    return close_at_exit(session)
