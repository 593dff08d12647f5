"""The one place that turns command-line flags into a Zenoh configuration.

Defaults are safe for a laptop and for parallel test runs: peer mode, multicast and gossip
scouting off, so a session talks only to the endpoints it is given.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass, field

import zenoh


@dataclass(frozen=True)
class ZenohOptions:
    config_file: str | None = None
    mode: str = "peer"
    listen: Sequence[str] = field(default_factory=tuple)
    connect: Sequence[str] = field(default_factory=tuple)

    def to_config(self) -> zenoh.Config:
        """A Zenoh config: the file's, if given, with explicit flags on top."""
        config = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        if not self.config_file:
            config.insert_json5("mode", json.dumps(self.mode))
            config.insert_json5("scouting/multicast/enabled", "false")
            config.insert_json5("scouting/gossip/enabled", "false")
        if self.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        if self.connect:
            config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        return config


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("Zenoh")
    group.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration file")
    group.add_argument(
        "--zenoh-mode", choices=("peer", "client"), default="peer", help="default: peer"
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


def open_session(options: ZenohOptions) -> zenoh.Session:
    return zenoh.open(options.to_config())
