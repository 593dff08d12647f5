"""Open-loop identification experiment: every model on the same plant samples.

The emulator's plant runs in-process (no sockets) under its own excitation; each model of
``MODEL_NAMES`` sees the same (u(t−1), y(t)) pairs and is scored on its a-priori one-step
prediction. This is the paper's experiment (figures 9–12) with the baselines beside it.

Beside the one-step scores, each model gets the multi-step figures of ``multistep.py``:
the free-run fit (percent) and the k-step-ahead NMSE at the control horizon, on the
samples after ``fit_split`` (default: the second half), the model frozen as the online
identifier had it at ``fit_split``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil_service.pipeline import DEFAULT_MODEL_OPTIONS, ControlSettings
from hil_service.umodel import MODEL_NAMES, OneStepModel, build_model, from_config, paper_preset
from hil_service.umodel.multistep import (
    MultiStepScores,
    control_horizon,
    converged_at,
    fit_percent,
    model_inputs,
    multistep_scores,
    train,
)
from hil_service.umodel.predictive import PredictiveInverse
from hil_service.umodel.scoring import ErrorStats
from plant_emulator.disturbances import NoDisturbance
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.models import CHANNELS
from plant_emulator.plant import GliderPlant, PlantConfig


@dataclass(frozen=True)
class IdentificationSettings:
    scenario: str = "paper"
    channel: str = "depth"
    samples: int = 5000
    seed: int = 0
    burn_in: int | None = None  # default: a fifth of the samples
    excitation: str = "steps"
    fit_split: int | None = None  # multi-step scores after this sample; default: half
    horizon: int | None = None  # k of the k-step NMSE; default: the control horizon

    def __post_init__(self) -> None:
        if self.channel not in CHANNELS:
            raise ValueError(f"channel must be one of {CHANNELS}, got {self.channel!r}")
        if self.samples < 10:
            raise ValueError(f"samples must be at least 10, got {self.samples}")
        if self.burn_in is not None and not 0 <= self.burn_in < self.samples - 1:
            raise ValueError(f"burn_in must be in 0..{self.samples - 2}, got {self.burn_in}")
        if self.fit_split is not None and not 1 <= self.fit_split <= self.samples - 2:
            raise ValueError(f"fit_split must be in 1..{self.samples - 2}, got {self.fit_split}")
        if self.horizon is not None and not 1 <= self.horizon < self.samples // 2:
            raise ValueError(f"horizon must be in 1..{self.samples // 2 - 1}, got {self.horizon}")

    @property
    def effective_burn_in(self) -> int:
        return self.samples // 5 if self.burn_in is None else self.burn_in

    @property
    def effective_fit_split(self) -> int:
        return self.samples // 2 if self.fit_split is None else self.fit_split

    @property
    def horizon_cap(self) -> int:
        """The longest derived horizon: the validation segment holds several windows."""
        return max(1, (self.samples - self.effective_fit_split) // 4)

    @property
    def effective_horizon(self) -> int:
        """The k-step horizon before any model is identified: given, or the fallback of
        ``control_horizon`` (capped). ``run_identification`` derives it from the
        identified model instead when it is not given (``IdentificationResult.horizon``)."""
        if self.horizon is not None:
            return self.horizon
        return max(1, min(control_horizon(self.channel), self.horizon_cap))


def derived_horizon(model: OneStepModel, control: ControlSettings | None = None) -> int:
    """The prediction horizon the service's predictive inverse derives from ``model``'s
    identified dynamics (the settling time of its step response); 0 when the model has
    no usable input map."""
    dynamics = getattr(model, "dynamics", None)
    if dynamics is None:  # persistence, ARX: no U-model map for the controller to read
        return 0
    settings = control or ControlSettings()
    inverse = PredictiveInverse(
        -settings.u_limit, settings.u_limit, settings.rate_limit, settings.predictive()
    )
    return inverse.horizon_for(dynamics())


@dataclass
class ModelTrace:
    """One model's run: scores and, per sample, prediction, error and U-model coefficients."""

    name: str
    config: dict[str, Any]
    y_hat: np.ndarray
    error: np.ndarray
    alpha: np.ndarray  # samples × (M+1): α₀, α₁, … as used for the prediction
    statuses: dict[str, int]
    nmse: float | None = None
    skill: float | None = None
    converged_at: int | None = None
    multistep: MultiStepScores | None = None

    @property
    def fit(self) -> float | None:
        return None if self.multistep is None else self.multistep.fit

    @property
    def k_step_nmse(self) -> float | None:
        return None if self.multistep is None else self.multistep.k_step_nmse

    def scores(self) -> dict[str, float | int | None]:
        scores: dict[str, float | int | None] = {
            "nmse": self.nmse,
            "skill": self.skill,
            "converged_at": self.converged_at,
        }
        if self.multistep is not None:
            scores.update(self.multistep.as_json())
        return scores


@dataclass
class IdentificationResult:
    settings: IdentificationSettings
    y: np.ndarray
    u: np.ndarray  # the input applied at each sample (u(t)); models see u(t−1)
    models: dict[str, ModelTrace] = field(default_factory=dict)
    #: k of the k-step NMSE: given, or the controller's horizon derived from the `dynamic`
    #: model frozen at the split ("derived"), or the fallback when it gives none.
    horizon: int = 0
    horizon_source: str = "given"

    def as_json(self) -> dict[str, Any]:
        return {
            "scenario": self.settings.scenario,
            "channel": self.settings.channel,
            "samples": self.settings.samples,
            "seed": self.settings.seed,
            "burn_in": self.settings.effective_burn_in,
            "fit_split": self.settings.effective_fit_split,
            "horizon": self.horizon,
            "horizon_source": self.horizon_source,
            "models": {name: trace.scores() for name, trace in self.models.items()},
        }


def experiment_models(channel: str, seed: int) -> dict[str, Any]:
    """The four models, configured as the service would run them on ``channel``."""
    return {
        "paper": paper_preset(seed=seed),
        "dynamic": build_model("dynamic", seed=seed, **DEFAULT_MODEL_OPTIONS["dynamic"][channel]),
        "rls-arx": build_model("rls-arx"),
        "persistence": build_model("persistence"),
    }


def _factory(config: dict[str, Any]) -> Callable[[], OneStepModel]:
    """Fresh models of ``config`` (same seed: the same initial parameters)."""
    return lambda: from_config(config)


def run_identification(settings: IdentificationSettings) -> IdentificationResult:
    plant = GliderPlant(PlantConfig(scenario=settings.scenario, seed=settings.seed))
    excitation = build_channel_excitations(settings.excitation, settings.seed)
    models = experiment_models(settings.channel, settings.seed)
    assert tuple(models) == MODEL_NAMES
    n, ch = settings.samples, settings.channel
    ys = np.empty(n)
    us = np.empty(n)
    y_hat = {name: np.empty(n) for name in models}
    errors = {name: np.empty(n) for name in models}
    alphas: dict[str, list[tuple[float, ...]]] = {name: [] for name in models}
    statuses: dict[str, dict[str, int]] = {name: {} for name in models}
    stats = {name: ErrorStats(burn_in=settings.effective_burn_in) for name in models}
    command = (0.0, 0.0)
    u_prev: float | None = None
    for k in range(n):
        sample = plant.step(*command)
        y, u_now = sample.output(ch), sample.input(ch)
        u_in = u_now if u_prev is None else u_prev
        estimates = {name: model.step(u_in, y) for name, model in models.items()}
        persistence_error = estimates["persistence"].error
        for name, estimate in estimates.items():
            y_hat[name][k] = estimate.y_hat
            errors[name][k] = estimate.error
            alphas[name].append(estimate.alpha)
            statuses[name][estimate.status] = statuses[name].get(estimate.status, 0) + 1
            stats[name].add(y, estimate.error, persistence_error)
        ys[k], us[k] = y, u_now
        u_prev = u_now
        command = (excitation["depth"].value(k), excitation["pitch"].value(k))
    horizon, source = _horizon(settings, models["dynamic"].config(), us, ys)
    result = IdentificationResult(
        settings=settings, y=ys, u=us, horizon=horizon, horizon_source=source
    )
    for name, model in models.items():
        width = max(len(a) for a in alphas[name])
        alpha = np.full((n, width), np.nan)
        for k, a in enumerate(alphas[name]):
            alpha[k, : len(a)] = a
        result.models[name] = ModelTrace(
            name=name,
            config=model.config(),
            y_hat=y_hat[name],
            error=errors[name],
            alpha=alpha,
            statuses=statuses[name],
            nmse=stats[name].nmse(),
            skill=stats[name].skill(),
            converged_at=converged_at(errors[name], ys),
            multistep=multistep_scores(
                _factory(model.config()),
                us,
                ys,
                settings.effective_fit_split,
                horizon,
            ),
        )
    return result


def _horizon(
    settings: IdentificationSettings, dynamic: dict[str, Any], u: np.ndarray, y: np.ndarray
) -> tuple[int, str]:
    """(k, how it was chosen): given; or derived, as the service's controller would, from
    the `dynamic` model as the identifier had it at the split, capped; or the fallback."""
    if settings.horizon is not None:
        return settings.horizon, "given"
    frozen = train(_factory(dynamic), model_inputs(u), y, settings.effective_fit_split)
    derived = derived_horizon(frozen)
    if derived < 1:
        return settings.effective_horizon, "fallback"
    return max(1, min(derived, settings.horizon_cap)), "derived"


@dataclass(frozen=True)
class FitBound:
    """The free-run fit no model driven by the input alone can beat in expectation.

    On the validation segment [split, n): y = x(u) + d, x the emulator's own plant without
    disturbance driven by the same commands, d the disturbance (independent of u). For any
    time-invariant predictor f(u) of a stationary input independent of the clock,
    E‖y − f(u)‖² ≥ ‖d − mean(d)‖² in expectation (docs/control.md, "The free-run fit's
    ceiling"), so ``bound`` = fit of x(u) + mean(d) (E[d] estimated from the realisation) is
    the ceiling; ``noise_free`` is the plant alone (mean(d) taken as 0). ``clock`` is the
    fit of x(u) + E[d(t)], the disturbance's mean at each instant over ``clock_seeds``
    disturbance seeds with the same input: the ceiling of a predictor that also knows the
    time (the disturbance's deterministic current wave), which no U-model has.
    """

    scenario: str
    channel: str
    seed: int
    split: int
    noise_free: float | None
    bound: float | None
    clock: float | None
    clock_seeds: int

    def as_json(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "channel": self.channel,
            "seed": self.seed,
            "fit_split": self.split,
            "noise_free_fit": _round(self.noise_free),
            "bound_fit": _round(self.bound),
            "clock_fit": _round(self.clock),
            "clock_seeds": self.clock_seeds,
        }


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


def plant_outputs(
    settings: IdentificationSettings, seed: int | None = None, disturbed: bool = True
) -> np.ndarray:
    """The channel's output under the experiment's excitation (``settings.seed``), with the
    disturbance of seed ``seed`` (default: the experiment's), or none."""
    plant = GliderPlant(
        PlantConfig(
            scenario=settings.scenario,
            seed=settings.seed if seed is None else seed,
        )
    )
    if not disturbed:
        plant.disturbances = {ch: NoDisturbance() for ch in CHANNELS}
    excitation = build_channel_excitations(settings.excitation, settings.seed)
    ys = np.empty(settings.samples)
    command = (0.0, 0.0)
    for k in range(settings.samples):
        ys[k] = plant.step(*command).output(settings.channel)
        command = (excitation["depth"].value(k), excitation["pitch"].value(k))
    return ys


def fit_bound(settings: IdentificationSettings, clock_seeds: int = 20) -> FitBound:
    """The ceiling of the free-run fit on ``settings``' validation segment (``FitBound``).

    The clock-aware mean averages ``clock_seeds`` disturbance seeds other than the
    experiment's (seeds 10⁶ + i: independent of any experiment seed below 10⁶).
    """
    if clock_seeds < 1:
        raise ValueError(f"clock_seeds must be at least 1, got {clock_seeds}")
    split = settings.effective_fit_split
    y = plant_outputs(settings)[split:]
    x = plant_outputs(settings, disturbed=False)[split:]
    d = y - x
    d_clock = np.zeros_like(d)
    for i in range(clock_seeds):
        d_clock += plant_outputs(settings, seed=1_000_000 + i)[split:] - x
    d_clock /= clock_seeds
    return FitBound(
        scenario=settings.scenario,
        channel=settings.channel,
        seed=settings.seed,
        split=split,
        noise_free=fit_percent(y, x),
        bound=fit_percent(y, x + float(np.mean(d))),
        clock=fit_percent(y, x + d_clock),
        clock_seeds=clock_seeds,
    )
