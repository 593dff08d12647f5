"""What the ArduSub wire tests hold a depth step to after the supervisor trips."""

from __future__ import annotations

#: m, where the neutral ballast input holds the emulated ArduSub vehicle (``--trim-depth``).
TRIM_DEPTH = 15.0


def depth_error_allowed_after_trip(enabled_depth: float, setpoint: float) -> float:
    """The mean |depth error| a depth step may end with once its channel tripped.

    A model whose steady state is wrong can pass the horizon test against holding the
    PRBS's swings and drive depth the wrong way until the supervisor trips
    (docs/control.md, "The horizon test", its limit on the wire). The safe input, neutral,
    then takes the vehicle back to its trim depth: at the end no worse than 1.2 times the
    error at enable or at trim, whichever is larger. The PRBS can leave the vehicle nearer
    the setpoint than its trim is, and no safe input keeps it there once the model that
    would have is distrusted."""
    return 1.2 * max(abs(enabled_depth - setpoint), abs(TRIM_DEPTH - setpoint))
