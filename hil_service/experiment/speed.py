"""How fast one channel identifies and inverts, on the emulator's plant, on one core.

Two figures per channel and model: the identifier update alone (``model.step`` on recorded
samples), and the service's control step (identifier update + IMC target + forecast +
inverse solve + command shaping + the supervisor, ``ChannelPipeline.observe``,
``supervise`` and ``solve``) in closed loop
with the plant. The plant's own cost is excluded from both timings.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

from hil_service.pipeline import ChannelPipeline, PipelineSettings
from hil_service.umodel import U_MODELS
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.models import CHANNELS
from plant_emulator.plant import GliderPlant, PlantConfig

#: Setpoints cycled through in the control timing, per channel (metres, radians).
_SETPOINTS = {"depth": (17.0, 14.0, 16.0), "pitch": (0.15, -0.1, 0.05)}


@dataclass(frozen=True)
class SpeedFigure:
    """Best of the repeated runs (the least disturbed on a shared machine) and the median."""

    channel: str
    model: str
    update_per_s: float
    control_per_s: float
    fallback_share: float
    control_per_s_median: float = 0.0
    repeats: int = 1


def rates(count: int, seconds: list[float]) -> dict[str, float]:
    """Best and median rate of repeated runs: on a shared machine the best run is the one
    least disturbed, the median shows the spread."""
    return {"best": count / min(seconds), "median": count / statistics.median(seconds)}


Recorded = list[tuple[float, float, float, float]]  # depth, u_depth, pitch, u_pitch


def _recorded(scenario: str, n: int, seed: int) -> Recorded:
    plant = GliderPlant(PlantConfig(scenario=scenario, seed=seed))
    excitation = build_channel_excitations("steps", seed)
    rows = []
    command = (0.0, 0.0)
    for k in range(n):
        s = plant.step(*command)
        rows.append((s.depth, s.u_depth, s.pitch, s.u_pitch))
        command = (excitation["depth"].value(k), excitation["pitch"].value(k))
    return rows


def measure(
    channel: str,
    model: str,
    samples: int,
    scenario: str = "paper",
    seed: int = 0,
    rows: Recorded | None = None,
) -> SpeedFigure:
    """``rows``: the open-loop recording to time the update on (made here when not given)."""
    settings = PipelineSettings(model=model, seed=seed, burn_in=min(300, samples // 4))
    rows = rows if rows is not None else _recorded(scenario, samples, seed)
    col = 0 if channel == "depth" else 2
    pipeline = ChannelPipeline(channel, settings, seed)
    start = time.perf_counter()
    for k, row in enumerate(rows):
        pipeline.observe(float(k), row[col], row[col + 1])
    update = time.perf_counter() - start

    # Closed loop: the plant is stepped outside the timed sections.
    pipeline = ChannelPipeline(channel, settings, seed)
    plant = GliderPlant(PlantConfig(scenario=scenario, seed=seed))
    excitation = build_channel_excitations("steps", seed)[channel]
    warm = settings.burn_in
    u = 0.0
    timed = 0.0
    fallbacks = 0
    levels = _SETPOINTS[channel]
    for k in range(samples + warm):
        sample = plant.step(u, 0.0) if channel == "depth" else plant.step(0.0, u)
        y, u_now = sample.output(channel), sample.input(channel)
        if k < warm:
            pipeline.observe(float(k), y, u_now)
            u = excitation.value(k)
            continue
        setpoint = levels[(k // 200) % len(levels)]
        t0 = time.perf_counter()
        pipeline.observe(float(k), y, u_now)
        pipeline.supervise(setpoint, u_now)  # the closed-loop supervisor's check
        u, path, _ = pipeline.solve(setpoint, u_now)
        timed += time.perf_counter() - t0
        fallbacks += path == "fallback"
    return SpeedFigure(
        channel=channel,
        model=model,
        update_per_s=samples / update,
        control_per_s=samples / timed,
        fallback_share=fallbacks / samples,
    )


def measure_all(
    samples: int, scenario: str = "paper", seed: int = 0, repeats: int = 3
) -> list[SpeedFigure]:
    """Each case ``repeats`` times (the same computation each time); best and median."""
    rows = _recorded(scenario, samples, seed)  # one recording serves every case
    figures = []
    for channel in CHANNELS:
        for model in U_MODELS:
            runs = [measure(channel, model, samples, scenario, seed, rows) for _ in range(repeats)]
            figures.append(
                SpeedFigure(
                    channel=channel,
                    model=model,
                    update_per_s=max(r.update_per_s for r in runs),
                    control_per_s=max(r.control_per_s for r in runs),
                    fallback_share=runs[0].fallback_share,
                    control_per_s_median=statistics.median(r.control_per_s for r in runs),
                    repeats=repeats,
                )
            )
    return figures
