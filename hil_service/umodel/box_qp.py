"""A small dense box-constrained QP, solved exactly: the predictive inverse's plan over
its input blocks (at most ``max_blocks`` variables, solved once per sample)."""

from __future__ import annotations

__all__ = ["solve_box_qp", "solve_linear"]


def solve_linear(a: list[list[float]], b: list[float]) -> list[float] | None:
    """x with a·x = b by Gaussian elimination with partial pivoting (a and b are
    consumed); None when a is singular to working precision."""
    k = len(b)
    for col in range(k):
        piv = col
        for r in range(col + 1, k):
            if abs(a[r][col]) > abs(a[piv][col]):
                piv = r
        if not abs(a[piv][col]) > 1e-300:
            return None
        if piv != col:
            a[col], a[piv] = a[piv], a[col]
            b[col], b[piv] = b[piv], b[col]
        pivot_row = a[col]
        for r in range(col + 1, k):
            row = a[r]
            factor = row[col] / pivot_row[col]
            if factor != 0.0:
                for c in range(col, k):
                    row[c] -= factor * pivot_row[c]
                b[r] -= factor * b[col]
    x = [0.0] * k
    for r in range(k - 1, -1, -1):
        acc = b[r]
        row = a[r]
        for c in range(r + 1, k):
            acc -= row[c] * x[c]
        x[r] = acc / row[r]
    return x


def solve_box_qp(
    h: list[list[float]],
    f: list[float],
    lo: list[float],
    hi: list[float],
    warm: list[int] | None = None,
) -> tuple[list[float], list[int]]:
    """argmin ½ xᵀHx + fᵀx over lo ≤ x ≤ hi (H symmetric positive definite): a primal
    active-set method (Nocedal & Wright, §16.5) from the centre of the box. Each
    iteration solves for the free variables, steps until a bound blocks, and releases
    the bound whose multiplier has the wrong sign once no step is left; finite, exact to
    rounding, deterministic. Returns the best point reached if the iteration limit hits,
    and the working set (0 free, −1 at lo, +1 at hi): given back as ``warm`` on the next
    sample, the last plan's active bounds, it usually leaves one or two iterations."""
    n = len(f)
    state = [0] * n
    if warm is not None and len(warm) == n:
        state = list(warm)
    x = [lo[i] if state[i] < 0 else hi[i] if state[i] > 0 else 0.5 * (lo[i] + hi[i])
         for i in range(n)]  # fmt: skip
    for _ in range(8 * n + 8):
        grad = [0.0] * n
        for i in range(n):
            acc = f[i]
            row = h[i]
            for j in range(n):
                acc += row[j] * x[j]
            grad[i] = acc
        free = [i for i in range(n) if state[i] == 0]
        step = [0.0] * n
        moved = False
        if free:
            sol = solve_linear(
                [[h[i][j] for j in free] for i in free], [-grad[i] for i in free]
            )
            if sol is None:
                return x, state
            for r in range(len(free)):
                step[free[r]] = sol[r]
            scale = 0.0
            for i in range(n):
                scale = max(scale, abs(x[i]), hi[i] - lo[i])
            moved = any(abs(v) > 1e-14 * (1.0 + scale) for v in step)
        if moved:
            alpha = 1.0
            block = -1
            for i in free:
                v = step[i]
                if v < 0.0 and x[i] + v < lo[i]:
                    t = (lo[i] - x[i]) / v
                    if t < alpha:
                        alpha, block = t, i
                elif v > 0.0 and x[i] + v > hi[i]:
                    t = (hi[i] - x[i]) / v
                    if t < alpha:
                        alpha, block = t, i
            for i in free:
                x[i] += alpha * step[i]
            if block >= 0:
                if step[block] < 0.0:
                    x[block], state[block] = lo[block], -1
                else:
                    x[block], state[block] = hi[block], 1
            continue
        # No step left on this face: release the bound that most wants to move inward.
        worst = -1
        worst_value = 0.0
        for i in range(n):
            # At lo the gradient must be ≥ 0, at hi ≤ 0 (multipliers of the right sign).
            g = grad[i] if state[i] == -1 else -grad[i] if state[i] == 1 else 0.0
            if g < worst_value:
                worst, worst_value = i, g
        if worst < 0:
            return x, state
        state[worst] = 0
    return x, state
