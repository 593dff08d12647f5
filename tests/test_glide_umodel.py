"""The two-input U-model of depth (buoyancy input and measured pitch)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_service.umodel import build_model
from hil_service.umodel.glide_umodel import GlideUModel, steady_glide_feature
from hil_service.umodel.steady_glide import SteadyGlide

DT = 10.0


def _glider(seed: int, n: int = 1500) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A steady-glide plant: buoyancy steps, and a pitch that changes on its own (the
    vehicle's pitch loop), independently of the buoyancy input."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.choice([-1.5, -0.8, 0.8, 1.5], size=n // 50), 50)[:n]
    pitch = np.sign(-u) * np.repeat(rng.uniform(0.25, 0.6, size=n // 30 + 1), 30)[:n]
    z = np.empty(n)
    z[0] = 500.0
    for t in range(1, n):
        b = u[t - 1] - 0.1 - 2e-4 * z[t - 1]
        rate = -0.25 * np.sign(b) * np.sqrt(abs(b)) * abs(np.sin(pitch[t - 1])) ** 1.5
        z[t] = z[t - 1] + DT * rate
    return u, pitch, z


def _train(model: GlideUModel, u: np.ndarray, pitch: np.ndarray, z: np.ndarray) -> None:
    model.observe_only(float(u[0]), float(z[0]), float(pitch[0]))
    for t in range(1, z.size):
        model.step(float(u[t - 1]), float(z[t]), float(pitch[t - 1]))


def _free_run(model: GlideUModel, u: np.ndarray, pitch: np.ndarray, z: np.ndarray) -> np.ndarray:
    model.observe_only(float(u[0]), float(z[0]), float(pitch[0]))
    out = [float(z[0])]
    for t in range(1, z.size):
        value = model.predict(float(u[t - 1]), float(pitch[t - 1]))
        model.observe_only(float(u[t - 1]), value, float(pitch[t - 1]))
        out.append(value)
    return np.asarray(out)


def _fit(y: np.ndarray, y_hat: np.ndarray) -> float:
    return 100.0 * (1.0 - np.linalg.norm(y - y_hat) / np.linalg.norm(y - y.mean()))


def test_free_run_follows_a_glider_whose_pitch_the_buoyancy_does_not_tell() -> None:
    u, pitch, z = _glider(1)
    model = GlideUModel()
    _train(model, u, pitch, z)
    tu, tp, tz = _glider(2)
    fit = _fit(tz, _free_run(model, tu, tp, tz))
    # The single-input U-model sees the same buoyancy steps without the pitch.
    single = build_model("dynamic")
    single.observe_only(float(u[0]), float(z[0]))
    for t in range(1, z.size):
        single.step(float(u[t - 1]), float(z[t]))
    single.observe_only(float(tu[0]), float(tz[0]))
    sim = [float(tz[0])]
    for t in range(1, tz.size):
        value = single.predict(float(tu[t - 1]))
        single.observe_only(float(tu[t - 1]), value)
        sim.append(value)
    single_fit = _fit(tz, np.asarray(sim))
    assert fit > 90.0
    assert fit > single_fit + 10.0


def test_bad_samples_rejected_without_touching_the_state() -> None:
    u, pitch, z = _glider(3, 300)
    model = GlideUModel()
    _train(model, u, pitch, z)
    before = model.snapshot()
    for u_prev, y, th in (
        (math.nan, 1.0, 0.3),
        (0.5, math.inf, 0.3),
        (0.5, 1.0, math.nan),
        (0.5, 1.0, 7.0),  # |pitch| > π rad: degrees given as radians
        (1e9, 1.0, 0.3),
    ):
        estimate = model.step(u_prev, y, th)
        assert estimate.status == "rejected"
        assert all(math.isfinite(v) for v in (estimate.y, estimate.y_hat, *estimate.alpha))
        assert model.observe_only(u_prev, y, th) is False
        assert math.isfinite(model.predict(u_prev, th))
    after = model.snapshot()
    assert after.pop("n_rejected") == before.pop("n_rejected") + 5
    assert after == before


def test_deterministic_and_rebuilt_from_its_config() -> None:
    u, pitch, z = _glider(4, 400)
    first = GlideUModel(degree=5, lam=0.999)
    _train(first, u, pitch, z)
    cfg = first.config()
    assert cfg.pop("name") == "glide-u"
    second = GlideUModel(**cfg)
    _train(second, u, pitch, z)
    assert first.parameters == second.parameters
    assert first.predict(0.7, -0.4) == second.predict(0.7, -0.4)


def test_alpha_reproduces_the_prediction() -> None:
    u, pitch, z = _glider(5, 300)
    model = GlideUModel()
    _train(model, u[:-1], pitch[:-1], z[:-1])
    estimate = model.step(float(u[-2]), float(z[-1]), float(pitch[-2]))
    a0, *poly = estimate.alpha
    x = float(u[-2])
    assert a0 + sum(a * x ** (m + 1) for m, a in enumerate(poly)) == pytest.approx(
        estimate.y_hat, rel=1e-12, abs=1e-9
    )


def test_divergence_resets_the_parameters() -> None:
    model = GlideUModel(guard={"param_limit": 1.0})
    u, pitch, z = _glider(6, 200)
    statuses = set()
    model.observe_only(float(u[0]), float(z[0]), float(pitch[0]))
    for t in range(1, z.size):
        statuses.add(model.step(float(u[t - 1]), float(z[t]) * 50, float(pitch[t - 1])).status)
    assert "diverged" in statuses
    assert math.sqrt(sum(v * v for v in model.parameters)) <= 1.0 + 1e-9


@pytest.mark.parametrize("bad", [{"degree": 0}, {"u_scale": 0.0}, {"y_scale": math.nan}])
def test_invalid_options_raise(bad: dict) -> None:
    with pytest.raises(ValueError):
        GlideUModel(**bad)


def test_without_drift_one_parameter_less_and_rebuilt_from_its_config() -> None:
    u, pitch, z = _glider(7, 400)
    model = GlideUModel(degree=2, drift=False)
    _train(model, u, pitch, z)
    assert len(model.parameters) == 2 + 2  # β₁, β₂, β₀, γ
    cfg = model.config()
    assert cfg.pop("name") == "glide-u" and cfg["drift"] is False
    again = GlideUModel(**cfg)
    _train(again, u, pitch, z)
    assert again.parameters == model.parameters
    assert len(GlideUModel(degree=2).parameters) == 5


def test_the_steady_glide_input_of_degree_one_is_the_flight_model() -> None:
    # With the plant's v₀ and c_p, degree 1 without drift learns β₁ = −k·Δt and then
    # predicts the flight model's depth step for step.
    u, pitch, z = _glider(8)
    model = GlideUModel(feature="steady-glide", degree=1, drift=False, v0=0.1, c_p=2e-4)
    _train(model, u, pitch, z)
    assert model.parameters == pytest.approx((-0.25 * DT,), rel=1e-3)
    law = SteadyGlide(k=0.25, v0=0.1, c_p=2e-4, rms=0.0, samples=0)
    tu, tp, tz = _glider(9, 400)
    model.observe_only(float(tu[0]), float(tz[0]), float(tp[0]))
    for t in range(1, tz.size):
        expected = law.step(float(tz[t - 1]), float(tu[t - 1]), float(tp[t - 1]), DT)
        assert model.predict(float(tu[t - 1]), float(tp[t - 1])) == pytest.approx(
            expected, abs=1e-3
        )
        model.observe_only(float(tu[t - 1]), float(tz[t]), float(tp[t - 1]))


def test_steady_glide_input_alpha_config_and_parameters() -> None:
    u, pitch, z = _glider(10, 400)
    model = GlideUModel(feature="steady-glide", degree=3, v0=0.05, c_p=1e-4)
    assert len(model.parameters) == 3 + 1  # β₁..β₃, c
    assert len(GlideUModel(feature="steady-glide", degree=3, drift=False).parameters) == 3
    _train(model, u[:-1], pitch[:-1], z[:-1])
    estimate = model.step(float(u[-2]), float(z[-1]), float(pitch[-2]))
    a0, *poly = estimate.alpha
    g = steady_glide_feature(float(u[-2]), float(pitch[-2]), float(z[-2]), 0.05, 1e-4)
    assert a0 + sum(a * g ** (m + 1) for m, a in enumerate(poly)) == pytest.approx(
        estimate.y_hat, rel=1e-12, abs=1e-9
    )
    cfg = model.config()
    assert cfg.pop("name") == "glide-u"
    assert (cfg["feature"], cfg["v0"], cfg["c_p"]) == ("steady-glide", 0.05, 1e-4)
    again = GlideUModel(**cfg)
    _train(again, u[:-1], pitch[:-1], z[:-1])
    assert again.step(float(u[-2]), float(z[-1]), float(pitch[-2])) == estimate


@pytest.mark.parametrize("bad", [{"feature": "pitch"}, {"v0": math.inf}, {"c_p": math.nan}])
def test_invalid_feature_options_raise(bad: dict) -> None:
    with pytest.raises(ValueError):
        GlideUModel(**bad)
