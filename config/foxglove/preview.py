"""Draws a Foxglove layout's panels from an MCAP log with matplotlib: a preview of what the
layout shows, for machines without the Foxglove app (this is not a Foxglove screenshot).

Each Plot panel's series and each State Transitions panel's paths are resolved the way the
layout names them (``topic.field.sub[i]``) on the log's messages, against log time.

Run: .venv/bin/python config/foxglove/preview.py LOG [--layout FILE] [-o PNG]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from mcap.reader import make_reader

HERE = Path(__file__).resolve().parent
PATH = re.compile(r"^(?P<topic>[A-Za-z0-9_/]+)\.(?P<field>.+)$")
STEP = re.compile(r"^(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?:\[(?P<index>\d+)\])?$")


def resolve(payload: Any, field: str) -> Any:
    for step in field.split("."):
        match = STEP.match(step)
        if match is None or not isinstance(payload, dict):
            return None
        payload = payload.get(match["name"])
        if match["index"] is not None:
            index = int(match["index"])
            payload = payload[index] if isinstance(payload, list) and index < len(payload) else None
    return payload


def panels(node: Any) -> list[dict[str, Any]]:
    if isinstance(node, dict):
        if node.get("type") == "panel":
            return [node]
        return [p for child in node.values() for p in panels(child)]
    if isinstance(node, list):
        return [p for child in node for p in panels(child)]
    return []


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("log")
    parser.add_argument("--layout", default=str(HERE / "glider-1.json"))
    parser.add_argument("-o", "--output", default="layout-preview.png")
    args = parser.parse_args()
    layout = json.loads(Path(args.layout).read_text())
    found = panels(layout["content"])
    topics = {PATH.match(p["value"])["topic"] for panel in found for p in panel["config"]["paths"]}
    messages: dict[str, list[tuple[float, Any]]] = defaultdict(list)
    with open(args.log, "rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(topics=sorted(topics)):
            messages[channel.topic].append((message.log_time / 1e9, json.loads(message.data)))
    start = min(t for series in messages.values() for t, _ in series[:1])
    columns = 3
    rows = -(-len(found) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(6 * columns, 3.2 * rows), squeeze=False)
    for ax, panel in zip(axes.flat, found, strict=False):
        state = panel["panelType"] == "StateTransitions"
        for offset, series in enumerate(panel["config"]["paths"]):
            match = PATH.match(series["value"])
            points = [
                (t - start, resolve(payload, match["field"]))
                for t, payload in messages.get(match["topic"], [])
            ]
            points = [(t, v) for t, v in points if v is not None]
            if not points:
                continue
            times, values = zip(*points, strict=True)
            label = series.get("label", series["value"])
            if state:
                kinds = sorted({str(v) for v in values})
                scale = 0.8 / max(1, len(kinds) - 1)
                codes = [offset + scale * kinds.index(str(v)) for v in values]
                ax.step(times, codes, where="post", label=f"{label}: {' → '.join(kinds)}"[:60])
            else:
                style = {"dashed": "--", "dotted": ":"}.get(series.get("lineStyle", ""), "-")
                drawstyle = "steps-post" if series.get("lineInterpolation") == "step" else "default"
                ax.plot(times, values, style, drawstyle=drawstyle, label=label, linewidth=1)
        ax.set_title(panel.get("title", panel["panelType"]), fontsize=9)
        ax.set_xlabel("log time, s", fontsize=8)
        ax.legend(fontsize=7, loc="best")
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(found) :]:
        ax.axis("off")
    figure.suptitle(f"{Path(args.layout).name} on {Path(args.log).name} (matplotlib preview)")
    figure.tight_layout()
    figure.savefig(args.output, dpi=80)
    print(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
