"""The probing excitation of a channel asked to command whose model does not predict over
the horizon (docs/control.md, "Probing").

Once the vehicle's own excitation has ended and its input is held, the record the horizon
test judges holds nothing that could show a model right: a held input's output is
predicted as well by holding it or by its mean, and the identifier, fed no excitation,
drifts along the directions the record does not pin down. A channel that failed the test
would then never pass it. With ``ControlSettings.probe`` > 0 (a share of the actuator's
range, 0: never), such a channel sends random steps about the input it held when probing
began: levels uniform within ± the amplitude, each held 10–40 samples (the family's and
the emulator's excitation), seeded per channel so that a run replays to the bit.
"""

from __future__ import annotations

import math

import numpy as np

#: Each level is held this many samples, inclusive.
SHORTEST_HOLD = 10
LONGEST_HOLD = 40


class Probe:
    """Random steps about a centre; ``level`` gives the next sample's input."""

    __slots__ = ("_left", "_level", "_random", "amplitude", "centre")

    def __init__(self, amplitude: float, seed: int, channel: str) -> None:
        if not (math.isfinite(amplitude) and amplitude >= 0.0):
            raise ValueError(f"probe amplitude must be finite and >= 0, got {amplitude}")
        self.amplitude = amplitude
        # numpy's seed sequences take non-negative integers: the seed's magnitude.
        self._random = np.random.default_rng([abs(seed), *channel.encode()])
        self._left = 0
        self._level = 0.0
        self.centre = math.nan  # NaN: not probing

    @property
    def running(self) -> bool:
        return not math.isnan(self.centre)

    def start(self, centre: float) -> None:
        self.centre = centre
        self._left = 0

    def stop(self) -> None:
        self.centre = math.nan

    def level(self) -> float:
        """The next sample's input: the current step's level, or a new step's."""
        if self._left <= 0:
            self._level = self.centre + self.amplitude * float(self._random.uniform(-1.0, 1.0))
            self._left = int(self._random.integers(SHORTEST_HOLD, LONGEST_HOLD, endpoint=True))
        self._left -= 1
        return self._level
