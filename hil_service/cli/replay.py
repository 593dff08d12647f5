"""``glider-hil replay``: feed a log's MAVLink frames through the service path again."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil_service.builder import publisher
from hil_service.cli.serve import add_foxglove_argument, foxglove_from_args, start_live
from hil_service.listeners.zenoh_config import add_zenoh_arguments, open_session, options_from_args
from hil_service.mcap.reader import LogError
from hil_service.offline.replay import ReplayError, ReplayOptions, replay
from hil_service.process_tuning import tune_for_service
from hil_service.umodel import U_MODELS
from protocols.profiles import MAX_SAMPLE_PERIOD, MIN_SAMPLE_PERIOD, ProfileError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "log",
        nargs="+",
        help="an MCAP log written by glider-hil serve; or the files of one log that serve "
        "rotated (--log-max-mb, --log-max-s), in order, replayed as one run",
    )
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=float, default=1.0, help="x the recorded pace")
    pace.add_argument("--fast", action="store_true", help="as fast as possible")
    parser.add_argument("--loop", action="store_true", help="start again at the end")
    parser.add_argument("--publish", action="store_true", help="republish on Zenoh")
    parser.add_argument(
        "--check", action="store_true", help="recomputed estimates and commands must match"
    )
    parser.add_argument("--model", choices=U_MODELS, default=None)
    parser.add_argument(
        "--profile",
        default=None,
        help="vehicle profile, a built-in name or a TOML file (default: the one the log "
        "stores); its period, if periodic, replaces the one the log recorded",
    )
    parser.add_argument(
        "--sample-period",
        type=float,
        default=None,
        metavar="S",
        help=f"periodic profiles: s between samples, {MIN_SAMPLE_PERIOD:g}..{MAX_SAMPLE_PERIOD:g}; "
        "wins over the period of --profile and the one the log recorded (default: --profile's "
        "period, else the log's, else its profile's)",
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    add_foxglove_argument(parser)
    add_zenoh_arguments(parser)


def _progress(done: int, total: int) -> None:
    if total:
        print(f"\r{100 * done / total:5.1f} %", end="", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    if args.check and args.model is not None:
        print("glider-hil replay: --check replays the stored model; drop --model", file=sys.stderr)
        return 2
    if not args.fast and not args.speed > 0:
        print("glider-hil replay: --speed must be positive", file=sys.stderr)
        return 2
    options = ReplayOptions(
        speed=None if args.fast else args.speed,
        check=args.check,
        model=args.model,
        profile=args.profile,
        sample_period=args.sample_period,
        progress=_progress if args.fast and sys.stderr.isatty() else None,
    )
    session = zenoh = live = None
    listeners: list[Any] = []
    try:
        live = start_live(foxglove_from_args(args), "replay")
        if args.publish:
            session = open_session(options_from_args(args))
            zenoh = publisher(session)
            listeners.append(zenoh)
        if live is not None:
            listeners.append(live)
        tune_for_service()
        while True:
            result = replay(args.log, options, listeners)
            if options.progress is not None:
                print(file=sys.stderr)
            if result.recovered:
                print(f"glider-hil replay: {result.recovered}", file=sys.stderr)
            if result.skipped_inputs:
                print(
                    f"glider-hil replay: {' '.join(args.log)}: {result.skipped_inputs} "
                    "decision-inputs "
                    f"record(s) could not be read and were skipped; the first: "
                    f"{result.first_skipped}",
                    file=sys.stderr,
                )
            if result.mismatch is not None or not args.loop:
                break
    except (LogError, ReplayError, ProfileError, OSError, ValueError) as error:
        print(f"glider-hil replay: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    finally:
        if zenoh is not None:
            zenoh.stop()
        if live is not None:
            live.close()
        if session is not None:
            session.close()
    report = {
        "samples": result.samples,
        "frames": result.frames,
        "compared": result.compared,
        "complete": result.complete,
        "wall_s": round(result.wall_s, 3),
        "max_lag_s": round(result.lag_s, 4),
        "bad_frames": result.bad_frames,
        "unknown_frames": result.unknown_frames,
        "empty_frames": result.empty_frames,
        "skipped_inputs": result.skipped_inputs,
        "identifier": {
            sid: v["identifier"] for sid, v in result.summary.get("vehicles", {}).items()
        },
    }
    if args.json:
        print(json.dumps(report))
    else:
        unusable = result.unusable()
        print(
            f"replayed {result.samples} samples ({result.frames} frames) in "
            f"{result.wall_s:.2f} s; {result.compared} recorded estimates/commands compared"
            + (f"; not decoded: {unusable}" if unusable else "")
        )
    if result.mismatch is not None:
        print(f"glider-hil replay: check failed: {result.mismatch.describe()}", file=sys.stderr)
        return 1
    return 0
