"""Input validation and divergence detection shared by all identifiers.

Divergence is declared when any of these holds:

* the prediction, the error or a parameter is non-finite;
* the Euclidean norm ‖θ‖₂ exceeds ``param_limit``;
* for ``divergence_steps`` consecutive samples, |e| > ``error_ratio`` · (scale +
  ``scale_floor``) or the prediction jumps that far from the last output (|ŷ − y(t−1)|),
  where *scale* is a robust running mean of |y|.

Why the jump: a model that adapts fast (RLS) learns an alternating burst of absurd outputs
within a few samples and then predicts it, so its errors alone drop below the limit every
other sample and the consecutive count never completes; a prediction that jumps by fifty
times the output's scale in one step is absurd whether it is right about the burst or not.

The scale is an exponential average of |y| whose innovation is clipped to
``error_ratio``·scale, so a burst of absurd outputs can only raise it geometrically
(≤ ×(1 + rate·(ratio−1)) per step) instead of instantly absorbing the outliers; a genuinely
diverging model is therefore still caught, while ordinary level changes are not.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from .finite import finite

__all__ = ["DIVERGENCE_ACTIONS", "DivergenceMonitor", "GuardConfig"]

DIVERGENCE_ACTIONS = ("reset", "freeze")


@dataclass(frozen=True, slots=True)
class GuardConfig:
    """Limits for rejecting samples and detecting divergence (JSON-friendly)."""

    input_limit: float = 1e6
    """|u| above this (or non-finite) → sample rejected, state untouched."""
    output_limit: float = 1e9
    """|y| above this (or non-finite) → sample rejected, state untouched."""
    error_ratio: float = 50.0
    divergence_steps: int = 10
    scale_floor: float = 1e-3
    scale_rate: float = 0.01
    param_limit: float = 1e6
    on_divergence: str = "reset"
    """"reset": restore initial parameters and keep adapting; "freeze": stop adapting
    (parameters kept if sane, otherwise reset) until ``unfreeze()``/``reset()``."""

    def __post_init__(self) -> None:
        for name in ("input_limit", "output_limit", "error_ratio", "scale_floor", "param_limit"):
            val = getattr(self, name)
            if not (isinstance(val, int | float) and finite(val) and val > 0):
                raise ValueError(f"guard {name} must be finite and > 0, got {val!r}")
        if not (0.0 < self.scale_rate <= 1.0):
            raise ValueError("guard scale_rate must be in (0, 1]")
        if int(self.divergence_steps) != self.divergence_steps or self.divergence_steps < 1:
            raise ValueError("guard divergence_steps must be an integer >= 1")
        if self.on_divergence not in DIVERGENCE_ACTIONS:
            raise ValueError(f"guard on_divergence must be one of {DIVERGENCE_ACTIONS}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def coerce(cls, value: GuardConfig | dict[str, Any] | None) -> GuardConfig:
        if value is None:
            return cls()
        if isinstance(value, GuardConfig):
            return value
        return cls(**value)


class DivergenceMonitor:
    """Tracks the output scale and counts consecutive large a-priori errors."""

    __slots__ = (
        "_floor",
        "_rate",
        "_ratio",
        "_steps",
        "count",
        "last",
        "n_divergences",
        "scale",
        "seen",
    )

    def __init__(self, cfg: GuardConfig) -> None:
        self._ratio = float(cfg.error_ratio)
        self._floor = float(cfg.scale_floor)
        self._rate = float(cfg.scale_rate)
        self._steps = int(cfg.divergence_steps)
        self.scale = 0.0
        self.seen = False
        self.count = 0
        self.n_divergences = 0
        self.last = 0.0  # the last accepted output

    def reset(self) -> None:
        self.scale = 0.0
        self.seen = False
        self.count = 0
        self.n_divergences = 0
        self.last = 0.0

    def observe(self, y: float, error: float) -> bool:
        """Account for one accepted sample; True when the error test declares divergence."""
        ay = abs(y)
        last = self.last
        self.last = y
        if not self.seen:
            self.seen = True
            self.scale = ay
            return False
        s = self.scale
        lim = self._ratio * (s + self._floor)
        # ŷ − y(t−1) = (y − e) − y(t−1): the one-step jump the model predicted.
        if abs(error) > lim or abs(y - error - last) > lim:
            self.count += 1
        else:
            self.count = 0
        self.scale = s + self._rate * ((ay if ay < lim else lim) - s)
        if self.count >= self._steps:
            self.count = 0
            return True
        return False

    def state(self) -> dict[str, Any]:
        return {
            "scale": self.scale,
            "seen": self.seen,
            "count": self.count,
            "last": self.last,
            "n_divergences": self.n_divergences,
        }
