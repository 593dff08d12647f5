"""Identifiers of hil_service.umodel: interface, guards, determinism, identification quality."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hil_service.umodel import (
    MODEL_NAMES,
    STATUSES,
    DynamicUModel,
    Estimate,
    OneStepModel,
    PaperUModel,
    PredictiveModel,
    build_model,
    from_config,
    paper_preset,
)


def random_steps(n: int, seed: int, lo: float = -2.0, hi: float = 2.0) -> list[float]:
    """Piecewise-constant input: random levels in [lo, hi] held 5..29 samples."""
    rng = np.random.default_rng(seed)
    u: list[float] = []
    while len(u) < n:
        u += [float(rng.uniform(lo, hi))] * int(rng.integers(5, 30))
    return u[:n]


def simulate(u: list[float]) -> list[float]:
    """y(t) = 1.5 y(t−1) − 0.7 y(t−2) + 0.2 u(t−1) + 0.1 u(t−1)³ (poles |z| = 0.84)."""
    y = [0.0] * len(u)
    for t in range(len(u)):
        y1 = y[t - 1] if t >= 1 else 0.0
        y2 = y[t - 2] if t >= 2 else 0.0
        u1 = u[t - 1] if t >= 1 else 0.0
        y[t] = 1.5 * y1 - 0.7 * y2 + 0.2 * u1 + 0.1 * u1**3
    return y


def run(model: OneStepModel, u: list[float], y: list[float]) -> list[Estimate]:
    """Drive a model with the convention step(u(t−1), y(t))."""
    return [model.step(u[t - 1] if t else 0.0, y[t]) for t in range(len(y))]


def nmse(errors: np.ndarray, y: np.ndarray) -> float:
    return float(np.mean(errors**2) / np.var(y))


def all_finite(est: Estimate) -> bool:
    vals = [est.y, est.y_hat, est.error, *est.alpha, *est.weights]
    return all(math.isfinite(v) for v in vals)


def test_factory_and_names() -> None:
    assert MODEL_NAMES == ("paper", "dynamic", "rls-arx", "persistence")
    for name in MODEL_NAMES:
        model = build_model(name)
        assert isinstance(model, OneStepModel)
        assert model.name == name
        # The controller's interface: the U-models give their multi-step input map.
        assert isinstance(model, PredictiveModel) == (name in ("paper", "dynamic"))
    with pytest.raises(ValueError):
        build_model("nope")
    with pytest.raises(TypeError):
        build_model("paper", not_an_option=1)
    with pytest.raises(ValueError):
        build_model("paper", mu=2.0)


def test_paper_preset_matches_paper() -> None:
    m = paper_preset(seed=3)
    cfg = m.config()
    assert cfg["name"] == "paper"
    assert cfg["degree"] == 3 and cfg["mu"] == 0.5 and cfg["beta"] == 0.25
    assert len(cfg["centres"]) == 17
    assert cfg["centres"][0] == -2.0 and cfg["centres"][-1] == 2.0
    theta = m.snapshot()["theta"]
    assert len(theta) == 17 + 3
    assert max(abs(t) for t in theta) <= 0.1
    assert PaperUModel(seed=3).config() == cfg


def test_estimate_shape_and_identity() -> None:
    m = paper_preset(seed=1)
    est = m.step(0.7, 0.4)
    with pytest.raises(AttributeError):  # immutable
        est.y = 1.0  # type: ignore[misc]
    assert est.model == "paper" and est.status in STATUSES
    assert len(est.alpha) == 4 and len(est.weights) == 17
    # alpha are the coefficients that produced y_hat: ŷ = α₀ + α₁u + α₂u² + α₃u³.
    u = 0.7
    a = est.alpha
    assert a[0] + a[1] * u + a[2] * u**2 + a[3] * u**3 == pytest.approx(est.y_hat, abs=1e-14)
    assert est.error == est.y - est.y_hat

    d = DynamicUModel(na=2, nb=3).step(0.5, 1.0)
    assert len(d.alpha) == 4 and len(d.weights) == 1 + 2 + 2 * 3  # bias, a_1..2, lags 2..3
    r = build_model("rls-arx", na=2, nb=2).step(0.5, 1.0)
    assert len(r.alpha) == 2 and len(r.weights) == 5
    p = build_model("persistence").step(0.5, 1.0)
    assert p.alpha == (0.0,) and p.weights == ()


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_y_hat_is_a_priori(name: str) -> None:
    u = random_steps(300, seed=2)
    y = simulate(u)
    a, b = build_model(name), build_model(name)
    run(a, u, y)
    run(b, u, y)
    before = a.predict(0.3)
    ea = a.step(0.3, 1.0)
    eb = b.step(0.3, -55.0)
    assert ea.y_hat == eb.y_hat == before
    assert ea.alpha == eb.alpha and ea.weights == eb.weights


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_predict_does_not_mutate(name: str) -> None:
    m = build_model(name)
    run(m, random_steps(50, 4), simulate(random_steps(50, 4)))
    snap = m.snapshot()
    for u in (-1.0, 0.0, 2.5, math.nan):
        m.predict(u)
        dynamics = getattr(m, "dynamics", None)
        if dynamics is not None:
            dynamics().simulate_held(u if math.isfinite(u) else 0.0, 5, 0.0)
    assert m.snapshot() == snap


@pytest.mark.parametrize("name", MODEL_NAMES)
@pytest.mark.parametrize(
    ("u", "y"),
    [
        (math.nan, 1.0),
        (0.1, math.nan),
        (math.inf, 1.0),
        (0.1, -math.inf),
        (1e300, 0.0),
        (0.0, 1e300),
    ],
)
def test_non_finite_samples_are_rejected_without_state_change(
    name: str, u: float, y: float
) -> None:
    m = build_model(name)
    run(m, random_steps(100, 6), simulate(random_steps(100, 6)))
    snap = m.snapshot()
    est = m.step(u, y)
    assert est.status == "rejected"
    assert all_finite(est)
    assert est.error == 0.0
    after = m.snapshot()
    assert after.pop("n_rejected") == snap.pop("n_rejected") + 1
    assert after == snap


@pytest.mark.parametrize("name", ["paper", "dynamic", "rls-arx"])
def test_divergence_guard_on_wild_output(name: str) -> None:
    m = build_model(name)
    u = random_steps(400, 8)
    y = simulate(u)
    assert all(e.status == "ok" for e in run(m, u, y)[5:])
    wild = [1e8 * (-1.0) ** k for k in range(60)]
    ests = [m.step(0.5, w) for w in wild]
    assert any(e.status == "diverged" for e in ests)
    assert all(all_finite(e) for e in ests)
    assert m.snapshot()["monitor"]["n_divergences"] >= 1
    assert all(math.isfinite(v) for v in m.snapshot()["theta"])
    # And it recovers once the data is sane again.
    back = [m.step(ui, yi) for ui, yi in zip(u[:200], y[:200], strict=True)]
    assert all(all_finite(e) for e in back)


def test_divergence_guard_on_error_ratio() -> None:
    # Parameters stay small (tiny μ) but the error is persistently ≫ the output scale.
    m = build_model("paper", mu=1e-9, guard={"divergence_steps": 5})
    for k in range(100):
        m.step(0.1, 0.01 * (-1) ** k)
    statuses = [m.step(0.1, 100.0 * (-1) ** k).status for k in range(12)]
    assert statuses[:4] == ["ok"] * 4
    assert statuses[4] == "diverged"


def test_freeze_mode_stops_adaptation_until_unfrozen() -> None:
    m = build_model("dynamic", guard={"on_divergence": "freeze", "param_limit": 50.0})
    u = random_steps(200, 9)
    run(m, u, simulate(u))
    ests = [m.step(0.5, 1e6) for _ in range(3)]
    assert ests[0].status == "diverged"
    assert [e.status for e in ests[1:]] == ["frozen", "frozen"]
    assert m.frozen
    theta = m.snapshot()["theta"]
    m.step(0.2, 0.0)
    assert m.snapshot()["theta"] == theta
    m.unfreeze()
    # a modest error (the last output was 1e6) adapts again once unfrozen
    assert m.step(0.2, 1e6 + 0.5).status == "ok"
    assert m.snapshot()["theta"] != theta


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_garbage_never_yields_nan(name: str) -> None:
    rng = np.random.default_rng(13)
    specials = [math.nan, math.inf, -math.inf, 1e308, -1e12, 0.0]
    m = build_model(name)
    for _ in range(2000):
        u = float(rng.normal()) if rng.random() > 0.05 else specials[int(rng.integers(6))]
        y = float(rng.normal(0, 10)) if rng.random() > 0.05 else specials[int(rng.integers(6))]
        est = m.step(u, y)
        assert all_finite(est)
        assert math.isfinite(m.predict(u))
        dynamics = getattr(m, "dynamics", None)
        if dynamics is not None:
            assert all(map(math.isfinite, dynamics().simulate_held(0.3, 5, 0.0)))


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_determinism_and_config_round_trip(name: str) -> None:
    u = random_steps(500, 10)
    y = simulate(u)
    a = build_model(name)
    b = build_model(name)
    cfg = json.loads(json.dumps(a.config()))  # must survive a JSON log
    c = from_config(cfg)
    assert c.config() == a.config()
    ra, rb, rc = run(a, u, y), run(b, u, y), run(c, u, y)
    assert ra == rb == rc  # dataclass equality: bit-for-bit floats


def test_config_round_trip_with_custom_options() -> None:
    u = random_steps(300, 12)
    y = simulate(u)
    for name, opts in [
        ("dynamic", {"na": 2, "nb": 4, "lam": 0.99, "u_scale": 1.5, "p0": 10.0, "seed": 42}),
        ("paper", {"degree": 2, "beta": 0.4, "centres": [-1.0, 0.0, 1.0], "seed": 5}),
        ("rls-arx", {"na": 1, "nb": 2, "lam": 0.98, "p0": 10.0, "trace_max": 50.0}),
        ("persistence", {"guard": {"output_limit": 10.0}}),
    ]:
        m = build_model(name, **opts)
        twin = from_config(json.loads(json.dumps(m.config())))
        assert run(m, u, y) == run(twin, u, y)


def test_seed_changes_initial_parameters() -> None:
    u = random_steps(100, 14)
    y = simulate(u)
    same = [run(paper_preset(seed=s), u, y) for s in (1, 1)]
    assert same[0] == same[1]
    other = run(paper_preset(seed=2), u, y)
    assert [e.y_hat for e in other] != [e.y_hat for e in same[0]]


def test_reset_restores_initial_state() -> None:
    m = build_model("dynamic", seed=4)
    fresh = m.snapshot()
    u = random_steps(100, 15)
    run(m, u, simulate(u))
    assert m.snapshot() != fresh
    m.reset()
    assert m.snapshot() == fresh


def test_dynamic_beats_persistence_on_linear_plant() -> None:
    u = random_steps(4000, seed=3)
    y = np.array(simulate(u))
    burn = 1000
    errs = {}
    for name in ("persistence", "dynamic", "rls-arx"):
        ests = run(build_model(name), u, y.tolist())
        assert all(e.status == "ok" for e in ests[burn:])
        errs[name] = nmse(np.array([e.error for e in ests])[burn:], y[burn:])
    assert errs["persistence"] > 0.02
    assert errs["dynamic"] < 0.05 * errs["persistence"]
    assert errs["rls-arx"] < 0.05 * errs["persistence"]


def test_paper_model_learns_static_map_with_causal_ordering() -> None:
    """The paper model explains y(t) by u(t−1): aligned data fits, misaligned does not."""
    rng = np.random.default_rng(21)
    n, burn = 3000, 1500
    u = rng.uniform(-1.8, 1.8, n).tolist()

    def g(x: float) -> float:
        return 0.3 + 0.8 * x - 0.15 * x**3

    y = [g(u[t - 1]) if t else g(0.0) for t in range(n)]
    aligned = run(paper_preset(seed=0), u, y)
    e_al = np.array([e.error for e in aligned])[burn:]
    y_arr = np.array(y)[burn:]
    assert nmse(e_al, y_arr) < 0.02
    # Feeding u(t−2) in place of u(t−1) breaks the causal ordering the model relies on.
    shifted = [0.0, *u[:-1]]
    misaligned = run(paper_preset(seed=0), shifted, y)
    e_mis = np.array([e.error for e in misaligned])[burn:]
    assert nmse(e_mis, y_arr) > 0.5
    # Controller's view: the model's input map approximates g on the excited range.
    model = paper_preset(seed=0)
    run(model, u, y)
    for x in (-1.5, -0.5, 0.0, 0.6, 1.4):
        assert model.predict(x) == pytest.approx(g(x), abs=0.1)


def test_rls_constant_input_stays_bounded() -> None:
    m = build_model("rls-arx", lam=0.98)
    y1 = 0.0
    u = 1.0
    for _ in range(10_000):
        y = 0.9 * y1 + 0.1 * u
        est = m.step(u, y)
        assert all_finite(est)
        y1 = y
    snap = m.snapshot()
    p = np.array(snap["p"])
    assert np.all(np.isfinite(p)) and np.trace(p) <= m.rls.trace_max / m.rls.lam + 1e-6
    assert max(abs(t) for t in snap["theta"]) < 1e3
    assert abs(est.error) < 1e-6
    assert m.snapshot()["monitor"]["n_divergences"] == 0
    # Excitation returns with a different plant: the estimator tracks it again.
    rng = np.random.default_rng(0)
    u_prev = u
    errs = []
    for _ in range(600):
        y = 0.5 * y1 + 0.4 * u_prev
        errs.append(m.step(u_prev, y).error)
        y1 = y
        u_prev = float(rng.uniform(-2, 2))
    assert max(abs(e) for e in errs[-100:]) < 1e-3


def test_dynamic_model_holds_over_the_horizon() -> None:
    """Identified on a noise-free second-order plant with a cubic input map, the frozen
    model's free run (simulation, no measured output fed back) fits new data at > 99 %."""
    rng = np.random.default_rng(8)

    def plant(u: list[float]) -> list[float]:
        y = [3.0, 3.0]  # an output level far from 0, as the depth channel's
        for t in range(2, len(u)):
            f1, f2 = u[t - 1] + 0.2 * u[t - 1] ** 3, u[t - 2] + 0.2 * u[t - 2] ** 3
            y.append(3.0 * 0.03 + 1.5 * y[t - 1] - 0.53 * y[t - 2] + 0.1 * f1 + 0.05 * f2)
        return y

    u = np.repeat(rng.uniform(-2, 2, 200), 20).tolist()
    y = plant(u)
    model = DynamicUModel()
    for t in range(1, 2000):
        model.step(u[t - 1], y[t])
    free = model.dynamics()
    sim = [free.advance(u[t - 1]) for t in range(2000, 4000)]
    ref = np.array(y[2000:4000])
    fit = 100 * (1 - np.linalg.norm(ref - sim) / np.linalg.norm(ref - ref.mean()))
    assert fit > 99.0


def test_rbf_values_list_memo_returns_fresh_equal_lists() -> None:
    model = build_model("paper", seed=1)
    rbf = model.rbf  # type: ignore[attr-defined]
    first = rbf.values_list(0.3)
    first.append(99.0)  # the caller owns the list: the memo must not see this
    again = rbf.values_list(0.3)
    assert again == rbf.values(0.3).tolist() or again == pytest.approx(rbf.values(0.3))
    assert len(again) == 17
    assert rbf.values_list(-1.1) == pytest.approx(rbf.values(-1.1), rel=1e-15)


def test_an_update_undone_restores_theta_and_the_covariance_exactly_once() -> None:
    from hil_service.umodel.models import DynamicUModel

    model = DynamicUModel()
    for k in range(40):
        model.step(0.5 * ((k // 7) % 3 - 1), 15.0 + 0.01 * k)
    theta = list(model._theta)
    covariance = model.rls.covariance()
    model.step(0.7, 15.5)
    assert model._theta != theta
    assert model.undo_last_update()
    assert model._theta == theta and model.rls.covariance() == covariance
    assert not model.undo_last_update()  # one sample only
    model.step(0.7, 15.5)
    model.step(0.7, 1e6)  # outgrows the output scale: no undo across the rescale
    assert not model.undo_last_update()
