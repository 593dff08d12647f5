"""Field data end to end: `glider-hil import` of a data set, then `glider-hil report`, timed.

Run: .venv/bin/python benchmarks/bench_field.py [DIR ...] [--period S] [--out DIR]
(default: seaglider-sg542 and seaexplorer-sea035 of the nearest shared/data/field above the
checkout)

Prints JSON per data set: the import's and the report's wall time (the two commands as a
user runs them, each in its own process), the share of in-dive samples that reached the
identifier through the grid and the samples the replayed identifier learnt from, and per
channel and model the held-out dives' free-run fit, one-step skill and k-step NMSE.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.mcap.reader import LogReader  # noqa: E402
from hil_service.offline.field.evaluate import ChannelResult  # noqa: E402
from hil_service.offline.field.report import field_results, field_section  # noqa: E402

#: The shared data sets: the nearest ``shared/data/field`` above the checkout.
SHARED = next(
    (
        p / "shared" / "data" / "field"
        for p in ROOT.parents
        if (p / "shared" / "data" / "field").is_dir()
    ),
    ROOT.parent / "shared" / "data" / "field",
)
DEFAULT = [SHARED / "seaglider-sg542", SHARED / "seaexplorer-sea035"]


def _run(*args: str) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "hil_service.cli", *args], capture_output=True, text=True
    )
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"glider-hil {' '.join(args)} failed: {done.stderr}")
    return wall, done.stdout


def _held_out(results: list[ChannelResult]) -> dict:
    return {
        r.channel: {
            "train_dives": r.train_dives,
            "held_out_dives": r.held_out,
            "k": r.horizon,
            "excited": r.excitation.excited,
            "models": {
                m.model: {
                    "fit": None if m.fit is None else round(m.fit, 2),
                    "skill": None if m.skill is None else round(m.skill, 4),
                    "k_step_nmse": m.k_step_nmse,
                    "fits": [None if d.fit is None else round(d.fit, 1) for d in m.dives],
                    **(
                        {"structure": m.parameters["structure"]}
                        if "structure" in m.parameters
                        else {}
                    ),
                }
                for m in r.models
            },
        }
        for r in results
    }


def bench(source: Path, out: Path, period: float | None) -> dict:
    log = out / f"{source.name}.mcap"
    extra = [] if period is None else ["--period", str(period)]
    import_s, stdout = _run("import", str(source), "-o", str(log), "--force", "--json", *extra)
    imported = json.loads(stdout)["import"]
    report_dir = out / f"{source.name}-report"
    report_s, _ = _run("report", str(log), "-o", str(report_dir))
    _, replayed = _run("replay", "--fast", "--json", str(log))
    identifier = json.loads(replayed)["identifier"]
    reader = LogReader(log)
    for _ in reader.messages({"glider/1/telemetry"}):
        pass
    _, _, results = field_section(log, reader.config(), report_dir)
    return {
        "data": str(source),
        "import_s": round(import_s, 2),
        "report_s": round(report_s, 2),
        "total_s": round(import_s + report_s, 2),
        "grid": imported["grid"],
        "replay_identifier_samples": {
            ch: v["samples"] for ch, v in next(iter(identifier.values())).items()
        },
        "replay_identifier_skipped": {
            ch: v["skipped"] for ch, v in next(iter(identifier.values())).items()
        },
        "held_out": _held_out(results),
        "held_out_alternate": _held_out(field_results(log, reader.config(), split="alternate")[1]),
        "report": str(report_dir / "report.md"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("sources", nargs="*", type=Path, default=DEFAULT)
    parser.add_argument("--period", type=float, default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-field-") as scratch:
        out = args.out or Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        for source in args.sources:
            print(json.dumps(bench(source, out, args.period)))


if __name__ == "__main__":
    main()
