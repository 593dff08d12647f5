"""``glider-hil fleet``: every vehicle that has a service, from the Zenoh network.

A vehicle is listed while a service holds its liveliness token ``glider/{id}/service``
(docs/zenoh.md): a liveliness subscriber with history sees the tokens present and every
later change, and a service that stops or dies (its session's lease runs out at the router)
drops its vehicles out. Each row shows what the vehicle's ``health`` (link rate, loss,
identification fit, control state) and ``command/ballast`` keys last said.

A row names its vehicle by key id (``vehicle``: ``7``, or ``2-7`` for system id 7 on a
service's link 2, ``serve --vehicle-ids link``), with ``system_id`` (the MAVLink one) and
``link`` (None for a plain system id) beside it.

Without ``--json``: a table refreshed in place every ``--period`` s until Ctrl-C. With
``--json``: one snapshot after ``--wait`` s (long enough for every service's 1 Hz health).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh

from hil_service.listeners.zenoh_config import ZenohOptions, open_session
from protocols import keys
from protocols.flag_types import non_negative_float, positive_float

HEALTH_KEYS = f"{keys.ROOT}/*/{keys.HEALTH}"
COMMAND_KEYS = f"{keys.ROOT}/*/{keys.COMMAND_BALLAST}"
SERVICE_KEYS = f"{keys.ROOT}/*/{keys.SERVICE}"


@dataclass
class VehicleRow:
    system_id: int  # the vehicle id (protocols.keys)
    health: dict[str, Any] = field(default_factory=dict)
    health_at: float | None = None  # monotonic s
    command: dict[str, Any] = field(default_factory=dict)
    command_at: float | None = None

    def snapshot(self, now: float) -> dict[str, Any]:
        health = self.health
        identifier = health.get("identifier") or {}
        control = health.get("control") or {}
        link, system_id = keys.split_vehicle_id(self.system_id)
        return {
            "vehicle": keys.key_id(self.system_id),
            "system_id": system_id,
            "link": link or None,
            "link_rate": health.get("link_rate"),
            "packet_loss": health.get("packet_loss"),
            "fit": {
                channel: (scores or {}).get("recent_skill")
                for channel, scores in identifier.items()
            },
            "converged": {
                channel: (scores or {}).get("converged") for channel, scores in identifier.items()
            },
            "control": {
                "enabled": control.get("enabled"),
                "commanding": control.get("commanding"),
                "reason": control.get("reason"),
            },
            "last_command": (
                {k: self.command.get(k) for k in ("t", "u_depth", "u_pitch", "setpoints")}
                if self.command
                else None
            ),
            "command_age_s": None if self.command_at is None else round(now - self.command_at, 2),
            "health_age_s": None if self.health_at is None else round(now - self.health_at, 2),
        }


class Fleet:
    """What the network says about the vehicles; filled by Zenoh callbacks (under a lock)."""

    def __init__(self, clock: Any = time.monotonic) -> None:
        self.clock = clock
        self.lock = threading.Lock()
        self.served: set[int] = set()
        self.rows: dict[int, VehicleRow] = {}
        self._raw: dict[tuple[int, str], tuple[bytes, float]] = {}  # newest, not yet parsed

    def _row(self, system_id: int) -> VehicleRow:
        row = self.rows.get(system_id)
        if row is None:
            row = self.rows[system_id] = VehicleRow(system_id)
        return row

    def on_liveliness(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse(str(sample.key_expr))
        if parsed is None or parsed.kind != keys.SERVICE:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self.served.discard(parsed.system_id)
                self.rows.pop(parsed.system_id, None)
                for kind in (keys.HEALTH, keys.COMMAND_BALLAST):
                    self._raw.pop((parsed.system_id, kind), None)
            else:
                self.served.add(parsed.system_id)

    def on_sample(self, sample: zenoh.Sample) -> None:
        # Kept as bytes and parsed when a snapshot shows it: a fleet of 100 sends 1,000
        # commands a second, and this observer must cost the machine it watches little.
        parsed = keys.parse(str(sample.key_expr))
        if parsed is None or parsed.kind not in (keys.HEALTH, keys.COMMAND_BALLAST):
            return
        raw = sample.payload.to_bytes()
        now = self.clock()
        with self.lock:
            self._raw[parsed.system_id, parsed.kind] = (raw, now)

    def _parse_pending(self) -> None:
        """Move the raw payloads received since the last snapshot into the rows (under the
        lock); one that is not a JSON object is skipped (the table shows what parses)."""
        pending, self._raw = self._raw, {}
        for (system_id, kind), (raw, at) in pending.items():
            try:
                payload = json.loads(raw)
            except ValueError:
                continue
            if not isinstance(payload, dict):
                continue
            row = self._row(system_id)
            if kind == keys.HEALTH:
                row.health, row.health_at = payload, at
            else:
                row.command, row.command_at = payload, at

    def snapshot(self) -> list[dict[str, Any]]:
        """One entry per served vehicle, by system id."""
        now = self.clock()
        with self.lock:
            self._parse_pending()
            return [self._row(system_id).snapshot(now) for system_id in sorted(self.served)]


def _fmt(value: Any, spec: str = ".3g") -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return format(value, spec)
    return str(value)


def render(rows: list[dict[str, Any]]) -> str:
    header = (
        f"{'id':>7} {'rate/s':>7} {'loss':>7} {'fit d':>7} {'fit p':>7} "
        f"{'control':<34} {'last command (u_d, u_p)':<24} {'age s':>6}"
    )
    lines = [f"glider-hil fleet: {len(rows)} vehicles served", header]
    for row in rows:
        control = row["control"]
        state = "commanding" if control.get("commanding") else (control.get("reason") or "-")
        if control.get("enabled") is False and not control.get("commanding"):
            state = f"off: {state}"
        command = row["last_command"]
        last = (
            "-"
            if command is None
            else (f"{_fmt(command.get('u_depth'))}, {_fmt(command.get('u_pitch'))}")
        )
        lines.append(
            f"{row.get('vehicle', row['system_id']):>7} {_fmt(row['link_rate'], '.1f'):>7} "
            f"{_fmt(row['packet_loss'], '.2%'):>7} {_fmt(row['fit'].get('depth')):>7} "
            f"{_fmt(row['fit'].get('pitch')):>7} {state[:34]:<34} {last[:24]:<24} "
            f"{_fmt(row['command_age_s'], '.1f'):>6}"
        )
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="router or service to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; with "
        "--zenoh-config, on top of the file's endpoints)",
    )
    parser.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="Zenoh JSON5 configuration file (e.g. config/zenoh/observer.json5)",
    )
    parser.add_argument("--json", action="store_true", help="print one snapshot as JSON")
    parser.add_argument(
        "--wait",
        type=non_negative_float,
        default=2.5,
        help="with --json: s to listen first (default 2.5)",
    )
    parser.add_argument(
        "--period", type=positive_float, default=1.0, help="table refresh, s (default 1)"
    )


def open_fleet(session: zenoh.Session, fleet: Fleet) -> list[Any]:
    return [
        session.liveliness().declare_subscriber(SERVICE_KEYS, fleet.on_liveliness, history=True),
        session.declare_subscriber(HEALTH_KEYS, fleet.on_sample),
        session.declare_subscriber(COMMAND_KEYS, fleet.on_sample),
    ]


def run(args: argparse.Namespace) -> int:
    options = ZenohOptions(
        config_file=args.zenoh_config,
        mode="client" if args.zenoh_connect else "peer",
        connect=tuple(args.zenoh_connect),
    )
    try:
        session = open_session(options)
    except Exception as error:  # zenoh raises ZError for a bad file or endpoint
        print(f"glider-hil fleet: cannot open Zenoh session: {error}", file=sys.stderr)
        return 2
    fleet = Fleet()
    try:
        declared = open_fleet(session, fleet)
    except Exception as error:  # a router that refuses the declarations
        session.close()
        print(f"glider-hil fleet: cannot listen for the fleet: {error}", file=sys.stderr)
        return 2
    stop = threading.Event()
    try:
        if args.json:
            time.sleep(args.wait)  # listening: the health keys come at 1 Hz
            print(json.dumps({"vehicles": fleet.snapshot()}))
            return 0
        signal.signal(signal.SIGINT, lambda *_: stop.set())
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        while not stop.wait(args.period):
            sys.stdout.write("\x1b[H\x1b[J" + render(fleet.snapshot()) + "\n")
            sys.stdout.flush()
        return 0
    finally:
        for item in declared:
            item.undeclare()
        session.close()
