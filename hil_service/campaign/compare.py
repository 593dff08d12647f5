"""``campaign compare DIR_A DIR_B``: paired differences per seed, with a t-interval.

Runs are paired by (scenario, seed); only pairs where both runs are ``ok`` count. For each
scenario and metric the mean of B − A is given with a two-sided 95 % Student t confidence
interval (n − 1 degrees of freedom), which assumes the paired differences are roughly
normal; the median difference and how many pairs B improved are printed beside it. A
pair whose metric value is not a finite number (NaN, a string) is left out of that metric
and counted.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from statistics import mean, median, stdev
from typing import Any, NamedTuple

from scipy import stats

from hil_service.campaign.runner import MISSION_SETTINGS, SPEC_FILE
from plant_emulator.models import CHANNELS
from protocols.payload_json import is_finite_number

#: Compared metrics; lower is better for every one of them.
METRICS = tuple(
    f"{ch}_{name}" for ch in CHANNELS for name in ("iae", "ratio_reference", "ratio_oracle")
)


class Runs(NamedTuple):
    """A campaign's usable rows of runs.json, and how many rows were skipped as unusable."""

    rows: list[dict[str, Any]]
    skipped: int


def _usable(row: Any) -> bool:
    """A row that can be paired: an object with a scenario name and an integer seed."""
    return (
        isinstance(row, dict)
        and isinstance(row.get("scenario"), str)
        and type(row.get("seed")) is int
    )


def load_runs(directory: Path) -> Runs:
    """The rows of ``directory/runs.json`` that can be paired; rows that are not an object
    with a ``scenario`` string and an integer ``seed`` are skipped and counted. ValueError
    names the file when it cannot be read, holds no usable row, or records a mission twice
    (a campaign records each once, so which of the two is right cannot be told)."""
    path = directory / "runs.json"
    if not path.exists():
        raise ValueError(f"{directory}: no runs.json (not a campaign directory?)")
    try:
        rows = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: cannot be read: {error}") from None
    if not isinstance(rows, list):
        raise ValueError(f"{path}: expected a list of runs")
    usable = [row for row in rows if _usable(row)]
    if not usable:
        raise ValueError(
            f"{path}: none of its {len(rows)} rows is a run with a scenario name and an "
            "integer seed"
        )
    seen: set[tuple[str, int]] = set()
    for row in usable:
        key = (row["scenario"], row["seed"])
        if key in seen:
            raise ValueError(f"{path}: {key[0]} seed {key[1]} is recorded more than once")
        seen.add(key)
    return Runs(usable, len(rows) - len(usable))


def mission_differences(a: Path, b: Path) -> list[str]:
    """The mission settings (``runner.MISSION_SETTINGS``) in which the campaigns in ``a``
    and ``b`` differ, as "steps 2400 against 1800": such campaigns ran different missions,
    whose IAEs do not pair. None when either has no readable ``campaign.json``."""
    specs = []
    for directory in (a, b):
        try:
            spec = json.loads((directory / SPEC_FILE).read_text())
        except (OSError, ValueError):
            return []
        if not isinstance(spec, dict):
            return []
        specs.append(spec)
    return [
        f"{name} {specs[0].get(name)} against {specs[1].get(name)}"
        for name in MISSION_SETTINGS
        if specs[0].get(name) != specs[1].get(name)
    ]


def _invalid(value: Any) -> bool:
    """A metric recorded but not a finite number (NaN, a string); None means not measured."""
    return value is not None and not is_finite_number(value)


def t_interval(differences: list[float], level: float = 0.95) -> tuple[float, float] | None:
    """The two-sided t confidence interval of the mean difference (None under 2 pairs)."""
    n = len(differences)
    if n < 2:
        return None
    centre = mean(differences)
    half = float(stats.t.ppf(0.5 + level / 2, n - 1)) * stdev(differences) / math.sqrt(n)
    return centre - half, centre + half


def compare(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per scenario and metric with a finished pair (one left out counts too).

    ``a`` and ``b`` are rows as ``load_runs`` returns them (one per scenario and seed). A
    pair where both runs are ``ok`` but either metric value is present and not a finite
    number is left out of that metric's statistics and counted in its ``excluded``.
    """
    index_a = {(r["scenario"], r["seed"]): r for r in a}
    results = []
    scenarios = list(dict.fromkeys(r["scenario"] for r in b))
    for scenario in scenarios:
        pairs = [
            (index_a[(scenario, r["seed"])], r)
            for r in b
            if r["scenario"] == scenario and (scenario, r["seed"]) in index_a
        ]
        ok_pairs = [(ra, rb) for ra, rb in pairs if ra.get("status") == rb.get("status") == "ok"]
        for metric in METRICS:
            values: list[tuple[Any, Any]] = [
                (ra.get(metric), rb.get(metric)) for ra, rb in ok_pairs
            ]
            differences = [
                float(vb) - float(va)
                for va, vb in values
                if is_finite_number(va) and is_finite_number(vb)
            ]
            excluded = sum(_invalid(va) or _invalid(vb) for va, vb in values)
            if not differences and not excluded:
                continue
            results.append(
                {
                    "scenario": scenario,
                    "metric": metric,
                    "pairs": len(differences),
                    "excluded": excluded,
                    "mean_difference": mean(differences) if differences else None,
                    "ci95": t_interval(differences),
                    "median_difference": median(differences) if differences else None,
                    "b_better": sum(d < 0 for d in differences),
                }
            )
    return results


def _signed(value: float | None) -> str:
    return "—" if value is None else f"{value:+.4g}"


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
            f"| {r['scenario']} | {r['metric']} | {r['pairs']} | {_signed(r['mean_difference'])} | "
            f"{ci_text} | {_signed(r['median_difference'])} | {r['b_better']}/{r['pairs']} |"
        )
    excluded = [r for r in results if r["excluded"]]
    if excluded:
        lines.append("")
    for r in excluded:
        lines.append(
            f"Left out of {r['scenario']} {r['metric']}: {r['excluded']} pair(s) of ok runs "
            "with a value that is not a finite number."
        )
    return "\n".join(lines)
