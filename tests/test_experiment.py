"""``glider-hil experiment``: the orderings the identification targets claim, the closed-loop
metrics, the JSON contract and the figures."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hil_service.cli import main
from hil_service.experiment.closed_loop import (
    ClosedLoopSettings,
    nmp_iae_bound,
    run_closed_loop,
    step_metrics,
)
from hil_service.experiment.identification import (
    IdentificationSettings,
    converged_at,
    fit_bound,
    run_identification,
)
from hil_service.experiment.speed import measure
from plant_emulator.models import DEPTH_NUM
from plant_emulator.scenarios import SCENARIOS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def default_runs():
    """docs/identification.md's table: every scenario and channel, default length (5000)."""
    return {
        (scenario, channel): run_identification(IdentificationSettings(scenario, channel))
        for scenario in SCENARIOS
        for channel in ("depth", "pitch")
    }


def test_dynamic_model_beats_persistence_by_the_target_margin_everywhere(default_runs):
    for key, result in default_runs.items():
        models = result.models
        assert models["dynamic"].skill >= 0.8, key
        assert models["persistence"].skill == pytest.approx(0.0), key
        # The paper's static-in-u(t−1) structure cannot follow the inner loop's dynamics.
        assert models["paper"].nmse > models["dynamic"].nmse, key


def test_dynamic_model_is_no_worse_than_arx_where_the_plant_is_nonlinear(default_runs):
    for channel in ("depth", "pitch"):
        models = default_runs[("nonlinear", channel)].models
        assert models["dynamic"].nmse <= models["rls-arx"].nmse, channel


def test_dynamic_model_holds_over_the_horizon(default_runs):
    """The free-run targets on seed 0 (docs/identification.md: 100/99.7, 87.7/96.4, 96.0/95.5 %)."""
    for (scenario, channel), result in default_runs.items():
        models = result.models
        fit, arx = models["dynamic"].fit, models["rls-arx"].fit
        assert fit is not None and arx is not None, (scenario, channel)
        floor = 85.0 if (scenario, channel) == ("disturbed", "depth") else 90.0
        assert fit >= floor + 2.0, (scenario, channel, fit)
        # Free run is what control needs: persistence (skill 0) simulates a constant.
        assert models["persistence"].fit < 0.0 < fit, (scenario, channel)
        if scenario == "nonlinear":
            assert fit >= arx + 5.0, (channel, fit, arx)


def test_dynamic_model_is_near_the_ceiling_on_disturbed_depth(default_runs):
    """No model of u beats E[y|u] (docs/control.md); dynamic comes within a few points."""
    result = default_runs[("disturbed", "depth")]
    bound = fit_bound(result.settings, clock_seeds=1)
    fit = result.models["dynamic"].fit
    assert bound.bound is not None and fit is not None
    assert bound.bound - 5.0 <= fit <= bound.bound


def test_identification_is_deterministic_for_a_seed():
    settings = IdentificationSettings("disturbed", "pitch", samples=600, seed=3)
    a, b = run_identification(settings), run_identification(settings)
    for name in a.models:
        np.testing.assert_array_equal(a.models[name].y_hat, b.models[name].y_hat)
    other = run_identification(IdentificationSettings("disturbed", "pitch", samples=600, seed=4))
    assert not np.array_equal(a.y, other.y)


def test_converged_at_is_the_first_sample_after_the_last_excursion():
    y = np.linspace(0.0, 10.0, 100)  # range 10 → band 0.5
    error = np.zeros(100)
    error[[3, 40]] = [2.0, -0.6]
    assert converged_at(error, y) == 41
    error[99] = 1.0
    assert converged_at(error, y) is None
    assert converged_at(np.zeros(100), y) == 0


def test_step_metrics_on_a_known_response():
    setpoint = np.array([np.nan] * 2 + [1.0] * 8)
    y = np.array([0.0, 0.0, 0.5, 1.2, 1.05, 1.0, 1.0, 1.0, 1.0, 1.0])
    m = step_metrics(y, setpoint, start=2, band=0.1, period=2.0)
    assert m.iae == pytest.approx((0.5 + 0.2 + 0.05) * 2.0)
    assert m.overshoot == pytest.approx(20.0)
    assert m.settling_median == pytest.approx(2 * 2.0)  # inside ±0.1 from index 4 of the step
    assert (m.steps, m.settled, m.step_total) == (1, 1, 1.0)


def test_nmp_bound_comes_from_the_depth_plants_zero_outside_the_unit_circle():
    # eq. 12's numerator: roots 0, 1 (cancelled against a pole at 1) and z₀ ≈ 1.0045.
    zeros = np.roots(DEPTH_NUM)
    z0 = max(z.real for z in zeros if abs(z.imag) < 1e-9)
    assert 1.0 < z0 < 1.01
    assert nmp_iae_bound("depth") == pytest.approx(z0 / (z0 - 1.0), rel=1e-6)
    assert nmp_iae_bound("depth", period=2.0) == pytest.approx(2.0 * z0 / (z0 - 1.0), rel=1e-6)


def max_error_late_in_each_step(result, settings, channel: str) -> list[float]:
    """max |y − r| over the last quarter of every setpoint segment after identification."""
    y, r = result.inverse.y[channel], result.inverse.setpoint[channel]
    errors = []
    for k0 in range(settings.identify, settings.samples, settings.step_every):
        late = slice(k0 + 3 * settings.step_every // 4, k0 + settings.step_every)
        errors.append(float(np.max(np.abs(y[late] - r[k0]))))
    return errors


#: Tracking bands over the last quarter of each 400-sample step (2600 samples, seed 0),
#: measured with the predictive inverse: disturbed depth 5.40 / 2.38 / 0.31 / 0.55 m. The
#: first step's is the worst: the controller plans over the depth channel's ~700-sample
#: settling horizon and, on a 400-sample step, is still in its wrong-way (non-minimum-phase)
#: excursion. Depth stays loose on purpose; pitch is tight.
BANDS = {
    "paper": {"depth": 2.0, "pitch": 0.005},
    "disturbed": {"depth": 6.0, "pitch": 0.01},
}


def test_closed_loop_tracks_without_divergence_under_disturbance():
    settings = ClosedLoopSettings("disturbed", samples=2600, identify=1000, step_every=400)
    result = run_closed_loop(settings)
    data = result.as_json()
    assert result.blocked == 0
    assert result.divergences == {"depth": 0, "pitch": 0}
    for ch in ("depth", "pitch"):
        for run_name in ("inverse", "reference_only"):
            m = data["channels"][ch][run_name]
            assert math.isfinite(m["iae"]) and m["iae"] > 0
            assert m["steps"] == 4
        u = result.inverse.u[ch][settings.identify :]
        assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= 2.0 + 1e-9)
        errors = max_error_late_in_each_step(result, settings, ch)
        assert max(errors) <= BANDS["disturbed"][ch], (ch, errors)


def test_closed_loop_holds_each_setpoint_within_its_band_without_disturbance():
    settings = ClosedLoopSettings("paper", samples=2600, identify=1000, step_every=400)
    result = run_closed_loop(settings)
    for ch in ("depth", "pitch"):
        errors = max_error_late_in_each_step(result, settings, ch)
        assert len(errors) == 4
        assert max(errors) <= BANDS["paper"][ch], (ch, errors)


def test_cli_json_carries_the_documented_keys(capsys):
    assert (
        main(
            [
                "experiment",
                "--scenario",
                "nonlinear",
                "--channel",
                "pitch",
                "--samples",
                "400",
                "--json",
            ]
        )
        == 0
    )
    data = json.loads(capsys.readouterr().out)
    assert (data["scenario"], data["channel"]) == ("nonlinear", "pitch")
    assert set(data["models"]) == {"paper", "dynamic", "rls-arx", "persistence"}
    for scores in data["models"].values():
        assert set(scores) == {
            "nmse",
            "skill",
            "converged_at",
            "fit",
            "k_step_nmse",
            "horizon",
            "fit_split",
            "k_step_windows",
        }


def test_cli_table_and_plots(tmp_path, capsys):
    assert main(["experiment", "--samples", "300", "--plots", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for name in ("paper", "dynamic", "rls-arx", "persistence"):
        assert f"depth   {name}" in out
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == [f"paper_depth_{n}.png" for n in ("dynamic", "paper", "persistence", "rls-arx")]
    for p in tmp_path.glob("*.png"):
        assert p.read_bytes()[:8] == PNG_MAGIC and p.stat().st_size > 10_000


def test_cli_closed_loop_json_and_plots(tmp_path, capsys):
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
        "--plots",
        str(tmp_path),
    ]
    assert main(args) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data["channels"]) == {"depth", "pitch"}
    assert {"inverse", "reference_only", "iae_ratio", "iae_lower_bound"} <= set(
        data["channels"]["depth"]
    )
    assert {p.name for p in tmp_path.glob("*.png")} == {
        "closed_loop_paper_depth.png",
        "closed_loop_paper_pitch.png",
        "step_paper_depth.png",  # one step as the paper shows it
        "step_paper_pitch.png",
    }


def test_cli_rejects_a_bad_setting_with_a_message(capsys):
    assert main(["experiment", "--samples", "5"]) == 2
    assert "samples must be at least 10" in capsys.readouterr().err


def test_bench_measures_the_service_control_step():
    figure = measure("pitch", "dynamic", samples=400)
    assert figure.update_per_s > 0 and figure.control_per_s > 0
    assert 0.0 <= figure.fallback_share <= 1.0


def test_pitch_inverse_control_beats_reference_only_under_disturbance():
    # Measured 0.629 on this run (0.40 over 20000 samples; 1.08 with the former H = 20
    # without trajectory); the margin is not a tolerance for a worse controller.
    result = run_closed_loop(ClosedLoopSettings("disturbed", samples=5000, seed=0))
    pitch = result.as_json()["channels"]["pitch"]
    assert pitch["iae_ratio"] < 0.7
    assert pitch["inverse"]["settled_steps"] == pitch["inverse"]["steps"]
    assert result.blocked == 0 and result.divergences == {"depth": 0, "pitch": 0}
    # The pitch map at H = 3 is monotone: the grid fallback is the exception.
    fallback = sum(n for mode, n in result.solver_paths.items() if mode.endswith("/fallback"))
    assert fallback < 0.01 * sum(result.solver_paths.values())
