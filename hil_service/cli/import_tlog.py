"""``glider-hil import``: a telemetry log (.tlog, as MAVProxy and QGroundControl write it)
into an MCAP log that ``info``, ``report`` and ``replay`` read."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from hil_service.offline.tlog_import import import_tlog
from protocols.profiles import DEFAULT_PROFILE, ProfileError, load_profile


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("tlog", help="a telemetry log: 8-byte big-endian µs timestamp + frame")
    parser.add_argument("-o", "--output", required=True, help="the MCAP log to write")
    parser.add_argument(
        "--profile",
        default=DEFAULT_PROFILE,
        help="the vehicle's profile, stored in the log (default %(default)s)",
    )
    parser.add_argument(
        "--vehicle",
        type=int,
        default=None,
        help="the vehicle's system id (default: the first autopilot heard)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite the output")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def run(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.exists() and not args.force:
        print(f"glider-hil import: {output} exists (--force to overwrite)", file=sys.stderr)
        return 2
    try:
        profile = load_profile(args.profile)
        report = import_tlog(args.tlog, output, profile, args.vehicle)
    except (ProfileError, OSError) as error:
        print(f"glider-hil import: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"import": report.as_dict(), "output": str(output)}))
    else:
        print(report.describe())
        print(
            f"  vehicle system id {report.vehicle}; frames in {report.directions['in']}, "
            f"out {report.directions['out']}; bad {report.bad_frames}; -> {output}"
        )
    return 0 if report.complete else 1
