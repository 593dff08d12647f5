"""``glider-hil emulate``: run the emulated autopilot on a MAVLink link."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

from plant_emulator.arguments import (
    autopilot_config,
    check_connection,
    check_flags,
    check_value_flags,
    telemetry_mapping,
    unit_flags_given,
)
from plant_emulator.autopilot import FALLBACKS, Autopilot, AutopilotConfig, run_steps
from plant_emulator.excitation import EXCITATIONS, build_channel_excitations
from plant_emulator.fleet import add_fleet_arguments, check_links, run_fleet
from plant_emulator.lockstep import DEFAULT_TIMEOUT, LockstepRunner
from plant_emulator.models import CHANNELS
from plant_emulator.plant import FamilyPlant, GliderPlant, PlantConfig, wire_bounds
from plant_emulator.reboot import RebootAt
from plant_emulator.scenarios import PLANT_CHANGES, SCENARIOS, ChangingActuator
from plant_emulator.streams import DEFAULT_RATES_HZ, MAX_UPTIME, ArduSubAutopilot, StreamConfig
from protocols.flag_types import (
    non_negative_float,
    non_negative_int,
    positive_float,
    spin_wait_us,
)
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import Link
from protocols.profiles import DEFAULT_PROFILE, Profile, ProfileError, load_profile
from protocols.samples import DEPTH_RANGE, TelemetrySample
from protocols.units import (
    FULL_SCALE_RANGE,
    SURFACE_PRESSURE_RANGE,
    WATER_DENSITY_RANGE,
    InputScale,
    PressureDepth,
)

# The one home of each default: the dataclasses the options configure.
_PLANT = PlantConfig()
_AUTOPILOT = AutopilotConfig()
_STREAMS = StreamConfig()
_INPUTS = InputScale()
_PRESSURE = PressureDepth()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # One helper per topic, called in the order the flags appear in the usage line.
    _add_link_arguments(parser)
    _add_time_arguments(parser)
    _add_plant_arguments(parser)
    _add_autopilot_arguments(parser)
    _add_signing_arguments(parser)
    _add_event_arguments(parser)
    _add_units_arguments(parser)
    parser.add_argument(
        "--print-every",
        type=non_negative_int,
        default=0,
        help="print every Nth sample as JSON (0: none)",
    )
    _add_lockstep_arguments(parser)
    add_fleet_arguments(parser)


def _add_link_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("MAVLink link and vehicle")
    group.add_argument(
        "--connect",
        default="udpout:127.0.0.1:14550",
        help="pymavlink connection string of the link to the service (default %(default)s)",
    )
    group.add_argument(
        "--sysid",
        type=int,
        default=_AUTOPILOT.system_id,
        help="MAVLink system id (default %(default)s)",
    )
    group.add_argument(
        "--profile",
        default=DEFAULT_PROFILE,
        help="vehicle profile, a built-in name (glider, ardusub) or a TOML file: a lockstep "
        "profile streams as glider-hil's emulator, a periodic one the ArduSub way "
        "(default %(default)s)",
    )


def _add_time_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("time and telemetry streams")
    group.add_argument(
        "--period",
        type=float,
        default=None,
        help=f"plant step, simulated s (default {_PLANT.period:g}; a periodic profile: its "
        "sample period)",
    )
    group.add_argument(
        "--uptime",
        type=float,
        default=_STREAMS.uptime,
        help="periodic profiles: simulated s since boot at start, under "
        f"{MAX_UPTIME:g} (the uint32 ms clock's wrap; 4290: the uint32 µs clock of "
        "SERVO_OUTPUT_RAW wraps 5 s in)",
    )
    group.add_argument(
        "--jitter",
        type=float,
        default=_STREAMS.jitter,
        help="periodic profiles: fraction of each interval (default %(default)s)",
    )
    for name, hz in DEFAULT_RATES_HZ.items():
        group.add_argument(
            f"--rate-{name.lower().replace('_', '-')}",
            type=non_negative_float,
            default=hz,
            metavar="HZ",
            help=f"periodic profiles: {name} per simulated s (default %(default)s, 0: off)",
        )
    group.add_argument(
        "--speed", type=float, default=_AUTOPILOT.speed, help="times faster than real time"
    )
    group.add_argument(
        "--duration",
        type=positive_float,
        default=None,
        help="simulated seconds to run (default: forever)",
    )


def _add_plant_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("plant")
    group.add_argument("--scenario", choices=SCENARIOS, default=_PLANT.scenario)
    group.add_argument("--excitation", choices=EXCITATIONS, default="steps")
    group.add_argument("--seed", type=non_negative_int, default=_PLANT.seed)
    group.add_argument(
        "--trim-depth",
        type=non_negative_float,
        default=_PLANT.trim_depth,
        help=f"m below the surface, at most {DEPTH_RANGE[1]:g} (default %(default)s)",
    )
    group.add_argument(
        "--rate-limit",
        type=positive_float,
        default=_PLANT.rate_limit,
        help="model units per step (default %(default)s)",
    )


def _add_autopilot_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("autopilot")
    group.add_argument(
        "--command-timeout",
        type=positive_float,
        default=_AUTOPILOT.command_timeout,
        help="simulated s without a command before falling back (default %(default)s)",
    )
    group.add_argument("--fallback", choices=FALLBACKS, default=_AUTOPILOT.fallback)


def _add_signing_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("MAVLink 2 signing")
    group.add_argument(
        "--signing-key",
        metavar="FILE",
        help="MAVLink 2 signing key file (32 bytes or 64 hex digits, mode 600): sign all "
        "frames, accept only signed ones",
    )
    group.add_argument(
        "--accept-unsigned-non-commands",
        action="store_true",
        help="with --signing-key: also accept unsigned frames that are not commands",
    )


def _add_event_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("plant changes, family vehicles and reboots")
    group.add_argument(
        "--change",
        choices=tuple(PLANT_CHANGES),
        default=None,
        help="the plant changes at --change-at: 'flip' the input's sign, 'gain5' a fivefold "
        "gain (on --change-channel)",
    )
    group.add_argument(
        "--family",
        metavar="SEED:INDEX",
        default=None,
        help="emulate vehicle INDEX of the seeded family of SEED (plant_emulator/family.py) "
        "instead of --scenario: its two plants behind the glider's actuator, at its drawn "
        "sample period unless --period gives one",
    )
    group.add_argument(
        "--reboot-at",
        type=int,
        default=None,
        metavar="STEP",
        help="periodic profiles: the vehicle reboots after plant step STEP (its clock starts "
        "again from boot, it forgets the companion's commands and stream rates)",
    )
    group.add_argument("--change-channel", choices=CHANNELS, default="pitch")
    group.add_argument(
        "--change-at",
        type=non_negative_int,
        default=None,
        metavar="STEP",
        help="with --change: the plant step (from 0) it changes at, within --duration (default 0)",
    )


def _add_units_arguments(parser: argparse.ArgumentParser) -> None:
    # None: not given, the default below (a periodic profile gives its own units).
    group = parser.add_argument_group("units (the glider profile; a periodic one gives its own)")
    group.add_argument(
        "--full-scale",
        type=float,
        default=None,
        help=f"model units at wire 1.0, {_span(FULL_SCALE_RANGE)} (default {_INPUTS.full_scale:g})",
    )
    group.add_argument(
        "--water-density",
        type=float,
        default=None,
        help=f"kg/m³, {_span(WATER_DENSITY_RANGE)} (default {_PRESSURE.water_density:g})",
    )
    group.add_argument(
        "--surface-pressure",
        type=float,
        default=None,
        help=f"hPa, {_span(SURFACE_PRESSURE_RANGE)} (default {_PRESSURE.surface_hpa:g})",
    )


def _span(bounds: tuple[float, float]) -> str:
    return f"{bounds[0]:g}..{bounds[1]:g}"


def _add_lockstep_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("lockstep")
    group.add_argument(
        "--lockstep",
        action="store_true",
        help="step k+1 only once the service has finished with step k (docs/lockstep.md); "
        "as fast as the loop allows, --speed is ignored",
    )
    group.add_argument(
        "--lockstep-timeout",
        type=positive_float,
        default=DEFAULT_TIMEOUT,
        metavar="S",
        help="wall s a step waits for the service before going on, counted (default %(default)s)",
    )
    group.add_argument(
        "--spin-wait",
        type=spin_wait_us,
        default=0.0,
        metavar="US",
        help="poll the link up to US µs before sleeping: faster lockstep when the emulator "
        'and the service each have a core of their own (docs/lockstep.md, "Two cores"); '
        "slower on a shared core (default 0)",
    )


@dataclass
class _Vehicle:
    """One emulated vehicle as the flags configure it, checked before any link opens."""

    profile: Profile
    plant: GliderPlant | FamilyPlant
    config: AutopilotConfig
    mapping: TelemetryMapping
    streams: StreamConfig

    @property
    def periodic(self) -> bool:
        return self.profile.sampling.mode == "periodic"


def run(args: argparse.Namespace) -> int:
    fleet = args.vehicles != 1 or bool(args.fleet_connect)
    try:
        _check_common_flags(args, fleet)
        if fleet:
            return _run_fleet(args)
        vehicle = _vehicle_from_args(args)
    except (ValueError, ProfileError) as error:
        print(f"glider-hil emulate: {error}", file=sys.stderr)
        return 2
    return _emulate(args, vehicle)


def _check_common_flags(args: argparse.Namespace, fleet: bool) -> None:
    """Raise ValueError, naming the flag, for what neither one vehicle nor a fleet takes:
    a connection string that cannot be a link (the ones the run would open), a
    ``--fleet-connect`` no vehicle would use, a trim depth or unit out of bounds,
    ``--change-at`` without ``--change``."""
    if fleet and args.fleet_connect:
        for connection in args.fleet_connect:
            check_connection("--fleet-connect", connection)
        check_links(args.vehicles, args.fleet_connect)
    else:
        check_connection("--connect", args.connect)
    check_value_flags(args)
    if args.change_at is not None and args.change is None:
        raise ValueError("--change-at needs --change (the plant change it times)")


def _run_fleet(args: argparse.Namespace) -> int:
    """``--vehicles N`` or ``--fleet-connect``: refuse what only one vehicle does, then
    ``run_fleet``."""
    if args.lockstep or args.spin_wait:
        flag = "--lockstep" if args.lockstep else "--spin-wait"
        print(f"glider-hil emulate: {flag} runs one vehicle", file=sys.stderr)
        return 2
    if args.profile != DEFAULT_PROFILE:
        print("glider-hil emulate: --vehicles runs the glider profile only", file=sys.stderr)
        return 2
    if args.family is not None or args.reboot_at is not None:
        print("glider-hil emulate: --family and --reboot-at run one vehicle", file=sys.stderr)
        return 2
    if args.period is None:
        args.period = _PLANT.period  # the glider profile's plant step
    return run_fleet(args)


def _vehicle_from_args(args: argparse.Namespace) -> _Vehicle:
    """Flags → one vehicle; raises ValueError (or ProfileError) on bad ones."""
    profile = load_profile(args.profile)
    periodic = profile.sampling.mode == "periodic"
    _check_single_vehicle_flags(args, periodic)
    check_flags([("--uptime", lambda: StreamConfig(uptime=args.uptime))])
    streams = StreamConfig(
        uptime=args.uptime,
        jitter=args.jitter,
        rates_hz={name: getattr(args, f"rate_{name.lower()}") for name in DEFAULT_RATES_HZ},
        seed=args.seed,
    )
    plant = _plant_from_args(args, profile)
    _check_steps_within_run(args, plant.config.period)
    config = autopilot_config(args, args.sysid)
    mapping = telemetry_mapping(args)
    return _Vehicle(profile, plant, config, mapping, streams)


def _check_single_vehicle_flags(args: argparse.Namespace, periodic: bool) -> None:
    if args.latency_trace:
        raise ValueError(
            "--latency-trace measures a fleet: it needs --vehicles N or --fleet-connect"
        )
    if args.lockstep and periodic:
        raise ValueError("--lockstep needs the glider profile (one timestamp per step)")
    if args.reboot_at is not None and not periodic:
        raise ValueError("--reboot-at needs a periodic profile (the vehicle's own clock)")
    if args.reboot_at is not None and args.reboot_at < 1:
        raise ValueError(f"--reboot-at must be a plant step ≥ 1, got {args.reboot_at}")
    given = unit_flags_given(args)
    if periodic and given:
        raise ValueError(
            f"{', '.join(given)}: the profile {args.profile} is periodic and gives its own "
            "units ([units] and [ballast] full_scale, docs/profiles.md): set them there"
        )


def _check_steps_within_run(args: argparse.Namespace, period: float) -> None:
    """With ``--duration`` the run's plant steps are known: ``--reboot-at`` (after step
    1..N) and ``--change-at`` (step 0..N−1) must fall within them."""
    steps = run_steps(args.duration, period)
    if steps is None:
        return
    run = f"the run has {steps} plant steps (--duration {args.duration:g} s, period {period:g} s)"
    if args.reboot_at is not None and args.reboot_at > steps:
        raise ValueError(f"--reboot-at {args.reboot_at} is beyond the run: {run}")
    if args.change_at is not None and args.change_at >= steps:
        raise ValueError(f"--change-at {args.change_at} is beyond the run: {run}, numbered from 0")


def _plant_from_args(args: argparse.Namespace, profile: Profile) -> GliderPlant | FamilyPlant:
    """The family's vehicle (``--family``) or the scenario's glider, with ``--change`` on
    its actuator."""
    plant: GliderPlant | FamilyPlant
    if args.family is not None:  # at its own drawn period unless --period gives one
        plant = family_plant(args.family, args.period, args.sysid)
    else:
        period = args.period
        if period is None:
            periodic = profile.sampling.mode == "periodic"
            period = _PLANT.period
            if periodic and profile.sampling.period:
                period = profile.sampling.period
        plant = GliderPlant(
            PlantConfig(
                scenario=args.scenario,
                period=period,
                seed=args.seed,
                trim_depth=args.trim_depth,
                rate_limit=args.rate_limit,
            ),
            system_id=args.sysid,
        )
    if args.change is not None:
        actuator = plant.actuators[args.change_channel]
        at = 0 if args.change_at is None else args.change_at
        changing = ChangingActuator(actuator, PLANT_CHANGES[args.change], at)
        plant.actuators[args.change_channel] = changing  # type: ignore[assignment]
    return plant


def _emulate(args: argparse.Namespace, vehicle: _Vehicle) -> int:
    """Run the vehicle on its link until SIGINT/SIGTERM or ``--duration``; print the
    summary as JSON."""
    try:
        link = Link(
            args.connect, source_system=args.sysid, source_component=1, spin_wait=args.spin_wait
        )
    except Exception as error:  # pymavlink raises many kinds (a TCP peer not listening)
        print(f"glider-hil emulate: cannot open {args.connect}: {error}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def request_stop(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    autopilot, rebooter = _autopilot(args, vehicle, link)
    lockstep = LockstepRunner(autopilot, args.lockstep_timeout) if args.lockstep else None
    pace = "in lockstep" if lockstep is not None else f"at {args.speed:g}x"
    what = args.scenario if args.family is None else f"family {args.family}"
    print(
        f"emulating glider sysid {args.sysid} ({what}, {args.excitation}, profile "
        f"{vehicle.profile.name}, {vehicle.plant.config.period:g} s) on {args.connect} {pace}",
        file=sys.stderr,
        flush=True,
    )
    try:
        stats = autopilot.run(stop) if lockstep is None else lockstep.run(stop)
    finally:
        link.close()
    summary = stats.as_dict(autopilot.codec)
    summary["gcs"] = autopilot.manners.counters.as_dict()
    summary["mission"] = autopilot.mission.counters.as_dict()
    if isinstance(autopilot, ArduSubAutopilot):
        summary["streams_sent"] = dict(autopilot.sent)
    if lockstep is not None:
        summary["lockstep"] = lockstep.stats.as_dict()
    if isinstance(vehicle.plant, FamilyPlant):
        summary["family"] = {ch: spec.as_json() for ch, spec in vehicle.plant.specs.items()}
    if rebooter is not None:
        summary["reboot"] = {"at_step": rebooter.step, "clock_back_s": rebooter.went_back}
    print(json.dumps({"emulator": summary}), flush=True)
    return 0


def _autopilot(
    args: argparse.Namespace, vehicle: _Vehicle, link: Link
) -> tuple[Autopilot, RebootAt | None]:
    """The profile's autopilot on ``link``, with its step hooks (``--print-every``,
    ``--reboot-at``: the latter's hook, returned too, for the summary)."""

    def print_sample(sample: TelemetrySample) -> None:
        if args.print_every and autopilot.stats.steps % args.print_every == 0:
            print(json.dumps(sample.to_payload()), flush=True)

    excitations = build_channel_excitations(args.excitation, seed=args.seed)
    on_step: Callable[[TelemetrySample], None] | None = print_sample if args.print_every else None
    rebooter = None
    if args.reboot_at is not None:
        on_step = rebooter = RebootAt(args.reboot_at, on_step)
    autopilot: Autopilot
    if vehicle.periodic:
        autopilot = ArduSubAutopilot(
            vehicle.plant,
            link,
            excitations,
            vehicle.profile,
            vehicle.config,
            vehicle.streams,
            on_step=on_step,
        )
    else:
        autopilot = Autopilot(
            vehicle.plant, link, excitations, vehicle.config, vehicle.mapping, on_step=on_step
        )
    if rebooter is not None:
        assert isinstance(autopilot, ArduSubAutopilot)
        rebooter.autopilot = autopilot
    return autopilot, rebooter


def family_plant(choice: str, period: float | None, system_id: int) -> FamilyPlant:
    """``--family SEED:INDEX``: the family's vehicle; a warning on stderr for an output
    that may leave what the glider's telemetry carries (the service drops such samples)."""
    seed, sep, index = choice.partition(":")
    try:
        if not sep:
            raise ValueError
        plant = FamilyPlant(int(seed), int(index), period, system_id)
    except ValueError as error:
        detail = f": {error}" if str(error) else ""
        raise ValueError(
            f"--family wants SEED:INDEX (two integers), got {choice!r}{detail}"
        ) from None
    for spec in plant.specs.values():
        reason = wire_bounds(spec)
        if reason:
            print(f"glider-hil emulate: warning: family {choice} {reason}", file=sys.stderr)
    return plant
