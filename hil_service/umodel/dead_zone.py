"""An input dead zone of half-width δ taken out ahead of the identified model: the model
and the plan see ``narrow(u)``, the part of an input beyond the zone, and a plan's input v
is sent as ``widen(v)``, which steps over the zone (docs/control.md, "An input dead zone,
chosen from the record"). Compiled with the pipeline, which calls both on every sample."""

from __future__ import annotations

import math

from .finite import finite


def narrow(u: float, width: float) -> float:
    """The part of ``u`` beyond a dead zone of half-width ``width``: what moves the plant
    (0 inside the zone; NaN stays NaN)."""
    if width == 0.0:
        return u
    return math.copysign(max(abs(u) - width, 0.0), u)


def widen(v: float, width: float) -> float:
    """The input whose part beyond the zone is ``v``: 0 stays 0 (the neutral input), any
    other value steps over the zone; ``narrow(widen(v)) == v``."""
    if width == 0.0 or v == 0.0 or not finite(v):
        return v
    return v + math.copysign(width, v)
