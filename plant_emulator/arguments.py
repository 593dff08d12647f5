"""What ``emulate``'s flags configure, built once for the single vehicle and the fleet alike;
and the argparse types of the numeric flags of ``emulate``, ``demo``, ``experiment`` and
``campaign``.

``float("nan")``, ``float("inf")`` and negative numbers all parse, and a NaN compares false
with every limit, so a flag typed ``float`` lets a NaN duration, timeout or rate through to
crash deep in a run or to switch a check off silently. These types refuse such a value
where it enters, in argparse's one-line error naming the flag (exit 2).

The emulator's modules are imported where the settings are built, not here: ``campaign``
takes these types for a parser that is built without importing the numerics (python-control
and scipy, two seconds).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    from plant_emulator.autopilot import AutopilotConfig
    from protocols.mapping import TelemetryMapping

Number = TypeVar("Number", int, float)


def _checked(
    text: str, parse: Callable[[str], Number], wanted: str, ok: Callable[[Number], bool]
) -> Number:
    """``text`` parsed, if it is what ``ok`` accepts; else argparse's error saying ``wanted``."""
    refused = argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}")
    try:
        value = parse(text)
    except ValueError:
        raise refused from None
    if not ok(value):
        raise refused
    return value


def positive_float(text: str) -> float:
    """A finite number > 0: a duration, speed, timeout or rate limit."""
    return _checked(text, float, "a finite number > 0", lambda v: math.isfinite(v) and v > 0)


def non_negative_float(text: str) -> float:
    """A finite number ≥ 0: a depth below the surface, a rate where 0 turns it off."""
    return _checked(text, float, "a finite number >= 0", lambda v: math.isfinite(v) and v >= 0)


def positive_int(text: str) -> int:
    """An integer ≥ 1: a count of steps or samples."""
    return _checked(text, int, "an integer >= 1", lambda v: v >= 1)


def non_negative_int(text: str) -> int:
    """An integer ≥ 0: a seed (numpy's generators take no negative one), a plant step, an
    every-Nth where 0 means never."""
    return _checked(text, int, "an integer >= 0", lambda v: v >= 0)


def autopilot_config(args: argparse.Namespace, system_id: int) -> AutopilotConfig:
    """The autopilot's settings from the flags, for the vehicle with ``system_id``."""
    from plant_emulator.autopilot import AutopilotConfig
    from protocols.signing import load_key

    return AutopilotConfig(
        system_id=system_id,
        speed=args.speed,
        duration=args.duration,
        command_timeout=args.command_timeout,
        fallback=args.fallback,
        signing_key=None if args.signing_key is None else load_key(args.signing_key),
        accept_unsigned_non_commands=args.accept_unsigned_non_commands,
    )


def telemetry_mapping(args: argparse.Namespace) -> TelemetryMapping:
    """How telemetry is encoded: the water and surface pressure of the depth conversion and
    the inputs' full scale."""
    from protocols.mapping import TelemetryMapping
    from protocols.units import InputScale, PressureDepth

    return TelemetryMapping(
        pressure=PressureDepth(args.water_density, args.surface_pressure),
        inputs=InputScale(args.full_scale),
    )
