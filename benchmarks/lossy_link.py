"""Control on a link that loses samples, with and without short gaps bridged
(docs/control.md, "Short gaps bridged").

In process, on the plants of ``tests/harm_rig.py``: 2,500 samples of the vehicle's own
excitation, then 3,000 with a depth setpoint 0.8 above trim, each sample lost
independently with the given probability. Per plant, loss rate and ``bridge_gap``:

* ``commanded``: the share of the samples read from 300 after control is enabled that
  the channel commanded on (no plant change);
* ``error``: the mean |depth − setpoint| over the last 300 samples read, over its value
  when control was enabled (no plant change);
* ``flip`` / ``gain5``: the input's sign flips, or its gain grows fivefold, 400 samples into
  control: the samples from the change to the supervisor's trip ("-" when it never
  commanded before the change, "none" when it commanded and never tripped), and the end
  error over the error at enable.

    python benchmarks/lossy_link.py
    python benchmarks/lossy_link.py --poles 0.97,0.9 --loss 0.05 --bridge-gap 5 0
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil_service.pipeline import PipelineSettings
from tests.harm_rig import Loop, spec

IDENTIFY = 2500
CONTROL = 3000
CHANGE = IDENTIFY + 400
SETPOINT = 15.8

CHANGES: dict[str, Callable[[int, float], float] | None] = {
    "none": None,
    "flip": lambda k, u: -u if k >= CHANGE else u,
    "gain5": lambda k, u: 5.0 * u if k >= CHANGE else u,
}


def _mean_error(values: list[float]) -> float:
    read = [abs(y - SETPOINT) for y in values if math.isfinite(y)]
    return sum(read) / len(read) if read else math.nan


def run(poles: tuple[float, ...], loss: float, bridge_gap: int, change: str) -> dict:
    loop = Loop(
        spec(poles=poles),
        spec(),
        settings=PipelineSettings(bridge_gap=bridge_gap),
        change=CHANGES[change],
        loss_share=loss,
    )
    loop.run(IDENTIFY, {"depth": None, "pitch": None})
    loop.run(CONTROL, {"depth": SETPOINT, "pitch": None})
    enabled = next(abs(y - SETPOINT) for y in loop.y[IDENTIFY:] if math.isfinite(y))
    stop = CHANGE if change != "none" else len(loop.modes)
    read = [m for m in loop.modes[IDENTIFY + 300 : stop] if m != "lost"]
    commanded = sum(m.startswith(("newton", "fallback")) for m in read) / max(len(read), 1)
    trip = next((k for k, m in enumerate(loop.modes) if m.startswith("safe")), None)
    return {
        "commanded": commanded,
        "trip_after": None if trip is None else trip - CHANGE,
        "end_ratio": _mean_error(loop.y[-300:]) / enabled,
        "bridged": loop.pipeline.channels["depth"].bridged,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--poles", nargs="+", default=["0.8,0.7", "0.97,0.9", "0.98,0.95", "0.99,0.8"]
    )
    parser.add_argument("--loss", nargs="+", type=float, default=[0.0, 0.01, 0.02, 0.05, 0.1])
    parser.add_argument("--bridge-gap", nargs="+", type=int, default=[5, 0])
    args = parser.parse_args()
    print(
        f"{'poles':>10s} {'loss':>5s} {'bridge':>6s} {'commanded':>9s} {'error':>6s} "
        f"{'bridged':>7s} {'flip: trip after, end':>22s} {'gain5: trip after, end':>23s}"
    )
    for text in args.poles:
        poles = tuple(float(p) for p in text.split(","))
        for loss in args.loss:
            for gap in args.bridge_gap:
                calm = run(poles, loss, gap, "none")
                cells = []
                for change in ("flip", "gain5"):
                    row = run(poles, loss, gap, change)
                    if row["commanded"] == 0.0:
                        after = "-"
                    elif row["trip_after"] is None:
                        after = "none"
                    else:
                        after = str(row["trip_after"])
                    cells.append(f"{after:>6s}, {row['end_ratio']:5.2f}")
                print(
                    f"{text:>10s} {loss:5.2f} {gap:6d} {calm['commanded']:9.3f} "
                    f"{calm['end_ratio']:6.3f} {calm['bridged']:7d} {cells[0]:>22s} "
                    f"{cells[1]:>23s}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
