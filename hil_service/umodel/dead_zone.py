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


def widen_beside(v: float, width: float, applied: float, band: float) -> float:
    """``widen(v)``, except that a ``v`` of the other sign than the ``applied`` input and
    smaller than ``band`` is sent as the zone's edge on the applied input's side (its part
    beyond the zone is 0 either way).

    Across the zone the command jumps by twice its width, and the width is a choice from a
    grid (``structure.DEAD_ZONE_CANDIDATES``): a plan whose steady state lies at the zone's
    edge would otherwise send the input across the zone and back as its estimate of that
    steady state wanders by less than the width's own uncertainty, each crossing a kick
    wherever the true zone is narrower. A plan that needs the other side goes on asking
    for it (its disturbance estimate integrates the error the edge leaves) until its
    input is beyond the band."""
    if width == 0.0 or not (finite(v) and finite(applied)) or applied == 0.0:
        return widen(v, width)
    if v * applied <= 0.0 and abs(v) < band:
        return math.copysign(width, applied)
    return widen(v, width)
