"""A campaign's outputs: runs.csv, runs.json, figures and summary.md (the review table)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from statistics import median
from typing import Any

from hil_service.campaign.metrics import columns
from plant_emulator.models import CHANNELS

FIGURE = "iae_ratios.png"
WORST = 5


def _values(rows: list[dict[str, Any]], key: str) -> list[float]:
    return [
        float(r[key])
        for r in rows
        if r.get("status") == "ok"
        and isinstance(r.get(key), (int, float))
        and math.isfinite(r[key])
    ]


def _numbers(rows: list[dict[str, Any]], key: str) -> list[float]:
    return [float(r[key]) for r in rows if isinstance(r.get(key), (int, float))]


def _fmt(value: float | None, digits: int = 3) -> str:
    return "—" if value is None else f"{value:.{digits}g}"


def _median(values: list[float]) -> float | None:
    return median(values) if values else None


def _quantile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    position = q * (len(ordered) - 1)
    low = math.floor(position)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (position - low)


def write_tables(out: Path, rows: list[dict[str, Any]]) -> None:
    with (out / "runs.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns(), extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in columns()})
    (out / "runs.json").write_text(json.dumps(rows, indent=1))


def ratio_figure(path: Path, rows: list[dict[str, Any]], scenarios: list[str]) -> Path:
    """Distribution of IAE ratios (HIL over reference only, and over the oracle when run)
    per scenario and channel: one box per scenario, the runs as dots."""
    from matplotlib.figure import Figure  # only when figures are drawn

    kinds = [("ratio_reference", "IAE / reference-only IAE")]
    if any(r.get(f"{ch}_ratio_oracle") is not None for r in rows for ch in CHANNELS):
        kinds.append(("ratio_oracle", "IAE / oracle IAE"))
    fig = Figure(figsize=(5.0 * len(CHANNELS), 3.6 * len(kinds)), dpi=110, layout="constrained")
    axes = fig.subplots(len(kinds), len(CHANNELS), squeeze=False)
    for i, (kind, label) in enumerate(kinds):
        for j, ch in enumerate(CHANNELS):
            ax = axes[i][j]
            data = [
                _values([r for r in rows if r.get("scenario") == s], f"{ch}_{kind}")
                for s in scenarios
            ]
            positions = list(range(1, len(scenarios) + 1))
            shown = [(p, d) for p, d in zip(positions, data, strict=True) if d]
            if shown:
                ax.boxplot([d for _, d in shown], positions=[p for p, _ in shown], widths=0.5)
                for p, d in shown:
                    ax.plot([p] * len(d), d, ".", alpha=0.5, color="tab:blue")
            ax.axhline(1.0, color="grey", linewidth=0.8, linestyle="--")
            ax.set_xticks(positions, scenarios)
            ax.set_yscale("log")
            ax.set_title(f"{ch}: {label}")
            ax.grid(True, which="both", alpha=0.3)
    fig.savefig(path)
    return path


def summary_markdown(
    rows: list[dict[str, Any]], spec: dict[str, Any], figure: str | None, wall_s: float | None
) -> str:
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    lines = [
        "# Campaign summary",
        "",
        f"{len(rows)} missions: scenarios {', '.join(scenarios)}; seeds "
        f"{min(spec['seeds'])}–{max(spec['seeds'])}; {spec['steps']} steps each "
        f"(identification {spec['identify']}, a setpoint step every {spec['step_every']}); "
        f"lockstep HIL over loopback UDP; oracle {'on' if spec['oracle'] else 'off'}"
        + (f"; {wall_s:.0f} s wall" if wall_s is not None else "")
        + ".",
        "",
        f"Per mission: median wall {_fmt(_median(_numbers(rows, 'wall_s')))} s, median CPU "
        f"{_fmt(_median(_numbers(rows, 'cpu_s')))} s (the worker, its emulator and its "
        "service, scoring included).",
        "",
        "Ratios are the HIL run's IAE over the yardstick's on the same plant, disturbance and "
        "setpoints (below 1: better). Medians with the 10–90 % range, over the runs that "
        "finished (`ok`).",
        "",
        "| scenario | runs | ok | diverged | failed | channel | IAE / reference (median, 10–90 %) "
        "| IAE / oracle | overshoot % | settling s | skill | refused |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scenarios:
        group = [r for r in rows if r["scenario"] == s]
        counts = {k: sum(r.get("status") == k for r in group) for k in ("ok", "diverged", "failed")}
        refused = sum(int(r.get("commands_refused") or 0) for r in group)
        for ch in CHANNELS:
            ratio = _values(group, f"{ch}_ratio_reference")
            oracle = _values(group, f"{ch}_ratio_oracle")
            lines.append(
                f"| {s} | {len(group)} | {counts['ok']} | {counts['diverged']} | "
                f"{counts['failed']} | {ch} | {_fmt(_median(ratio))} "
                f"({_fmt(_quantile(ratio, 0.1))}–{_fmt(_quantile(ratio, 0.9))}) | "
                f"{_fmt(_median(oracle))} | "
                f"{_fmt(_median(_values(group, f'{ch}_overshoot_pct')))} | "
                f"{_fmt(_median(_values(group, f'{ch}_settling_s')))} | "
                f"{_fmt(_median(_values(group, f'{ch}_skill')))} | {refused} |"
            )
    if figure:
        lines += ["", f"![IAE ratios per scenario]({figure})"]
    lines += ["", "## Worst runs (IAE / reference only)", ""]
    lines += ["| channel | scenario | seed | ratio | log |", "|---|---|---|---|---|"]
    for ch in CHANNELS:
        ranked = sorted(
            (r for r in rows if isinstance(r.get(f"{ch}_ratio_reference"), (int, float))),
            key=lambda r: -float(r[f"{ch}_ratio_reference"]),
        )
        for r in ranked[:WORST]:
            lines.append(
                f"| {ch} | {r['scenario']} | {r['seed']} | {r[f'{ch}_ratio_reference']:.3g} "
                f"| `{r.get('log') or '—'}` |"
            )
    bad = [r for r in rows if r.get("status") != "ok"]
    lines += ["", "## Runs not ok", ""]
    if not bad:
        lines.append("None.")
    else:
        lines += ["| scenario | seed | status | reason | log |", "|---|---|---|---|---|"]
        for r in bad:
            lines.append(
                f"| {r['scenario']} | {r['seed']} | {r['status']} | {r.get('reason') or ''} "
                f"| `{r.get('log') or '—'}` |"
            )
    return "\n".join(lines) + "\n"


def write_outputs(
    out: Path,
    rows: list[dict[str, Any]],
    spec: dict[str, Any],
    figures: bool = True,
    wall_s: float | None = None,
) -> None:
    write_tables(out, rows)
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    figure = ratio_figure(out / FIGURE, rows, scenarios).name if figures else None
    (out / "summary.md").write_text(summary_markdown(rows, spec, figure, wall_s))
