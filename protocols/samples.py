"""The sample and command types that flow through the whole system, one per plant step."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple


class TelemetrySample(NamedTuple):
    """One plant step of one vehicle, assembled from the messages sharing its timestamp.

    Immutable; a named tuple rather than a frozen dataclass because one is built per step
    on the service's hot path (a frozen dataclass's ``__init__`` costs five times more).

    ``depth`` m (positive down), ``pitch`` rad, ``u_depth``/``u_pitch`` the ballast inputs
    applied during this step in model units (the paper's −2..2 range is full scale).
    """

    system_id: int
    time_boot_ms: int
    depth: float
    pitch: float
    u_depth: float
    u_pitch: float
    pitch_rate: float = 0.0
    climb: float = 0.0
    #: The vehicle rebooted just before this sample, where the timestamp does not show it
    #: (a periodic source keeps ``time_boot_ms`` increasing across a reboot).
    restarted: bool = False

    @property
    def t(self) -> float:
        return self.time_boot_ms / 1000.0

    def output(self, channel: str) -> float:
        return self.depth if channel == "depth" else self.pitch

    def input(self, channel: str) -> float:
        return self.u_depth if channel == "depth" else self.u_pitch

    def is_finite(self) -> bool:
        return all(
            math.isfinite(v)
            for v in (self.depth, self.pitch, self.u_depth, self.u_pitch, self.pitch_rate)
        )

    def to_payload(self) -> dict[str, float]:
        """The Zenoh ``telemetry`` payload (docs/zenoh.md)."""
        return {
            "t": self.t,
            "depth": self.depth,
            "pitch": self.pitch,
            "u_depth": self.u_depth,
            "u_pitch": self.u_pitch,
        }

    def as_dict(self) -> dict[str, float | int]:
        return self._asdict()


def new_sample(
    system_id: int,
    time_boot_ms: int,
    depth: float,
    pitch: float,
    u_depth: float,
    u_pitch: float,
    pitch_rate: float = 0.0,
    climb: float = 0.0,
    restarted: bool = False,
) -> TelemetrySample:
    """``TelemetrySample(...)``, the same tuple, made by ``tuple.__new__``: the named
    tuple's own ``__new__`` is a Python function, a frame for every sample an assembler
    compiled with mypyc builds."""
    return tuple.__new__(
        TelemetrySample,
        (system_id, time_boot_ms, depth, pitch, u_depth, u_pitch, pitch_rate, climb, restarted),
    )


#: Depths a sample may report, m: above the surface by a wave crest .. the deepest trench.
DEPTH_RANGE = (-50.0, 11_000.0)


def is_plausible(sample: TelemetrySample, full_scale: float) -> bool:
    """Finite, a depth in ``DEPTH_RANGE``, |pitch| ≤ π and both inputs within the actuator's
    full scale (model units, with a rounding margin): what either assembler passes on."""
    limit = full_scale * (1 + 1e-6)
    return (
        sample.is_finite()
        and DEPTH_RANGE[0] <= sample.depth <= DEPTH_RANGE[1]
        and abs(sample.pitch) <= math.pi
        and abs(sample.u_depth) <= limit
        and abs(sample.u_pitch) <= limit
    )


@dataclass(frozen=True, init=False)
class BallastCommand:
    """A ballast command in model units; NaN leaves that channel unchanged."""

    u_depth: float
    u_pitch: float

    # Written out, not generated (``init=False``): docs/compiled.md.
    def __init__(self, u_depth: float, u_pitch: float) -> None:
        object.__setattr__(self, "u_depth", u_depth)
        object.__setattr__(self, "u_pitch", u_pitch)
