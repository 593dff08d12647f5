"""``glider-hil experiment``: placeholder until the experiment module lands."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    pass


def run(args: argparse.Namespace) -> int:
    raise SystemExit("glider-hil experiment: not available yet")
