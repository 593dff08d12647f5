"""Regenerate the replay fixtures: one short service log per emulator scenario.

Run from the project root: .venv/bin/python tests/data/regenerate.py
Each log comes from `glider-hil demo` (emulator and service as real processes on loopback,
control enabled over Zenoh partway through), so it holds identification and commands.
Regenerate after an intended change to the identifier or the controller: the replay tests
compare recomputed estimates and commands with these logs bit for bit.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCENARIOS = ("paper", "disturbed", "nonlinear")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scenarios", nargs="+", choices=SCENARIOS, default=list(SCENARIOS),
        help="the fixtures to write (all by default)",
    )  # fmt: skip
    for scenario in parser.parse_args().scenarios:
        with tempfile.TemporaryDirectory() as log_dir:
            subprocess.run(
                [sys.executable, "-m", "hil_service.cli", "demo", "--scenario", scenario,
                 "--duration", "20", "--speed", "100", "--log-dir", log_dir],
                check=True, cwd=HERE.parent.parent,
            )  # fmt: skip
            (log,) = Path(log_dir).glob("*.mcap")
            shutil.copy(log, HERE / f"{scenario}.mcap")
            print(f"wrote {HERE / f'{scenario}.mcap'} ({log.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
