"""A U-model's multi-step map, as each model exposes it to the predictive controller.

Every U-model of the package is, at a given instant, linear in its past outputs and a sum of
static maps of each input lag::

    y(t) = bias + Σ_{i=1..na} c_i·y(t−i) + Σ_{L=1..nb} P_L(u(t−L)) [+ RBF(u(t−1))]

with P_L a polynomial without constant term in x = poly_scale·u (the paper model: na = 0,
nb = 1, and its RBF layer on lag 1). ``ModelDynamics`` is that snapshot (coefficients and
the histories they act on); the controller simulates it over its horizon and inverts it.
The model builds it (``dynamics()``), so nothing outside a model reads its private state.
"""

from __future__ import annotations

from collections.abc import Sequence

from librt.vecs import append, vec
from mypy_extensions import i64

from .finite import all_finite, finite
from .rbf import GaussianRBF

__all__ = ["ModelDynamics", "StaticMap"]


class StaticMap:
    """w = N(u) = Σ_m p_m·x^m + g·Σ_j w_j Φ_j(u), x = scale·u; value and slope by Horner.

    The U-model's input nonlinearity, the thing the controller's inverse step root-solves.
    """

    __slots__ = ("poly", "rbf", "rbf_gain", "rbf_weights", "scale")

    def __init__(
        self,
        poly: Sequence[float],
        scale: float,
        rbf: GaussianRBF | None = None,
        rbf_weights: Sequence[float] = (),
        rbf_gain: float = 1.0,
    ) -> None:
        self.poly: list[float] = list(poly)  # p_1 … p_M
        self.scale = scale
        self.rbf = rbf
        self.rbf_weights: list[float] = list(rbf_weights)
        self.rbf_gain = rbf_gain

    def evaluate(self, u: float) -> tuple[float, float]:
        """(N(u), dN/du)."""
        x = u * self.scale
        q = 0.0
        dq = 0.0
        poly = self.poly
        for i in range(len(poly) - 1, -1, -1):
            dq = dq * x + q
            q = q * x + poly[i]
        value = q * x
        slope = (dq * x + q) * self.scale
        rbf = self.rbf
        if rbf is not None:
            s, ds = rbf.weighted(u, self.rbf_weights)
            value += self.rbf_gain * s
            slope += self.rbf_gain * ds
        return value, slope

    def value(self, u: float) -> float:
        return self.evaluate(u)[0]

    def derivative(self, u: float) -> float:
        return self.evaluate(u)[1]


class ModelDynamics:
    """One instant of a U-model: coefficients and histories (see the module docstring).

    ``outputs`` = y(k), y(k−1), … (at least na values); ``inputs`` = u(k−1), u(k−2), …
    (nb values: the input that produced y(k) and the older ones);
    ``lag_polys[L−1]`` = P_L's coefficients of x, x², …
    """

    __slots__ = ("ar", "bias", "inputs", "lag_polys", "outputs", "poly_scale", "rbf", "rbf_weights")

    def __init__(
        self,
        ar: list[float],
        bias: float,
        lag_polys: list[list[float]],
        poly_scale: float,
        outputs: list[float],
        inputs: list[float],
        rbf: GaussianRBF | None = None,
        rbf_weights: Sequence[float] = (),
    ) -> None:
        self.ar = ar
        self.bias = bias
        self.lag_polys = lag_polys
        self.poly_scale = poly_scale
        self.outputs = outputs
        self.inputs = inputs
        self.rbf = rbf
        self.rbf_weights: list[float] = list(rbf_weights)

    def ar_gain(self) -> float:
        """1 − Σ c_i: what divides the forcing in the steady state, y = (bias + Σ_L P_L(u)) /
        (1 − Σ c_i) with every input lag held at u (0: an integrator, no steady state)."""
        gain = 1.0
        for a in self.ar:
            gain -= a
        return gain

    def lag_value(self, lag: int, u: float) -> float:
        """P_L(u) (plus the RBF term on lag 1)."""
        x = u * self.poly_scale
        poly = self.lag_polys[lag - 1]
        q = 0.0
        for i in range(len(poly) - 1, -1, -1):
            q = q * x + poly[i]
        value = q * x
        if lag == 1 and self.rbf is not None:
            value += self.rbf.weighted(u, self.rbf_weights)[0]
        return value

    def simulate_held(
        self, u_now: float, horizon: int, forcing: float, outputs: list[float] | None = None
    ) -> list[float]:
        """ŷ(k+1 … k+horizon) with u(k), u(k+1), … all equal to ``u_now`` and ``forcing``
        added to the bias, from ``outputs`` (y(k), y(k−1), …; default: the measured ones).
        Non-finite values are the caller's to screen."""
        na = len(self.ar)
        nb = len(self.lag_polys)
        ar = self.ar
        # y history, newest first, padded with the oldest known value.
        start = self.outputs if outputs is None else outputs
        past = list(start[:na]) if na else []
        while len(past) < na:
            past.append(past[-1] if past else 0.0)
        # Contribution of each input lag for step j: the held value for L ≤ j, else history.
        held = [self.lag_value(lag, u_now) for lag in range(1, nb + 1)]
        history = [
            self.lag_value(lag, self.inputs[lag - j - 1] if lag - j - 1 < len(self.inputs) else 0.0)
            for j in range(1, nb)
            for lag in range(j + 1, nb + 1)
        ]
        # history is laid out per step j = 1..nb−1: lags j+1..nb. From step nb on every
        # lag sees the held input: one constant.
        held_sum = 0.0
        for v in held:
            held_sum += v
        # Outputs oldest first, the predictions appended: y(k+j−i) is seq[len − i].
        seq = [past[na - 1 - i] for i in range(na)]
        out: list[float] = []
        base = self.bias + forcing
        pos = 0
        for j in range(1, horizon + 1):
            acc = base
            end = len(seq)
            for i in range(na):
                acc += ar[i] * seq[end - 1 - i]
            if j < nb:
                for lag in range(1, nb + 1):
                    if lag <= j:
                        acc += held[lag - 1]
                    else:
                        acc += history[pos + lag - j - 1]
                pos += nb - j
            else:
                acc += held_sum
            out.append(acc)
            seq.append(acc)
        return out

    def input_forcing(self, u_now: float, count: int) -> tuple[list[float], float]:
        """The non-autoregressive part of ŷ(k+l) with u(k), u(k+1), … held at ``u_now``:
        bias + Σ_L P_L(u(k+l−L)) for l = 1 … ``count``, and its constant value from l = nb
        on (every lag then sees the held input). ``simulate_held`` is this run through
        1/A(q); the controller does that in closed form at its cost points."""
        nb = len(self.lag_polys)
        held = [self.lag_value(lag, u_now) for lag in range(1, nb + 1)]
        constant = self.bias
        for v in held:
            constant += v
        terms: list[float] = []
        inputs = self.inputs
        for step in range(1, count + 1):
            if step >= nb:
                terms.append(constant)
                continue
            acc = self.bias
            for lag in range(1, nb + 1):
                if lag <= step:
                    acc += held[lag - 1]
                else:
                    index = lag - step - 1
                    acc += self.lag_value(lag, inputs[index] if index < len(inputs) else 0.0)
            terms.append(acc)
        return terms, constant

    def one_step(self, outputs: list[float]) -> float:
        """ŷ(k) from ``outputs`` = y(k−1), y(k−2), … and this snapshot's inputs u(k−1), …
        (the input history already holds the input that produced y(k)): one step of the
        controller's internal model, which runs on its own outputs."""
        acc = self.bias
        na = len(self.ar)
        for i in range(min(na, len(outputs))):
            acc += self.ar[i] * outputs[i]
        inputs = self.inputs
        for lag in range(1, len(self.lag_polys) + 1):
            if lag - 1 < len(inputs):
                acc += self.lag_value(lag, inputs[lag - 1])
        return acc

    def advance(self, u_prev: float) -> float:
        """Free run: ŷ of the next sample from u_prev = the input one step before it and
        this snapshot's own histories, which then take ŷ and u_prev in (the coefficients
        stay frozen). The health report's multi-step accuracy runs this."""
        ar = self.ar
        na = len(ar)
        acc = self.bias
        outputs = self.outputs
        for i in range(min(na, len(outputs))):
            acc += ar[i] * outputs[i]
        nb = len(self.lag_polys)
        acc += self.lag_value(1, u_prev)
        inputs = self.inputs
        for lag in range(2, min(nb, len(inputs) + 1) + 1):
            acc += self.lag_value(lag, inputs[lag - 2])
        if na:
            self.outputs = [acc, *outputs[: na - 1]]
        self.inputs = [u_prev, *inputs[: nb - 1]]
        return acc

    def free_run(
        self, outputs: list[float], inputs: list[float], start: int, end: int
    ) -> list[float]:
        """ŷ(start + 1 … end) run freely from the measured ``outputs`` up to ``start`` on the
        recorded ``inputs`` (``inputs[j]``: the input one step before ``outputs[j]``): the
        sums of ``advance``, in its order, from a snapshot whose histories are those
        records at ``start``. Needs start ≥ max(na, nb) − 1.

        ``lag_value``'s Horner sums are written out here, on unboxed copies of the AR
        coefficients, the lags' polynomials, the inputs the run reads and the run itself
        (``vec[float]``): the horizon test runs segments of hundreds of steps, each reading
        every lag's coefficients and nb inputs; the arithmetic and its order are
        ``lag_value``'s and ``advance``'s."""
        ar = self.ar
        lag_polys = self.lag_polys
        na: i64 = len(ar)
        nb: i64 = len(lag_polys)
        first: i64 = start
        last_step: i64 = end
        if first < max(na, nb) - 1:
            raise ValueError(f"a free run from {start} needs {max(na, nb) - 1} earlier samples")
        a = vec[float](ar)
        polys = [vec[float](poly) for poly in lag_polys]
        oldest: i64 = first + 2 - nb  # the oldest input the run reads
        us = vec[float](inputs[oldest : last_step + 1])
        run = vec[float](outputs[first - na + 1 : first + 1])  # oldest first, ŷ appended
        bias = self.bias
        scale = self.poly_scale
        rbf = self.rbf
        predictions: list[float] = []
        for j in range(first + 1, last_step + 1):
            acc = bias
            last = len(run) - 1
            for i in range(na):
                acc += a[i] * run[last - i]
            for lag in range(1, nb + 1):
                u = us[j - lag + 1 - oldest]
                x = u * scale
                poly = polys[lag - 1]
                q = 0.0
                for k in range(len(poly) - 1, -1, -1):
                    q = q * x + poly[k]
                value = q * x
                if lag == 1 and rbf is not None:
                    value += rbf.weighted(u, self.rbf_weights)[0]
                acc += value
            if na:
                run = append(run, acc)
            predictions.append(acc)
        return predictions

    def is_finite(self) -> bool:
        if not (
            finite(self.bias)
            and all_finite(self.ar)
            and all_finite(self.outputs)
            and all_finite(self.inputs)
        ):
            return False
        return all(all_finite(poly) for poly in self.lag_polys)
