"""``glider-hil router``: a Zenoh router, so services on several processes or machines and
their subscribers meet on one network.

zenoh's Python package opens a session in router mode: this verb is that session, held until
SIGINT/SIGTERM (or ``--duration``). Any other Zenoh router (``zenohd -c FILE``) does the same
job. With ``--config`` the file is used as it is (``config/zenoh/router.json5``: TLS, user and
password, access control; relative paths resolve from the working directory, as for zenohd);
``--listen`` adds endpoints. Without a file: router mode, multicast and gossip scouting off,
listening where ``--listen`` says (default ``tcp/127.0.0.1:7447``).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

import zenoh

from hil_service.listeners.zenoh_config import (
    check_file_endpoints,
    config_from_file,
    insert_flag,
    unscouted_config,
    zenoh_error_text,
)
from protocols.flag_types import positive_float

#: What ``router`` prints on stderr once it listens.
ROUTER_READY = "glider-hil router: ready"
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="Zenoh JSON5 router configuration")
    parser.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to listen on (repeatable; default without --config: {DEFAULT_LISTEN})",
    )
    parser.add_argument(
        "--duration", type=positive_float, default=None, help="wall s, then exit (default: run)"
    )


def router_config(config_file: str | None, listen: list[str]) -> zenoh.Config:
    """The router's Zenoh configuration (raises on a bad file or endpoint)."""
    if config_file:
        config = config_from_file(config_file, "--config")
        config.insert_json5("mode", json.dumps("router"))
    else:
        config = unscouted_config("router")
        listen = listen or [DEFAULT_LISTEN]
    if listen:
        insert_flag(config, "listen/endpoints", listen, "--listen")
    if config_file:
        replaced = {"listen/endpoints"} if listen else set()
        check_file_endpoints(config, replaced, f"--config {config_file}")
    return config


def run(args: argparse.Namespace) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        session = zenoh.open(router_config(args.config, list(args.listen)))
    except Exception as error:  # zenoh raises ZError for a bad file, endpoint or port in use
        print(f"glider-hil router: {zenoh_error_text(error)}", file=sys.stderr)
        return 2
    try:
        print(f"{ROUTER_READY} zid {session.zid()}", file=sys.stderr, flush=True)
        stop.wait(args.duration)
    finally:
        session.close()
    return 0
