"""In-dive samples on a uniform grid, split into segments at gaps.

The identifiers of ``hil_service.umodel`` are discrete-time models of one fixed step, as a
live vehicle's samples are (a periodic profile's sampler puts a jittering vehicle on a
uniform grid of its own). Field data come at the vehicle's varying rates (a Seaglider
samples every 5, 10 or 20 s by depth band), so they are put on a grid of ``period`` s:

* a **segment** is a run of in-dive samples of one dive whose steps are all at most
  ``gap`` s; a longer step (a surface interval, a lost stretch) or a new dive starts a new
  segment, and the grid restarts at the segment's first sample;
* each grid time inside a segment takes the **linear interpolation** of the two raw samples
  around it (depth, pitch and both inputs); a grid time within ``period``/100 of a raw
  sample is that sample; the others are counted as interpolated, with the largest distance
  to the nearest raw sample;
* raw samples whose inputs are NaN (before the first value of a dive) leave their segment
  and are counted.

``GridResult.raw_used`` counts the raw in-dive samples that lie inside a segment (the ones
the identifier sees, through the grid); the rest are named in ``lost``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil_service.offline.field.table import FieldData
from protocols.profiles import MIN_SAMPLE_PERIOD

#: Segments shorter than this many grid samples are not worth identifying on.
MIN_SEGMENT = 4
#: Grid samples per raw sample, at most. A finer grid is nearly all interpolation: it gives
#: the identifier nothing the raw samples do not, and costs log size and time (about 400
#: bytes and 40 µs of writing a grid sample, measured on SEA035), so such a period is a
#: mistake (a unit, a typo); 1e-6 s over a day of 10 s samples would be 10¹⁰ grid samples.
MAX_UPSAMPLING = 100


@dataclass(frozen=True)
class GridSegment:
    dive: int
    start: int  # first grid index
    stop: int
    t0: float  # s since the epoch of the first grid sample
    raw: int  # raw samples inside


@dataclass
class GridResult:
    period: float
    gap: float
    t: np.ndarray  # s since the epoch
    depth: np.ndarray
    pitch: np.ndarray
    buoyancy: np.ndarray  # native units
    pitch_input: np.ndarray
    segments: list[GridSegment]
    raw_in_dive: int
    raw_used: int
    interpolated: int  # grid samples not at a raw sample
    max_distance: float  # s from an interpolated grid sample to its nearest raw sample
    lost: dict[str, int] = field(default_factory=dict)

    @property
    def size(self) -> int:
        return int(self.t.size)

    @property
    def used_fraction(self) -> float:
        return self.raw_used / self.raw_in_dive if self.raw_in_dive else 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "period_s": self.period,
            "gap_s": self.gap,
            "interpolation": (
                "linear between the raw samples around each grid time"
                if self.period > 0
                else "none: the samples as recorded (period 0)"
            ),
            "grid_samples": self.size,
            "segments": [
                {"dive": s.dive, "start": s.start, "stop": s.stop, "t0": s.t0, "raw": s.raw}
                for s in self.segments
            ],
            "raw_in_dive": self.raw_in_dive,
            "raw_used": self.raw_used,
            "used_fraction": round(self.used_fraction, 6),
            "interpolated": self.interpolated,
            "max_distance_s": round(self.max_distance, 3),
            "lost": dict(self.lost),
        }


def default_period(data: FieldData) -> float:
    """The median step between in-dive samples of a dive (s) to two significant digits
    (a clock's jitter does not set the grid), at least ``MIN_SAMPLE_PERIOD`` (the log
    stamps whole ms)."""
    mask = data.in_dive
    steps = np.diff(data.t)
    same = (data.dive[1:] == data.dive[:-1]) & mask[1:] & mask[:-1]
    good = steps[same & (steps > 0)]
    if not good.size:
        return 10.0
    return max(MIN_SAMPLE_PERIOD, float(f"{float(np.median(good)):.2g}"))  # 10.002 s → 10 s


def check_period(period: float) -> float:
    """``period`` if a grid can have it (finite, at least ``MIN_SAMPLE_PERIOD``: the log
    stamps whole ms), else ValueError."""
    if not (math.isfinite(period) and period >= MIN_SAMPLE_PERIOD):
        raise ValueError(
            f"grid period must be at least {MIN_SAMPLE_PERIOD:g} s (the log stamps whole ms), "
            f"got {period:g}"
        )
    return period


def _grid_count(t_raw: np.ndarray, period: float) -> int:
    """Grid samples of a segment whose raw samples are at ``t_raw``."""
    return math.floor((t_raw[-1] - t_raw[0]) / period + 1e-9) + 1


def _check_upsampling(total: int, raw: int, period: float) -> None:
    """Refuse a grid of more than ``MAX_UPSAMPLING`` samples per raw sample, before any is
    made (the grid arrays alone could exhaust the memory)."""
    if total > MAX_UPSAMPLING * max(raw, 1):
        raise ValueError(
            f"grid period {period:g} s would make {total:,} grid samples from {raw:,} raw "
            f"samples (at most {MAX_UPSAMPLING} per raw sample: the rest is interpolation); "
            "give a longer period"
        )


def resample(data: FieldData, period: float | None = None, gap: float | None = None) -> GridResult:
    period = check_period(default_period(data) if period is None else float(period))
    gap = max(60.0, 6.0 * period) if gap is None else float(gap)
    finite_inputs = np.isfinite(data.buoyancy) & np.isfinite(data.pitch_input)
    usable = data.in_dive & finite_inputs
    lost = {"no input value yet": int(np.count_nonzero(data.in_dive & ~finite_inputs))}
    raw_in_dive = int(np.count_nonzero(data.in_dive))
    index = np.flatnonzero(usable)
    runs: list[np.ndarray] = []
    if index.size:
        t = data.t[index]
        # A long step, a new dive, or rows not used in between (the surface) split.
        dive = data.dive[index]
        split = (np.diff(t) > gap) | (dive[1:] != dive[:-1]) | (np.diff(index) > 1)
        breaks = np.flatnonzero(split) + 1
        runs = np.split(index, breaks)
    names = ("depth", "pitch", "buoyancy", "pitch_input")
    out: dict[str, list[np.ndarray]] = {n: [] for n in ("t", *names)}
    segments: list[GridSegment] = []
    lost["in segments too short"] = 0
    interpolated = 0
    max_distance = 0.0
    size = 0
    used = 0
    counts = [_grid_count(data.t[run], period) for run in runs]
    kept = [(int(run.size), count) for run, count in zip(runs, counts, strict=True)]
    kept = [(raw, count) for raw, count in kept if count >= MIN_SEGMENT]
    _check_upsampling(sum(c for _, c in kept), sum(r for r, _ in kept), period)
    for run, count in zip(runs, counts, strict=True):
        t_raw = data.t[run]
        if count < MIN_SEGMENT:
            lost["in segments too short"] += int(run.size)
            continue
        grid = t_raw[0] + period * np.arange(count)
        out["t"].append(grid)
        for name in names:
            out[name].append(np.interp(grid, t_raw, getattr(data, name)[run]))
        nearest = _nearest(grid, t_raw)
        off = nearest > period / 100.0
        interpolated += int(np.count_nonzero(off))
        if off.any():
            max_distance = max(max_distance, float(nearest[off].max()))
        dive_number = int(data.dive[run[0]])
        segments.append(GridSegment(dive_number, size, size + count, float(grid[0]), run.size))
        size += count
        used += int(run.size)
    arrays = {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}
    return GridResult(
        period,
        gap,
        arrays["t"],
        arrays["depth"],
        arrays["pitch"],
        arrays["buoyancy"],
        arrays["pitch_input"],
        segments,
        raw_in_dive,
        used,
        interpolated,
        max_distance,
        {k: v for k, v in lost.items() if v},
    )


def as_recorded(data: FieldData, gap: float | None = None) -> GridResult:
    """The in-dive samples at their own times, segmented as ``resample`` does, nothing
    interpolated: what the identifier sees of samples taken as they come. Its step
    continuity takes a step longer than 1.5 of its shortest for a lost sample, so a vehicle
    that changes its sample period loses samples to resynchronisation there (measured in
    docs/field-data.md); ``period`` is the median step."""
    period = default_period(data)
    gap = max(60.0, 6.0 * period) if gap is None else float(gap)
    usable = data.in_dive & np.isfinite(data.buoyancy) & np.isfinite(data.pitch_input)
    index = np.flatnonzero(usable)
    lost = {"no input value yet": int(np.count_nonzero(data.in_dive & ~usable))}
    runs: list[np.ndarray] = []
    if index.size:
        t = data.t[index]
        dive = data.dive[index]
        split = (np.diff(t) > gap) | (dive[1:] != dive[:-1]) | (np.diff(index) > 1)
        runs = np.split(index, np.flatnonzero(split) + 1)
    kept = [run for run in runs if run.size >= MIN_SEGMENT]
    lost["in segments too short"] = sum(int(r.size) for r in runs if r.size < MIN_SEGMENT)
    segments, size = [], 0
    for run in kept:
        segments.append(
            GridSegment(
                int(data.dive[run[0]]), size, size + run.size, float(data.t[run[0]]), run.size
            )
        )
        size += run.size
    chosen = np.concatenate(kept) if kept else np.zeros(0, dtype=int)
    return GridResult(
        0.0,
        gap,
        data.t[chosen],
        data.depth[chosen],
        data.pitch[chosen],
        data.buoyancy[chosen],
        data.pitch_input[chosen],
        segments,
        int(np.count_nonzero(data.in_dive)),
        size,
        0,
        0.0,
        {k: v for k, v in lost.items() if v},
    )


def _nearest(grid: np.ndarray, t_raw: np.ndarray) -> np.ndarray:
    if t_raw.size == 1:
        return np.abs(grid - t_raw[0])
    at = np.clip(np.searchsorted(t_raw, grid), 1, t_raw.size - 1)
    return np.minimum(np.abs(grid - t_raw[at - 1]), np.abs(t_raw[at] - grid))
