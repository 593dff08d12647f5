"""Writes the Foxglove layout of one vehicle (``glider-{id}.json`` beside this file).

Built with ``foxglove.layouts`` (foxglove-sdk), the layout format the Foxglove app imports
(Layouts → Import from file). Its message paths name only topics and fields that the
service publishes, which the live view (``serve --foxglove``) streams and the MCAP log
records under the same names: the same file opens a live run and a log.
``tests/test_foxglove_layout.py`` regenerates it and checks every path against a recorded
log.

Run: .venv/bin/python config/foxglove/make_layout.py [--sysid N]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import foxglove.layouts as fl

HERE = Path(__file__).resolve().parent
N_ALPHA = 4  # U-model coefficients of the default (dynamic) model


def _series(value: str, label: str, **style: object) -> fl.PlotSeries:
    return fl.PlotSeries(value=value, label=label, timestamp_method="receiveTime", **style)


def _plot(title: str, unit: str, series: list[fl.PlotSeries]) -> fl.PlotPanel:
    return fl.PlotPanel(
        title=title,
        config=fl.PlotConfig(
            paths=series, show_legend=True, legend_display="top", y_axis_label=unit, is_synced=True
        ),
    )


def channel_plot(system_id: int, channel: str, unit: str) -> fl.PlotPanel:
    """The measurement, its setpoint and the a-priori one-step prediction."""
    root = f"glider/{system_id}"
    return _plot(
        f"{channel}: measured, setpoint, a-priori prediction",
        unit,
        [
            _series(f"{root}/telemetry.{channel}", f"{channel}"),
            _series(
                f"{root}/health.control.setpoints.{channel}",
                "setpoint",
                line_interpolation="step",
            ),
            _series(f"{root}/umodel/{channel}.y_hat", "a-priori y_hat", line_style="dashed"),
        ],
    )


def ballast_plot(system_id: int) -> fl.PlotPanel:
    root = f"glider/{system_id}"
    series = []
    for channel in ("depth", "pitch"):
        series += [
            _series(f"{root}/command/ballast.u_{channel}", f"u_{channel} commanded"),
            _series(f"{root}/telemetry.u_{channel}", f"u_{channel} applied", line_style="dashed"),
        ]
    return _plot("ballast: commanded vs applied (model units)", "u", series)


def coefficient_plot(system_id: int, channel: str) -> fl.PlotPanel:
    root = f"glider/{system_id}"
    return _plot(
        f"U-model coefficients ({channel})",
        "alpha",
        [_series(f"{root}/umodel/{channel}.alpha[{i}]", f"alpha{i}") for i in range(N_ALPHA)],
    )


def fit_plot(system_id: int) -> fl.PlotPanel:
    root = f"glider/{system_id}/health"
    return _plot(
        "identification fit (skill vs persistence; 1 = perfect, 0 = persistence)",
        "skill",
        [
            _series(f"{root}.identifier.{channel}.{field}", f"{channel} {field}")
            for channel in ("depth", "pitch")
            for field in ("recent_skill", "skill")
        ],
    )


def control_panel(system_id: int) -> fl.StateTransitionsPanel:
    root = f"glider/{system_id}/health"
    return fl.StateTransitionsPanel(
        title="control state",
        config=fl.StateTransitionsConfig(
            paths=[
                fl.StateTransitionsSeries(value=f"{root}.control.enabled", label="enabled"),
                fl.StateTransitionsSeries(value=f"{root}.control.commanding", label="commanding"),
                fl.StateTransitionsSeries(value=f"{root}.control.reason", label="reason"),
                fl.StateTransitionsSeries(
                    value=f"{root}.identifier.depth.converged", label="depth converged"
                ),
                fl.StateTransitionsSeries(
                    value=f"{root}.identifier.pitch.converged", label="pitch converged"
                ),
            ],
            is_synced=True,
        ),
    )


def layout(system_id: int) -> fl.Layout:
    def row(*panels: fl.BasePanel) -> fl.SplitItem:
        return fl.SplitItem(
            content=fl.SplitContainer(
                direction="row", items=[fl.SplitItem(content=p) for p in panels]
            )
        )

    return fl.Layout(
        content=fl.SplitContainer(
            direction="column",
            items=[
                row(channel_plot(system_id, "depth", "m"), channel_plot(system_id, "pitch", "rad")),
                row(ballast_plot(system_id), fit_plot(system_id)),
                row(
                    coefficient_plot(system_id, "depth"),
                    coefficient_plot(system_id, "pitch"),
                    control_panel(system_id),
                ),
            ],
        )
    )


def layout_json(system_id: int) -> str:
    """The layout as the file holds it (indented, stable key order)."""
    return json.dumps(json.loads(layout(system_id).to_json()), indent=2) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sysid", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or HERE / f"glider-{args.sysid}.json"
    out.write_text(layout_json(args.sysid))
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
