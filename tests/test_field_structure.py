"""The two-input U-model's structure chosen on the training dives only."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hil_service.offline.field.evaluate import Arrays, identify_dives
from hil_service.offline.field.structure import (
    CANDIDATES,
    DEFAULT,
    Piece,
    choose_structure,
    label,
    neutral_and_compression,
)
from tests.test_field_evaluate import DATA, _arrays

DT = 10.0


def _dive(seed: int, levels: list[float], n: int = 600) -> Piece:
    """A steady-glide plant's dive: the buoyancy input stepping between ``levels``, the
    pitch following it as a glider's pitch loop sets it, a little noise on the depth."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.choice(levels, size=n // 60 + 1), 60)[:n]
    pitch = -np.sign(u) * (0.3 + 0.1 * np.abs(u)) + 0.02 * rng.standard_normal(n)
    z = np.empty(n)
    z[0] = 300.0
    for t in range(1, n):
        b = u[t - 1] - 0.1 - 2e-4 * z[t - 1]
        rate = -0.25 * np.sign(b) * np.sqrt(abs(b)) * abs(np.sin(pitch[t - 1])) ** 1.5
        z[t] = z[t - 1] + DT * rate
    return Piece(seed, z + 0.05 * rng.standard_normal(n), u, pitch)


def _free_pitch_dive(seed: int, levels: list[float], cubic: float, n: int = 600) -> Piece:
    """A glider whose pitch its own loop moves independently of the buoyancy input, and
    whose depth rate departs from the square-root law by a cubic in the law's regressor
    g (ż = −(0.25·g + cubic·g³)): a drag that does not grow as the square of the speed."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.choice(levels, size=n // 60 + 1), 60)[:n]
    magnitude = np.repeat(rng.uniform(0.25, 0.6, size=n // 30 + 1), 30)[:n]
    pitch = -np.sign(u) * magnitude + 0.02 * rng.standard_normal(n)
    z = np.empty(n)
    z[0] = 300.0
    for t in range(1, n):
        b = u[t - 1] - 0.1 - 2e-4 * z[t - 1]
        g = np.sign(b) * np.sqrt(abs(b)) * abs(np.sin(pitch[t - 1])) ** 1.5
        z[t] = z[t - 1] - DT * (0.25 * g + cubic * g**3)
    return Piece(seed, z + 0.05 * rng.standard_normal(n), u, pitch)


BUOYANCY = tuple(c for c in CANDIDATES if c[0] == "buoyancy")


def test_a_steady_glide_plant_chooses_the_flight_model_and_recovers_its_law() -> None:
    pieces = [_dive(seed, [-1.6, -0.9, -0.4, 0.5, 1.0, 1.7]) for seed in range(5)]
    choice = choose_structure(pieces, sync=3, min_samples=20, u_scale=2.0)
    assert (choice.feature, choice.degree, choice.drift) == ("steady-glide", 1, False)
    assert choice.scores[choice.label] > 99.0  # type: ignore[operator]
    values = neutral_and_compression(pieces, 2.0)
    assert values is not None
    assert values[0] == pytest.approx(0.1, abs=0.01)
    assert values[1] == pytest.approx(2e-4, rel=0.05)


def test_several_buoyancy_levels_need_the_curvature_of_the_square_root() -> None:
    pieces = [_dive(seed, [-1.6, -0.9, -0.4, 0.5, 1.0, 1.7]) for seed in range(5)]
    choice = choose_structure(pieces, sync=3, min_samples=20, u_scale=2.0, candidates=BUOYANCY)
    assert choice.folds == [0, 1, 2, 3, 4]
    assert choice.degree >= 3, choice.scores
    better = choice.scores[choice.label]
    assert better > choice.scores[label("buoyancy", 1, False)] + 1.0  # type: ignore[operator]


def test_two_buoyancy_levels_choose_the_fewest_parameters() -> None:
    pieces = [_dive(seed, [-1.6, 1.2]) for seed in range(5)]
    choice = choose_structure(pieces, sync=3, min_samples=20, u_scale=2.0, candidates=BUOYANCY)
    # Two levels fix two values of the input map: any degree fits them alike.
    assert (choice.degree, choice.drift) == (1, False), choice.scores
    # and the flight model, first at one parameter count, is chosen among all.
    choice = choose_structure(pieces, sync=3, min_samples=20, u_scale=2.0)
    assert (choice.feature, choice.degree, choice.drift) == ("steady-glide", 1, False)


def test_a_departure_from_the_law_keeps_the_polynomial_on_top_of_it() -> None:
    # Two buoyancy levels, as SEA035 flies: the buoyancy input cannot show the cubic, the
    # flight model's regressor, which moves with the pitch along each leg, can.
    pieces = [_free_pitch_dive(seed, [-1.6, 1.2], cubic=1.0) for seed in range(5)]
    choice = choose_structure(pieces, sync=3, min_samples=20, u_scale=2.0)
    assert choice.feature == "steady-glide" and choice.degree >= 3, choice.scores
    flight = choice.scores[label("steady-glide", 1, False)]
    best_buoyancy = max(v for k, v in choice.scores.items() if k.startswith("buoyancy"))
    assert choice.scores[choice.label] > flight + 5.0  # type: ignore[operator]
    assert choice.scores[choice.label] > best_buoyancy + 5.0  # type: ignore[operator]
    # Without the departure the same plant keeps the flight model alone.
    plain = [_free_pitch_dive(seed, [-1.6, 1.2], cubic=0.0) for seed in range(5)]
    choice = choose_structure(plain, sync=3, min_samples=20, u_scale=2.0)
    assert (choice.feature, choice.degree, choice.drift) == ("steady-glide", 1, False)


def test_too_few_dives_to_validate_keep_the_default() -> None:
    pieces = [_dive(0, [-1.6, 1.2]), _dive(1, [-1.6, 1.2], n=8)]
    choice = choose_structure(pieces, sync=3, min_samples=20, u_scale=2.0)
    assert (choice.feature, choice.degree, choice.drift) == DEFAULT
    assert "1 training dive" in choice.why


@pytest.fixture(scope="module")
def sea035(tmp_path_factory: pytest.TempPathFactory) -> Arrays:
    return _arrays(DATA / "seaexplorer-sea035", tmp_path_factory.mktemp("sea") / "log.mcap")


@pytest.mark.parametrize("split", ["first", "alternate"])
def test_the_choice_never_sees_the_held_out_dives(sea035: Arrays, split: str) -> None:
    depth = identify_dives(sea035, split=split)[0]
    glide = next(m for m in depth.models if m.model == "glide-u")
    choice = glide.parameters["structure_choice"]
    assert set(choice["folds"]) <= set(depth.train_dives)
    # Scramble every held-out dive: the structure chosen and its validation do not move.
    depth_m = sea035.depth.copy()
    for s in sea035.segments:
        if s.dive in depth.held_out:
            depth_m[s.start : s.stop] = depth_m[s.start : s.stop][::-1] * 1.3
    again = identify_dives(replace(sea035, depth=depth_m), split=split)[0]
    glide_again = next(m for m in again.models if m.model == "glide-u")
    assert glide_again.parameters["structure_choice"] == choice
    assert glide_again.parameters["structure"] == glide.parameters["structure"]
    assert glide_again.fit != glide.fit  # the scores did see the change


def test_a_candidate_whose_free_run_diverges_is_scored_none_not_raised() -> None:
    # A dive that starts at an absurd depth makes every polynomial's free run blow up.
    pieces = [_dive(seed, [-1.6, -0.9, 0.5, 1.7]) for seed in range(3)]
    wild = Piece(9, pieces[0].y * 1e150, pieces[0].u * 1e100, pieces[0].pitch)
    choice = choose_structure([*pieces, wild], sync=3, min_samples=20, u_scale=2.0)
    assert choice.folds == [0, 1, 2, 9]
    assert all(v is None or math.isfinite(v) for v in choice.scores.values())
