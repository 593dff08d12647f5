"""Throughput of one channel of hil_service.umodel on one core.

Per sample: identifier ``step`` + IMC target + ``invert_model`` + ``CommandShaper``, in closed
loop with a small simulated plant. Reports the best of ``--repeats`` runs (the machine may be
shared) and how often the inverse needed the (slower) fallback path.

Run: .venv/bin/python benchmarks/bench_umodel.py [--samples N] [--repeats R]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from hil_service.umodel import CommandShaper, ImcReference, build_model, invert_model

Plant = Callable[[float, float, float], float]


def second_order(y1: float, y2: float, u1: float) -> float:
    """Linear 2nd-order dynamics + cubic input (the dynamic model's home ground)."""
    return 1.5 * y1 - 0.7 * y2 + 0.2 * u1 + 0.1 * u1**3


def near_static(y1: float, y2: float, u1: float) -> float:
    """Fast Hammerstein plant: the paper model's home ground (static map in u(t−1))."""
    return 0.1 * y1 + 0.9 * (0.6 * u1 + 0.15 * u1**3)


def closed_loop(name: str, plant: Plant, n: int, seed: int = 1) -> tuple[float, float, float]:
    """Return (samples/s for step+inverse, samples/s for step only, fallback share)."""
    rng = np.random.default_rng(seed)
    setpoints = np.repeat(rng.uniform(-1.5, 1.5, size=n // 50 + 1), 50)[:n].tolist()
    model = build_model(name, seed=seed)
    shaper = CommandShaper(-2.0, 2.0, max_rate=0.5)
    ref = ImcReference(a=0.8)
    y1 = y2 = u = 0.0
    fallbacks = 0
    t0 = time.perf_counter()
    for k in range(n):
        y = plant(y1, y2, u)
        est = model.step(u, y)
        v = ref.target(setpoints[k], y, est.y_hat)
        res = invert_model(model, v, u, -2.0, 2.0)
        fallbacks += res.path == "fallback"
        u = shaper.shape(res.u).u
        y2, y1 = y1, y
    loop = time.perf_counter() - t0

    # Identifier alone on a recorded-like open-loop sequence.
    model = build_model(name, seed=seed)
    us = rng.uniform(-2.0, 2.0, n).tolist()
    y1 = y2 = 0.0
    ys = []
    for k in range(n):
        y = plant(y1, y2, us[k - 1] if k else 0.0)
        ys.append(y)
        y2, y1 = y1, y
    t0 = time.perf_counter()
    u_prev = 0.0
    for k in range(n):
        model.step(u_prev, ys[k])
        u_prev = us[k]
    upd = time.perf_counter() - t0
    return n / loop, n / upd, fallbacks / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=30_000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    cases = [
        ("dynamic", "2nd-order", second_order),
        ("paper", "near-static", near_static),
        ("paper", "2nd-order", second_order),
    ]
    head = ("model", "plant", "step+inverse/s", "step only/s", "fallback")
    print(f"{head[0]:8s} {head[1]:12s} {head[2]:>15s} {head[3]:>12s} {head[4]:>9s}")
    for name, label, plant in cases:
        runs = [closed_loop(name, plant, args.samples) for _ in range(args.repeats)]
        best_loop = max(r[0] for r in runs)
        best_upd = max(r[1] for r in runs)
        print(f"{name:8s} {label:12s} {best_loop:15.0f} {best_upd:12.0f} {runs[0][2]:9.1%}")


if __name__ == "__main__":
    main()
