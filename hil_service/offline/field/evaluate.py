"""Identification of a field data set dive by dive: train on the first dives, score the rest.

Models per channel (depth: buoyancy input; pitch: pitch input):

* ``persistence``: ŷ(t) = y(t−1), and a free run that holds the first output;
* ``rls-arx`` and the U-model the log's configuration names (``dynamic`` by default), the
  project's online identifiers (``hil_service.umodel``): each training segment refills the
  model's history (``history_length`` samples, ``observe_only``) and then learns with
  ``step``; after training they never learn again;
* the first-principles baseline (``hil_service.umodel.steady_glide``): the steady-glide
  flight model for depth (from buoyancy, the measured pitch and depth), the static moment
  balance for pitch, least squares on the same training samples; for depth also
  ``steady-glide-buoyancy-only``, the same model given only what the U-model is given (the
  buoyancy input; |pitch| held at its training mean), which says how much of the physical
  model's lead is the measured pitch;
* for depth, ``glide-u`` (``hil_service.umodel.glide_umodel``): the U-model given what the
  flight model is given, the buoyancy input and the measured pitch, its polynomial either
  in the buoyancy input scaled by |sin θ|^{3/2} or in the flight model's regressor
  sign(b)·√|b|·|sin θ|^{3/2} (v₀ and c_p those of the flight model fitted on the training
  dives), the input, degree and drift chosen on the training dives (``structure``);
  trained online on the training dives like the single-input U-model.

The dives are split as ``split`` says (``SPLITS``): the first ``train_fraction`` of them for
training by default, or every other one.

Scores per held-out dive (each its own segment; the first ``L`` samples, L = 1 + the longest
history of the models, sync every model and are not scored):

* one-step skill = 1 − MSE(model) / MSE(persistence) of ŷ(t | measured y up to t−1);
* free-run fit = 100·(1 − ‖y − ŷ_sim‖/‖y − ȳ‖) % (``umodel.scoring.fit_from_nmse``, as
  ``experiment`` and ``health`` compute it), the model simulated on the recorded inputs
  from its own outputs over the whole dive;
* k-step NMSE = mean((y(t+k) − ŷ(t+k|t))²)/var(y) over windows that start every L + k
  samples, each re-synchronised on the L measured samples before it.

**Excitation** of a channel's input over the training part (docs/field-data.md): the input
is *excited enough* when (1) its standard deviation is at least 2 % of full scale, (2) it
starts a move (|Δu| > 0.5 % of full scale after a sample without one) at least once per
training dive on average (a glider's buoyancy engine moves a few times a dive, in large
steps: each step excites), and (3) the regressor
[y(t−1), u(t−1), 1] is not degenerate: its reciprocal condition number (after scaling each
column to unit RMS) is at least 1e-3. A glider that holds its pitch with its own loop moves
its pitch mass to cancel disturbances: the input moves, but in closed loop the output
barely answers; (3) and the skill say so.

One module over 500 lines: the runners of every model and the per-dive scoring share the
segment, array and result types and are read together; the models themselves live in
``hil_service.umodel``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hil_service.offline.field.structure import Piece, choose_structure, label
from hil_service.umodel import OneStepModel, PersistenceModel, build_model
from hil_service.umodel.glide_umodel import GlideUModel
from hil_service.umodel.scoring import fit_from_nmse, normalised_square_error
from hil_service.umodel.steady_glide import SteadyGlide, fit_static_pitch, fit_steady_glide

CHANNEL_INPUT = {"depth": "u_depth", "pitch": "u_pitch"}
EXCITATION_STD = 0.02
EXCITATION_MOVES = 1.0  # move onsets per training dive
EXCITATION_RCOND = 1e-3
PHYSICAL = {"depth": "steady-glide", "pitch": "static-balance"}
#: How the dives are split: ``first`` trains on the first ``train_fraction`` of them and
#: scores the rest; ``alternate`` trains on dives 1, 3, 5, … and scores 2, 4, 6, ….
SPLITS = ("first", "alternate")


@dataclass(frozen=True)
class Segment:
    dive: int
    start: int
    stop: int


@dataclass
class Arrays:
    """Grid samples of one vehicle (model units for the inputs), with their segments."""

    period: float
    depth: np.ndarray
    pitch: np.ndarray
    u_depth: np.ndarray
    u_pitch: np.ndarray
    segments: list[Segment]
    full_scale: float = 2.0

    def output(self, channel: str) -> np.ndarray:
        return self.depth if channel == "depth" else self.pitch

    def input(self, channel: str) -> np.ndarray:
        return self.u_depth if channel == "depth" else self.u_pitch


@dataclass
class DiveScore:
    dive: int
    samples: int
    one_step_mse: float | None = None
    skill: float | None = None
    fit: float | None = None
    k_step_nmse: float | None = None
    why: str = ""  # when a figure could not be computed


@dataclass
class ModelResult:
    model: str
    dives: list[DiveScore] = field(default_factory=list)
    skill: float | None = None  # pooled over the held-out dives
    fit: float | None = None  # mean of the per-dive fits
    k_step_nmse: float | None = None
    why: str = ""
    parameters: dict[str, Any] = field(default_factory=dict)
    #: the figure's dive: (y, one-step ŷ, free-run ŷ), aligned with the dive's samples
    trace: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


@dataclass
class Excitation:
    std: float  # of the input, in fractions of full scale
    moves: float  # move onsets per training dive
    rcond: float
    excited: bool
    why: str


@dataclass
class ChannelResult:
    channel: str
    train_dives: list[int]
    held_out: list[int]
    horizon: int
    excitation: Excitation
    models: list[ModelResult]
    figure_dive: int | None
    sync: int = 0  # samples at the start of each scored dive that synchronise the models


def nmse(y: np.ndarray, y_hat: np.ndarray) -> float | None:
    """Σ(y − ŷ)² / Σ(y − ȳ)² (``umodel.scoring``: None for a flat or non-finite y or ŷ)."""
    with np.errstate(invalid="ignore", over="ignore"):
        error = np.asarray(y, dtype=float) - np.asarray(y_hat, dtype=float)
    return normalised_square_error(np.asarray(y, dtype=float).tolist(), error.tolist())


def fit_percent(y: np.ndarray, y_sim: np.ndarray) -> float | None:
    return fit_from_nmse(nmse(y, y_sim))


def excitation(arrays: Arrays, channel: str, train: list[Segment]) -> Excitation:
    y, u = arrays.output(channel), arrays.input(channel)
    pieces_u = [u[s.start : s.stop] for s in train]
    pieces_y = [y[s.start : s.stop] for s in train]
    if not pieces_u or sum(p.size for p in pieces_u) < 3:
        return Excitation(0.0, 0.0, 0.0, False, "no training samples")
    uu = np.concatenate(pieces_u)
    std = float(np.std(uu)) / arrays.full_scale
    onsets = 0
    for piece in pieces_u:
        moving = np.abs(np.diff(piece)) > 0.005 * arrays.full_scale
        onsets += int(np.count_nonzero(moving[1:] & ~moving[:-1])) + int(moving[:1].sum())
    dives = len({s.dive for s in train})
    moves = onsets / dives
    rows = [
        np.column_stack([py[:-1], pu[:-1], np.ones(py.size - 1)])
        for py, pu in zip(pieces_y, pieces_u, strict=True)
        if py.size > 1
    ]
    x = np.concatenate(rows)
    rms = np.sqrt(np.mean(x**2, axis=0))
    rms[rms == 0] = 1.0
    singular = np.linalg.svd(x / rms, compute_uv=False)
    rcond = float(singular[-1] / singular[0]) if singular[0] > 0 else 0.0
    reasons = []
    if std < EXCITATION_STD:
        reasons.append(f"input std {100 * std:.2f} % of full scale < {100 * EXCITATION_STD:g} %")
    if moves < EXCITATION_MOVES:
        reasons.append(f"{moves:.1f} input moves per dive < {EXCITATION_MOVES:g}")
    if rcond < EXCITATION_RCOND:
        reasons.append(f"regressor rcond {rcond:.1e} < {EXCITATION_RCOND:g}")
    return Excitation(std, moves, rcond, not reasons, "; ".join(reasons) or "excited")


# ---- the runners: one-step, free-run and k-step predictions of one segment ----------------
#: (y, u_in, start, stop) → one-step ŷ[start+L:stop], free-run ŷ[start+L:stop], k-step
#: (targets, predictions) for one held-out segment.
Runner = Callable[[Segment], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def _model_inputs(u: np.ndarray, start: int, stop: int) -> np.ndarray:
    """u(t−1) for each sample of the segment (u of the first sample for the first)."""
    piece = u[start:stop]
    return np.concatenate((piece[:1], piece[:-1])) if piece.size else piece


def _train_online(model: OneStepModel, y: np.ndarray, u: np.ndarray, train: list[Segment]) -> None:
    sync = model.history_length
    for s in train:
        u_in = _model_inputs(u, s.start, s.stop)
        for j, k in enumerate(range(s.start, s.stop)):
            if j < sync:
                model.observe_only(float(u_in[j]), float(y[k]))
            else:
                model.step(float(u_in[j]), float(y[k]))


def _online_runner(
    model: OneStepModel, y: np.ndarray, u: np.ndarray, sync: int, horizon: int
) -> Runner:
    """The trained ``model`` never learns again, so ``sync`` measured samples (at least its
    ``history_length``) put it in the same state wherever it is: one instance serves the
    one-step pass, the free run and every k-step window (each window re-synchronised on the
    ``sync`` measured samples before its start, windows every sync + k samples)."""

    def resync(u_in: np.ndarray, yy: np.ndarray, start: int) -> None:
        for j in range(start - sync, start):
            model.observe_only(float(u_in[j]), float(yy[j]))

    def run(s: Segment) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        u_in = _model_inputs(u, s.start, s.stop)
        yy = y[s.start : s.stop]
        n = yy.size
        one = np.empty(n - sync)
        resync(u_in, yy, sync)
        for j in range(sync, n):
            one[j - sync] = model.predict(float(u_in[j]))
            model.observe_only(float(u_in[j]), float(yy[j]))
        sim = np.empty(n - sync)
        resync(u_in, yy, sync)
        for j in range(sync, n):
            value = model.predict(float(u_in[j]))
            model.observe_only(float(u_in[j]), value)
            sim[j - sync] = value
        targets: list[int] = []
        predictions: list[float] = []
        for start in range(sync, n - horizon + 1, sync + horizon):
            resync(u_in, yy, start)
            value = math.nan
            for i in range(start, start + horizon):
                value = model.predict(float(u_in[i]))
                model.observe_only(float(u_in[i]), value)
            targets.append(start + horizon - 1)
            predictions.append(value)
        return one, sim, np.asarray(targets, dtype=int), np.asarray(predictions)

    return run


def _steady_glide(arrays: Arrays, train: list[Segment]) -> SteadyGlide:
    """The flight model fitted by least squares on the training segments' depth rate."""
    dt = arrays.period
    z, b, th = arrays.depth, arrays.u_depth, arrays.pitch
    rate = np.concatenate([np.diff(z[s.start : s.stop]) / dt for s in train])
    b_in, th_in, z_in = (
        np.concatenate([a[s.start : s.stop - 1] for s in train]) for a in (b, th, z)
    )
    return fit_steady_glide(rate, b_in, th_in, z_in, (-arrays.full_scale, arrays.full_scale))


def _glide_runner(
    arrays: Arrays, train: list[Segment], horizon: int, sync: int
) -> tuple[Runner, dict]:
    dt = arrays.period
    z, b, th = arrays.depth, arrays.u_depth, arrays.pitch
    model = _steady_glide(arrays, train)

    def run(s: Segment) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        zz, bb, tt = z[s.start : s.stop], b[s.start : s.stop], th[s.start : s.stop]
        n = zz.size
        one = zz[sync - 1 : n - 1] + dt * model.depth_rate(
            bb[sync - 1 : n - 1], tt[sync - 1 : n - 1], zz[sync - 1 : n - 1]
        )
        sim = np.empty(n - sync)
        value = float(zz[sync - 1])
        for j in range(sync, n):
            value = model.step(value, float(bb[j - 1]), float(tt[j - 1]), dt)
            sim[j - sync] = value
        targets, predictions = [], []
        for j in range(sync, n - horizon + 1, sync + horizon):
            value = float(zz[j - 1])
            for i in range(j, j + horizon):
                value = model.step(value, float(bb[i - 1]), float(tt[i - 1]), dt)
            targets.append(j + horizon - 1)
            predictions.append(value)
        return one, sim, np.asarray(targets, dtype=int), np.asarray(predictions)

    return run, model.as_dict()


BUOYANCY_ONLY = "steady-glide-buoyancy-only"
GLIDE_U = GlideUModel.name


def _glide_u_runner(
    model: GlideUModel, arrays: Arrays, train: list[Segment], sync: int, horizon: int
) -> Runner:
    """The two-input U-model (buoyancy input and measured pitch), trained online on the
    training segments like the single-input models, then run as ``_online_runner`` runs
    them with θ(t−1) beside u(t−1)."""
    y, u, th = arrays.depth, arrays.u_depth, arrays.pitch
    lead = model.history_length
    for s in train:
        u_in = _model_inputs(u, s.start, s.stop)
        th_in = _model_inputs(th, s.start, s.stop)
        for j, k in enumerate(range(s.start, s.stop)):
            if j < lead:
                model.observe_only(float(u_in[j]), float(y[k]), float(th_in[j]))
            else:
                model.step(float(u_in[j]), float(y[k]), float(th_in[j]))

    def run(s: Segment) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        u_in = _model_inputs(u, s.start, s.stop).tolist()
        th_in = _model_inputs(th, s.start, s.stop).tolist()
        yy = y[s.start : s.stop].tolist()
        n = len(yy)

        def resync(start: int) -> None:
            for j in range(start - sync, start):
                model.observe_only(u_in[j], yy[j], th_in[j])

        one = np.empty(n - sync)
        resync(sync)
        for j in range(sync, n):
            one[j - sync] = model.predict(u_in[j], th_in[j])
            model.observe_only(u_in[j], yy[j], th_in[j])
        sim = np.empty(n - sync)
        resync(sync)
        for j in range(sync, n):
            value = model.predict(u_in[j], th_in[j])
            model.observe_only(u_in[j], value, th_in[j])
            sim[j - sync] = value
        targets: list[int] = []
        predictions: list[float] = []
        for start in range(sync, n - horizon + 1, sync + horizon):
            resync(start)
            value = math.nan
            for i in range(start, start + horizon):
                value = model.predict(u_in[i], th_in[i])
                model.observe_only(u_in[i], value, th_in[i])
            targets.append(start + horizon - 1)
            predictions.append(value)
        return one, sim, np.asarray(targets, dtype=int), np.asarray(predictions)

    return run


def _glide_u(
    arrays: Arrays,
    train: list[Segment],
    held: list[Segment],
    horizon: int,
    sync: int,
    figure: Segment | None,
    options: dict[str, Any],
) -> ModelResult:
    options = dict(options)
    choice = None
    if not {"feature", "degree", "drift"} & set(options):
        pieces = [
            Piece(
                s.dive,
                arrays.depth[s.start : s.stop],
                arrays.u_depth[s.start : s.stop],
                arrays.pitch[s.start : s.stop],
            )
            for s in train
        ]
        choice = choose_structure(
            pieces, sync, sync + horizon, arrays.full_scale, options.get("y_scale", 100.0)
        )
        options.update(feature=choice.feature, degree=choice.degree, drift=choice.drift)
    result = ModelResult(GLIDE_U)
    if options.get("feature") == "steady-glide" and not {"v0", "c_p"} <= set(options):
        try:
            flight = _steady_glide(arrays, train)
        except ValueError as error:
            result.why = f"no steady-glide input: {error}"
            return result
        options.update(v0=flight.v0, c_p=flight.c_p)
    model = GlideUModel(u_scale=arrays.full_scale, **options)
    run = _glide_u_runner(model, arrays, train, sync, horizon)
    names = [f"beta_{m + 1}" for m in range(model.degree)]
    if model.feature == "steady-glide":
        names += ["c"] if model.drift else []
    else:
        names += ["beta_0"] + (["c", "gamma"] if model.drift else ["gamma"])
    result.parameters = dict(zip(names, model.parameters, strict=True))
    if model.feature == "steady-glide":
        result.parameters.update(v0=model.v0, c_p=model.c_p)
    result.parameters["structure"] = label(model.feature, model.degree, model.drift)
    if choice is not None:
        result.parameters["structure_choice"] = choice.as_dict()
    _score(result, run, arrays.depth, held, sync, figure, horizon)
    return result


def _buoyancy_only(
    arrays: Arrays,
    train: list[Segment],
    held: list[Segment],
    horizon: int,
    sync: int,
    figure: Segment | None,
) -> ModelResult:
    """The steady-glide model given what the depth channel's U-model and RLS-ARX are given,
    the buoyancy input alone: |pitch| held at its mean over the training dives."""
    pitch = np.concatenate([arrays.pitch[s.start : s.stop] for s in train])
    level = float(np.mean(np.abs(pitch)))
    blind = replace(arrays, pitch=np.full_like(arrays.pitch, level))
    result = ModelResult(BUOYANCY_ONLY)
    try:
        run, result.parameters = _glide_runner(blind, train, horizon, sync)
        result.parameters["mean_abs_pitch"] = level
        _score(result, run, arrays.depth, held, sync, figure, horizon)
    except ValueError as error:
        result.why = str(error)
    return result


def _static_runner(
    arrays: Arrays, train: list[Segment], horizon: int, sync: int
) -> tuple[Runner, dict]:
    cols = [
        np.concatenate([a[s.start : s.stop] for s in train])
        for a in (arrays.pitch, arrays.u_pitch, arrays.u_depth)
    ]
    model = fit_static_pitch(*cols)

    def run(s: Segment) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        m = _model_inputs(arrays.u_pitch, s.start, s.stop)
        v = _model_inputs(arrays.u_depth, s.start, s.stop)
        hat = model.pitch(m, v)[sync:]
        n = s.stop - s.start
        targets = np.arange(sync + horizon - 1, n, sync + horizon)
        return hat, hat.copy(), targets, model.pitch(m, v)[targets]

    return run, model.as_dict()


def _score(
    result: ModelResult,
    run: Runner,
    y: np.ndarray,
    held: list[Segment],
    sync: int,
    figure: Segment | None,
    horizon: int,
) -> None:
    one_err, base_err, fits, k_nmses = [], [], [], []
    for s in held:
        yy = y[s.start : s.stop]
        score = DiveScore(s.dive, int(yy.size))
        if yy.size < sync + horizon:
            score.why = (
                f"dive too short: {yy.size} samples, {sync + horizon} needed "
                f"({sync} to synchronise + the {horizon}-step horizon)"
            )
            result.dives.append(score)
            continue
        one, sim, targets, predictions = run(s)
        actual = yy[sync:]
        e = actual - one
        base = actual - yy[sync - 1 : -1]
        score.one_step_mse = float(np.mean(e**2))
        b2 = float(np.mean(base**2))
        score.skill = 1.0 - score.one_step_mse / b2 if b2 > 0 else None
        score.fit = fit_percent(actual, sim)
        if targets.size >= 2:
            score.k_step_nmse = nmse(yy[targets], predictions)
        else:
            score.why = "dive shorter than the horizon: no k-step window"
        if not all(map(np.isfinite, (score.one_step_mse,))) or score.fit is None:
            score.why = score.why or "non-finite predictions (the model diverged)"
        one_err.append(e)
        base_err.append(base)
        if score.fit is not None and math.isfinite(score.fit):
            fits.append(score.fit)
        if score.k_step_nmse is not None:
            k_nmses.append(score.k_step_nmse)
        if figure is not None and s == figure:
            result.trace = (actual, one, sim)
        result.dives.append(score)
    if one_err:
        e, b = np.concatenate(one_err), np.concatenate(base_err)
        b2 = float(np.mean(b**2))
        if np.all(np.isfinite(e)) and b2 > 0:
            result.skill = 1.0 - float(np.mean(e**2)) / b2
    result.fit = float(np.mean(fits)) if fits else None
    result.k_step_nmse = float(np.mean(k_nmses)) if k_nmses else None
    if result.fit is None:
        result.why = "no held-out dive could be scored"


def identify_dives(
    arrays: Arrays,
    model_name: str = "dynamic",
    model_options: dict[str, dict[str, Any]] | None = None,
    train_fraction: float = 0.5,
    horizon_s: float = 300.0,
    seed: int = 0,
    glide_options: dict[str, Any] | None = None,
    split: str = "first",
    extra_models: dict[str, Callable[[int], OneStepModel]] | None = None,
) -> list[ChannelResult]:
    """Per channel: every model trained on the training dives and scored on the others.

    ``glide_options``: options of ``GlideUModel`` (``u_scale`` is the log's full scale;
    with none of ``feature``, ``degree``, ``drift`` the structure is chosen on the training
    dives; ``feature="steady-glide"`` without ``v0`` and ``c_p`` takes the flight model's,
    fitted on the training dives).
    ``extra_models``: more online models scored beside ``model_name`` (name → a factory
    given the channel's seed), as ``glider-hil experiment --log`` adds the paper's preset.
    """
    train_dives, held_dives, train, held = _split_dives(arrays, train_fraction, split)
    horizon = max(2, round(horizon_s / arrays.period))
    figure = max(held, key=lambda s: s.stop - s.start) if held else None
    results = []
    for i, channel in enumerate(CHANNEL_INPUT):
        options = (model_options or {}).get(channel, {})
        built = _online_models(model_name, options, seed * 2 + i, extra_models)
        sync = max(m.history_length for _, m in built) + 1
        y = arrays.output(channel)
        models = _score_online(built, y, arrays.input(channel), train, held, horizon, sync, figure)
        models.append(_physical(channel, arrays, y, train, held, horizon, sync, figure))
        if channel == "depth":
            models.append(_buoyancy_only(arrays, train, held, horizon, sync, figure))
            glide = _glide_u(arrays, train, held, horizon, sync, figure, glide_options or {})
            models.insert(len(built), glide)
        results.append(
            ChannelResult(
                channel,
                train_dives,
                held_dives,
                horizon,
                excitation(arrays, channel, train),
                models,
                None if figure is None else figure.dive,
                sync,
            )
        )
    return results


def _split_dives(
    arrays: Arrays, train_fraction: float, split: str
) -> tuple[list[int], list[int], list[Segment], list[Segment]]:
    """The training and held-out dives, and their segments, as ``split`` says."""
    segments = [s for s in arrays.segments if s.stop - s.start >= 2]
    if len({s.dive for s in segments}) < 2:
        # One file holding several yos (a Slocum segment file): its segments are the dives.
        segments = [Segment(i, s.start, s.stop) for i, s in enumerate(segments)]
    dives = sorted({s.dive for s in segments})
    if len(dives) < 2:
        raise ValueError(f"at least two dives are needed to hold one out, got {len(dives)}")
    if split == "first":
        n_train = min(len(dives) - 1, max(1, math.ceil(train_fraction * len(dives))))
        train_dives, held_dives = dives[:n_train], dives[n_train:]
    elif split == "alternate":
        train_dives, held_dives = dives[0::2], dives[1::2]
    else:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    train = [s for s in segments if s.dive in train_dives]
    held = [s for s in segments if s.dive in held_dives]
    return train_dives, held_dives, train, held


def _online_models(
    model_name: str,
    options: dict[str, Any],
    seed: int,
    extra_models: dict[str, Callable[[int], OneStepModel]] | None,
) -> list[tuple[str, OneStepModel]]:
    """A channel's online models, untrained: persistence, RLS-ARX, ``model_name`` and the
    extra ones (a name already taken is not built twice)."""
    built: list[tuple[str, OneStepModel]] = [
        ("persistence", PersistenceModel()),
        ("rls-arx", build_model("rls-arx")),
        (model_name, build_model(model_name, seed=seed, **options)),
    ]
    built += [
        (name, make(seed)) for name, make in (extra_models or {}).items() if name not in dict(built)
    ]
    return built


def _score_online(
    built: list[tuple[str, OneStepModel]],
    y: np.ndarray,
    u: np.ndarray,
    train: list[Segment],
    held: list[Segment],
    horizon: int,
    sync: int,
    figure: Segment | None,
) -> list[ModelResult]:
    """Each online model trained on the training dives, then scored on the held-out ones."""
    models: list[ModelResult] = []
    for name, model in built:
        result = ModelResult(name)
        _train_online(model, y, u, train)
        _score(result, _online_runner(model, y, u, sync, horizon), y, held, sync, figure, horizon)
        models.append(result)
    return models


def _physical(
    channel: str,
    arrays: Arrays,
    y: np.ndarray,
    train: list[Segment],
    held: list[Segment],
    horizon: int,
    sync: int,
    figure: Segment | None,
) -> ModelResult:
    """The channel's first-principles baseline (``PHYSICAL``), fitted and scored; its
    ``why`` says so when the fit is impossible."""
    result = ModelResult(PHYSICAL[channel])
    try:
        make = _glide_runner if channel == "depth" else _static_runner
        run, result.parameters = make(arrays, train, horizon, sync)
        _score(result, run, y, held, sync, figure, horizon)
    except ValueError as error:
        result.why = str(error)
    return result
