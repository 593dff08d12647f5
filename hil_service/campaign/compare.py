"""``campaign compare DIR_A DIR_B``: paired differences per seed, with a t-interval.

Runs are paired by (scenario, seed); only pairs where both runs are ``ok`` count. For each
scenario and metric the mean of B − A is given with a two-sided 95 % Student t confidence
interval (n − 1 degrees of freedom), which assumes the paired differences are roughly
normal; the median difference and how many pairs B improved are printed beside it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from statistics import mean, median, stdev
from typing import Any

from scipy import stats

from plant_emulator.models import CHANNELS

#: Compared metrics; lower is better for every one of them.
METRICS = tuple(
    f"{ch}_{name}" for ch in CHANNELS for name in ("iae", "ratio_reference", "ratio_oracle")
)


def load_runs(directory: Path) -> list[dict[str, Any]]:
    path = directory / "runs.json"
    if not path.exists():
        raise ValueError(f"{directory}: no runs.json (not a campaign directory?)")
    rows = json.loads(path.read_text())
    if not isinstance(rows, list):
        raise ValueError(f"{path}: expected a list of runs")
    return rows


def t_interval(differences: list[float], level: float = 0.95) -> tuple[float, float] | None:
    """The two-sided t confidence interval of the mean difference (None under 2 pairs)."""
    n = len(differences)
    if n < 2:
        return None
    centre = mean(differences)
    half = float(stats.t.ppf(0.5 + level / 2, n - 1)) * stdev(differences) / math.sqrt(n)
    return centre - half, centre + half


def compare(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per scenario and metric with at least one finished pair."""
    index_a = {(r["scenario"], r["seed"]): r for r in a}
    results = []
    scenarios = list(dict.fromkeys(r["scenario"] for r in b))
    for scenario in scenarios:
        pairs = [
            (index_a[(scenario, r["seed"])], r)
            for r in b
            if r["scenario"] == scenario and (scenario, r["seed"]) in index_a
        ]
        for metric in METRICS:
            differences = []
            for ra, rb in pairs:
                va, vb = ra.get(metric), rb.get(metric)
                if ra.get("status") == rb.get("status") == "ok" and None not in (va, vb):
                    differences.append(float(vb) - float(va))
            if not differences:
                continue
            interval = t_interval(differences)
            results.append(
                {
                    "scenario": scenario,
                    "metric": metric,
                    "pairs": len(differences),
                    "mean_difference": mean(differences),
                    "ci95": interval,
                    "median_difference": median(differences),
                    "b_better": sum(d < 0 for d in differences),
                }
            )
    return results


def format_table(results: list[dict[str, Any]], a: str, b: str) -> str:
    lines = [
        f"Paired differences B − A per seed (A = {a}, B = {b}); lower is better for every "
        "metric; 95 % Student t interval of the mean difference.",
        "",
        "| scenario | metric | pairs | mean B − A | 95 % CI | median B − A | B better |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        ci = r["ci95"]
        ci_text = "—" if ci is None else f"[{ci[0]:+.4g}, {ci[1]:+.4g}]"
        lines.append(
            f"| {r['scenario']} | {r['metric']} | {r['pairs']} | {r['mean_difference']:+.4g} | "
            f"{ci_text} | {r['median_difference']:+.4g} | {r['b_better']}/{r['pairs']} |"
        )
    return "\n".join(lines)
