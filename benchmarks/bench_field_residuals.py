"""Where glide-u and the steady-glide model part on held-out dives: speed bias per leg.

Run: .venv/bin/python benchmarks/bench_field_residuals.py [LOG.mcap ...]
(LOG: a field import, ``glider-hil import``; default: imports of the shared SG542 and
SEA035 data sets made in a scratch directory)

For each split of the dives and each of the two depth models given the measured pitch,
prints the one-step residual of the vertical speed (measured − predicted, mm/s, + the
glider deeper than predicted) averaged over the held-out dives' descents (ż > 0.05 m/s),
ascents (ż < −0.05 m/s) and the samples in between (the turns at the bottom and the
surface), and the free run's mean |error| at the deepest sample and at the last one. The
glide-u structure is the one the evaluation chooses on the training dives.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.bench_field import DEFAULT  # noqa: E402
from hil_service.mcap.reader import LogReader  # noqa: E402
from hil_service.offline.field import evaluate as ev  # noqa: E402
from hil_service.offline.field.report import field_results  # noqa: E402
from hil_service.umodel.glide_umodel import GlideUModel  # noqa: E402


def _legs(log: Path, split: str) -> dict:
    reader = LogReader(log)
    for _ in reader.messages({"glider/1/telemetry"}):
        pass
    arrays, results = field_results(log, reader.config(), split=split)
    depth = results[0]
    glide = next(m for m in depth.models if m.model == ev.GLIDE_U)
    segments = [s for s in arrays.segments if s.stop - s.start >= 2]
    if len({s.dive for s in segments}) < 2:
        segments = [ev.Segment(i, s.start, s.stop) for i, s in enumerate(segments)]
    train = [s for s in segments if s.dive in depth.train_dives]
    held = [s for s in segments if s.dive in depth.held_out]
    sync = depth.sync
    horizon = depth.horizon
    steady, _ = ev._glide_runner(arrays, train, horizon, sync)
    choice = glide.parameters["structure_choice"]
    model = GlideUModel(
        u_scale=arrays.full_scale,
        feature=choice["feature"],
        degree=choice["degree"],
        drift=choice["drift"],
        v0=glide.parameters.get("v0", 0.0),
        c_p=glide.parameters.get("c_p", 0.0),
    )
    runners = {
        "steady-glide": steady,
        "glide-u": ev._glide_u_runner(model, arrays, train, sync, horizon),
    }
    out: dict = {"structure": glide.parameters["structure"]}
    for name, run in runners.items():
        d, a, t, bottom, end = [], [], [], [], []
        for s in held:
            z = arrays.depth[s.start : s.stop]
            if z.size < sync + horizon:
                continue
            actual = z[sync:]
            rate = np.diff(z)[sync - 1 :] / arrays.period
            one, sim, _, _ = run(s)
            e = (actual - one) / arrays.period
            d.append(e[rate > 0.05])
            a.append(e[rate < -0.05])
            t.append(e[(rate <= 0.05) & (rate >= -0.05)])
            bottom.append(abs(actual[np.argmax(actual)] - sim[np.argmax(actual)]))
            end.append(abs(actual[-1] - sim[-1]))

        def mm(parts: list[np.ndarray]) -> float | None:
            joined = np.concatenate(parts) if parts else np.empty(0)
            return round(1000 * float(joined.mean()), 1) if joined.size else None

        out[name] = {
            "fit": next(m.fit for m in depth.models if m.model == name),
            "bias_descent_mm_s": mm(d),
            "bias_ascent_mm_s": mm(a),
            "bias_turns_mm_s": mm(t),
            "turn_samples": int(sum(p.size for p in t)),
            "abs_error_at_bottom_m": round(float(np.mean(bottom)), 1),
            "abs_error_at_end_m": round(float(np.mean(end)), 1),
        }
    return out


def main() -> None:
    logs = [Path(a) for a in sys.argv[1:]]
    with tempfile.TemporaryDirectory(prefix="bench-field-res-") as scratch:
        if not logs:
            for source in DEFAULT:
                log = Path(scratch) / f"{source.name}.mcap"
                subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "hil_service.cli",
                        "import",
                        str(source),
                        "-o",
                        str(log),
                    ],
                    check=True,
                    capture_output=True,
                )
                logs.append(log)
        for log in logs:
            for split in ev.SPLITS:
                print(json.dumps({"log": log.name, "split": split, **_legs(log, split)}))


if __name__ == "__main__":
    main()
