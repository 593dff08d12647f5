"""Throughput of one channel: identifier step + IMC target + inverse solve + command shaping.

Run: .venv/bin/python benchmarks/bench_umodel.py [n_samples]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from hil_service.umodel import CommandShaper, ImcReference, build_model, invert_model


def plant(y1: float, y2: float, u1: float) -> float:
    return 1.5 * y1 - 0.7 * y2 + 0.2 * u1 + 0.1 * u1**3


def run(name: str, n: int, seed: int = 1) -> tuple[float, dict[str, int]]:
    rng = np.random.default_rng(seed)
    setpoints = np.repeat(rng.uniform(-3.0, 3.0, size=n // 50 + 1), 50)[:n].tolist()
    model = build_model(name, seed=seed)
    shaper = CommandShaper(-2.0, 2.0, max_rate=0.5)
    ref = ImcReference(a=0.8)
    y1 = y2 = 0.0
    u = 0.0
    y_hat = 0.0
    paths = {"newton": 0, "fallback": 0}
    t0 = time.perf_counter()
    for k in range(n):
        y = plant(y1, y2, u)
        est = model.step(u, y)
        v = ref.target(setpoints[k], y, est.y_hat)
        res = invert_model(model, v, u, -2.0, 2.0)
        paths[res.path] += 1
        u = shaper.shape(res.u).u
        y2, y1 = y1, y
        y_hat = est.y_hat
    dt = time.perf_counter() - t0
    assert np.isfinite(y_hat)
    return n / dt, paths


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 50_000
    for name in ("paper", "dynamic"):
        rate, paths = run(name, n)
        print(f"{name:8s} update+inverse: {rate:10.0f} samples/s  paths={paths}")


if __name__ == "__main__":
    main()
