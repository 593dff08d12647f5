"""Building blocks of hil_service.umodel: NLMS, RBF layer, RLS, purity of the package."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from hil_service.umodel import (
    NLMS,
    RLS,
    GaussianRBF,
    evenly_spaced_centres,
)
from hil_service.umodel.dynamics import ModelDynamics

UMODEL_DIR = Path(__file__).resolve().parents[1] / "hil_service" / "umodel"


def test_nlms_hand_computed_example() -> None:
    # θ = [0.5, −1], φ = [1, 2], y = 1  →  ŷ = 0.5 − 2 = −1.5, e = 2.5
    # μ = 0.5, ε = 1  →  g = 0.5·2.5 / (1 + 1 + 4) = 1.25/6 = 0.208333…
    # θ' = [0.5 + 0.208333…, −1 + 0.416666…] = [0.708333…, −0.583333…]
    theta = [0.5, -1.0]
    phi = [1.0, 2.0]
    error = 1.0 - (0.5 * 1.0 + (-1.0) * 2.0)
    assert error == 2.5
    new, gain, phi_sq = NLMS(0.5, 1.0).update_with_terms(theta, phi, error)
    assert (gain, phi_sq) == (pytest.approx(0.2083333333333333, abs=1e-15), 5.0)
    assert new == pytest.approx([0.7083333333333334, -0.5833333333333333], abs=1e-15)
    assert theta == [0.5, -1.0]  # pure: input untouched
    assert NLMS(0.5, 1.0).update(theta, phi, error) == new
    # After the update the same regressor is predicted closer: ŷ' = 0.7083 − 1.1667 = −0.4583.
    assert sum(t * p for t, p in zip(new, phi, strict=True)) == pytest.approx(-0.4583333333333333)


@pytest.mark.parametrize("mu", [0.0, -0.1, 2.0, 2.5, math.nan])
def test_nlms_rejects_unstable_step_size(mu: float) -> None:
    with pytest.raises(ValueError):
        NLMS(mu)


def test_evenly_spaced_centres_paper() -> None:
    c = evenly_spaced_centres(17, -2.0, 2.0)
    assert len(c) == 17
    assert c[0] == -2.0 and c[-1] == 2.0
    assert np.allclose(np.diff(c), 0.25)


def test_rbf_values_follow_eq8_convention() -> None:
    rbf = GaussianRBF([0.0, 1.0], beta=0.5)
    # Φ(u) = exp(−(u − c)² / β²): at u = 0.5 both are exp(−0.25/0.25) = e^{-1}.
    assert rbf.values(0.5) == pytest.approx([math.exp(-1.0)] * 2, rel=1e-15)
    assert rbf.values_list(0.5) == pytest.approx([math.exp(-1.0)] * 2, rel=1e-15)
    assert rbf.values(0.0)[0] == 1.0


@pytest.mark.parametrize("u", [-2.3, -1.0, -0.11, 0.0, 0.37, 1.9, 3.0])
def test_rbf_derivative_matches_finite_differences(u: float) -> None:
    rbf = GaussianRBF(evenly_spaced_centres(17, -2.0, 2.0), beta=0.25)
    h = 1e-6
    fd = (rbf.values(u + h) - rbf.values(u - h)) / (2 * h)
    assert np.allclose(rbf.derivatives(u), fd, rtol=1e-6, atol=1e-8)

    w = np.random.default_rng(3).uniform(-1, 1, 17).tolist()
    s, ds = rbf.weighted(u, w)
    assert s == pytest.approx(float(np.dot(w, rbf.values(u))), rel=1e-12, abs=1e-14)
    s_p, _ = rbf.weighted(u + h, w)
    s_m, _ = rbf.weighted(u - h, w)
    assert ds == pytest.approx((s_p - s_m) / (2 * h), rel=1e-6, abs=1e-8)


def test_rbf_validation() -> None:
    with pytest.raises(ValueError):
        GaussianRBF([0.0], beta=0.0)
    with pytest.raises(ValueError):
        GaussianRBF([], beta=1.0)
    with pytest.raises(ValueError):
        GaussianRBF([math.nan], beta=1.0)


def test_rls_identifies_linear_map() -> None:
    rng = np.random.default_rng(0)
    true = np.array([0.7, -0.2, 0.3])
    theta = np.zeros(3)
    rls = RLS(3, lam=0.99)
    for _ in range(300):
        phi = np.array([rng.normal(), rng.normal(), 1.0])
        rls.update_(theta, phi, float(true @ phi - theta @ phi))
    assert np.allclose(theta, true, atol=1e-8)


def test_rls_covariance_bounded_without_excitation() -> None:
    theta = np.zeros(3)
    rls = RLS(3, lam=0.95, p0=10.0)
    phi = np.array([1.0, 1.0, 1.0])  # constant regressor: only one direction excited
    for _ in range(10_000):
        rls.update_(theta, phi, float(2.0 - theta @ phi))
    assert np.all(np.isfinite(rls.p))
    assert np.trace(rls.p) <= rls.trace_max / rls.lam + 1e-9
    assert np.allclose(rls.p, rls.p.T)
    # Forgetting is suspended while trace(P) is at the bound, so convergence along the one
    # excited direction slows down (≈1/k) but never stalls or blows up.
    assert float(theta @ phi) == pytest.approx(2.0, abs=1e-4)
    assert np.all(np.abs(theta) < 10.0)


ALLOWED_IMPORTS = {
    "__future__",
    "math",
    "numpy",
    "scipy.signal",  # lfilter: a linear recursion in C (cancellation's record check), no I/O
    "dataclasses",
    "typing",
    "collections",
    "collections.abc",
    "operator",
    "functools",
    "bisect",
    "itertools",
    "librt.vecs",  # mypyc's unboxed float vectors: storage, no I/O
    "mypy_extensions",  # i64, the machine integer type mypyc compiles natively
}


def test_rls_update_into_a_spare_buffer_is_the_in_place_update_and_keeps_the_old_p() -> None:
    """``ListRLS.update(..., into=spare)``: the same θ and P, bit for bit, as the update in
    place; the new P lives in ``spare`` and the P from before is left untouched (the model
    keeps it to undo an update without copying P every sample)."""
    from hil_service.umodel.rls import ListRLS

    rng = np.random.default_rng(5)
    in_place, into = ListRLS(6), ListRLS(6)
    theta_a, theta_b = [0.0] * 6, [0.0] * 6
    spare = into.blank()
    for _ in range(40):
        phi = [float(v) for v in rng.normal(size=6)]
        error = float(rng.normal())
        before = into.p
        kept = list(before)
        assert in_place.update(theta_a, phi, error)
        assert into.update(theta_b, phi, error, spare)
        assert list(into.p) == list(spare) and list(before) == kept
        spare = before
        assert theta_a == theta_b and in_place.p == into.p


def test_package_is_pure() -> None:
    """No I/O, clocks or middleware: only numpy, scipy's linear filter and side-effect-free
    stdlib modules."""
    files = sorted(UMODEL_DIR.glob("*.py"))
    assert files
    for path in files:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative import inside the package
                    continue
                names = [node.module or ""]
            else:
                continue
            for name in names:
                assert name in ALLOWED_IMPORTS, f"{path.name} imports {name}"


def test_no_builtin_sum_on_the_identification_and_control_path() -> None:
    """``sum`` of floats changed in Python 3.12 (compensated summation): a log recorded under
    one version would not replay bit for bit under another. ``reproducible.dot`` (a loop) or
    element-wise array sums are used instead."""
    sources = [*sorted(UMODEL_DIR.glob("*.py")), UMODEL_DIR.parent / "pipeline.py"]
    offenders = []
    for path in sources:
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "sum"
            ):
                offenders.append(f"{path.name}:{node.lineno}")
    assert offenders == []


def test_divergence_guard_sees_the_exact_parameter_norm() -> None:
    """The guard updates ‖θ‖² from the NLMS step's own products; it must stay the norm of
    θ itself (to rounding), or the parameter limit would fire early or late."""
    from hil_service.umodel import PaperUModel
    from hil_service.umodel.reproducible import dot

    rng = np.random.default_rng(4)
    model = PaperUModel(seed=4, init_scale=0.5)
    y = 0.0
    worst = 0.0
    for k in range(20_000):
        u = float(rng.uniform(-2, 2))
        y = 0.95 * y + 0.3 * u + 0.2 * math.sin(0.01 * k) + float(rng.normal(0, 0.05))
        model.step(u, y)
        exact = dot(model._theta, model._theta)
        worst = max(worst, abs(model._sq_norm - exact) / exact)
    assert worst < 1e-12


@pytest.mark.parametrize(("na", "nb", "with_rbf"), [(4, 6, False), (0, 1, True), (2, 3, True)])
def test_free_run_is_advance_repeated_to_the_bit(na: int, nb: int, with_rbf: bool) -> None:
    """``ModelDynamics.free_run`` (the horizon test's free runs over a record) gives the
    predictions of a snapshot at ``start`` advanced on the recorded inputs, bit for bit."""
    rng = np.random.default_rng(na * 10 + nb)
    outputs = rng.normal(size=300).tolist()
    inputs = rng.uniform(-2.0, 2.0, size=300).tolist()
    ar = (0.3 * rng.normal(size=na)).tolist()
    lag_polys = [rng.normal(size=3).tolist() for _ in range(nb)]
    rbf = GaussianRBF(evenly_spaced_centres(9, -2.0, 2.0), 0.5) if with_rbf else None
    weights = rng.normal(size=9).tolist() if with_rbf else []
    start, end = 40, 140
    snapshot = ModelDynamics(
        ar, 0.1, lag_polys, 0.5,
        [outputs[start - i] for i in range(na)], [inputs[start - i] for i in range(nb)],
        rbf, weights,
    )  # fmt: skip
    advanced = [snapshot.advance(inputs[j]) for j in range(start + 1, end + 1)]
    free = ModelDynamics(ar, 0.1, lag_polys, 0.5, [], [], rbf, weights)
    assert free.free_run(outputs, inputs, start, end) == advanced
