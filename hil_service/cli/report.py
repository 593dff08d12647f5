"""``glider-hil report``: placeholder until the report module lands."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log")
    parser.add_argument("-o", "--output", default="report")


def run(args: argparse.Namespace) -> int:
    raise SystemExit("glider-hil report: not available yet")
