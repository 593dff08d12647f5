"""The two-input U-model's structure, chosen on the training dives only.

``glide-u``'s structure is its input (``feature``: the buoyancy input scaled by the pitch,
or the steady-glide flight model's regressor g = sign(b)·√|b|·|sin θ|^{3/2}), the degree M
of its polynomial in that input, and whether it has a constant drift term
(``GlideUModel``). Which one generalises depends on the data: a glider that flies two
buoyancy levels (SEA035: −1.97 and ≈ 0.62 model units, nearly every sample) determines two
values of the buoyancy input's map and nothing of its shape between them, so a polynomial
in the buoyancy input has nothing to learn its curvature from, while a polynomial in g,
which varies along each leg with the pitch and the depth, has; one that flies several
levels (SG542: five to seven per mission) can learn the curvature of the sign(b)·√|b| law
from the buoyancy input itself. The steady-glide input of degree 1 without drift is the
flight model: the baseline is a candidate, and the U-model's polynomial is kept on top of
it only when the validation says so.

The choice is made by leave-one-dive-out validation over the training dives: for each
candidate, each training dive long enough to be scored is held out in turn, the
candidate's regressor (``glide_regressor``, the model's own) fitted by least squares on the
other training dives (for the steady-glide input, v₀ and c_p first, by the flight model's
least squares on the same dives: ``fit_steady_glide``), and run free over the held-out one
from its first ``sync`` samples; the candidate with the highest median free-run fit wins,
a candidate later in ``CANDIDATES`` (as many parameters or more) only when it beats the
best earlier one by more than ``TIE`` points. The median, since a short dive (a test dive
of a few metres) gives a fit far off the others. The held-out dives of the evaluation
never enter.

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
from hil_service.umodel.steady_glide import fit_steady_glide, glide_regressor_of

#: (feature, degree, drift) candidates, in order of parameter count (ties go to the first):
#: degree M of the steady-glide input has M (+ c) linear parameters and v₀, c_p, the
#: buoyancy input's M + β₀, γ (+ c), so at each degree and drift the flight model's
#: regressor comes first.
CANDIDATES: tuple[tuple[str, int, bool], ...] = tuple(
    (feature, degree, drift)
    for degree in (1, 2, 3, 4, 5)
    for drift in (False, True)
    for feature in ("steady-glide", "buoyancy")
)
#: Without two training dives to validate on: the flight model, nothing added on top of it.
DEFAULT = ("steady-glide", 1, False)
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
    feature: str
    degree: int
    drift: bool
    folds: list[int]  # the training dives held out in turn
    scores: dict[str, float | None] = field(default_factory=dict)  # label → median fit %
    why: str = ""

    @property
    def label(self) -> str:
        return label(self.feature, self.degree, self.drift)

    def as_dict(self) -> dict[str, object]:
        return {
            "feature": self.feature,
            "degree": self.degree,
            "drift": self.drift,
            "folds": self.folds,
            "median_fit": self.scores,
            "why": self.why,
        }


def label(feature: str, degree: int, drift: bool) -> str:
    name = "steady-glide input" if feature == "steady-glide" else "buoyancy input"
    return f"{name}, M={degree}{', drift' if drift else ''}"


@dataclass(frozen=True)
class _Form:
    """A candidate's regressor: ``glide_regressor`` with its structure and feature values."""

    feature: str
    degree: int
    drift: bool
    u_scale: float
    y_scale: float
    v0: float = 0.0
    c_p: float = 0.0

    def phi(self, u: float, pitch: float, y: float) -> list[float]:
        return glide_regressor(
            u,
            pitch,
            y,
            self.degree,
            self.u_scale,
            self.y_scale,
            self.drift,
            self.feature,
            self.v0,
            self.c_p,
        )


def _design(piece: Piece, form: _Form) -> tuple[np.ndarray, np.ndarray]:
    """Rows φ(t), t = 1..n−1, and targets y(t) − y(t−1)."""
    if form.feature == "steady-glide":  # the same regressor, by columns
        with np.errstate(invalid="ignore", over="ignore"):
            b = piece.u[:-1] - form.v0 - form.c_p * piece.y[:-1]
            g = glide_regressor_of(b, piece.pitch[:-1])
            columns = [g**m for m in range(1, form.degree + 1)]
        if form.drift:
            columns.append(np.ones(g.size))
        return np.column_stack(columns), np.diff(piece.y)
    rows = [
        form.phi(float(piece.u[t - 1]), float(piece.pitch[t - 1]), float(piece.y[t - 1]))
        for t in range(1, piece.y.size)
    ]
    return np.asarray(rows, dtype=float).reshape(len(rows), -1), np.diff(piece.y)


def _free_run_fit(theta: np.ndarray, piece: Piece, form: _Form, sync: int) -> float | None:
    weights = theta.tolist()
    value = float(piece.y[sync - 1])
    sim = []
    for t in range(sync, piece.y.size):
        phi = form.phi(float(piece.u[t - 1]), float(piece.pitch[t - 1]), value)
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


def neutral_and_compression(pieces: Sequence[Piece], u_scale: float) -> tuple[float, float] | None:
    """(v₀, c_p) of the flight model fitted by least squares on ``pieces`` (the depth rate
    per sample: v₀ and c_p do not depend on its unit); None when it cannot be fitted."""
    rate = np.concatenate([np.diff(p.y) for p in pieces])
    columns = [np.concatenate([getattr(p, a)[:-1] for p in pieces]) for a in ("u", "pitch", "y")]
    try:
        with np.errstate(invalid="ignore", over="ignore"):
            buoyancy, pitch, depth = columns
            model = fit_steady_glide(rate, buoyancy, pitch, depth, (-u_scale, u_scale))
    except ValueError:
        return None
    if not (math.isfinite(model.v0) and math.isfinite(model.c_p)):
        return None
    return model.v0, model.c_p


def _fold_fit(
    pieces: Sequence[Piece],
    held: int,
    form: _Form,
    designs: list[tuple[np.ndarray, np.ndarray]],
    sync: int,
) -> float | None:
    x = np.vstack([d[0] for i, d in enumerate(designs) if i != held])
    y = np.concatenate([d[1] for i, d in enumerate(designs) if i != held])
    theta = _least_squares(x, y)
    return None if theta is None else _free_run_fit(theta, pieces[held], form, sync)


def choose_structure(
    pieces: Sequence[Piece],
    sync: int,
    min_samples: int,
    u_scale: float,
    y_scale: float = 100.0,
    candidates: Sequence[tuple[str, int, bool]] = CANDIDATES,
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
    # The flight model's v₀ and c_p of each fold, fitted without the dive it holds out.
    feature_of_fold: dict[int, tuple[float, float] | None] = {}
    if any(c[0] == "steady-glide" for c in candidates):
        for held in folds:
            rest = [p for i, p in enumerate(pieces) if i != held]
            feature_of_fold[held] = neutral_and_compression(rest, u_scale)
    best: tuple[float, str, int, bool] | None = None
    scores: dict[str, float | None] = {}
    for feature, degree, drift in candidates:
        form = _Form(feature, degree, drift, u_scale, y_scale)
        fits: list[float] = []
        if feature == "steady-glide":
            for held in folds:
                values = feature_of_fold[held]
                fit = None
                if values is not None:
                    fold_form = _Form(feature, degree, drift, u_scale, y_scale, *values)
                    designs = [_design(p, fold_form) for p in pieces]
                    fit = _fold_fit(pieces, held, fold_form, designs, sync)
                fits.append(-math.inf if fit is None else fit)
        else:
            designs = [_design(p, form) for p in pieces]
            for held in folds:
                fit = _fold_fit(pieces, held, form, designs, sync)
                fits.append(-math.inf if fit is None else fit)
        median = float(np.median(fits))
        scores[label(feature, degree, drift)] = median if math.isfinite(median) else None
        if math.isfinite(median) and (best is None or median > best[0] + TIE):
            best = (median, feature, degree, drift)
    if best is None:
        return StructureChoice(
            *DEFAULT, [pieces[i].dive for i in folds], scores, "no candidate could be fitted"
        )
    return StructureChoice(
        best[1],
        best[2],
        best[3],
        [pieces[i].dive for i in folds],
        scores,
        f"best median leave-one-dive-out free-run fit over {len(folds)} training dives",
    )
