"""argparse types of numeric flags, shared by the emulator's verbs and the service's.

``float("nan")``, ``float("inf")`` and negative numbers all parse, and a NaN compares false
with every limit, so a flag typed ``float`` lets a NaN duration, timeout or rate through to
crash deep in a run or to switch a check off silently. These types refuse such a value
where it enters, in argparse's one-line error naming the flag (exit 2).

Here, beside the protocols both sides import, so that a verb that takes them loads nothing
of the emulator or the service (``fleet`` and ``campaign`` build their parsers light).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TypeVar

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


#: The longest a link polls before it sleeps, µs (``protocols.mavlink_io.readable``): a peer
#: that answers within a lockstep step answers well within this; longer only burns a core.
MAX_SPIN_WAIT_US = 10_000


def spin_wait_us(text: str) -> float:
    """``--spin-wait US``: 0..``MAX_SPIN_WAIT_US`` µs, returned in seconds."""
    wanted = f"0..{MAX_SPIN_WAIT_US} µs"
    return _checked(text, float, wanted, lambda v: 0 <= v <= MAX_SPIN_WAIT_US) * 1e-6
