"""An emulated vehicle that reboots mid-run (``glider-hil emulate --reboot-at STEP``).

A reboot, as an autopilot has one: its clock starts again from boot (``time_boot_ms`` and
the µs clocks go back to ``BOOT_S``), it forgets what a companion set (the ballast commands
it was obeying, the stream rates it was asked for: back to its defaults) and runs its own
program until commanded again. The water does not reboot: the plant's state, actuator
positions and disturbances go on.

Only the periodic (ArduSub-style) profile's clock is the autopilot's own; the glider
profile stamps each step with the plant's time, so its restart is a plant matter and not
emulated here.
"""

from __future__ import annotations

from collections.abc import Callable

from plant_emulator.streams import ArduSubAutopilot
from protocols.samples import TelemetrySample

#: Simulated s since boot at the first step after a reboot (rounded up to a whole period,
#: as the vehicle's loop runs at multiples of its period since boot).
BOOT_S = 3.0


def reboot(autopilot: ArduSubAutopilot, boot_s: float = BOOT_S) -> float:
    """Reboot ``autopilot`` so that its next step is ``boot_s`` after boot
    (``ArduSubAutopilot.reboot``). Returns how far the clock went back (simulated s)."""
    return autopilot.reboot(boot_s)


class RebootAt:
    """A step hook (``Autopilot.on_step``) that reboots ``autopilot`` once, after its
    ``step``-th step, and calls ``on_step`` on every step."""

    def __init__(self, step: int, on_step: Callable[[TelemetrySample], None] | None = None) -> None:
        if step < 1:
            raise ValueError(f"the reboot's step must be ≥ 1, got {step}")
        self.step = step
        self.on_step = on_step
        self.autopilot: ArduSubAutopilot | None = None  # set once it exists
        self.went_back: float | None = None  # simulated s, once rebooted

    def __call__(self, sample: TelemetrySample) -> None:
        if self.on_step is not None:
            self.on_step(sample)
        autopilot = self.autopilot
        if autopilot is not None and autopilot.stats.steps == self.step:
            self.went_back = reboot(autopilot)
