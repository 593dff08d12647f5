"""``glider-hil serve``: the HIL service on a MAVLink link, publishing on Zenoh, logging MCAP.

    glider-hil serve --mavlink udpin:127.0.0.1:14550 --zenoh-listen tcp/127.0.0.1:7447 \\
        [--control] [--profile glider|ardusub|FILE] [--log-dir logs]
    glider-hil serve --mavlink udpin:127.0.0.1:14550 --mavlink udpin:127.0.0.1:14551 \\
        --vehicle-ids link --max-vehicles 500 --zenoh-connect tcp/ROUTER:7447

docs/running.md describes every flag. The code reads as zenoh-python's examples: flags →
``config_from_args`` → ``main(config)``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from hil_service.builder import Wired, open_recorder, wire
from hil_service.cli.processes import SERVICE_READY
from hil_service.config import (
    DEFAULT_MAX_VEHICLES,
    VEHICLE_ID_MODES,
    LinkSecurity,
    LogOptions,
    ServeConfig,
    ServiceConfig,
    Units,
    parse_system_ids,
    sample_period_delay_problem,
)
from hil_service.inputs import SetpointLimits
from hil_service.listeners.zenoh_config import add_zenoh_arguments, open_session, options_from_args
from hil_service.live.address import LiveAddress
from hil_service.pipeline import ControlSettings, PipelineSettings
from hil_service.process_tuning import tune_for_service
from hil_service.umodel import U_MODELS
from hil_service.vehicle_links import LinkSet
from protocols.flag_types import spin_wait_us
from protocols.link_address import connection_problem, normalized
from protocols.mavlink_io import Link
from protocols.profiles import (
    DEFAULT_PROFILE,
    MAX_SAMPLE_PERIOD,
    MIN_SAMPLE_PERIOD,
    Profile,
    load_profile,
)
from protocols.signing import load_key

if TYPE_CHECKING:
    from hil_service.live.view import LiveView

DEFAULT_MAVLINK = "udpin:127.0.0.1:14550"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # One helper per topic, called in the order the flags appear in the usage line.
    _add_link_arguments(parser)
    _add_profile_arguments(parser)
    _add_control_arguments(parser)
    _add_log_arguments(parser)
    _add_units_arguments(parser)
    parser.add_argument("--duration", type=float, default=None, help="wall s, then exit")
    _add_limits_arguments(parser)
    _add_signing_arguments(parser)
    add_foxglove_argument(parser)
    add_zenoh_arguments(parser)


def _add_link_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("MAVLink links and vehicles")
    group.add_argument(
        "--mavlink",
        action="append",
        default=[],
        metavar="CONNECTION",
        help="pymavlink connection string: udpin:HOST:PORT, udpout:, tcp:, or a serial device "
        f"(default {DEFAULT_MAVLINK}); repeatable: UDP links 1, 2, … (a gateway each; "
        "docs/fleet.md)",
    )
    group.add_argument(
        "--vehicle-ids",
        choices=VEHICLE_ID_MODES,
        default="sysid",
        help="sysid: a system id is one vehicle on every link (key id 7); link: each link "
        "has its own system ids, a vehicle is (link, system id) (key id 2-7; docs/zenoh.md)",
    )
    group.add_argument(
        "--sysid",
        action="append",
        default=[],
        metavar="IDS",
        help="vehicle system ids to serve: N, N-M or a comma list (repeatable; default: every "
        "vehicle on the link)",
    )
    group.add_argument(
        "--max-vehicles",
        type=int,
        default=DEFAULT_MAX_VEHICLES,
        metavar="N",
        help="without --sysid: serve the first N vehicles heard, 1..255 (--vehicle-ids link: "
        "255 per link) (default %(default)s; stored in the log's configuration; a --sysid "
        "list is served whole)",
    )
    group.add_argument(
        "--spin-wait",
        type=spin_wait_us,
        default=0.0,
        metavar="US",
        help="poll the links up to US µs before sleeping: faster lockstep when the service "
        'and the vehicle each have a core of their own (docs/lockstep.md, "Two cores"); '
        "slower on a shared core (default 0)",
    )


def _add_profile_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("vehicle profile")
    group.add_argument(
        "--profile",
        default=DEFAULT_PROFILE,
        help="vehicle profile: a built-in name (glider, ardusub) or a TOML file "
        "(docs/profiles.md; default %(default)s)",
    )
    group.add_argument(
        "--sample-period",
        type=float,
        default=None,
        metavar="S",
        help="periodic profiles: s between samples on the vehicle's clock, "
        f"{MIN_SAMPLE_PERIOD:g}..{MAX_SAMPLE_PERIOD:g} (default: the profile's)",
    )


def _add_control_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("control and vehicle health")
    group.add_argument("--model", choices=U_MODELS, default="dynamic")
    group.add_argument("--seed", type=int, default=0, help="identifier initialisation seed")
    control = group.add_mutually_exclusive_group()
    control.add_argument(
        "--control", dest="control", action="store_true", help="control enabled at start"
    )
    control.add_argument("--no-control", dest="control", action="store_false")
    parser.set_defaults(control=False)
    group.add_argument(
        "--lockstep",
        action="store_true",
        help="release every step to the vehicle from the start (docs/lockstep.md; default: "
        "when the vehicle announces lockstep)",
    )
    group.add_argument(
        "--stale-timeout",
        type=float,
        default=3.0,
        metavar="S",
        help="s without a sample before commands stop, positive (default 3)",
    )
    group.add_argument(
        "--health-period",
        type=float,
        default=1.0,
        metavar="S",
        help="s between two health publications of one vehicle (default 1; a fleet at 1 Hz "
        "publishes as many health payloads as samples: docs/fleet.md)",
    )
    group.add_argument("--burn-in", type=int, default=None, help="samples before control")
    group.add_argument(
        "--input-lags",
        default=None,
        metavar="N|auto",
        help="the dynamic identifier's input lags: auto (default) chooses 4, 6 or 8 from each "
        "channel's first samples; N gives them, at least the vehicle's input delay + 2 "
        "(docs/control.md)",
    )
    group.add_argument(
        "--bridge-gap",
        type=int,
        default=None,
        metavar="N",
        help="the most samples lost in a row that are carried across when the inputs over "
        "them are known (default 5; 0: every gap resynchronises the identifier and restarts "
        "the horizon test's record; docs/control.md)",
    )
    group.add_argument(
        "--lag-smoothing-gain",
        type=float,
        default=None,
        metavar="K",
        help="with --input-lags auto, the smoothness prior on neighbouring input lags: its "
        "weight is K times the record's one-step residual share (default 100; 0: none; "
        "docs/control.md)",
    )
    group.add_argument(
        "--disturbance-forecast",
        type=float,
        default=None,
        metavar="RATIO",
        help="plan against a forecast of the disturbance over the horizon (an AR(2) of the "
        "residual) while its one-step errors' mean square is below RATIO times the held "
        "level's, as far ahead as it has beaten the level (0..1; default "
        f"{ControlSettings().disturbance_forecast:g}; 0: the level held; docs/control.md)",
    )
    group.add_argument(
        "--no-input-dead-zone",
        action="store_true",
        help="with --input-lags auto, choose no input dead zone from the record (by default "
        "each channel chooses one with its lags; docs/control.md)",
    )


def _add_log_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("MCAP log")
    group.add_argument("--log-dir", default="logs", help="MCAP directory (default logs)")
    group.add_argument("--no-log", action="store_true", help="do not record MCAP")
    group.add_argument("--log-max-mb", type=float, default=256.0, help="rotate after this size")
    group.add_argument("--log-max-s", type=float, default=3600.0, help="rotate after this long")


def _add_units_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("units (default: the profile's)")
    group.add_argument("--full-scale", type=float, default=None, help="model units at wire 1.0")
    group.add_argument("--water-density", type=float, default=None, help="kg/m³")
    group.add_argument("--surface-pressure", type=float, default=None, help="hPa")


def _add_limits_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("limits (setpoints outside them are refused)")
    group.add_argument("--min-depth", type=float, default=None, help="shallowest setpoint, m")
    group.add_argument("--max-depth", type=float, default=None, help="deepest setpoint, m")
    group.add_argument("--max-pitch", type=float, default=None, help="largest |pitch|, rad")
    group.add_argument(
        "--max-ballast-rate",
        type=float,
        default=None,
        help="largest command change per step, model units (default: the actuator's 0.5)",
    )


def _add_signing_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("MAVLink 2 signing")
    group.add_argument(
        "--signing-key",
        metavar="FILE",
        help="key file (32 bytes or 64 hex digits, mode 600): sign commands, require signed "
        "telemetry",
    )
    group.add_argument(
        "--accept-unsigned",
        action="store_true",
        help="with --signing-key: accept unsigned telemetry too (counted in health)",
    )


def add_foxglove_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        default=None,
        help="serve a Foxglove live view (WebSocket) on PORT, loopback unless HOST is given",
    )


def foxglove_from_args(args: argparse.Namespace) -> LiveAddress | None:
    return None if args.foxglove is None else LiveAddress.parse(args.foxglove)


def start_live(address: LiveAddress | None, verb: str) -> LiveView | None:
    """The started live view, announced on stderr (its URL), or None without an address."""
    if address is None:
        return None
    from hil_service.live.view import LiveView  # the Foxglove SDK, only when asked for

    try:
        live = LiveView(address, name=f"glider-hil {verb}").start()
    except Exception as error:  # foxglove raises its own error type, e.g. for a port in use
        raise OSError(f"cannot start the Foxglove server on {address}: {error}") from error
    print(f"glider-hil {verb}: Foxglove live view on {live.url}", file=sys.stderr, flush=True)
    return live


def settings_from_args(args: argparse.Namespace, profile: Profile) -> PipelineSettings:
    """The pipeline's settings: the flags', with the ``[control]`` choices of ``profile``."""
    choices = profile.control
    settings = PipelineSettings(model=args.model, seed=args.seed)
    settings = settings.replace(
        control=replace(settings.control, safe_input=choices.safe_input, probe=choices.probe)
    )
    if args.burn_in is not None:
        settings = settings.replace(burn_in=args.burn_in)
    if args.input_lags is not None:
        settings = settings.with_input_lag_choice(args.input_lags)
    if args.bridge_gap is not None:
        settings = settings.replace(bridge_gap=args.bridge_gap)
    if args.lag_smoothing_gain is not None:
        settings = settings.replace(lag_smoothing_gain=args.lag_smoothing_gain)
    if args.no_input_dead_zone:
        settings = settings.replace(choose_dead_zone=False)
    if args.disturbance_forecast is not None:
        control = replace(settings.control, disturbance_forecast=args.disturbance_forecast)
        settings = settings.replace(control=control)
    if args.max_ballast_rate is not None:
        if not args.max_ballast_rate > 0:
            raise ValueError("--max-ballast-rate must be positive")
        control = replace(settings.control, rate_limit=args.max_ballast_rate)
        settings = settings.replace(control=control)
    return settings


def security_from_args(args: argparse.Namespace) -> LinkSecurity:
    if args.signing_key is None:
        if args.accept_unsigned:
            raise ValueError("--accept-unsigned needs --signing-key")
        return LinkSecurity()
    return LinkSecurity(load_key(args.signing_key), accept_unsigned=args.accept_unsigned)


def units_from_args(args: argparse.Namespace, profile: Profile) -> Units | None:
    """The units the flags give, each one not given the profile's; None without any."""
    given = (args.full_scale, args.water_density, args.surface_pressure)
    if all(value is None for value in given):
        return None
    stated = Units.of(profile)
    return Units(
        stated.full_scale if args.full_scale is None else args.full_scale,
        stated.water_density if args.water_density is None else args.water_density,
        stated.surface_pressure if args.surface_pressure is None else args.surface_pressure,
    )


def config_from_args(args: argparse.Namespace) -> ServeConfig:
    """Flags → configuration; raises ValueError (or OSError for the key file) on bad ones."""
    profile = load_profile(args.profile)
    periodic = profile.sampling.mode == "periodic"
    if args.sample_period is not None and not periodic:
        raise ValueError(f"--sample-period needs a periodic profile; {profile.name} is not")
    if args.sample_period is not None:
        problem = sample_period_delay_problem(profile, args.sample_period)
        if problem:
            raise ValueError(problem)
    system_ids = [i for text in args.sysid for i in parse_system_ids(str(text))]
    if args.lockstep and periodic:
        raise ValueError(f"--lockstep needs a lockstep profile; {profile.name} is periodic")
    service = ServiceConfig(
        system_ids=tuple(dict.fromkeys(system_ids)),
        control_default=args.control,
        stale_timeout=args.stale_timeout,
        health_period=args.health_period,
        pipeline=settings_from_args(args, profile),
        security=security_from_args(args),
        units=units_from_args(args, profile),
        limits=SetpointLimits(args.min_depth, args.max_depth, args.max_pitch),
        profile=profile,
        sample_period=(
            (profile.sampling.period if args.sample_period is None else args.sample_period)
            if periodic
            else None
        ),
        lockstep=args.lockstep,
        max_vehicles=args.max_vehicles,
        vehicle_ids=args.vehicle_ids,
    )
    log = LogOptions(
        directory=None if args.no_log else args.log_dir,
        max_bytes=int(args.log_max_mb * 1024 * 1024),
        max_seconds=args.log_max_s,
    )
    links = list(dict.fromkeys(normalized(c) for c in args.mavlink)) or [DEFAULT_MAVLINK]
    if len(links) != len(args.mavlink) and args.mavlink:
        raise ValueError("--mavlink: the same link given twice")
    for connection in links:
        problem = connection_problem(connection, free_port=True)
        if problem:
            raise ValueError(f"--mavlink {problem}")
    return ServeConfig(
        service,
        links[0],
        options_from_args(args),
        log,
        args.duration,
        foxglove_from_args(args),
        more_mavlink=tuple(links[1:]),
        spin_wait=args.spin_wait,
    )


def prepare_log_directory(log: LogOptions) -> None:
    """Create the log directory now, so that one that cannot hold a log (a file is there,
    no permission) is an error at start-up rather than every record dropped; OSError says
    why."""
    if log.directory is None:
        return
    directory = Path(log.directory)
    if directory.exists() and not directory.is_dir():
        raise OSError(f"--log-dir {directory}: not a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OSError(f"--log-dir {directory}: cannot create: {error.strerror}") from error
    if not os.access(directory, os.W_OK | os.X_OK):
        raise OSError(f"--log-dir {directory}: not writable")


def run(args: argparse.Namespace) -> int:
    try:
        config = config_from_args(args)
        config.zenoh.to_config()  # a bad config file is reported here, before anything opens
    except Exception as error:
        print(f"glider-hil serve: {error}", file=sys.stderr)
        return 2
    return main(config)


def main(config: ServeConfig) -> int:
    """Run the service until SIGINT/SIGTERM or ``config.duration``; 2 if a part cannot open."""
    try:
        prepare_log_directory(config.log)
    except OSError as error:
        print(f"glider-hil serve: {error}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    connections = (config.mavlink, *config.more_mavlink)
    wired = _start(config, connections)
    if wired is None:
        return 2
    tune_for_service()
    model = config.service.pipeline.model
    where = ", ".join(connections) if wired.link is None else wired.link.bound()
    print(f"{SERVICE_READY} on {where}, model {model}", file=sys.stderr, flush=True)
    if config.duration is not None:
        timer = threading.Timer(config.duration, stop.set)
        timer.daemon = True
        timer.start()
    started = time.monotonic()
    try:
        wired.service.run(stop)
    finally:
        summary = wired.service.summary()
        summary["wall_s"] = time.monotonic() - started
        if wired.live is not None:
            summary["foxglove"] = wired.live.status()
        log = wired.close()
        if log is not None:
            summary["log"] = log
    print(json.dumps({"service": summary}), flush=True)
    return 0


def _start(config: ServeConfig, connections: tuple[str, ...]) -> Wired | None:
    """The service wired on its parts, opened in turn (log, MAVLink links, Zenoh session,
    live view); None when one cannot open or the service cannot be wired, with the reason
    on stderr and every part opened so far closed again, the last opened first."""
    with contextlib.ExitStack() as opened:
        recorder = open_recorder(config.service, config.log)
        if recorder is not None:
            opened.callback(recorder.close)
        try:
            link: Link | LinkSet
            if len(connections) > 1 or config.service.vehicle_ids == "link":
                # Replies carry the link number (LinkSet): each vehicle's go back on its own.
                link = LinkSet(connections, 255, 191, spin_wait=config.spin_wait)
            else:
                link = Link(config.mavlink, 255, 191, spin_wait=config.spin_wait)
        except Exception as error:  # pymavlink raises many kinds for a bad connection string
            print(
                f"glider-hil serve: cannot open {', '.join(connections)}: {error}",
                file=sys.stderr,
            )
            return None
        opened.callback(link.close)
        try:
            session = open_session(config.zenoh)
        except Exception as error:  # zenoh raises its own ZError for bad endpoints
            print(f"glider-hil serve: cannot open Zenoh session: {error}", file=sys.stderr)
            return None
        opened.callback(session.close)
        try:
            live = start_live(config.foxglove, "serve")
        except OSError as error:
            print(f"glider-hil serve: {error}", file=sys.stderr)
            return None
        if live is not None:
            opened.callback(live.close)
        try:
            wired = wire(config.service, session=session, link=link, recorder=recorder, live=live)
        except Exception as error:  # zenoh raises its own ZError for a declaration it refuses
            print(f"glider-hil serve: cannot start the service: {error}", file=sys.stderr)
            return None
        opened.pop_all()  # from here on ``Wired.close`` closes them
        return wired
