"""``finite(x)``: ``math.isfinite`` for a float, as compiled code can call it cheaply, and
``all_finite`` for a list of them.

mypyc has no primitive for ``math.isfinite``: compiled, each call looks the function up
on the module and calls it through Python with the float boxed, about 35 ns, and the
commanding path makes some seventy a sample. x − x is 0 for a finite x and NaN for ±inf
and NaN, so the test is a float subtraction and a comparison (docs/benchmarks.md, "With
the controller commanding").
"""

from __future__ import annotations


def finite(x: float) -> bool:
    """True for a finite float, False for ±inf and NaN (as ``math.isfinite``)."""
    return x - x == 0.0


def all_finite(values: list[float]) -> bool:
    """Every value finite (a typed list: compiled, the floats are read unboxed)."""
    return all(finite(v) for v in values)
