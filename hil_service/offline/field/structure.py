"""The two-input U-model's structure, chosen on the training dives only.

``glide-u``'s structure is its polynomial degree M in the buoyancy input and whether it has
a constant drift term (``GlideUModel``). Which one generalises depends on the data: a
glider that flies two buoyancy levels (SEA035: −1.97 and ≈ 0.62 model units, nearly every
sample) determines two values of the input map and nothing of its shape between them, so
a cubic's extra coefficients are set by the few samples taken while the pump runs; one that
flies several levels (SG542: five to seven per mission) needs the curvature of the
sign(b)·√|b| law. The choice is made by leave-one-dive-out validation over the training
dives: for each candidate, each training dive long enough to be scored is held out in
turn, the candidate's regressor (``glide_regressor``, the model's own) fitted by least
squares on the other training dives, and run free over the held-out one from its first
``sync`` samples; the candidate with the highest median free-run fit wins, a candidate
with more parameters only when it beats the best simpler one by more than ``TIE`` points.
The median, since a short dive (a test dive of a few metres) gives a fit far off the
others. The held-out dives of the evaluation never enter.

Least squares, not the model's recursive least squares: RLS with forgetting close to 1
converges to it, and it is fast enough to run every candidate on every fold. Pure numerics,
deterministic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hil_service.umodel.glide_umodel import glide_regressor
from hil_service.umodel.scoring import fit_from_nmse, normalised_square_error

#: (degree, drift) candidates, in order of parameter count (ties go to the first).
CANDIDATES: tuple[tuple[int, bool], ...] = tuple(
    (degree, drift) for degree in (1, 2, 3, 4, 5) for drift in (False, True)
)
DEFAULT = (3, True)
#: Points of median fit a candidate must gain over a simpler one to be chosen instead.
TIE = 0.1


@dataclass(frozen=True)
class Piece:
    """One dive's samples: depth y, buoyancy input u and pitch, aligned."""

    dive: int
    y: np.ndarray
    u: np.ndarray
    pitch: np.ndarray


@dataclass
class StructureChoice:
    degree: int
    drift: bool
    folds: list[int]  # the training dives held out in turn
    scores: dict[str, float | None] = field(default_factory=dict)  # label → median fit %
    why: str = ""

    @property
    def label(self) -> str:
        return label(self.degree, self.drift)

    def as_dict(self) -> dict[str, object]:
        return {
            "degree": self.degree,
            "drift": self.drift,
            "folds": self.folds,
            "median_fit": self.scores,
            "why": self.why,
        }


def label(degree: int, drift: bool) -> str:
    return f"M={degree}{', drift' if drift else ''}"


def _design(
    piece: Piece, degree: int, drift: bool, u_scale: float, y_scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rows φ(t), t = 1..n−1, and targets y(t) − y(t−1)."""
    rows = [
        glide_regressor(
            float(piece.u[t - 1]),
            float(piece.pitch[t - 1]),
            float(piece.y[t - 1]),
            degree,
            u_scale,
            y_scale,
            drift,
        )
        for t in range(1, piece.y.size)
    ]
    return np.asarray(rows, dtype=float), np.diff(piece.y)


def _free_run_fit(
    theta: np.ndarray,
    piece: Piece,
    degree: int,
    drift: bool,
    u_scale: float,
    y_scale: float,
    sync: int,
) -> float | None:
    weights = theta.tolist()
    value = float(piece.y[sync - 1])
    sim = []
    for t in range(sync, piece.y.size):
        phi = glide_regressor(
            float(piece.u[t - 1]), float(piece.pitch[t - 1]), value, degree, u_scale, y_scale, drift
        )
        value += sum(w * p for w, p in zip(weights, phi, strict=True))  # inf, never raises
        if not math.isfinite(value):
            return None
        sim.append(value)
    actual = piece.y[sync:]
    error = (actual - np.asarray(sim)).tolist()
    return fit_from_nmse(normalised_square_error(actual.tolist(), error))


def _least_squares(x: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """θ of y ≈ x·θ over the finite rows; None when they cannot determine it."""
    with np.errstate(invalid="ignore", over="ignore"):
        ok = np.all(np.isfinite(x), axis=1) & np.isfinite(y)
    if np.count_nonzero(ok) < x.shape[1]:
        return None
    try:
        theta, *_ = np.linalg.lstsq(x[ok], y[ok], rcond=None)
    except np.linalg.LinAlgError:
        return None
    return theta if np.all(np.isfinite(theta)) else None


def choose_structure(
    pieces: Sequence[Piece],
    sync: int,
    min_samples: int,
    u_scale: float,
    y_scale: float = 100.0,
    candidates: Sequence[tuple[int, bool]] = CANDIDATES,
) -> StructureChoice:
    """The candidate with the best median leave-one-dive-out free-run fit over ``pieces``
    (the training dives), each dive of at least ``min_samples`` samples a fold."""
    folds = [i for i, p in enumerate(pieces) if p.y.size >= max(min_samples, sync + 2)]
    if len(folds) < 2 or len(pieces) < 2:
        return StructureChoice(
            *DEFAULT,
            [],
            why=f"{len(folds)} training dive(s) long enough to validate on, 2 needed: "
            f"the default {label(*DEFAULT)}",
        )
    best: tuple[float, int, bool] | None = None
    scores: dict[str, float | None] = {}
    for degree, drift in candidates:
        designs = [_design(p, degree, drift, u_scale, y_scale) for p in pieces]
        fits: list[float] = []
        for held in folds:
            x = np.vstack([d[0] for i, d in enumerate(designs) if i != held])
            y = np.concatenate([d[1] for i, d in enumerate(designs) if i != held])
            theta = _least_squares(x, y)
            fit = (
                None
                if theta is None
                else _free_run_fit(theta, pieces[held], degree, drift, u_scale, y_scale, sync)
            )
            fits.append(-math.inf if fit is None else fit)
        median = float(np.median(fits))
        scores[label(degree, drift)] = median if math.isfinite(median) else None
        if math.isfinite(median) and (best is None or median > best[0] + TIE):
            best = (median, degree, drift)
    if best is None:
        return StructureChoice(
            *DEFAULT, [pieces[i].dive for i in folds], scores, "no candidate could be fitted"
        )
    return StructureChoice(
        best[1],
        best[2],
        [pieces[i].dive for i in folds],
        scores,
        f"best median leave-one-dive-out free-run fit over {len(folds)} training dives",
    )
