"""What ``emulate``'s flags configure, built once for the single vehicle and the fleet alike,
and the checks that refuse a bad flag, naming it, before any link opens."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable

from plant_emulator.autopilot import AutopilotConfig
from plant_emulator.plant import PlantConfig
from protocols.link_address import connection_problem
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
    the inputs' full scale (a flag not given: the default of ``protocols.units``)."""
    pressure = PressureDepth()
    return TelemetryMapping(
        pressure=PressureDepth(
            pressure.water_density if args.water_density is None else args.water_density,
            pressure.surface_hpa if args.surface_pressure is None else args.surface_pressure,
        ),
        inputs=InputScale() if args.full_scale is None else InputScale(args.full_scale),
    )


def unit_flags_given(args: argparse.Namespace) -> list[str]:
    """The unit flags given on the command line (a periodic profile gives its own units)."""
    given = (
        ("--full-scale", args.full_scale),
        ("--water-density", args.water_density),
        ("--surface-pressure", args.surface_pressure),
    )
    return [flag for flag, value in given if value is not None]


def check_value_flags(args: argparse.Namespace) -> None:
    """Raise ValueError, naming the flag, for a plant step, trim depth or unit outside the
    bounds of the dataclass it configures (``PlantConfig``, ``protocols.units``)."""
    checks: list[tuple[str, Callable[[], object]]] = [
        ("--trim-depth", lambda: PlantConfig(trim_depth=args.trim_depth))
    ]
    if args.period is not None:
        checks.append(("--period", lambda: PlantConfig(period=args.period)))
    if args.full_scale is not None:
        checks.append(("--full-scale", lambda: InputScale(args.full_scale)))
    if args.water_density is not None:
        checks.append(("--water-density", lambda: PressureDepth(water_density=args.water_density)))
    if args.surface_pressure is not None:
        checks.append(
            ("--surface-pressure", lambda: PressureDepth(surface_hpa=args.surface_pressure))
        )
    check_flags(checks)


def check_flags(checks: Iterable[tuple[str, Callable[[], object]]]) -> None:
    """Call each check (a dataclass built from one flag's value: its own checks); the first
    ValueError is raised again with the flag's name in front."""
    for flag, check in checks:
        try:
            check()
        except ValueError as error:
            raise ValueError(f"{flag}: {error}") from None


def check_connection(flag: str, connection: str) -> None:
    """Raise ValueError naming ``flag`` when ``connection`` cannot be a link."""
    problem = connection_problem(connection)
    if problem:
        raise ValueError(f"{flag} {problem}")
