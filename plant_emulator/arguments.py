"""What ``emulate``'s flags configure, built once for the single vehicle and the fleet alike."""

from __future__ import annotations

import argparse

from plant_emulator.autopilot import AutopilotConfig
from protocols.mapping import TelemetryMapping
from protocols.signing import load_key
from protocols.units import InputScale, PressureDepth


def autopilot_config(args: argparse.Namespace, system_id: int) -> AutopilotConfig:
    """The autopilot's settings from the flags, for the vehicle with ``system_id``."""
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
    return TelemetryMapping(
        pressure=PressureDepth(args.water_density, args.surface_pressure),
        inputs=InputScale(args.full_scale),
    )
