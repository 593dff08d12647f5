"""A small dense box-constrained QP, solved exactly: the predictive inverse's plan over
its input blocks (at most ``max_blocks`` variables, solved once per sample).

Matrices are row-major ``vec[float]`` (``librt``, mypyc's runtime library): compiled, their
elements are C doubles, where lists of lists box and unbox every value an elimination
touches. ``flat_matrix`` makes one from rows. Sizes and indices are ``i64``: compiled,
their arithmetic is then on machine integers, not on Python ints.
"""

from __future__ import annotations

from librt.vecs import vec
from mypy_extensions import i64

__all__ = ["flat_matrix", "solve_box_qp", "solve_linear"]


def flat_matrix(rows: list[list[float]]) -> vec[float]:
    """A square matrix given as rows, row-major in one vector."""
    return vec[float]([float(v) for row in rows for v in row])


def solve_linear(a: vec[float], b: vec[float], k: i64) -> vec[float] | None:
    """x with a·x = b by Gaussian elimination with partial pivoting (a, k × k row-major,
    and b are consumed); None when a is singular to working precision."""
    for col in range(k):
        piv = col
        for r in range(col + 1, k):
            if abs(a[r * k + col]) > abs(a[piv * k + col]):
                piv = r
        if not abs(a[piv * k + col]) > 1e-300:
            return None
        if piv != col:
            for c in range(k):
                a[col * k + c], a[piv * k + c] = a[piv * k + c], a[col * k + c]
            b[col], b[piv] = b[piv], b[col]
        top = col * k
        for r in range(col + 1, k):
            base = r * k
            factor = a[base + col] / a[top + col]
            if factor != 0.0:
                for c in range(col, k):
                    a[base + c] -= factor * a[top + c]
                b[r] -= factor * b[col]
    x = vec[float]([0.0] * k)
    for r in range(k - 1, -1, -1):
        acc = b[r]
        base = r * k
        for c in range(r + 1, k):
            acc -= a[base + c] * x[c]
        x[r] = acc / a[base + r]
    return x


def solve_box_qp(
    h: vec[float],
    f: list[float],
    lo: list[float],
    hi: list[float],
    warm: list[int] | None = None,
) -> tuple[list[float], list[int]]:
    """argmin ½ xᵀHx + fᵀx over lo ≤ x ≤ hi (H symmetric positive definite, n × n
    row-major with n = len(f)): a primal active-set method (Nocedal & Wright, §16.5)
    from the centre of the box. Each iteration solves for the free variables, steps until
    a bound blocks, and releases the bound whose multiplier has the wrong sign once no
    step is left; finite, exact to rounding, deterministic. Returns the best point
    reached if the iteration limit hits, and the working set (0 free, −1 at lo, +1 at
    hi): given back as ``warm`` on the next sample, the last plan's active bounds, it
    usually leaves one or two iterations."""
    n: i64 = len(f)
    linear = vec[float](f)
    low = vec[float](lo)
    high = vec[float](hi)
    state = [0] * n
    if warm is not None and len(warm) == n:
        state = list(warm)
    x = vec[float]([0.0] * n)
    for i in range(n):
        x[i] = low[i] if state[i] < 0 else high[i] if state[i] > 0 else 0.5 * (low[i] + high[i])
    for _ in range(8 * n + 8):
        grad = vec[float]([0.0] * n)
        for i in range(n):
            acc = linear[i]
            base = i * n
            for j in range(n):
                acc += h[base + j] * x[j]
            grad[i] = acc
        free = vec[i64]([i for i in range(n) if state[i] == 0])
        step = vec[float]([0.0] * n)
        moved = False
        m: i64 = len(free)
        if m:
            sub = vec[float]([0.0] * (m * m))
            rhs = vec[float]([0.0] * m)
            for r in range(m):
                base = free[r] * n
                for c in range(m):
                    sub[r * m + c] = h[base + free[c]]
                rhs[r] = -grad[free[r]]
            sol = solve_linear(sub, rhs, m)
            if sol is None:
                return list(x), state
            for r in range(m):
                step[free[r]] = sol[r]
            scale = 0.0  # max(scale, |x_i|, hi_i − lo_i) over i, without boxing the floats
            for i in range(n):
                size = abs(x[i])
                if size > scale:
                    scale = size
                width = high[i] - low[i]
                if width > scale:
                    scale = width
            limit = 1e-14 * (1.0 + scale)
            for i in range(n):
                if abs(step[i]) > limit:
                    moved = True
                    break
        if moved:
            alpha = 1.0
            block: i64 = -1
            for i in free:
                v = step[i]
                if v < 0.0 and x[i] + v < low[i]:
                    t = (low[i] - x[i]) / v
                    if t < alpha:
                        alpha, block = t, i
                elif v > 0.0 and x[i] + v > high[i]:
                    t = (high[i] - x[i]) / v
                    if t < alpha:
                        alpha, block = t, i
            for i in free:
                x[i] += alpha * step[i]
            if block >= 0:
                if step[block] < 0.0:
                    x[block], state[block] = low[block], -1
                else:
                    x[block], state[block] = high[block], 1
            continue
        # No step left on this face: release the bound that most wants to move inward.
        worst: i64 = -1
        worst_value = 0.0
        for i in range(n):
            # At lo the gradient must be ≥ 0, at hi ≤ 0 (multipliers of the right sign).
            g = grad[i] if state[i] == -1 else -grad[i] if state[i] == 1 else 0.0
            if g < worst_value:
                worst, worst_value = i, g
        if worst < 0:
            return list(x), state
        state[worst] = 0
    return list(x), state
