"""``glider-hil import``: a vehicle's own logs into an MCAP log that ``info``, ``report``,
``replay`` and ``experiment`` read.

* a telemetry log (``.tlog``, as MAVProxy and QGroundControl write it);
* field data (docs/field-data.md): Seaglider per-dive netCDF (``pGGGDDDD.nc``: files or a
  directory), SeaExplorer navigation files (``*.gli.sub.N`` / ``*.gli.raw.N``, gzipped or
  not), Slocum binary logs (``.dbd`` … through dbdreader, with ``--cache-dir``), or any CSV
  / Parquet with a ``--mapping`` TOML file. Field samples are put on a uniform grid of
  ``--period`` s, split into segments at gaps longer than ``--gap`` s.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from hil_service.offline.field import FORMATS, FieldError, read_field
from hil_service.offline.field.grid import as_recorded, check_period, resample
from hil_service.offline.field.write import write_field_log
from hil_service.offline.tlog_import import TlogError, import_tlog
from protocols.flag_types import positive_float
from protocols.profiles import DEFAULT_PROFILE, ProfileError, load_profile


def system_id(text: str) -> int:
    """A MAVLink system id, 1..255: the one byte a frame carries (0 is the broadcast)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 1 <= value <= 255:
        raise argparse.ArgumentTypeError(f"a MAVLink system id is 1..255, got {value}")
    return value


def grid_period(text: str) -> float:
    """A grid period, s (``grid.check_period``)."""
    try:
        return check_period(float(text))
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "inputs",
        nargs="+",
        help="a .tlog, or field data files / a directory of them (docs/field-data.md)",
    )
    parser.add_argument("-o", "--output", required=True, help="the MCAP log to write")
    parser.add_argument(
        "--format",
        choices=("tlog", *FORMATS),
        default=None,
        help="the input's format (default: from the file names)",
    )
    parser.add_argument("--mapping", help="CSV/Parquet: the TOML mapping file")
    parser.add_argument("--cache-dir", help="Slocum: the directory of the sensor-list .cac files")
    parser.add_argument(
        "--period",
        type=grid_period,
        default=None,
        help="field data: grid period, s (default: median step)",
    )
    parser.add_argument(
        "--gap",
        type=positive_float,
        default=None,
        help="field data: a longer step starts a new segment, s (default max(60, 6 periods))",
    )
    parser.add_argument(
        "--as-recorded",
        action="store_true",
        help="field data: the samples at their own times, no grid (docs/field-data.md)",
    )
    parser.add_argument(
        "--system-id",
        type=system_id,
        default=1,
        help="field data: the vehicle's MAVLink system id, 1..255 (default 1)",
    )
    parser.add_argument(
        "--profile",
        default=DEFAULT_PROFILE,
        help="tlog: the vehicle's profile, stored in the log (default %(default)s)",
    )
    parser.add_argument(
        "--vehicle",
        type=system_id,
        default=None,
        help="tlog: the vehicle's system id (default: the first autopilot heard)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite the output")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def _is_tlog(args: argparse.Namespace) -> bool:
    if args.format is not None:
        return bool(args.format == "tlog")
    return any(Path(given).suffix.lower() == ".tlog" for given in args.inputs)


def run(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.is_dir():
        print(
            f"glider-hil import: -o {output} is a directory (give the .mcap file to write)",
            file=sys.stderr,
        )
        return 2
    if output.exists() and not args.force:
        print(f"glider-hil import: {output} exists (--force to overwrite)", file=sys.stderr)
        return 2
    if not _is_tlog(args):
        return _run_field(args, output)
    if len(args.inputs) != 1:
        print(
            f"glider-hil import: a tlog import takes one file, got {len(args.inputs)} "
            f"({', '.join(args.inputs)})",
            file=sys.stderr,
        )
        return 2
    try:
        profile = load_profile(args.profile)
        report = import_tlog(args.inputs[0], output, profile, args.vehicle)
    except (ProfileError, TlogError, OSError) as error:
        print(f"glider-hil import: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"import": report.as_dict(), "output": str(output)}))
    else:
        print(report.describe())
        print(
            f"  vehicle system id {report.vehicle}; frames in {report.directions['in']}, "
            f"out {report.directions['out']}; bad {report.bad_frames}; records with a time "
            f"beyond what a log holds {report.bad_times} (skipped); -> {output}"
        )
    return 0 if report.complete else 1


def _run_field(args: argparse.Namespace, output: Path) -> int:
    try:
        data = read_field(args.inputs, args.format, args.mapping, args.cache_dir)
        if data.size == 0:
            raise FieldError(f"{', '.join(args.inputs)}: no sample with a time, depth and pitch")
        if args.as_recorded:
            grid = as_recorded(data, args.gap)
        else:
            grid = resample(data, args.period, args.gap)
        if grid.size == 0:
            raise FieldError(f"{', '.join(args.inputs)}: no in-dive segment to put on a grid")
        written = write_field_log(data, grid, output, args.system_id)
    except (FieldError, ValueError, OSError) as error:
        print(f"glider-hil import: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(
            json.dumps(
                {
                    "import": {
                        "format": data.format,
                        "vehicle": data.vehicle,
                        "files": data.files,
                        "issues": data.issues.as_dict(),
                        "grid": {k: v for k, v in grid.as_dict().items() if k != "segments"},
                        "segments": len(grid.segments),
                        **written.as_dict(),
                    },
                    "output": str(output),
                }
            )
        )
        return 0
    heading = " ".join(part for part in (data.format, data.vehicle) if part)
    print(f"{heading}: {len(data.files)} file(s)")
    for line in data.issues.describe():
        print(f"  {line}")
    spacing = f"grid {grid.period:g} s" if grid.period > 0 else "as recorded"
    print(
        f"  {spacing} (segments split at gaps > {grid.gap:g} s): {grid.size} samples "
        f"in {len(grid.segments)} segments; {grid.raw_used} of {grid.raw_in_dive} in-dive "
        f"samples used ({100 * grid.used_fraction:.1f} %); {grid.interpolated} grid samples "
        f"interpolated (linear, at most {grid.max_distance:.1f} s from a raw sample)"
    )
    if grid.lost:
        print("  not used: " + ", ".join(f"{n} {why}" for why, n in grid.lost.items()))
    if any(written.clipped.values()):
        print(f"  clipped to full scale: {written.clipped}")
    print(f"  -> {output} ({written.frames} frames)")
    return 0
