"""Figures shared by ``experiment --plots`` and ``report``, in the style of the paper's 9–12.

Built on ``matplotlib.figure.Figure`` directly (no pyplot): no global state, no GUI
backend, safe to call from any thread or a headless CI machine.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

#: Units of each channel's output, for axis labels.
UNITS = {"depth": "m", "pitch": "rad"}

_SIZE = (10.0, 8.0)
_DPI = 110


def prediction_figure(
    path: Path,
    title: str,
    channel: str,
    t: np.ndarray,
    y: np.ndarray,
    y_hat: np.ndarray,
    alpha: np.ndarray | None,
    time_unit: str = "s",
    restarts: Sequence[float] = (),
    baseline: np.ndarray | None = None,
    note: str = "",
) -> Path:
    """Actual vs predicted output, the a-priori error, and the U-model coefficients;
    ``restarts``: times at which the vehicle's clock restarted (drawn as dotted lines);
    ``baseline``: the persistence prediction, whose error is drawn beside the model's;
    ``note``: a line under the title (the multi-step fit, the skill)."""
    unit = UNITS.get(channel, "")
    has_alpha = alpha is not None and alpha.size > 0
    wide = alpha is not None and has_alpha and alpha.shape[1] > 1
    rows = 2 + (2 if wide else 1 if has_alpha else 0)
    fig = Figure(figsize=(_SIZE[0], _SIZE[1] + 2.0 * (rows - 3)), dpi=_DPI, layout="constrained")
    axes = fig.subplots(rows, 1, sharex=True)
    axes[0].plot(t, y, color="black", linewidth=1.0, label=f"actual {channel}")
    axes[0].plot(t, y_hat, color="tab:red", linewidth=0.8, linestyle="--", label="predicted ŷ")
    axes[0].set_ylabel(f"{channel} [{unit}]")
    if channel == "depth":
        axes[0].invert_yaxis()  # deeper is down, as on a depth chart
    axes[0].legend(loc="upper right")
    if baseline is not None and baseline.size == y.size:
        axes[1].plot(
            t, y - baseline, color="grey", linewidth=0.8, linestyle="--", label="persistence error"
        )
    axes[1].plot(t, y - y_hat, color="tab:blue", linewidth=0.8, label="y − ŷ (a priori)")
    axes[1].axhline(0.0, color="grey", linewidth=0.5)
    axes[1].set_ylabel(f"error [{unit}]")
    axes[1].legend(loc="upper right")
    if has_alpha and alpha is not None:
        # α₀ carries the output level (and, in the dynamic model, its past), so it gets its
        # own axis; the input coefficients α₁…α_M are small and would be flattened beside it.
        axes[2].plot(t, alpha[:, 0], color="tab:purple", linewidth=0.9, label="α₀")
        axes[2].set_ylabel(f"α₀ [{unit}]")
        axes[2].legend(loc="upper right")
        if rows == 4:
            for i in range(1, alpha.shape[1]):
                axes[3].plot(t, alpha[:, i], linewidth=0.9, label=f"α{_subscript(i)}")
            axes[3].set_ylabel(f"αᵢ [{unit} per unitⁱ]")
            axes[3].legend(loc="upper right", ncol=min(alpha.shape[1] - 1, 4))
    axes[-1].set_xlabel(_time_label(time_unit, restarts))
    for ax in axes:
        ax.grid(True, alpha=0.3)
        _mark_restarts(ax, restarts)
    fig.suptitle(title if not note else f"{title}\n{note}")
    fig.savefig(path)
    return path


def tracking_figure(
    path: Path,
    title: str,
    channel: str,
    t: np.ndarray,
    series: Sequence[tuple[str, np.ndarray]],
    setpoint: np.ndarray | None,
    inputs: Sequence[tuple[str, np.ndarray]],
    time_unit: str = "s",
    restarts: Sequence[float] = (),
) -> Path:
    """Outputs against the setpoint (top) and the ballast inputs (bottom, model units);
    ``restarts`` as in ``prediction_figure``."""
    unit = UNITS.get(channel, "")
    fig = Figure(figsize=(_SIZE[0], 6.5), dpi=_DPI, layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    if setpoint is not None:
        top.step(t, setpoint, where="post", color="black", linewidth=1.2, label="setpoint")
    for label, values in series:
        top.plot(t, values, linewidth=0.9, label=label)
    top.set_ylabel(f"{channel} [{unit}]")
    if channel == "depth":
        top.invert_yaxis()
    top.legend(loc="upper right")
    for i, (label, values) in enumerate(inputs):
        # Later series dashed so that one drawn over an identical one stays visible.
        bottom.step(
            t,
            values,
            where="post",
            linewidth=0.9,
            linestyle="-" if i == 0 else "--",
            label=label,
        )
    bottom.set_ylabel("ballast input [model units]")
    bottom.set_xlabel(_time_label(time_unit, restarts))
    bottom.legend(loc="upper right")
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
        _mark_restarts(ax, restarts)
    fig.suptitle(title)
    fig.savefig(path)
    return path


def _time_label(unit: str, restarts: Sequence[float]) -> str:
    if not restarts:
        return f"time [{unit}]"
    return f"time [{unit}], run on across {len(restarts)} clock restart(s) (dotted)"


def _mark_restarts(ax: Axes, restarts: Sequence[float]) -> None:
    for x in restarts:
        ax.axvline(x, color="dimgrey", linestyle=":", linewidth=1.2)


def _subscript(i: int) -> str:
    return "".join("₀₁₂₃₄₅₆₇₈₉"[int(d)] for d in str(i))
