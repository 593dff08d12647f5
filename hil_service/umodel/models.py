"""One-step-ahead identifiers sharing a common interface.

Timing convention (all models): ``step(u_prev, y)`` is called once per sample with
u_prev = u(t−1), the input applied *before* y(t) was measured. The model first forms the
a-priori prediction ŷ(t) from u(t−1) and its internal history (which only contains data up
to t−1), then reveals y(t), computes e = y(t) − ŷ(t), adapts, and finally shifts y(t) and
u(t−1) into its history. ``predict(u)`` returns the same a-priori prediction without changing
anything. The controller uses the U-models' multi-step map instead (``dynamics()``, see
:mod:`.dynamics` and :mod:`.predictive`).

Models (``MODEL_NAMES``):

* ``paper``       — Abbasi et al. 2015: y(t) = α₀(t) + Σ_{i=1..M} α_i(t)·u^i(t−1) with
  α₀ = Σ_j w_j Φ_j(u(t−1)), Φ_j(u) = exp(−(u−c_j)²/β²) (eq. 8 convention). α_i and w are
  adapted by one NLMS on φ = [Φ(u(t−1)), u, …, u^M].
* ``dynamic``     — the same polynomial in u(t−1), with α₀ holding a bias, past output
  levels y(t−1..t−na) and polynomials of the older inputs u(t−2..t−nb), identified by RLS
  with forgetting: a model that holds over the control horizon (see the class).
* ``persistence`` — ŷ(t) = y(t−1); the baseline every identifier must beat.
* ``rls-arx``     — ARX y(t) = Σ a_i y(t−i) + Σ b_k u(t−k) + c by RLS with forgetting and a
  covariance trace bound (see :mod:`.rls`).

Every model rejects non-finite/absurd samples without touching its state, detects
divergence (see :mod:`.guards`) and never returns NaN.

The four identifiers share one module, over 500 lines: each is a short set of hooks on the
same step skeleton (``_ModelBase``), which reads best beside them, and ``build_model``
registers them all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from operator import mul
from typing import Any, ClassVar

import numpy as np

from .dynamics import ModelDynamics
from .estimate import STATUSES, Estimate, Status, new_estimate
from .finite import finite
from .guards import DivergenceMonitor, GuardConfig
from .interface import OneStepModel
from .lag_prior import smooth_lag_prior
from .nlms import DEFAULT_EPS, NLMS
from .rbf import GaussianRBF, evenly_spaced_centres
from .reproducible import dot
from .rls import RLS, ListRLS

__all__ = [
    "MODEL_NAMES",
    "STATUSES",
    "U_MODELS",
    "DynamicUModel",
    "Estimate",
    "OneStepModel",
    "PaperUModel",
    "PersistenceModel",
    "RlsArxModel",
    "Status",
    "build_model",
    "from_config",
    "option_names",
    "paper_preset",
]

#: The U-models: what the service identifies and inverts (``PipelineSettings.model``).
U_MODELS: tuple[str, ...] = ("paper", "dynamic")
#: Every model, the U-models and the baselines the experiments score them against.
MODEL_NAMES: tuple[str, ...] = (*U_MODELS, "rls-arx", "persistence")

PAPER_DEGREE = 3
PAPER_MU = 0.5
PAPER_N_CENTRES = 17
PAPER_CENTRE_RANGE = (-2.0, 2.0)
PAPER_BETA = 0.25
PAPER_INIT_SCALE = 0.1


_isfinite = math.isfinite


class _ModelBase:
    """Guards and the step skeleton; subclasses provide the numerics via small hooks."""

    name: ClassVar[str] = ""
    _checks_error: ClassVar[bool] = True

    def __init__(self, guard: GuardConfig | dict[str, Any] | None) -> None:
        self.guard = GuardConfig.coerce(guard)
        self._monitor = DivergenceMonitor(self.guard)
        self._frozen = False
        self._y_last = 0.0
        self._u_last = 0.0
        self._n_accepted = 0
        self._n_rejected = 0

    # ---- hooks -------------------------------------------------------------------------
    def _predict(self, u: float) -> float:  # may write scratch buffers only
        raise NotImplementedError

    def _coefficients(self, u: float, y_hat: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        raise NotImplementedError

    def _adapt(self, error: float) -> None:
        raise NotImplementedError

    def _params_ok(self) -> bool:
        return True

    def undo_last_update(self) -> bool:
        """Restore the parameters from before the last update; False when the model keeps
        no copy (then nothing changes)."""
        return False

    def _reset_params(self) -> None:
        pass

    def _push(self, u: float, y: float) -> None:
        pass

    def _reset_history(self) -> None:
        pass

    def _options(self) -> dict[str, Any]:
        raise NotImplementedError

    def _state(self) -> dict[str, Any]:
        return {}

    # ---- public API --------------------------------------------------------------------
    @property
    def frozen(self) -> bool:
        return self._frozen

    @property
    def history_length(self) -> int:
        """Contiguous samples needed before the regressor holds no pre-gap value again.

        One for u(t−1) plus the model's own lags; ``observe_only`` that many samples after
        a gap in the telemetry and learning resumes on a correctly aligned regressor.
        """
        return 1 + self._lags()

    def _lags(self) -> int:
        return 0

    def observe_only(self, u_prev: float, y: float) -> bool:
        """Advance the history by one sample without predicting or learning from it.

        For the samples after a gap: ``u_prev`` may not be the input really applied one step
        before ``y``, so the pair must not train the model, but ``y`` must enter the history.
        Non-finite or out-of-range values are ignored (False).
        """
        g = self.guard
        ok = (
            _isfinite(u_prev)
            and abs(u_prev) <= g.input_limit
            and _isfinite(y)
            and abs(y) <= g.output_limit
        )
        if ok:
            self._push(u_prev, y)
            self._y_last = y
            self._u_last = u_prev
        return ok

    def predict(self, u_prev: float) -> float:
        """A-priori ŷ for input ``u_prev`` given the current history; never NaN, no mutation.

        An invalid ``u_prev`` (non-finite or beyond ``input_limit``) is replaced by the last
        accepted input; a non-finite result by the last accepted output.
        """
        if not (_isfinite(u_prev) and abs(u_prev) <= self.guard.input_limit):
            u_prev = self._u_last
        y_hat = self._predict(u_prev)
        return y_hat if _isfinite(y_hat) else self._y_last

    def step(self, u_prev: float, y: float) -> Estimate:
        """Predict ŷ(t) from u(t−1), then learn from y(t). See module docstring."""
        g = self.guard
        u_ok = _isfinite(u_prev) and abs(u_prev) <= g.input_limit
        if not (u_ok and _isfinite(y) and abs(y) <= g.output_limit):
            self._n_rejected += 1
            y_hat = self.predict(u_prev if u_ok else self._u_last)
            alpha, weights = self._coefficients(u_prev if u_ok else self._u_last, y_hat)
            return new_estimate(
                self.name, "rejected", y if _isfinite(y) else y_hat, y_hat, 0.0, alpha, weights
            )

        y_hat = self._predict(u_prev)
        error = y - y_hat
        if not (_isfinite(y_hat) and _isfinite(error)):
            y_hat = self._y_last
            error = y - y_hat
            alpha, weights = self._coefficients(u_prev, y_hat)
            self._diverged()
            return self._finish(u_prev, y, y_hat, error, alpha, weights, "diverged")

        alpha, weights = self._coefficients(u_prev, y_hat)
        status: Status = "frozen" if self._frozen else "ok"
        if not self._frozen:
            self._adapt(error)
            if not self._params_ok():
                self._diverged()
                status = "diverged"
        if self._checks_error and self._monitor.observe(y, error) and status != "diverged":
            self._diverged()
            status = "diverged"
        return self._finish(u_prev, y, y_hat, error, alpha, weights, status)

    def unfreeze(self) -> None:
        """Resume adaptation after a freeze (parameters are kept)."""
        self._frozen = False
        self._monitor.count = 0

    def reset(self) -> None:
        """Back to the freshly constructed state (same seed → same initial parameters)."""
        self._reset_params()
        self._reset_history()
        self._monitor.reset()
        self._frozen = False
        self._y_last = 0.0
        self._u_last = 0.0
        self._n_accepted = 0
        self._n_rejected = 0

    def config(self) -> dict[str, Any]:
        """JSON-serialisable construction parameters; ``from_config`` rebuilds exactly."""
        cfg: dict[str, Any] = {"name": self.name}
        cfg.update(self._options())
        cfg["guard"] = self.guard.to_dict()
        return cfg

    def snapshot(self) -> dict[str, Any]:
        """Plain-Python copy of the full mutable state (for logs and tests)."""
        snap: dict[str, Any] = {
            "name": self.name,
            "frozen": self._frozen,
            "y_last": self._y_last,
            "u_last": self._u_last,
            "n_accepted": self._n_accepted,
            "n_rejected": self._n_rejected,
            "monitor": self._monitor.state(),
        }
        snap.update(self._state())
        return snap

    # ---- internals ---------------------------------------------------------------------
    def _finish(
        self,
        u: float,
        y: float,
        y_hat: float,
        error: float,
        alpha: tuple[float, ...],
        weights: tuple[float, ...],
        status: Status,
    ) -> Estimate:
        self._push(u, y)
        self._y_last = y
        self._u_last = u
        self._n_accepted += 1
        return new_estimate(self.name, status, y, y_hat, error, alpha, weights)

    def _diverged(self) -> None:
        mon = self._monitor
        mon.n_divergences += 1
        mon.count = 0
        if self.guard.on_divergence == "reset" or not self._params_ok():
            self._reset_params()
        if self.guard.on_divergence == "freeze":
            self._frozen = True


#: The dynamic U-model's output scale s is this many times the largest deviation from the
#: first level seen when it last outgrew s (so it is re-expressed at most once per
#: fourfold growth).
SCALE_MARGIN = 4.0
#: While its covariance has had fewer than this many × n updates, a rescale starts it
#: again at p0·I (see ``DynamicUModel``).
SCALE_SETTLE = 10

#: Samples between two exact recomputations of ‖θ‖² (updated incrementally in between).
NORM_RESYNC_PERIOD = 4096


def _norm_ok(sq_norm: float, limit: float) -> bool:
    # ‖θ‖₂ ≤ limit; the comparison is False for NaN, so it also catches non-finite θ.
    return sq_norm <= limit * limit


class _UModelCore(_ModelBase):
    """The RBF + polynomial machinery of ``paper`` (NLMS on a static U-model).

    θ layout: [w_1..w_J (RBF), α_1..α_M]; φ is built in the same order. Plain
    Python lists are used on the per-sample path (see :mod:`.nlms`).
    """

    def __init__(
        self,
        *,
        degree: int,
        mu: float,
        eps: float,
        centres: Sequence[float] | None,
        beta: float,
        init_scale: float,
        seed: int,
        guard: GuardConfig | dict[str, Any] | None,
        poly_scale: float = 1.0,
    ) -> None:
        super().__init__(guard)
        if not (finite(poly_scale) and poly_scale > 0.0):
            raise ValueError("poly_scale must be finite and > 0")
        self.poly_scale = float(poly_scale)
        if int(degree) != degree or degree < 1:
            raise ValueError("degree M must be an integer >= 1")
        if not (finite(init_scale) and init_scale >= 0.0):
            raise ValueError("init_scale must be finite and >= 0")
        if int(seed) != seed:
            raise ValueError("seed must be an integer")
        if centres is None:
            centres = evenly_spaced_centres(PAPER_N_CENTRES, *PAPER_CENTRE_RANGE)
        self.rbf = GaussianRBF(centres, beta)
        self.degree = int(degree)
        #: poly_scale^i for α_i in ``_coefficients``, computed once.
        self._scale_powers = [self.poly_scale ** (i + 1) for i in range(self.degree)]
        self.nlms = NLMS(float(mu), float(eps))
        self.init_scale = float(init_scale)
        self.seed = int(seed)
        self._nr = self.rbf.size
        self._np = self._nr + self.degree  # end of the polynomial block
        n = self._np
        rng = np.random.default_rng(self.seed)
        self._theta0: tuple[float, ...] = tuple(
            rng.uniform(-self.init_scale, self.init_scale, size=n).tolist()
        )
        self._theta: list[float] = list(self._theta0)
        self._sq_norm = dot(self._theta, self._theta)  # ‖θ‖², kept up to date by _adapt
        self._phi: list[float] = [0.0] * n  # scratch: regressor of the last _predict
        self._theta_phi = 0.0  # scratch: θᵀφ of the last _predict

    def _fill(self, u: float) -> list[float]:
        phi = self.rbf.values_list(u)
        p = 1.0
        x = u * self.poly_scale
        for _ in range(self.degree):
            p *= x
            phi.append(p)
        return phi

    def _predict(self, u: float) -> float:
        phi = self._fill(u)
        self._phi = phi
        self._theta_phi = dot(self._theta, phi)
        return self._theta_phi

    def _coefficients(self, u: float, y_hat: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        th = self._theta
        poly = list(map(mul, th[self._nr : self._np], self._scale_powers))
        # α₀ collects everything that is not a power of u(t−1): keeps y_hat = α₀ + Σα_i u^i.
        a0 = y_hat
        p = 1.0
        for a in poly:
            p *= u
            a0 -= a * p
        return (a0, *poly), tuple(th[: self._nr] + th[self._np :])

    def _adapt(self, error: float) -> None:
        self._theta, g, phi_sq = self.nlms.update_with_terms(self._theta, self._phi, error)
        if self._n_accepted % NORM_RESYNC_PERIOD:
            # ‖θ + gφ‖² = ‖θ‖² + g·(2θᵀφ + g·φᵀφ), from products the step already has: the
            # guard needs no pass over θ. A non-finite θ makes it non-finite too.
            self._sq_norm += g * (2.0 * self._theta_phi + g * phi_sq)
        else:
            self._sq_norm = dot(self._theta, self._theta)  # the rounding never drifts far

    def _params_ok(self) -> bool:
        return _norm_ok(self._sq_norm, self.guard.param_limit)

    def _reset_params(self) -> None:
        self._theta = list(self._theta0)
        self._sq_norm = dot(self._theta, self._theta)

    def _core_options(self) -> dict[str, Any]:
        return {
            "degree": self.degree,
            "mu": self.nlms.mu,
            "eps": self.nlms.eps,
            "centres": list(self.rbf.centres),
            "beta": self.rbf.beta,
            "init_scale": self.init_scale,
            "seed": self.seed,
        }

    def _state(self) -> dict[str, Any]:
        return {"theta": list(self._theta)}


class PaperUModel(_UModelCore):
    """Paper U-model (defaults = paper preset: M=3, μ=0.5, 17 centres on [−2, 2], β=0.25)."""

    name: ClassVar[str] = "paper"

    def __init__(
        self,
        *,
        degree: int = PAPER_DEGREE,
        mu: float = PAPER_MU,
        eps: float = DEFAULT_EPS,
        centres: Sequence[float] | None = None,
        beta: float = PAPER_BETA,
        init_scale: float = PAPER_INIT_SCALE,
        seed: int = 0,
        guard: GuardConfig | dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            degree=degree,
            mu=mu,
            eps=eps,
            centres=centres,
            beta=beta,
            init_scale=init_scale,
            seed=seed,
            guard=guard,
        )

    def _options(self) -> dict[str, Any]:
        return self._core_options()

    def dynamics(self) -> ModelDynamics:
        """ŷ(t) = Σ α_i x(t−1)^i + Σ w_j Φ_j(u(t−1)): no output lags, one input lag."""
        theta = self._theta
        return ModelDynamics(
            [], 0.0, [list(theta[self._nr : self._np])], self.poly_scale, [], [self._u_last],
            self.rbf, theta[: self._nr],
        )  # fmt: skip


class DynamicUModel(_ModelBase):
    """U-model whose α₀ also depends on past outputs and older inputs (Zhu & Guo's U-model),
    identified by recursive least squares so that it holds over the control horizon::

        y(t) = α₀(t) + Σ_{m=1..M} α_m(t)·u(t−1)^m,
        α₀(t) = c + Σ_{i=1..na} a_i·y(t−i) + Σ_{k=2..nb} Σ_{m=1..M} b_{k,m}·x(t−k)^m

    with x = u/u_scale. φ = [x, x², …, x^M, 1, y(t−1)…y(t−na), x(t−2), x(t−2)², …, x(t−nb)^M]
    and θ is adapted by RLS with forgetting (``ListRLS``). Why this shape (figures in
    docs/control.md):

    * output *levels*, not increments: a stable plant's steady state is then a fixed point
      of the model (consistency: a held input gives a constant output), where the
      increment form integrates every small input-map error over the horizon;
    * RLS, not NLMS: the regressor mixes levels (≈ 15 m of depth) with inputs of O(1);
      RLS is invariant to that scaling and converges in a few times n samples, NLMS crawls
      along the badly conditioned directions that decide the long-horizon response;
    * the same polynomial degree on every input lag: a static input nonlinearity (a pump)
      acts on every lag, and the controller reads the lag polynomials as one static map
      times a linear filter (see :mod:`.predictive`).

    θ starts at persistence (a₁ = 1), so the first predictions are sane. ``lag_smoothing``
    > 0 starts P from a smoothness prior on neighbouring input lags (``lag_prior``; the
    pipeline gives it with the input lags' choice).

    **Output scale.** The regression runs on normalised outputs (y − y_ref)/s, with y_ref
    the first measured level and s = ``SCALE_MARGIN`` × the largest |y − y_ref| seen when it
    last outgrew s. So θ, the prior P0 = p0·I and the error fed to RLS are the same in any
    output unit and offset (the AR coefficients are unit-free; the bias and the input
    coefficients are in units of s). When s grows, θ is re-expressed in the new units; the
    covariance starts again at p0·I while it has had fewer than ``SCALE_SETTLE`` × n
    updates (the scale is still being found, and a prior carried over from much smaller
    units would pin the input coefficients), and is re-expressed exactly afterwards (no
    jump in the learning gain of a model already in use).
    """

    name: ClassVar[str] = "dynamic"

    def __init__(
        self,
        *,
        na: int = 4,
        nb: int = 4,
        degree: int = PAPER_DEGREE,
        u_scale: float = 2.0,
        lam: float = 0.9999,
        p0: float = 1000.0,
        lag_smoothing: float = 0.0,
        seed: int = 0,
        guard: GuardConfig | dict[str, Any] | None = None,
    ) -> None:
        super().__init__(guard)
        if not (finite(lag_smoothing) and lag_smoothing >= 0.0):
            raise ValueError("lag_smoothing must be finite and >= 0")
        if int(na) != na or na < 1:
            raise ValueError("na must be an integer >= 1")
        if int(nb) != nb or nb < 1:
            raise ValueError("nb must be an integer >= 1 (lag 1 is the U-model polynomial)")
        if int(degree) != degree or degree < 1:
            raise ValueError("degree M must be an integer >= 1")
        if not (finite(u_scale) and u_scale > 0.0):
            raise ValueError("u_scale must be finite and > 0")
        if int(seed) != seed:
            raise ValueError("seed must be an integer")
        self.na = int(na)
        self.nb = int(nb)
        self.degree = int(degree)
        self.u_scale = float(u_scale)
        self.poly_scale = 1.0 / self.u_scale
        self.seed = int(seed)  # no random initialisation; kept for a uniform config
        n = self.degree * self.nb + 1 + self.na
        #: The smoothness prior's weight on neighbouring input lags (``lag_prior``; 0: none).
        self.lag_smoothing = float(lag_smoothing)
        prior = None
        if self.lag_smoothing > 0.0 and self.nb > 1:
            prior = smooth_lag_prior(n, float(p0), self.lag_smoothing, self._lag_chains())
        self.rls = ListRLS(n, lam, p0, prior=prior)
        self._ia = self.degree + 1  # index of a_1 (after the lag-1 powers and the bias)
        self._theta0: tuple[float, ...] = tuple(1.0 if i == self._ia else 0.0 for i in range(n))
        self._theta: list[float] = list(self._theta0)
        self._phi: list[float] = [0.0] * n  # scratch: regressor of the last _predict
        self._levels: list[float] = []  # y(t), y(t−1), …
        self._inputs: list[float] = []  # u(t−1), u(t−2), …
        self._tail: list[float] = []  # φ after the lag-1 powers
        self._primed = False  # the output history holds a measured level
        self._y_ref = 0.0  # the first measured level: regressors are taken relative to it
        self._y_scale = 0.0  # s of the class docstring (0: no deviation seen yet)
        self._inv_scale = 1.0  # 1/s (1 while s is 0: every deviation is then exactly 0)
        self._updates = 0  # RLS updates since the covariance last started at p0·I
        # θ and P before the last update, for one sample (``undo_last_update``): two spare
        # buffers copied into and swapped, so that a sample allocates no new lists (with a
        # fleet of models, per-sample copies keep the garbage collector's young generation
        # full: docs/benchmarks.md, "A fleet").
        self._spare_theta: list[float] = [0.0] * n
        self._spare_p = self.rls.blank()
        self._can_undo = False
        self._reset_history()

    def _lag_chains(self) -> list[list[int]]:
        """θ's indices of each power's input lags 1 … nb, in lag order."""
        m = self.degree
        start = m + 1 + self.na
        return [[power] + [start + k * m + power for k in range(self.nb - 1)] for power in range(m)]

    def _powers(self, u: float) -> list[float]:
        x = u * self.poly_scale
        out = []
        p = 1.0
        for _ in range(self.degree):
            p *= x
            out.append(p)
        return out

    def _predict(self, u: float) -> float:
        phi = self._powers(u)
        phi += self._tail
        self._phi = phi
        return self._y_ref + dot(self._theta, phi) * self._unit()

    def _unit(self) -> float:
        """The output units of one normalised unit (s, or 1 before any deviation)."""
        return self._y_scale if self._y_scale > 0.0 else 1.0

    def _coefficients(self, u: float, y_hat: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        th = self._theta
        m = self.degree
        unit = self._unit()
        poly = []
        scale = unit
        for i in range(m):
            scale *= self.poly_scale
            poly.append(th[i] * scale)
        a0 = y_hat
        p = 1.0
        for a in poly:
            p *= u
            a0 -= a * p
        ia, ib = self._ia, self._ia + self.na
        weights = [th[m] * unit]
        weights += th[ia:ib]
        weights += [v * unit for v in th[ib:]]
        return (a0, *poly), tuple(weights)

    def _adapt(self, error: float) -> None:
        # Before the first level is known the regressor holds no measured output: the
        # error says nothing about θ (and would bury the bias under the output's level).
        if self._primed:
            # Kept for one sample: the pipeline undoes an update learnt from readings that
            # turn out, on the next sample, to have been served ahead of time.
            self._spare_theta[:] = self._theta
            before = self.rls.p
            self._can_undo = True
            # The new P goes into the spare buffer; the one before the update becomes the
            # spare (no copy of P a sample).
            self.rls.update(self._theta, self._phi, error * self._inv_scale, self._spare_p)
            self._spare_p = before
            self._updates += 1

    def undo_last_update(self) -> bool:
        if not self._can_undo:
            return False
        self._theta, self._spare_theta = self._spare_theta, self._theta
        self.rls.p, self._spare_p = self._spare_p, self.rls.p
        self._can_undo = False
        self._updates = max(self._updates - 1, 0)
        return True

    def _params_ok(self) -> bool:
        return _norm_ok(dot(self._theta, self._theta), self.guard.param_limit)

    def _reset_params(self) -> None:
        self._theta = list(self._theta0)
        self.rls.reset()
        self._updates = 0

    def _rescale(self, deviation: float) -> None:
        """|y − y_ref| outgrew s: s becomes ``SCALE_MARGIN`` × ``deviation`` and θ (and P)
        are re-expressed in the new units (see the class docstring)."""
        new = SCALE_MARGIN * deviation
        ratio = self._y_scale / new  # 0 before any deviation: θ's output terms are 0 then
        self._y_scale = new
        self._inv_scale = 1.0 / new
        self._can_undo = False  # an update from before the rescale cannot be undone after it
        ia, ib = self._ia, self._ia + self.na
        factors = [1.0 if ia <= i < ib else ratio for i in range(len(self._theta))]
        self._theta = [v * f for v, f in zip(self._theta, factors, strict=True)]
        if self._updates < SCALE_SETTLE * self.rls.n:
            self.rls.reset()
            self._updates = 0
            return
        self.rls.scale(factors)

    def _lags(self) -> int:
        return max(self.na - 1, self.nb - 1)

    def _push(self, u: float, y: float) -> None:
        if self._primed:
            self._levels = [y, *self._levels[:-1]]
        else:
            # The first level fills the whole history: with θ at persistence the model
            # starts from a steady state, not from a jump from 0.
            self._levels = [y] * self.na
            self._y_ref = y
            self._primed = True
        deviation = abs(y - self._y_ref)
        if deviation > self._y_scale:
            self._rescale(deviation)
        self._inputs = [u, *self._inputs[:-1]]
        self._rebuild_tail()

    def _rebuild_tail(self) -> None:
        tail = [1.0]
        ref = self._y_ref
        inv = self._inv_scale
        tail += [(v - ref) * inv for v in self._levels]
        for past in self._inputs[: self.nb - 1]:
            tail += self._powers(past)
        self._tail = tail

    def _reset_history(self) -> None:
        self._primed = False
        self._y_ref = 0.0
        self._y_scale = 0.0
        self._inv_scale = 1.0
        self._levels = [0.0] * self.na
        # u(t−1) … u(t−nb): the regressor uses the first nb − 1 (lags 2..nb of the next
        # sample); the controller's internal model all of them.
        self._inputs = [0.0] * self.nb
        self._rebuild_tail()

    def dynamics(self) -> ModelDynamics:
        """This instant's multi-step map (see :mod:`.dynamics`)."""
        th = self._theta
        m, na, nb = self.degree, self.na, self.nb
        unit = self._unit()
        lag_polys = [[v * unit for v in th[:m]]]
        start = m + 1 + na
        for k in range(nb - 1):
            lag_polys.append([v * unit for v in th[start + k * m : start + (k + 1) * m]])
        ar = list(th[m + 1 : m + 1 + na])
        # (y − y_ref)/s = c + Σ a_i (y(t−i) − y_ref)/s + … ⇒ bias = s·c + y_ref·(1 − Σ a_i).
        bias = 1.0
        for a in ar:
            bias -= a
        bias = th[m] * unit + self._y_ref * bias
        return ModelDynamics(
            ar,
            bias,
            lag_polys,
            self.poly_scale,
            list(self._levels),
            list(self._inputs),
        )

    def _options(self) -> dict[str, Any]:
        return {
            "na": self.na,
            "nb": self.nb,
            "degree": self.degree,
            "u_scale": self.u_scale,
            "lam": self.rls.lam,
            "p0": self.rls.p0,
            "lag_smoothing": self.lag_smoothing,
            "seed": self.seed,
        }

    def _state(self) -> dict[str, Any]:
        return {
            "theta": list(self._theta),
            "output_scale": self._y_scale,
            "history": {"outputs": list(self._levels), "inputs": list(self._inputs)},
        }


class PersistenceModel(_ModelBase):
    """ŷ(t) = y(t−1) (0 before the first sample). Nothing to adapt, so it never diverges."""

    name: ClassVar[str] = "persistence"
    _checks_error: ClassVar[bool] = False  # a level change is not a divergence here

    def __init__(self, *, guard: GuardConfig | dict[str, Any] | None = None) -> None:
        super().__init__(guard)

    def _predict(self, u: float) -> float:
        return self._y_last

    def _coefficients(self, u: float, y_hat: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (y_hat,), ()

    def _adapt(self, error: float) -> None:
        pass

    def _options(self) -> dict[str, Any]:
        return {}


class RlsArxModel(_ModelBase):
    """ARX(na, nb) with bias identified by RLS (forgetting λ, trace-bounded covariance)."""

    name: ClassVar[str] = "rls-arx"

    def __init__(
        self,
        *,
        na: int = 3,
        nb: int = 3,
        lam: float = 0.995,
        p0: float = 100.0,
        trace_max: float | None = None,
        guard: GuardConfig | dict[str, Any] | None = None,
    ) -> None:
        super().__init__(guard)
        if int(na) != na or na < 0:
            raise ValueError("na must be an integer >= 0")
        if int(nb) != nb or nb < 1:
            raise ValueError("nb must be an integer >= 1")
        self.na = int(na)
        self.nb = int(nb)
        n = self.na + self.nb + 1
        self.rls = RLS(n, lam, p0, trace_max)
        self._trace_max_opt = None if trace_max is None else float(trace_max)
        # φ = [y(t−1..t−na), u(t−1), u(t−2..t−nb), 1]; the u(t−1) slot is scratch.
        self._theta = np.zeros(n)
        self._phi = np.zeros(n)
        self._phi[-1] = 1.0
        self._iu = self.na

    def _predict(self, u: float) -> float:
        self._phi[self._iu] = u
        return float(np.dot(self._theta, self._phi))

    def _coefficients(self, u: float, y_hat: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        th = self._theta.tolist()
        b1 = th[self._iu]
        return (y_hat - b1 * u, b1), tuple(th)

    def _adapt(self, error: float) -> None:
        self.rls.update_(self._theta, self._phi, error)

    def _params_ok(self) -> bool:
        return _norm_ok(float(np.dot(self._theta, self._theta)), self.guard.param_limit)

    def _reset_params(self) -> None:
        self._theta[:] = 0.0
        self.rls.reset()

    def _lags(self) -> int:
        return max(self.na - 1, self.nb - 1)

    def _push(self, u: float, y: float) -> None:
        phi = self._phi
        na, iu = self.na, self._iu
        if na:
            phi[1:na] = phi[: na - 1]
            phi[0] = y
        if self.nb > 1:
            phi[iu + 1 : iu + self.nb] = phi[iu : iu + self.nb - 1]
            phi[iu + 1] = u

    def _reset_history(self) -> None:
        self._phi[:-1] = 0.0

    def _options(self) -> dict[str, Any]:
        return {
            "na": self.na,
            "nb": self.nb,
            "lam": self.rls.lam,
            "p0": self.rls.p0,
            "trace_max": self._trace_max_opt,
        }

    def _state(self) -> dict[str, Any]:
        hist = self._phi.tolist()
        return {
            "theta": self._theta.tolist(),
            "p": self.rls.p.tolist(),
            "history": hist[: self.na] + hist[self.na + 1 : -1],
        }


_REGISTRY: dict[str, type[_ModelBase]] = {
    "paper": PaperUModel,
    "dynamic": DynamicUModel,
    "rls-arx": RlsArxModel,
    "persistence": PersistenceModel,
}


def build_model(name: str, **options: Any) -> OneStepModel:
    """Construct a model by name (one of ``MODEL_NAMES``); unknown options raise TypeError."""
    try:
        cls = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown model {name!r}; expected one of {MODEL_NAMES}") from None
    model: OneStepModel = cls(**options)
    return model


def option_names(name: str) -> frozenset[str]:
    """The options ``build_model(name, ...)`` takes: the keys of its default model's
    ``config()``, which lists every option (``from_config`` rebuilds from it)."""
    return frozenset(build_model(name).config()) - {"name"}


def from_config(cfg: dict[str, Any]) -> OneStepModel:
    """Rebuild a fresh model from ``model.config()`` (bit-identical behaviour)."""
    opts = dict(cfg)
    name = opts.pop("name")
    return build_model(name, **opts)


def paper_preset(seed: int = 0) -> PaperUModel:
    """Abbasi et al. 2015 preset: M=3, μ=0.5, 17 centres on [−2, 2], β=0.25, θ₀~U(±0.1)."""
    return PaperUModel(
        degree=PAPER_DEGREE,
        mu=PAPER_MU,
        centres=evenly_spaced_centres(PAPER_N_CENTRES, *PAPER_CENTRE_RANGE),
        beta=PAPER_BETA,
        init_scale=PAPER_INIT_SCALE,
        seed=seed,
    )
