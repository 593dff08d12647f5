"""Multi-step accuracy of an identified model: free-run fit and k-step-ahead NMSE.

The one-step skill says how well a model predicts y(t) from the measured y(t−1 …); control
depends on the model's own outputs fed back over a horizon. Two figures, as system
identification reports them, on a **validation segment** the model did not learn from:

* **Free-run (simulation) fit**, percent::

      fit = 100 · (1 − ‖y − ŷ_sim‖ / ‖y − mean(y)‖)

  100 is a perfect simulation, 0 is no better than the validation mean, and it is negative
  when worse. ŷ_sim is the model simulated on the recorded inputs from its own past
  outputs.
* **k-step-ahead NMSE** at the control horizon k: from each start t, the model is given the
  measured history up to y(t) and simulated k steps on the recorded inputs; the error is
  y(t+k) − ŷ(t+k|t). NMSE = mean(e²) / var(y) over the starts, as the one-step NMSE of
  ``hil_service.umodel.scoring``.

How the model is frozen (the same for every model of ``hil_service.umodel``, through its
public interface only): a fresh model is built from ``model.config()`` (same seed, so the
same initial parameters) and re-run with ``step`` on the first ``split`` samples, exactly
as the online identifier saw them, so its parameters are those the online model had at
``split``. From then on it never learns: ``predict(u(t−1))`` gives ŷ(t) and
``observe_only(u(t−1), value)`` shifts a value into its history without adapting, the
value being its own prediction while it simulates and the measured output while it is
re-synchronised to the data between k-step windows.

k-step windows: a frozen copy alternates ``history_length`` measured samples (after which
its regressor holds no simulated value) with k simulated ones; copies staggered by
``stride`` samples cover starts ``split + L, split + L + stride, …`` (L = history_length).

Pure functions of arrays: no I/O, deterministic.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import numpy as np

from .interface import OneStepModel
from .scoring import fit_from_nmse, normalised_square_error, significant

ModelFactory = Callable[[], OneStepModel]


#: An error that stays within this share of the output's range counts as converged.
CONVERGENCE_BAND = 0.05

#: The k of the k-step scores where neither the log nor an identified model gives a
#: horizon (the fixed horizons of the controller before the predictive inverse).
FALLBACK_HORIZON = {"depth": 150, "pitch": 3}


def control_horizon(channel: str) -> int:
    """The k-step horizon scored on ``channel`` when nothing derives one."""
    return FALLBACK_HORIZON[channel]


def converged_at(error: np.ndarray, y: np.ndarray, band: float = CONVERGENCE_BAND) -> int | None:
    """First sample after which |error| stays within ``band`` × range(y); None if never."""
    span = float(np.max(y) - np.min(y)) if y.size else 0.0
    outside = np.flatnonzero(np.abs(error) > band * span)
    if outside.size == 0:
        return 0
    last = int(outside[-1])
    return None if last == error.size - 1 else last + 1


def fit_percent(
    y: Sequence[float] | np.ndarray, y_sim: Sequence[float] | np.ndarray
) -> float | None:
    """100·(1 − ‖y − ŷ‖ / ‖y − mean(y)‖); None for a constant y, an empty or non-finite one
    (``scoring.normalised_square_error`` and ``fit_from_nmse``: the one definition)."""
    return fit_from_nmse(nmse(y, y_sim))


def nmse(y: Sequence[float] | np.ndarray, y_hat: Sequence[float] | np.ndarray) -> float | None:
    """mean((y − ŷ)²) / var(y); None for fewer than two samples, a constant or non-finite y
    (``scoring.normalised_square_error``)."""
    y_arr = np.asarray(y, dtype=float)
    hat = np.asarray(y_hat, dtype=float)
    if y_arr.shape != hat.shape:
        raise ValueError(f"y and y_hat differ in shape: {y_arr.shape} and {hat.shape}")
    with np.errstate(invalid="ignore", over="ignore"):
        error = y_arr - hat
    return normalised_square_error(y_arr.ravel().tolist(), error.ravel().tolist())


def model_inputs(u_applied: np.ndarray) -> np.ndarray:
    """The input each sample's ``step`` receives: u(t−1), and u(0) for the first sample.

    The convention of ``identification.run_identification`` and of the pipeline.
    """
    u = np.asarray(u_applied, dtype=float)
    if u.size == 0:
        return u.copy()
    return np.concatenate((u[:1], u[:-1]))


def train(factory: ModelFactory, u_in: np.ndarray, y: np.ndarray, split: int) -> OneStepModel:
    """A fresh model that learnt online from samples 0 … split−1, as the identifier did."""
    model = factory()
    for k in range(split):
        model.step(float(u_in[k]), float(y[k]))
    return model


def free_run(model: OneStepModel, u_in: np.ndarray, start: int, stop: int) -> np.ndarray:
    """ŷ_sim(start … stop−1): the model fed its own outputs; it does not learn."""
    sim = np.empty(stop - start)
    for k in range(start, stop):
        u = float(u_in[k])
        y_hat = model.predict(u)
        model.observe_only(u, y_hat)
        sim[k - start] = y_hat
    return sim


def k_step_predictions(
    factory: ModelFactory,
    u_in: np.ndarray,
    y: np.ndarray,
    split: int,
    horizon: int,
    stride: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(targets t+k, ŷ(t+k|t)) for starts t = split + L, split + L + stride, … (see module)."""
    if horizon < 1 or stride < 1:
        raise ValueError(f"horizon and stride must be ≥ 1, got {horizon} and {stride}")
    n = y.size
    base = train(factory, u_in, y, split)
    sync = base.history_length
    cycle = sync + horizon
    copies = max(1, math.ceil(cycle / stride))
    targets: list[int] = []
    predictions: list[float] = []
    for c in range(copies):
        # Each copy replays the training part to get the parameters at ``split``, then
        # cycles: at least ``sync`` measured samples, then k simulated.
        model = base if c == 0 else train(factory, u_in, y, split)
        first = split + sync + c * stride  # first start of this copy
        k = split
        start = first
        while start + horizon < n:
            while k <= start:  # measured samples up to and including y(start)
                model.observe_only(float(u_in[k]), float(y[k]))
                k += 1
            y_hat = math.nan
            for j in range(1, horizon + 1):
                u = float(u_in[start + j])
                y_hat = model.predict(u)
                model.observe_only(u, y_hat)
            targets.append(start + horizon)
            predictions.append(y_hat)
            k = start + horizon + 1
            start += copies * stride  # ≥ cycle: the copy re-synchronises in between
    order = np.argsort(targets, kind="stable")
    return np.asarray(targets, dtype=int)[order], np.asarray(predictions)[order]


@dataclass(frozen=True)
class MultiStepScores:
    """Free-run fit (percent) and k-step NMSE on the validation segment [split, n)."""

    fit: float | None
    k_step_nmse: float | None
    horizon: int
    split: int
    windows: int

    def as_json(self) -> dict[str, Any]:
        return {
            "fit": _round(self.fit, 3),
            "k_step_nmse": significant(self.k_step_nmse),
            "horizon": self.horizon,
            "fit_split": self.split,
            "k_step_windows": self.windows,
        }


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None or not math.isfinite(value) else round(value, digits)


def multistep_scores(
    factory: ModelFactory,
    u_applied: np.ndarray,
    y: np.ndarray,
    split: int,
    horizon: int,
    stride: int | None = None,
) -> MultiStepScores:
    """Free-run fit and k-step NMSE of the model ``factory`` builds, trained on [0, split).

    ``u_applied[k]`` is the input applied during sample k, ``y[k]`` the output measured at
    its start (the plant's ``TelemetrySample``). ``stride`` defaults to max(1, k // 5):
    about five windows start within any k samples (each copy replays the training part,
    so the cost grows with the number of copies, about (k + L) / stride).
    """
    y_arr = np.asarray(y, dtype=float)
    u_in = model_inputs(np.asarray(u_applied, dtype=float))
    n = y_arr.size
    if u_in.size != n:
        raise ValueError(f"u and y differ in length: {u_in.size} and {n}")
    if not 1 <= split <= n - 2:
        raise ValueError(f"split must be in 1..{n - 2}, got {split}")
    model = train(factory, u_in, y_arr, split)
    sim = free_run(model, u_in, split, n)
    fit = fit_percent(y_arr[split:], sim)
    stride = max(1, horizon // 5) if stride is None else stride
    targets, predictions = k_step_predictions(factory, u_in, y_arr, split, horizon, stride)
    k_nmse = nmse(y_arr[targets], predictions) if targets.size >= 2 else None
    return MultiStepScores(fit, k_nmse, horizon, split, int(targets.size))


def longest_contiguous(t: Sequence[float], tolerance: float = 1.5) -> tuple[int, int]:
    """[start, stop) of the longest run of samples each one period after the previous.

    The period is the smallest positive step of ``t`` (as the pipeline learns it); a step
    longer than ``tolerance`` periods, or not forward, breaks the run. (0, 0) when empty.
    """
    times = np.asarray(t, dtype=float)
    if times.size == 0:
        return 0, 0
    steps = np.diff(times)
    positive = steps[steps > 0]
    if positive.size == 0:
        return 0, 1
    period = float(np.min(positive))
    breaks = np.flatnonzero(~((steps > 0) & (steps <= tolerance * period))) + 1
    edges = [0, *breaks.tolist(), times.size]
    best = max(pairwise(edges), key=lambda e: e[1] - e[0])
    return int(best[0]), int(best[1])
