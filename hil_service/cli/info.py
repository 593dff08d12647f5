"""``glider-hil info``: what an MCAP log holds: duration, channels, stored configuration."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil_service.config import ServiceConfig, stored_profile
from hil_service.mcap.reader import LogError, LogReader, StoredConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="an MCAP log written by glider-hil serve")
    parser.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    reader = LogReader(args.log)
    first: int | None = None
    last = 0
    try:
        for message in reader.messages():
            first = message.log_time_ns if first is None else first
            last = message.log_time_ns
    except (LogError, OSError) as error:
        print(f"glider-hil info: {error}", file=sys.stderr)
        return 2
    report = reader.report
    info = {
        "path": report.path,
        "complete": report.complete,
        "damaged_chunks": report.damaged_chunks,
        "messages": report.messages,
        "duration_s": 0.0 if first is None else (last - first) / 1e9,
        "channels": {
            topic: {"count": c["count"], "encoding": c["encoding"], "schema": c["schema"]}
            for topic, c in sorted(report.channels.items())
        },
    }
    info.update(_config_entries(reader))
    if not report.intact:
        info["recovery"] = report.describe()
    try:
        _print(info, args.json)
    except BrokenPipeError:  # `glider-hil info LOG | head`
        sys.stderr.close()
    return 0


def _config_entries(reader: LogReader) -> dict[str, Any]:
    """``config``: the stored configuration as the service reads it back (defaults filled in
    for fields an older log lacks, listed in ``config_defaults``), or what the file holds
    when that is not a service configuration. When a stored value cannot be read: what the
    file holds (a value that is not JSON as its text) and ``config_error`` naming it."""
    stored, problems = reader.config_parts()
    if problems:
        return {"config": stored, "config_error": "; ".join(str(p) for p in problems)}
    try:
        config = ServiceConfig.from_stored(stored, reader.path)
        if config is None:
            stored_profile(stored, reader.path)  # what replay runs with, an import's too
    except StoredConfigError as error:
        return {"config": stored, "config_error": str(error)}
    read = stored if config is None else config.stored()
    defaults = _defaulted(stored, read)
    return {"config": read, **({"config_defaults": defaults} if defaults else {})}


def _defaulted(stored: dict[str, Any], read: dict[str, Any]) -> list[str]:
    """Fields of the configuration read back that the log does not hold (an older log):
    they show the defaults, not what that service ran with."""
    missing = []
    for part, fields in read.items():
        if not isinstance(fields, dict):
            continue
        held = stored.get(part)
        if not isinstance(held, dict):
            missing.append(part)
        else:
            missing += [f"{part}.{name}" for name in fields if name not in held]
    return missing


def _print(info: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(info, indent=2))
        return
    print(f"{info['path']}: {info['messages']} messages over {info['duration_s']:.1f} s")
    if "recovery" in info:
        print(f"  {info['recovery']}")
    print(f"  {'channel':48} {'count':>8}  encoding  schema")
    for topic, channel in info["channels"].items():
        print(f"  {topic:48} {channel['count']:>8}  {channel['encoding']:8}  {channel['schema']}")
    print("  configuration:")
    print("    " + json.dumps(info["config"], indent=2).replace("\n", "\n    "))
    if "config_error" in info:
        print(f"  configuration unreadable, shown as stored: {info['config_error']}")
    if "config_defaults" in info:
        print(f"  not in this log, shown with their defaults: {', '.join(info['config_defaults'])}")
