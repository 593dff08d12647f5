"""The yardsticks of the controller: the free-run fit and k-step NMSE, the known-model oracle, and
the random plant families. Short runs on fixed seeds."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hil_service.cli import main
from hil_service.experiment.closed_loop import (
    GLIDER_ORACLE,
    ClosedLoopSettings,
    _drive,
    known_plant,
    oracle_run,
    score,
    setpoint_schedule,
)
from hil_service.experiment.oracle import (
    SMALL_MATRIX_VALUE,
    KnownPlant,
    OracleController,
    OracleSettings,
    _quiet_highs,
)
from hil_service.experiment.random_loop import channel_levels, oracle_settings_for
from hil_service.umodel import build_model
from hil_service.umodel.multistep import (
    fit_percent,
    free_run,
    multistep_scores,
    nmse,
    train,
)
from plant_emulator.actuator import BallastActuator, PumpNonlinearity
from plant_emulator.models import DEFAULT_DESIGNS
from plant_emulator.plant import GliderPlant, PlantConfig
from plant_emulator.random_plants import (
    CUBIC_RANGE,
    DC_GAIN_RANGE,
    DEAD_ZONE_RANGE,
    INPUT_LIMIT,
    NMP_ZERO_RANGE,
    PERIODS,
    PITCH_FULL_SCALE,
    POLE_RANGE,
    RandomVehicle,
    RandomVehicleConfig,
    draw_family,
)

# ---- fit and k-step NMSE -----------------------------------------------------------------


def test_fit_is_100_for_a_perfect_model_and_0_for_the_mean():
    y = np.sin(np.arange(200) / 7.0) + 3.0
    assert fit_percent(y, y) == pytest.approx(100.0)
    assert fit_percent(y, np.full_like(y, y.mean())) == pytest.approx(0.0, abs=1e-12)
    # Twice the mean's error norm: −100 %.
    assert fit_percent(y, y.mean() + 3.0 * (y - y.mean())) == pytest.approx(-100.0)
    assert nmse(y, y) == 0.0 and nmse(y, np.full_like(y, y.mean())) == pytest.approx(1.0)


def test_fit_refuses_what_it_cannot_score():
    assert fit_percent([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]) is None  # constant y
    assert fit_percent([1.0, 2.0], [1.0, math.nan]) is None
    assert nmse([1.0], [1.0]) is None
    with pytest.raises(ValueError, match="shape"):
        fit_percent([1.0, 2.0], [1.0])


def _arx_data(n: int = 1200, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """y(t) = 0.9·y(t−1) + 0.5·u(t−1): the sample convention of the plant (u applied at t)."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-2.0, 2.0, n // 10 + 1), 10)[:n]
    y = np.zeros(n)
    for k in range(1, n):
        y[k] = 0.9 * y[k - 1] + 0.5 * u[k - 1]
    return u, y


def test_an_exact_model_class_simulates_the_validation_data():
    u, y = _arx_data()
    scores = multistep_scores(lambda: build_model("rls-arx"), u, y, split=600, horizon=20)
    assert scores.fit is not None and scores.fit > 99.0
    assert scores.k_step_nmse is not None and scores.k_step_nmse < 1e-3
    assert scores.windows >= 100  # starts every max(1, 20 // 5) = 4 samples


def test_persistence_free_run_is_a_constant_and_scores_below_zero():
    u, y = _arx_data()
    model = train(lambda: build_model("persistence"), np.concatenate((u[:1], u[:-1])), y, 600)
    sim = free_run(model, u, 600, y.size)
    assert np.all(sim == y[599])  # it repeats the last output it learnt from
    scores = multistep_scores(lambda: build_model("persistence"), u, y, split=600, horizon=5)
    assert scores.fit is not None and scores.fit < 0.0
    assert scores.k_step_nmse is not None and scores.k_step_nmse > 0.1


def test_multistep_scores_are_deterministic_and_leave_no_learning_after_the_split():
    u, y = _arx_data()
    a = multistep_scores(lambda: build_model("dynamic", seed=1), u, y, split=600, horizon=10)
    b = multistep_scores(lambda: build_model("dynamic", seed=1), u, y, split=600, horizon=10)
    assert a == b
    # The validation outputs after the split do not change the fit's model: scrambling
    # the outputs the free run is compared with changes the fit, not the simulation.
    y2 = y.copy()
    y2[700:] += 1.0
    c = multistep_scores(lambda: build_model("dynamic", seed=1), u, y2, split=600, horizon=10)
    assert c.fit != a.fit


# ---- the oracle --------------------------------------------------------------------------


def _second_order() -> tuple[RandomVehicle, KnownPlant]:
    family = draw_family(seed=0, plants=2)
    spec = family[0][0]
    vehicle = RandomVehicle(RandomVehicleConfig(depth=spec, pitch=family[0][1]))
    return vehicle, known_plant(vehicle, "depth", 15.0)


def test_oracle_tracks_a_step_within_the_actuator_limits():
    loop_plant = KnownPlant(
        a=np.array([[1.7, -0.72], [1.0, 0.0]]),  # poles 0.8 and 0.9
        b=np.array([1.0, 0.0]),
        c=np.array([0.0, 0.02]),  # DC gain 0.02 / (1 − 1.7 + 0.72) = 1
        u_limit=2.0,
        rate_limit=0.5,
    )
    oracle = OracleController(loop_plant, OracleSettings(horizon=80, blocks=(1, 1, 2, 4, 8, 16)))
    actuator = BallastActuator(limit=2.0, rate_limit=0.5)
    x = np.zeros(2)
    ys, us = [], []
    command = 0.0
    for _ in range(120):
        actuator.apply(command)
        u = actuator.position
        y = float(loop_plant.c @ x)
        x = loop_plant.a @ x + loop_plant.b * u
        oracle.observe(y, u)
        command = oracle.command(1.5, u)
        ys.append(y)
        us.append(command)
    commands = np.array(us)
    assert np.all(np.abs(commands) <= 2.0 + 1e-9)
    assert np.all(np.abs(np.diff(commands)) <= 0.5 + 1e-6)
    assert abs(commands[0]) <= 0.5 + 1e-6  # first move from rest
    assert np.max(np.abs(commands)) > 1.5 + 0.1  # it uses the room above the static input
    assert abs(ys[-1] - 1.5) < 1e-3
    # Faster than the static input 1.5 applied at once (reference only).
    ref_x, ref_iae = np.zeros(2), 0.0
    ref = BallastActuator(limit=2.0, rate_limit=0.5)
    for _ in range(120):
        ref.apply(1.5)
        ref_iae += abs(float(loop_plant.c @ ref_x) - 1.5)
        ref_x = loop_plant.a @ ref_x + loop_plant.b * ref.position
    assert sum(abs(y - 1.5) for y in ys) < 0.8 * ref_iae
    assert oracle.failures == 0


def test_an_lp_with_entries_highs_would_drop_is_built_and_tracks():
    """A fast plant over a long horizon: its step response falls below HiGHS's
    ``small_matrix_value`` (0.332¹⁹ ≈ 8·10⁻¹⁰), which HiGHS answers with a warning; the
    oracle drops those entries itself and builds (as for family seed 41's vehicle 21
    depth)."""
    assert _quiet_highs().getOptionValue("small_matrix_value")[1] == SMALL_MATRIX_VALUE
    fast = KnownPlant(
        a=np.array([[0.332]]), b=np.array([1.0]), c=np.array([0.3417]), u_limit=2.0,
        rate_limit=0.5,
    )  # fmt: skip
    oracle = OracleController(fast, OracleSettings(horizon=20, blocks=(1, 1, 2, 4)))
    x, y, command = np.zeros(1), 0.0, 0.0
    actuator = BallastActuator(limit=2.0, rate_limit=0.5)
    for _ in range(60):
        actuator.apply(command)
        y = float(fast.c @ x)
        x = fast.a @ x + fast.b * actuator.position
        oracle.observe(y, actuator.position)
        command = oracle.command(0.3, actuator.position)
    assert abs(y - 0.3) < 1e-6
    assert oracle.failures == 0


def test_oracle_inverts_the_pump_map():
    plant = KnownPlant(
        a=np.array([[0.5]]),
        b=np.array([1.0]),
        c=np.array([0.5]),
        pump=PumpNonlinearity(dead_zone=0.2, cubic=0.1),
    )
    for u in (-1.7, -0.5, 0.3, 1.9):
        assert plant.invert_pump(plant.pump(u), 0.0) == pytest.approx(u, abs=1e-9)
    assert plant.invert_pump(1e9, 0.0) == 2.0
    # A dead zone without a cubic term gives 0 on all of it: the position nearest the
    # current one is kept.
    flat = KnownPlant(
        a=np.array([[0.5]]),
        b=np.array([1.0]),
        c=np.array([0.5]),
        pump=PumpNonlinearity(dead_zone=0.2, cubic=0.0),
    )
    assert flat.invert_pump(0.0, 0.1) == pytest.approx(0.1, abs=1e-9)
    assert flat.invert_pump(0.0, 0.5) == pytest.approx(0.2, abs=1e-9)


@pytest.mark.parametrize("scenario", ["disturbed", "nonlinear"])
def test_the_warm_started_lp_finds_the_optimum_linprog_finds_from_scratch(scenario):
    """Each sample's LP, solved on the persistent model from the last basis, has the optimal
    cost that ``scipy.optimize.linprog`` (HiGHS from scratch) finds for the same LP."""
    from scipy.optimize import linprog

    settings = ClosedLoopSettings(scenario, samples=1300, identify=1000, step_every=150)
    config = PlantConfig(scenario=scenario, seed=1)
    plant = GliderPlant(config)
    controller = OracleController(
        known_plant(plant, "depth", config.trim_depth), GLIDER_ORACLE["depth"]
    )
    nb = controller._nb
    solve = controller._lp.solve
    checked = []

    def checking(row_lower, row_upper, col_index, lower, upper):
        x = solve(row_lower, row_upper, col_index, lower, upper)
        cols = controller._cost.size
        bounds = [(float(lo), float(hi)) for lo, hi in zip(lower, upper, strict=True)]
        bounds += [(0.0, None)] * (cols - nb)
        # The same LP in linprog's A_ub x ≤ b_ub form: each finite row bound a row.
        a = controller._a
        has_upper, has_lower = np.isfinite(row_upper), np.isfinite(row_lower)
        reference = linprog(
            controller._cost,
            A_ub=np.vstack((a[has_upper], -a[has_lower])),
            b_ub=np.concatenate((row_upper[has_upper], -row_lower[has_lower])),
            bounds=bounds, method="highs",
            options={"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10},
        )  # fmt: skip
        assert reference.status == 0 and x is not None
        assert float(controller._cost @ x) == pytest.approx(reference.fun, rel=1e-6, abs=1e-6)
        assert np.all(a @ x <= row_upper + 1e-7) and np.all(a @ x >= row_lower - 1e-7)
        checked.append(reference.fun)
        return x

    controller._lp.solve = checking  # type: ignore[method-assign]
    schedule = setpoint_schedule(settings)
    command = 0.0
    for k in range(settings.samples):
        sample = plant.step(command if k >= settings.identify else 0.0, 0.0)
        controller.observe(sample.depth, sample.u_depth)
        if k >= settings.identify:
            command = controller.command(float(schedule["depth"][k]), sample.u_depth)
    assert len(checked) > 100 and controller.failures == 0
    assert max(checked) > 1.0  # setpoint steps: LPs with a real error to remove
    # Many of these answers (about half, on this run of steps) came from the last
    # optimum's basis, without a HiGHS run.
    assert controller._lp.reused > len(checked) // 4


def test_with_a_move_weight_the_lp_has_the_optimum_of_the_slack_form():
    """Sample after sample of a noisy loop, the oracle's LP with a move weight (the error's
    parts on equality rows, the move rows about v(k)) reaches the optimal cost of the LP
    written independently in the slack form: min Σ w·t + μ Σ m, t ≥ ±(F V − gap),
    m_b ≥ ±(V_b − V_{b−1}), |V_b − V_{b−1}| ≤ rate, V_{−1} = v(k)."""
    from scipy.optimize import linprog

    plant = KnownPlant(
        a=np.array([[0.9, 0.1], [0.0, 0.8]]), b=np.array([0.0, 0.5]), c=np.array([1.0, 0.0])
    )
    settings = OracleSettings(
        horizon=30, blocks=(1, 1, 2, 4, 8), move_weight=0.05, disturbance_tau=1.0
    )
    controller = OracleController(plant, settings)
    solve, nb, nt = controller._lp.solve, controller._nb, controller._nt
    forced, weights = controller._forced, controller._cost[nb : nb + nt]
    diff = np.eye(nb) - np.eye(nb, k=-1)
    zeros_t, zeros_b, eye_t, eye_b = np.zeros((nt, nb)), np.zeros((nb, nt)), np.eye(nt), np.eye(nb)
    a_ub = np.vstack((
        np.hstack((forced, -eye_t, zeros_t)), np.hstack((-forced, -eye_t, zeros_t)),
        np.hstack((diff, zeros_b, -eye_b)), np.hstack((-diff, zeros_b, -eye_b)),
        np.hstack((diff, zeros_b, 0 * eye_b)), np.hstack((-diff, zeros_b, 0 * eye_b)),
    ))  # fmt: skip
    cost = np.concatenate((np.zeros(nb), weights, np.full(nb, settings.move_weight)))
    gaps = []

    def checking(row_lower, row_upper, col_index, lower, upper):
        x = solve(row_lower, row_upper, col_index, lower, upper)
        assert x is not None
        gap = row_lower[:nt]
        v_now = 0.5 * (row_lower[nt] + row_upper[nt])
        rate = 0.5 * (row_upper[nt] - row_lower[nt])
        first = np.zeros(nb)
        first[0] = v_now
        rate_rows = np.full(nb, rate)
        rate_rows[0] += v_now
        falling = np.full(nb, rate)
        falling[0] -= v_now
        b_ub = np.concatenate((gap, -gap, first, -first, rate_rows, falling))
        bounds = [(float(lo), float(hi)) for lo, hi in zip(lower, upper, strict=True)]
        reference = linprog(
            cost, A_ub=a_ub, b_ub=b_ub, bounds=bounds + [(0.0, None)] * (nt + nb),
            method="highs",
            options={"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10},
        )  # fmt: skip
        assert reference.status == 0
        moves = np.diff(np.concatenate(([v_now], x[:nb])))
        ours = float(weights @ np.abs(forced @ x[:nb] - gap)) + settings.move_weight * float(
            np.sum(np.abs(moves))
        )
        gaps.append(abs(ours - reference.fun))
        return x

    controller._lp.solve = checking  # type: ignore[method-assign]
    rng = np.random.default_rng(1)
    state, u = np.zeros(2), 0.0
    for k in range(300):
        controller.observe(float(plant.c @ state) + 0.01 * rng.normal(), u)
        u = controller.command(1.0 if (k // 60) % 2 == 0 else -0.5, u)
        state = plant.a @ state + plant.b * u
    assert len(gaps) == 300 and controller.failures == 0
    assert max(gaps) < 1e-6


def _random_lp(seed: int):
    """An L1 fit as the oracle's LP: min Σ t, |F v − g| ≤ t, box bounds on v."""
    rng = np.random.default_rng(seed)
    rows, nv = 30, 6
    forced = rng.normal(size=(rows, nv))
    eye = np.eye(rows)
    a_ub = np.vstack((np.hstack((forced, -eye)), np.hstack((-forced, -eye))))
    cost = np.concatenate((np.zeros(nv), np.ones(rows)))
    lower = np.concatenate((np.full(nv, -1.0), np.zeros(rows)))
    upper = np.full(nv + rows, np.inf)
    return a_ub, cost, lower, upper, forced, nv, rng


def test_the_last_optimums_basis_answers_a_nearby_lp_with_linprogs_optimum():
    """A small change of b keeps the optimal basis feasible: the answer comes without a
    HiGHS run and is the optimum linprog finds from scratch; a large one does not, and
    HiGHS is run. Either way the optimum is the same."""
    from scipy.optimize import linprog

    from hil_service.experiment.oracle import _LpModel

    a_ub, cost, lower, upper, forced, nv, rng = _random_lp(3)
    no_lower = np.full(a_ub.shape[0], -np.inf)
    model = _LpModel(cost, a_ub, no_lower, np.zeros(a_ub.shape[0]), lower, upper)
    blocks = np.arange(nv, dtype=np.int32)
    gap = forced @ rng.uniform(-0.5, 0.5, nv) + 0.1 * rng.normal(size=forced.shape[0])
    answered = []
    for scale in (0.0, 1e-6, 1e-4, 1.0):
        g = gap + scale * rng.normal(size=gap.size)
        b_ub = np.concatenate((g, -g))
        before = model.reused
        x = model.solve(no_lower, b_ub, blocks, np.full(nv, -1.0), np.full(nv, 1.0))
        answered.append(model.reused > before)
        bounds = [(-1.0, 1.0)] * nv + [(0.0, None)] * forced.shape[0]
        reference = linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
        assert x is not None and reference.status == 0
        assert float(cost @ x) == pytest.approx(reference.fun, rel=1e-9, abs=1e-12)
        assert np.all(a_ub @ x <= b_ub + 1e-9)
        assert np.all(np.abs(x[:nv]) <= 1.0 + 1e-12)
    assert answered == [False, True, True, False]


def test_bounds_set_on_a_solve_the_basis_answered_reach_the_solver_later():
    """A column bound changed on a solve the last basis answers (HiGHS not run) still
    holds on a later solve that sets other columns and needs HiGHS."""
    from scipy.optimize import linprog

    from hil_service.experiment.oracle import _LpModel

    a_ub, cost, lower, upper, forced, nv, rng = _random_lp(5)
    no_lower = np.full(a_ub.shape[0], -np.inf)
    model = _LpModel(cost, a_ub, no_lower, np.zeros(a_ub.shape[0]), lower, upper)
    gap = forced @ rng.uniform(-0.5, 0.5, nv)
    b_ub = np.concatenate((gap, -gap))
    blocks = np.arange(nv, dtype=np.int32)
    x = model.solve(no_lower, b_ub, blocks, np.full(nv, -1.0), np.full(nv, 1.0))
    # Column 0's upper bound moved just above its optimum: the same basis answers.
    first = np.array([0], dtype=np.int32)
    reused = model.reused
    x = model.solve(no_lower, b_ub, first, np.array([-1.0]), np.array([x[0] + 1e-3]))
    assert model.reused == reused + 1
    ceiling = float(x[0]) + 1e-3
    # A large change of b, with only column 1's bounds given: HiGHS runs.
    far = forced @ np.full(nv, 0.9)
    b_far = np.concatenate((far, -far))
    x = model.solve(
        no_lower, b_far, np.array([1], dtype=np.int32), np.array([-1.0]), np.array([1.0])
    )
    bounds = [(-1.0, ceiling)] + [(-1.0, 1.0)] * (nv - 1) + [(0.0, None)] * forced.shape[0]
    reference = linprog(cost, A_ub=a_ub, b_ub=b_far, bounds=bounds, method="highs")
    assert x is not None and reference.status == 0
    assert x[0] <= ceiling + 1e-9
    assert float(cost @ x) == pytest.approx(reference.fun, rel=1e-9, abs=1e-12)


def test_a_basis_that_is_not_square_or_is_singular_is_refused():
    from hil_service.experiment.lp_basis import OptimalBasis

    a = np.array([[1.0, 1.0], [2.0, 2.0], [1.0, -1.0]])
    at_upper = np.zeros(2, dtype=bool)
    row_at_upper = np.ones(3, dtype=bool)
    with pytest.raises(ValueError, match="not a basis"):
        OptimalBasis(
            a, np.array([True, True]), at_upper, np.array([True, False, False]), row_at_upper
        )
    with pytest.raises(ValueError, match=r"singular|ill-conditioned"):
        OptimalBasis(
            a, np.array([True, True]), at_upper, np.array([True, True, False]), row_at_upper
        )
    basis = OptimalBasis(
        a, np.array([True, True]), at_upper, np.array([True, False, True]), row_at_upper
    )
    # x = (1, 1) from rows 0 and 2 at their upper bounds (2, 0); row 1 (2x + 2y = 4) must
    # lie within its own bounds.
    lower, upper = np.full(2, -5.0), np.full(2, 5.0)
    no_lower = np.full(3, -np.inf)
    x = basis.primal(no_lower, np.array([2.0, 4.0, 0.0]), lower, upper, 1e-10)
    assert x is not None and np.allclose(x, [1.0, 1.0])
    assert basis.primal(no_lower, np.array([2.0, 3.9, 0.0]), lower, upper, 1e-10) is None
    assert (
        basis.primal(
            np.array([-np.inf, 4.1, -np.inf]), np.array([2.0, 9.0, 0.0]), lower, upper, 1e-10
        )
        is None
    )  # row 1 below its lower bound
    assert basis.primal(no_lower, np.array([2.0, 4.0, 0.0]), lower, np.full(2, 0.5), 1e-10) is None
    assert basis.primal(no_lower, np.array([np.nan, 4.0, 0.0]), lower, upper, 1e-10) is None
    # A singleton column whose one entry is tiny beside the rest: refused, not divided by.
    tiny = np.array([[1e-15, 1.0], [0.0, 1.0]])
    with pytest.raises(ValueError, match="ill-conditioned"):
        OptimalBasis(
            tiny, np.array([True, True]), at_upper, np.array([True, True]), row_at_upper[:2]
        )


def test_an_active_row_takes_the_bound_it_sits_at():
    """A ranged row active at its lower bound gives the basis its lower bound's value, an
    equality row its one value: the primal values follow the bound each active row is at."""
    from hil_service.experiment.lp_basis import from_basic_variables

    # Rows: x + y ∈ [1, 3] (active at 1), x − y = 0.2 (an equality); both columns basic.
    a = np.array([[1.0, 1.0], [1.0, -1.0]])
    lower, upper = np.full(2, -5.0), np.full(2, 5.0)
    x_opt = np.array([0.6, 0.4])
    basis = from_basic_variables(
        a, np.array([0, 1], dtype=np.int32), x_opt, lower, upper,
        np.array([1.0, 0.2]), np.array([3.0, 0.2]),
    )  # fmt: skip
    x = basis.primal(np.array([1.5, -0.1]), np.array([3.0, -0.1]), lower, upper, 1e-10)
    assert x is not None and np.allclose(x, [0.7, 0.8])


def test_a_reset_oracle_commands_as_a_fresh_one():
    plant = KnownPlant(
        a=np.array([[1.7, -0.72], [1.0, 0.0]]), b=np.array([1.0, 0.0]), c=np.array([0.0, 0.02])
    )
    settings = OracleSettings(horizon=60, blocks=(1, 1, 2, 4, 8))

    def run(oracle):
        x, u, commands = np.zeros(2), 0.0, []
        for k in range(40):
            y = float(plant.c @ x)
            x = plant.a @ x + plant.b * u
            oracle.observe(y, u)
            u = oracle.command(1.0 if k < 20 else -0.5, u)
            commands.append(u)
        return commands

    used = OracleController(plant, settings)
    run(used)
    used.reset()
    assert run(used) == run(OracleController(plant, settings))


def test_oracle_refuses_an_unstable_model():
    with pytest.raises(ValueError, match="stable"):
        KnownPlant(a=np.array([[1.01]]), b=np.array([1.0]), c=np.array([1.0]))


@pytest.mark.parametrize("scenario", ["paper", "disturbed"])
def test_oracle_beats_reference_only_on_the_glider(scenario):
    settings = ClosedLoopSettings(scenario, samples=1800, identify=1000, step_every=400)
    config = PlantConfig(scenario=scenario, seed=0)
    schedule = setpoint_schedule(settings)
    trims = {"depth": config.trim_depth, "pitch": 0.0}
    oracle, failures = oracle_run(settings, GliderPlant(config), schedule, GLIDER_ORACLE, trims)

    def reference_only(k, sample):
        return (
            (schedule["depth"][k] - config.trim_depth) / DEFAULT_DESIGNS["depth"].dc_gain,
            schedule["pitch"][k] / DEFAULT_DESIGNS["pitch"].dc_gain,
        )

    reference = _drive(settings, GliderPlant(config), schedule, reference_only)
    for run in (oracle, reference):
        score(run, settings, config.period)
    assert failures == 0
    ratios = {}
    for ch in ("depth", "pitch"):
        u = oracle.u[ch][settings.identify :]
        assert np.all(np.abs(u) <= 2.0 + 1e-9) and np.all(np.abs(np.diff(u)) <= 0.5 + 1e-9)
        ratios[ch] = oracle.metrics[ch].iae / reference.metrics[ch].iae
    # Measured on these two 400-sample steps (oracle / reference-only IAE): paper depth
    # 0.82, pitch 0.92; disturbed depth 0.91. Over 20,000 samples paper depth is 0.65 and
    # pitch 0.88: short steps leave the reference-only loop little time to be slow.
    assert max(ratios.values()) < 0.96, ratios


def _one_channel_oracle(scenario, channel, oracle_settings, settings):
    """One glider channel driven by the oracle (the other channel held at 0): the trace of
    outputs, applied inputs and setpoints, and the controller."""
    config = PlantConfig(scenario=scenario, seed=0)
    plant = GliderPlant(config)
    trim = config.trim_depth if channel == "depth" else 0.0
    controller = OracleController(known_plant(plant, channel, trim), oracle_settings)
    schedule = setpoint_schedule(settings)[channel]
    y, u = np.empty(settings.samples), np.empty(settings.samples)
    command = 0.0
    for k in range(settings.samples):
        sample = plant.step(*((command, 0.0) if channel == "depth" else (0.0, command)))
        y[k], u[k] = sample.output(channel), sample.input(channel)
        controller.observe(y[k], u[k])
        if k >= settings.identify:
            command = controller.command(float(schedule[k]), u[k])
    return y, u, schedule, controller


@pytest.mark.parametrize("channel", ["depth", "pitch"])
def test_glider_oracle_realises_the_full_resolution_optimum_of_each_step(channel):
    """On ``paper`` (exact model, no disturbance) the best any controller without preview can
    do after a setpoint step is the optimum of one long LP with a free input on every sample
    (its plan held fixed, since nothing unforeseen happens). GLIDER_ORACLE's receding-horizon
    run must realise that optimum: with blocks of 4 samples and the error costed every 4th
    sample (depth, before) it realised 0.04 % more; with a settled tolerance of 1e-7 (pitch,
    before) 0.05 % more."""
    settings = ClosedLoopSettings("paper", samples=1400, identify=1000, step_every=400)
    y, u, schedule, _ = _one_channel_oracle("paper", channel, GLIDER_ORACLE[channel], settings)
    # The reference: a fresh controller that knows the same model, replayed on the run up to
    # the step, then asked once for its plan: single-sample moves far beyond settling.
    config = PlantConfig(scenario="paper", seed=0)
    trim = config.trim_depth if channel == "depth" else 0.0
    fine = (
        OracleSettings(horizon=1000, blocks=(1,) * 250 + (750,), disturbance_tau=1.0)
        if channel == "depth"
        else OracleSettings(horizon=150, blocks=(1,) * 120 + (30,), disturbance_tau=1.0)
    )
    reference = OracleController(known_plant(GliderPlant(config), channel, trim), fine)
    s = settings.identify
    for k in range(s + 1):
        reference.observe(y[k], u[k])
    reference.command(float(schedule[s]), u[s])
    optimum = reference._lp.highs.getInfo().objective_function_value
    realised = float(np.sum(np.abs(y[s + 2 :] - schedule[s + 2 :])))
    assert optimum > (100.0 if channel == "depth" else 0.05)  # a real step to take
    assert realised == pytest.approx(optimum, rel=2e-6), (realised, optimum)
    # Settled before the run ends, so the realised sum is the whole step's.
    assert abs(y[-1] - schedule[-1]) < 1e-9


def test_the_error_is_costed_on_every_sample_before_stride_from():
    plant = KnownPlant(a=np.array([[0.6]]), b=np.array([0.4]), c=np.array([1.0]))
    dense = OracleController(plant, OracleSettings(horizon=20, blocks=(1,) * 4 + (8,),
                                                   cost_stride=4, stride_from=6))  # fmt: skip
    assert list(dense._ahead - 1) == [1, 2, 3, 4, 5, 6, 10, 14, 18]
    # Each costed sample's weight, on its error's positive and its negative part.
    weights = [1.0] * 5 + [4.0] * 4
    assert list(dense._cost[dense._nb :]) == weights + weights
    plain = OracleController(plant, OracleSettings(horizon=20, blocks=(1,) * 4 + (8,),
                                                   cost_stride=4))  # fmt: skip
    assert list(plain._ahead - 1) == [1, 5, 9, 13, 17]
    with pytest.raises(ValueError, match="stride_from"):
        OracleSettings(stride_from=-1)


def test_a_trend_in_the_disturbance_estimate_anticipates_a_ramp():
    """A current that ramps: held constant, d̂ lags the ramp by the loop's delay at every
    sample; extrapolated along its low-passed slope, the plan meets it."""
    plant = KnownPlant(a=np.array([[0.6]]), b=np.array([0.4]), c=np.array([1.0]))
    errors = {}
    for trend in (0.0, 30.0):
        settings = OracleSettings(horizon=20, blocks=(1,) * 10 + (10,), disturbance_tau=1.0,
                                  disturbance_trend=trend)  # fmt: skip
        oracle = OracleController(plant, settings)
        x, u, total = np.zeros(1), 0.0, 0.0
        for k in range(400):
            y = float(plant.c @ x) + 0.002 * k  # the ramp, 0.8 by the end (inside the limits)
            if k >= 200:
                total += abs(y)
            oracle.observe(y, u)
            x = plant.a @ x + plant.b * u
            u = oracle.command(0.0, u)
        errors[trend] = total
    assert errors[30.0] < 0.05 * errors[0.0], errors


def test_the_glider_pitch_oracle_gains_from_the_trend_on_disturbed():
    """Seed 0, disturbed, pitch alone: the slope term makes the yardstick better (on 20,000
    samples 26.85 against 27.31 without it)."""
    settings = ClosedLoopSettings("disturbed", samples=2600, identify=1000, step_every=400)
    iae = {}
    for trend in (0.0, GLIDER_ORACLE["pitch"].disturbance_trend):
        chosen = replace(GLIDER_ORACLE["pitch"], disturbance_trend=trend)
        y, _, schedule, oracle = _one_channel_oracle("disturbed", "pitch", chosen, settings)
        assert oracle.failures == 0
        iae[trend] = float(np.sum(np.abs(y[settings.identify :] - schedule[settings.identify :])))
    assert GLIDER_ORACLE["pitch"].disturbance_trend > 0
    assert iae[GLIDER_ORACLE["pitch"].disturbance_trend] < 0.99 * iae[0.0], iae


# ---- random plants -----------------------------------------------------------------------


def test_random_families_are_seeded_and_within_the_stated_ranges():
    family = draw_family(seed=5, plants=40)
    assert family == draw_family(seed=5, plants=40)
    assert family != draw_family(seed=6, plants=40)
    specs = [spec for pair in family for spec in pair]
    assert len(specs) == 40
    for spec in specs:
        assert spec.order in (2, 3)
        moduli = spec.pole_moduli()
        assert all(POLE_RANGE[0] <= m <= POLE_RANGE[1] for m in moduli)
        model = spec.channel_model("depth")
        assert model.spectral_radius() < 1.0
        assert model.dc_gain() == pytest.approx(spec.dc_gain, rel=1e-9)
        assert DC_GAIN_RANGE[0] <= spec.drawn_gain <= DC_GAIN_RANGE[1]
        assert spec.period in PERIODS
        if spec.zero is not None:
            assert NMP_ZERO_RANGE[0] <= spec.zero <= NMP_ZERO_RANGE[1]
            assert np.polyval(np.trim_zeros(spec.num(), "f"), spec.zero) == pytest.approx(0.0)
        assert spec.dead_zone == 0.0 or DEAD_ZONE_RANGE[0] <= spec.dead_zone <= DEAD_ZONE_RANGE[1]
        assert spec.cubic == 0.0 or CUBIC_RANGE[0] <= spec.cubic <= CUBIC_RANGE[1]
    # Every optional feature appears in a family of 40, and so do both orders.
    assert {s.order for s in specs} == {2, 3}
    assert any(s.zero is not None for s in specs) and any(s.zero is None for s in specs)
    assert any(s.dead_zone for s in specs) and any(s.cubic for s in specs)
    assert any(any(im != 0.0 for _, im in s.poles) for s in specs)
    assert len({s.period for s in specs}) > 1
    for depth, pitch in family:
        assert depth.period == pitch.period
        assert depth.unit == 1.0 and depth.dc_gain == depth.drawn_gain  # m per unit input
        assert pitch.unit < 0.1  # rad per unit of drawn gain: a scaled actuator


def test_random_pitch_plants_pitch_as_a_vehicle_could():
    """The strongest pitch plant holds PITCH_FULL_SCALE at full actuator, the others less, and
    bang-bang inputs (rate-limited square waves, resonances included) stay far inside the
    service's plausible ±π: the family's draws other than the pitch gain are unchanged."""
    steady, peaks = [], []
    for seed in range(40):
        depth, pitch = draw_family(seed, 1)[0]
        pump = pitch.pump()
        full = pump(INPUT_LIMIT) if pump else INPUT_LIMIT
        steady.append(pitch.dc_gain * full)
        assert steady[-1] == pytest.approx(
            PITCH_FULL_SCALE * pitch.drawn_gain / DC_GAIN_RANGE[1], rel=1e-12
        )
        for half in (5, 40, 300):
            vehicle = RandomVehicle(RandomVehicleConfig(depth=depth, pitch=pitch))
            outputs = [
                vehicle.step(0.0, INPUT_LIMIT if (k // half) % 2 == 0 else -INPUT_LIMIT).pitch
                for k in range(900)
            ]
            peaks.append(max(abs(y) for y in outputs))
    assert max(steady) <= PITCH_FULL_SCALE
    assert max(steady) / min(steady) > 10  # the family's gain spread is kept
    assert max(peaks) < math.pi / 2, max(peaks)


def test_a_random_vehicle_steps_like_the_glider_and_stays_bounded():
    family = draw_family(seed=1, plants=6)
    for depth, pitch in family:
        vehicle = RandomVehicle(RandomVehicleConfig(depth=depth, pitch=pitch))
        samples = [vehicle.step(2.0, -2.0) for _ in range(3000)]
        assert samples[1].time_boot_ms == round(depth.period * 1000)
        assert samples[-1].u_depth == 2.0 and samples[-1].u_pitch == -2.0  # rate-limited there
        for ch, spec, u in (("depth", depth, 2.0), ("pitch", pitch, -2.0)):
            pump = spec.pump()
            steady = spec.dc_gain * (pump(u) if pump else u) + (15.0 if ch == "depth" else 0.0)
            assert samples[-1].output(ch) == pytest.approx(steady, rel=1e-3, abs=1e-6)


def test_random_setpoints_are_reachable_and_oracle_settings_follow_the_dynamics():
    family = draw_family(seed=0, plants=20)
    for depth, _ in family:
        vehicle = RandomVehicle(RandomVehicleConfig(depth=depth, pitch=depth))
        plant = known_plant(vehicle, "depth", 15.0)
        levels = channel_levels(depth, 2.0, 15.0)
        for level in levels:
            u = plant.invert_pump((level - 15.0) / depth.dc_gain, 0.0)
            assert abs(u) < 2.0
        settings = oracle_settings_for(plant)
        slowest = max(depth.pole_moduli())
        assert 20 <= settings.horizon <= 600
        assert settings.horizon >= min(600, 4.0 / (1.0 - slowest))


# ---- the reports -------------------------------------------------------------------------


def test_identification_json_has_the_multistep_fields(capsys):
    args = ["experiment", "--channel", "pitch", "--samples", "600", "--json"]
    assert main(args) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["fit_split"] == 300
    assert data["horizon_source"] == "derived" and 1 <= data["horizon"] <= 75
    for name, scores in data["models"].items():
        assert {"nmse", "skill", "fit", "k_step_nmse", "horizon"} <= set(scores), name
        assert scores["fit"] is None or math.isfinite(scores["fit"])
    assert data["models"]["rls-arx"]["fit"] > data["models"]["persistence"]["fit"]


def test_identification_table_prints_fit_and_k_step(capsys):
    assert main(["experiment", "--samples", "400", "--horizon", "7"]) == 0
    out = capsys.readouterr().out
    assert "fit %" in out and "k-step NMSE" in out
    assert "   7 " in out


def test_closed_loop_json_has_the_oracle_beside_inverse_and_reference(capsys):
    args = [
        "experiment",
        "--closed-loop",
        "--scenario",
        "paper",
        "--samples",
        "900",
        "--identify",
        "500",
        "--step-every",
        "200",
        "--json",
    ]
    assert main(args) == 0
    data = json.loads(capsys.readouterr().out)
    for ch in ("depth", "pitch"):
        entry = data["channels"][ch]
        assert {"inverse", "reference_only", "oracle", "oracle_ratio"} <= set(entry)
        assert entry["oracle"]["iae"] > 0
        ratio = entry["oracle_ratio"]["inverse"]
        assert ratio == pytest.approx(entry["inverse"]["iae"] / entry["oracle"]["iae"], rel=1e-3)
    assert data["non_finite_commands"] == {"depth": 0, "pitch": 0}
    assert data["oracle_failures"] == 0


def test_closed_loop_json_on_stdout_is_json_alone_in_a_fresh_process():
    """HiGHS writes its banner onto file descriptor 1 from C++ the first time a solver is
    made in a process: a fresh process, so that this run makes the first one."""
    command = [sys.executable, "-m", "hil_service.cli", "experiment", "--closed-loop",
               "--scenario", "paper", "--samples", "900", "--identify", "500",
               "--step-every", "200", "--json"]  # fmt: skip
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run(command, cwd=root, capture_output=True, timeout=300, check=True)
    data = json.loads(done.stdout)
    assert data["oracle_failures"] == 0
    assert data["channels"]["pitch"]["oracle"]["iae"] > 0


def test_silencing_the_solver_keeps_what_python_printed_around_it(capfd):
    print("before", end=" ")  # still in Python's buffer when the descriptor is switched
    highs = _quiet_highs()
    print("after")
    highs.run()  # an empty model: with output_flag off, nothing on the console either
    assert capfd.readouterr().out == "before after\n"


def test_random_closed_loop_reports_every_plant_and_the_summary(capsys):
    args = [
        "experiment",
        "--closed-loop",
        "--scenario",
        "random",
        "--plants",
        "2",
        "--samples",
        "700",
        "--identify",
        "400",
        "--step-every",
        "150",
        "--json",
    ]
    assert main(args) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["scenario"] == "random" and len(data["plants"]) == 2
    summary = data["summary"]
    assert {"median_ratio", "max_ratio", "divergences", "non_finite_commands"} <= set(summary)
    for row in data["plants"]:
        assert row["oracle_iae"] > 0 and row["iae_ratio_oracle"] > 0
        assert row["oracle_iae"] < row["reference_only_iae"]
    ratios = [row["iae_ratio_oracle"] for row in data["plants"]]
    assert summary["max_ratio"] == pytest.approx(max(ratios), rel=1e-3)


def test_random_is_refused_for_identification(capsys):
    assert main(["experiment", "--scenario", "random"]) == 2
    assert "closed-loop" in capsys.readouterr().err
