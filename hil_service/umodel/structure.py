"""How many input lags the dynamic U-model needs, and the input dead zone ahead of it,
chosen from the identification record.

A plant whose input acts after a delay of d samples first responds at lag d + 1; the dynamic
U-model's default four input lags cannot hold a delay of 4 or more, and leave one lag of the
response after a delay of 3 (docs/control.md, "The input lags, chosen from the record").
The delay is not known and is hard to estimate on its own from slow excitation
(neighbouring lags look alike), so the *structure* is chosen the way the horizon test
judges a model: by how well it predicts over a horizon on data it was not fitted on.

For each candidate number of input lags the same regression as ``DynamicUModel`` (output
lags, a bias, a polynomial of the scaled input on every input lag) is fitted by least
squares on the first two thirds of the record, then run free over segments of ``segment``
samples of the last third, from the measured outputs at each segment's start; its fit is
``1 − ‖y − ŷ‖ / ‖y − y_hold‖`` as the horizon test's. The fewest lags whose fit is within
``tie`` of the best win: more lags are more parameters to learn online from the same data.
When no candidate reaches ``qualify`` (50 %: each candidate's error over the segments at
most half the change it predicts) the first candidate, the model's default, stays: among
models none of which predicts over the segments the choice would be noise. It is this
choice's own threshold, not the horizon test's, which judges a different question (may
this model command) on the controller's horizon.

With the lags comes the weight of the smoothness prior on them (``lag_prior``): the gain
given times the chosen candidate's one-step residual share on its training rows (the
residual's variance over the output's), none below ``lag_prior.NOISE_FLOOR``.

Pure (numpy only) and deterministic for a record.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .lag_prior import NOISE_FLOOR

__all__ = [
    "DEAD_ZONE_CANDIDATES", "INPUT_LAG_CANDIDATES", "VALIDATION_SEGMENT", "LagChoice",
    "choose_dead_zone", "choose_input_lags",
]  # fmt: skip

#: The input lags tried: the model's default and enough for the delays up to 6 samples.
INPUT_LAG_CANDIDATES: tuple[int, ...] = (4, 6, 8)
#: Samples of each free run that a candidate's validation fit is scored over.
VALIDATION_SEGMENT = 50
#: The input dead zones tried (half-widths, in shares of the input scale): none, and up to
#: 17.5 % of it in steps of 2.5 %.
DEAD_ZONE_CANDIDATES: tuple[float, ...] = (0.0, 0.025, 0.05, 0.075, 0.1, 0.125, 0.15, 0.175)
#: The narrowest dead zone whose validation fit is within this of the best is taken: on a
#: plant without one, a record's noise lets a wider candidate fit a little better by chance.
DEAD_ZONE_MARGIN = 0.005


class LagChoice:
    """The chosen number of input lags, each candidate's validation fit (0–1) and the
    smoothness prior's weight given with them."""

    __slots__ = (
        "dead_zone", "dead_zone_fits", "dead_zone_rejected", "fits", "lags", "output_lags",
        "residual", "smoothing", "smoothing_rejected", "smoothing_withheld",
    )  # fmt: skip

    def __init__(
        self, lags: int, fits: dict[int, float], smoothing: float = 0.0, residual: float = 0.0
    ) -> None:
        self.lags = lags
        self.fits = fits
        #: The smoothness prior's weight (``lag_prior``): the gain times ``residual``.
        self.smoothing = smoothing
        #: The chosen candidate's one-step residual share on the record (0–1).
        self.residual = residual
        self.smoothing_rejected = False
        #: The prior was not given: the choice came while the channel commanded and kept
        #: its lags (the pipeline's ``_choose_input_lags``).
        self.smoothing_withheld = False
        #: Fewer output lags than the model's own, taken because its AR part was unstable
        #: (the pipeline's ``_fewer_output_lags``); None: the model's own.
        self.output_lags: int | None = None
        #: The input dead zone's half-width, in the input's units (``choose_dead_zone``).
        self.dead_zone = 0.0
        self.dead_zone_fits: dict[float, float] = {}
        #: A dead zone was found, but the identifier rebuilt beyond it was unstable.
        self.dead_zone_rejected = False

    def reject_smoothing(self) -> None:
        """The identifier keeps no smoothness prior (``lag_prior.adds_a_slower_mode``)."""
        self.smoothing = 0.0
        self.smoothing_rejected = True

    def reject_dead_zone(self, smoothing: float) -> None:
        """The identifier rebuilt beyond the dead zone found was unstable (the pipeline's
        ``_choose_input_lags``): none is taken, and the lags are taken again without it,
        with the prior's weight ``smoothing`` as first given."""
        self.dead_zone = 0.0
        self.dead_zone_rejected = True
        self.smoothing = smoothing
        self.smoothing_rejected = self.smoothing_withheld = False
        self.output_lags = None

    def withhold_smoothing(self) -> None:
        """The identifier keeps no smoothness prior: it commands with these lags already."""
        self.smoothing = 0.0
        self.smoothing_withheld = True

    def as_json(self) -> dict[str, object]:
        return {
            "input_lags": self.lags,
            "output_lags": self.output_lags,
            "fits": {
                str(k): round(v, 4) if math.isfinite(v) else None for k, v in self.fits.items()
            },
            "residual": round(self.residual, 6),
            "lag_smoothing": round(self.smoothing, 6),
            "lag_smoothing_rejected": self.smoothing_rejected,
            "lag_smoothing_withheld": self.smoothing_withheld,
            "dead_zone": self.dead_zone,
            "dead_zone_rejected": self.dead_zone_rejected,
            "dead_zone_fits": {
                f"{k:g}": round(v, 4) if math.isfinite(v) else None
                for k, v in self.dead_zone_fits.items()
            },
        }


def _design(
    y: np.ndarray, u: np.ndarray, rows: np.ndarray, na: int, lags: int, degree: int
) -> np.ndarray:
    """The regression row of each sample t in ``rows``: 1, the outputs y(t−1)…y(t−na), then
    x, x², … x^degree of each input lag's x = u(t − lag + 1), written a column at a time
    into one array (x^k as x^(k−1)·x, from 1·x)."""
    design = np.empty((rows.size, 1 + na + lags * degree))
    design[:, 0] = 1.0
    for i in range(1, na + 1):
        design[:, i] = y[rows - i]
    column = na + 1
    for lag in range(1, lags + 1):
        x = u[rows - lag + 1]
        p = np.ones(rows.size)
        for _ in range(degree):
            p = p * x
            design[:, column] = p
            column += 1
    return design


def _segment_starts(runs: np.ndarray, start: int, size: int, segment: int, first: int) -> list[int]:
    """Where the free runs start: every ``segment`` samples from ``start`` on, a start moved
    on by one while its segment or its history reaches across a restart (``runs``)."""
    starts: list[int] = []
    s = start
    while s + segment <= size:
        if runs[s + segment - 1] < segment - 1 + first:
            s += 1
            continue
        starts.append(s)
        s += segment
    return starts


def _validation_fits(
    thetas: np.ndarray, y: np.ndarray, us: Sequence[np.ndarray], start: int, na: int,
    lags: int, degree: int, segment: int, runs: np.ndarray, first: int,
) -> list[float]:  # fmt: skip
    """Each candidate's fit (``thetas[c]`` on inputs ``us[c]``, the same lags): free runs
    of ``segment`` samples from ``start`` on, each from measured history and within one
    run of consecutive samples (``runs``), ``1 − ‖y − ŷ‖ / ‖y − y_hold‖`` over them all;
    −inf when a run blows up or there is nothing to judge.

    The runs are independent of each other and of the candidates', so they all advance
    together, one sample of every run of every candidate a step: a choice costs a few dozen
    stacked matrix products rather than a Python loop per sample or per candidate (a
    fleet's channels make theirs around the same sample)."""
    starts = np.asarray(_segment_starts(runs, start, y.size, segment, first), dtype=int)
    if starts.size == 0:
        return [-math.inf] * len(us)
    with np.errstate(over="ignore", invalid="ignore"):
        return _free_run_fits(thetas, y, us, starts, na, lags, degree, segment)


def _free_run_fits(
    thetas: np.ndarray, y: np.ndarray, us: Sequence[np.ndarray], starts: np.ndarray, na: int,
    lags: int, degree: int, segment: int,
) -> list[float]:  # fmt: skip
    # The regression rows of every sample the runs predict, measured inputs throughout;
    # their output columns are replaced by each run's own outputs as it advances. The
    # stacked product multiplies each candidate's rows by its own weights alone: a
    # candidate scores the same bits among others as on its own.
    targets = starts[:, None] + np.arange(1, segment)
    flat = targets.ravel()
    design = np.stack([_design(y, u, flat, na, lags, degree) for u in us])
    design = design.reshape(len(us), starts.size, segment - 1, -1)
    history = np.empty((len(us), starts.size, na + segment - 1))
    for i in range(na):
        history[:, :, na - 1 - i] = y[starts - i]
    weights = thetas[:, :, None]
    for m in range(segment - 1):
        rows = design[:, :, m, :]
        rows[:, :, 1 : na + 1] = history[:, :, m : m + na][:, :, ::-1]
        history[:, :, na + m] = np.matmul(rows, weights)[:, :, 0]
    measured = y[targets]
    hold = float(np.sum((measured - y[starts][:, None]) ** 2))
    if not hold > 0.0:
        return [-math.inf] * len(us)
    fits = []
    for predicted in history[:, :, na:]:
        # A run that blew up anywhere fails the candidate (the values after it are not used).
        if np.all(np.abs(predicted) < 1e100):
            fits.append(1.0 - math.sqrt(float(np.sum((measured - predicted) ** 2)) / hold))
        else:
            fits.append(-math.inf)
    return fits


def _record(
    outputs: Sequence[float],
    u: np.ndarray,
    runs: Sequence[int] | None,
    first: int,
    parameters: int,
    segment: int,
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray] | None:
    """A record made ready for a structure's fit and validation: the outputs normalised
    (the regression is the same in any output unit and offset), the runs, where the
    validation third starts, and the regression rows of the first two thirds (from
    ``first`` on, none reaching across a restart). None when the record is not finite, too
    short for ``parameters`` (four rows each) and two validation segments, or constant."""
    y = np.asarray(outputs, dtype=float)
    if y.size != u.size or not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
        return None
    run = np.arange(y.size) if runs is None else np.asarray(runs, dtype=int)
    if run.size != y.size:
        return None
    split = (2 * y.size) // 3
    rows = np.arange(first, split)
    rows = rows[run[rows] >= first]
    if rows.size < 4 * parameters or y.size - split < 2 * segment:
        return None
    spread = float(np.std(y))
    if not spread > 0.0:
        return None
    return (y - y[0]) / spread, run, split, rows


def _narrowed(u: np.ndarray, width: float) -> np.ndarray:
    """``dead_zone.narrow`` of every input, as one array operation (the same values)."""
    if width == 0.0:
        return u
    return np.copysign(np.maximum(np.abs(u) - width, 0.0), u)


def choose_input_lags(
    outputs: Sequence[float],
    inputs: Sequence[float],
    u_scale: float,
    na: int = 4,
    degree: int = 3,
    candidates: Sequence[int] = INPUT_LAG_CANDIDATES,
    segment: int = VALIDATION_SEGMENT,
    tie: float = 0.02,
    qualify: float = 0.5,
    runs: Sequence[int] | None = None,
    smoothing_gain: float = 0.0,
) -> LagChoice | None:
    """The input lags for a record of consecutive samples: ``outputs[t]`` and ``inputs[t]``,
    the input applied one step before it (as ``HorizonTest`` records them). ``runs[t]``,
    when given, counts the samples before t that follow on (``HorizonTest.runs``): no
    regression row or validation segment reaches across a restart. None when the record
    is too short for the largest candidate or a fit is not finite."""
    u = np.asarray(inputs, dtype=float) / u_scale
    first = max(na, max(candidates) - 1)
    record = _record(outputs, u, runs, first, degree * max(candidates) + 1 + na, segment)
    if record is None:
        return None
    y, run, split, row_index = record
    target = y[row_index]
    spread_rows = float(np.var(target))
    fits: dict[int, float] = {}
    residuals: dict[int, float] = {}
    for lags in candidates:
        design = _design(y, u, row_index, na, lags, degree)
        theta, *_ = np.linalg.lstsq(design, target, rcond=None)
        if not np.all(np.isfinite(theta)):
            return None
        fits[lags] = _validation_fits(
            theta[None], y, [u], split, na, lags, degree, segment, run, first
        )[0]
        residual = float(np.mean((target - design @ theta) ** 2))
        residuals[lags] = residual / spread_rows if spread_rows > 0.0 else 0.0
    best = max(fits.values())
    if not math.isfinite(best):
        return None
    lags = candidates[0] if best < qualify else min(k for k, v in fits.items() if v >= best - tie)
    residual = residuals[lags]
    weight = smoothing_gain * residual if residual >= NOISE_FLOOR else 0.0
    return LagChoice(lags, fits, weight, residual)


def choose_dead_zone(
    outputs: Sequence[float],
    inputs: Sequence[float],
    u_scale: float,
    lags: int,
    na: int = 4,
    degree: int = 3,
    candidates: Sequence[float] = DEAD_ZONE_CANDIDATES,
    segment: int = VALIDATION_SEGMENT,
    margin: float = DEAD_ZONE_MARGIN,
    qualify: float = 0.5,
    runs: Sequence[int] | None = None,
) -> tuple[float, dict[float, float]]:
    """The input dead zone's half-width (in the input's units) for a record, as
    ``choose_input_lags`` judges a structure: the same regression with ``lags`` input lags
    on the input beyond each candidate dead zone, fitted on the first two thirds and run
    free over the last third. The narrowest candidate within ``margin`` of the best fit,
    when that reaches ``qualify``; else 0 (so no dead zone whenever none fits within
    ``margin`` of the best). Also each candidate's fit, by its share of ``u_scale`` (empty
    when the record cannot be judged).

    A polynomial input map gives the plant a slope across a dead zone where it has none,
    so a loop settles inside the zone and creeps across it (docs/control.md, "An input
    dead zone, chosen from the record"); taken out ahead of the model, the zone is
    stepped over."""
    u = np.asarray(inputs, dtype=float)
    first = max(na, lags - 1)
    record = _record(outputs, u, runs, first, degree * lags + 1 + na, segment)
    if record is None or not u_scale > 0.0:
        return 0.0, {}
    y, run, split, rows = record
    target = y[rows]
    narrowed, thetas = [], []
    for share in candidates:
        v = _narrowed(u, share * u_scale) / u_scale
        design = _design(y, v, rows, na, lags, degree)
        theta, *_ = np.linalg.lstsq(design, target, rcond=None)
        if not np.all(np.isfinite(theta)):
            return 0.0, {}
        narrowed.append(v)
        thetas.append(theta)
    validated = _validation_fits(
        np.array(thetas), y, narrowed, split, na, lags, degree, segment, run, first
    )
    fits = dict(zip(candidates, validated, strict=True))
    best = max(fits.values())
    if not (math.isfinite(best) and best >= qualify):
        return 0.0, fits
    share = min(share for share, fit in fits.items() if fit >= best - margin)
    return share * u_scale, fits
