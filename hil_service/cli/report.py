"""``glider-hil report``: figures and a Markdown summary from a service log.

Per vehicle and channel: actual vs a-priori predicted output with the error and the U-model
coefficients (like the paper's figures 9–12), the setpoints, outputs and ballast commands
when control ran, and ``report.md`` with NMSE, skill versus persistence, convergence,
tracking error and the link's packet loss, embedding the figures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hil_service.mcap.reader import LogError, StoredConfigError
from hil_service.offline.report import write_report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, help="an MCAP log written by glider-hil serve")
    parser.add_argument(
        "-o", "--output", type=Path, default=Path("report"), help="directory (default: report)"
    )


def run(args: argparse.Namespace) -> int:
    if args.output.exists() and not args.output.is_dir():
        print(f"glider-hil report: {args.output} is a file, not a directory", file=sys.stderr)
        return 2
    try:
        report = write_report(args.log, args.output)
    except (LogError, OSError, StoredConfigError) as error:
        print(f"glider-hil report: {error}", file=sys.stderr)
        return 2
    if not report.summaries:
        print(f"glider-hil report: {args.log} holds no identifier publications", file=sys.stderr)
        return 1
    if report.offline:
        print(f"{args.log} holds no estimates: identified offline from its telemetry")
    for s in report.summaries:
        skill = "-" if s.skill is None else f"{s.skill:.3f}"
        print(f"glider {s.system_id} {s.channel}: {s.samples} samples, skill {skill}")
    for result in report.field:
        for model in result.models:
            fit = "-" if model.fit is None else f"{model.fit:.1f} %"
            skill = "-" if model.skill is None else f"{model.skill:.4f}"
            print(
                f"field {result.channel} {model.model}: held-out dives {result.held_out[0]}-"
                f"{result.held_out[-1]} free-run fit {fit}, one-step skill {skill}"
            )
    print(f"wrote {report.markdown} and {len(report.figures)} figures")
    return 0
