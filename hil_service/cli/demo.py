"""``glider-hil demo``: emulator and service as separate processes on loopback, driven over Zenoh.

Timeline (simulated time): the identifier learns from the emulator's excitation; then the
demo enables control over Zenoh and steps the depth and pitch setpoints twice; finally it
prints identification and tracking figures and where the MCAP log is.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil_service.cli.processes import (
    NotReady,
    free_port,
    last_json,
    start_service,
    start_verb,
    stop_process,
)
from hil_service.listeners.zenoh_config import ZenohOptions, open_session
from hil_service.live.address import LiveAddress
from hil_service.umodel import U_MODELS
from plant_emulator.scenarios import SCENARIOS
from protocols import keys
from protocols.flag_types import non_negative_int, positive_float

SYSTEM_ID = 1
TRIM_DEPTH = 15.0
ERROR_LINES = 20  # the last lines of a child's stderr shown when it exits early


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=positive_float, default=60.0, help="wall s (default 60)")
    parser.add_argument(
        "--speed", type=positive_float, default=50.0, help="x real time (default 50)"
    )
    parser.add_argument(
        "--scenario", choices=SCENARIOS, default="disturbed", help="emulator scenario"
    )
    parser.add_argument("--model", default="dynamic", choices=U_MODELS)
    parser.add_argument("--log-dir", default="logs")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument(
        "--signing",
        action="store_true",
        help="sign the MAVLink link both ways with a fresh key (kept in a private temp dir)",
    )
    parser.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        default=None,
        help="the service serves a Foxglove live view on PORT (loopback unless HOST is given)",
    )


@dataclass
class Observations:
    """What the demo's own Zenoh subscriber saw; written by Zenoh threads."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    telemetry: list[dict[str, Any]] = field(default_factory=list)
    commands: int = 0
    health: dict[str, Any] = field(default_factory=dict)

    def on_sample(self, sample: Any) -> None:
        parsed = keys.parse(str(sample.key_expr))
        kind = "" if parsed is None else parsed.kind
        payload = json.loads(sample.payload.to_bytes())
        with self.lock:
            if kind == keys.TELEMETRY:
                self.telemetry.append(payload)
            elif kind == keys.COMMAND_BALLAST:
                self.commands += 1
            elif kind == keys.HEALTH:
                self.health = payload

    def latest_t(self) -> float:
        with self.lock:
            return self.telemetry[-1]["t"] if self.telemetry else -1.0


def tracking_error(
    telemetry: list[dict[str, Any]], channel: str, segments: list[tuple[float, float, float]]
) -> float | None:
    """Mean |y − setpoint| over the second half of each setpoint segment (t0, t1, value)."""
    errors = []
    for t0, t1, value in segments:
        start = t0 + (t1 - t0) / 2
        errors += [abs(s[channel] - value) for s in telemetry if start <= s["t"] < t1]
    return sum(errors) / len(errors) if errors else None


def run(args: argparse.Namespace) -> int:
    udp_port, zenoh_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    sim_total = args.duration * args.speed
    t_control, t_second = 0.4 * sim_total, 0.7 * sim_total
    Path(args.log_dir).mkdir(parents=True, exist_ok=True)
    # Only with --signing: a demo killed outright cannot remove its temporary directory.
    key_dir = tempfile.TemporaryDirectory(prefix="glider-hil-demo-") if args.signing else None
    signing = signing_arguments(Path(key_dir.name)) if key_dir is not None else []
    try:
        service = start_service(
            "--mavlink", f"udpin:127.0.0.1:{udp_port}", "--zenoh-listen", endpoint,
            "--log-dir", args.log_dir, "--model", args.model, "--seed", str(args.seed),
            "--burn-in", str(int(0.25 * sim_total)), *signing,
            *(["--foxglove", args.foxglove] if args.foxglove else []),
        )  # fmt: skip
    except NotReady as error:
        print(f"demo: the service did not start: {error}", file=sys.stderr)
        if key_dir is not None:
            key_dir.cleanup()
        return 1
    emulator = None
    session = None
    observations = Observations()
    try:
        session = open_session(ZenohOptions(connect=(endpoint,)))
        subscriber = session.declare_subscriber(
            keys.vehicle_pattern(SYSTEM_ID), observations.on_sample
        )
        emulator = start_verb(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp_port}", "--speed", str(args.speed),
            "--duration", str(sim_total), "--scenario", args.scenario, "--seed", str(args.seed),
            "--trim-depth", str(TRIM_DEPTH), "--command-timeout", "5", "--fallback", "hold",
            *signing,
        )  # fmt: skip
        plan = [
            (t_control, {"depth": TRIM_DEPTH + 2.0, "pitch": 0.15}),
            (t_second, {"depth": TRIM_DEPTH - 1.0, "pitch": -0.1}),
        ]
        if args.foxglove:
            address = LiveAddress.parse(args.foxglove)
            print(f"demo: Foxglove live view on ws://{address.host}:{address.port}", flush=True)
        print(
            f"demo: {sim_total:.0f} simulated s at {args.speed:g}x; identification until "
            f"t={t_control:.0f}s, then setpoint steps at t={t_control:.0f}s and {t_second:.0f}s",
            flush=True,
        )
        deadline = time.monotonic() + args.duration + 20
        follow_plan(session, observations, (emulator, service), plan, deadline)
        subscriber.undeclare()
    finally:
        failed = {
            "emulator": emulator is not None and emulator.poll() not in (None, 0),
            "service": service.poll() is not None,  # it runs until the demo stops it
        }
        emulator_out, emulator_err = stop_process(emulator) if emulator is not None else ("", "")
        service_out, service_err = stop_process(service)
        if session is not None:
            session.close()
        if key_dir is not None:
            key_dir.cleanup()
    if failed["emulator"]:
        report_early_exit("emulator", emulator, emulator_err)
    if failed["service"]:
        report_early_exit("service", service, service_err)
    if any(failed.values()):
        return 1
    summary = last_json(service_out, "service")
    if not summary:
        print(f"demo: the service printed no summary\n{service_err}", file=sys.stderr)
        return 1
    result = demo_result(summary, observations, plan, sim_total, emulator_out)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print_summary(result)
    return 0 if result["samples"] and result["log"] else 1


def signing_arguments(key_dir: Path) -> list[str]:
    """A fresh signing key in ``key_dir`` (owner-only), as both processes' flag."""
    key_path = key_dir / "mavlink.key"
    key_path.touch(mode=0o600)
    key_path.write_bytes(os.urandom(32))
    return ["--signing-key", str(key_path)]


def report_early_exit(name: str, process: Any, stderr: str) -> None:
    """Say on stderr that the demo's ``name`` child ended before the demo stopped it, with
    its exit status and the end of its error output (an argparse error, a traceback)."""
    lines = stderr.strip().splitlines()[-ERROR_LINES:]
    print(
        f"demo: the {name} exited with status {process.returncode} before the demo's end; "
        "its stderr:",
        *lines,
        sep="\n",
        file=sys.stderr,
    )


def follow_plan(
    session: Any,
    observations: Observations,
    children: tuple[subprocess.Popen[str], ...],
    plan: list[tuple[float, dict[str, float]]],
    deadline: float,
) -> None:
    """Enable control and put each step's setpoints once the telemetry reaches its time,
    until one of ``children`` (the emulator, the service) exits or the wall-clock deadline
    passes."""
    step = 0
    while all(child.poll() is None for child in children) and time.monotonic() < deadline:
        t = observations.latest_t()
        if step < len(plan) and t >= plan[step][0]:
            session.put(keys.control(SYSTEM_ID), json.dumps({"enabled": True}))
            for channel, value in plan[step][1].items():
                session.put(keys.setpoint(SYSTEM_ID, channel), json.dumps({"value": value}))
            print(f"demo: t={t:.0f}s control on, setpoints {plan[step][1]}", flush=True)
            step += 1
        time.sleep(0.05)


def demo_result(
    summary: dict[str, Any],
    observations: Observations,
    plan: list[tuple[float, dict[str, float]]],
    sim_total: float,
    emulator_out: str,
) -> dict[str, Any]:
    """The demo's figures from the service's summary and what the subscriber saw."""
    segments = {
        ch: [
            (plan[0][0], plan[1][0], plan[0][1][ch]),
            (plan[1][0], sim_total, plan[1][1][ch]),
        ]
        for ch in ("depth", "pitch")
    }
    with observations.lock:
        telemetry = list(observations.telemetry)
        commands = observations.commands
        health = dict(observations.health)
    vehicle = summary.get("vehicles", {}).get(str(SYSTEM_ID), {})
    return {
        "samples": summary.get("counters", {}).get("samples", 0),
        "identification": {
            ch: {
                k: v.get(k)
                for k in (
                    "nmse",
                    "persistence_nmse",
                    "skill",
                    "multistep_fit",
                    "multistep_horizon",
                    "horizon_fit",
                )
            }
            for ch, v in vehicle.get("identifier", {}).items()
        },
        "tracking_mae": {ch: tracking_error(telemetry, ch, segments[ch]) for ch in segments},
        "commands_published": commands,
        "commands_sent": vehicle.get("commands_sent", 0),
        "acks": vehicle.get("acks", {}),
        "control_reason_at_end": health.get("control", {}).get("reason"),
        "log": summary.get("log", {}).get("file"),
        "emulator": last_json(emulator_out, "emulator").get("steps"),
        "signing": {
            k: v for k, v in summary.get("counters", {}).items() if k.startswith("signing_")
        },
    }


def _percent(value: Any) -> str:
    return "n/a" if value is None else f"{value:.1f} %"


def _multistep(scores: dict[str, Any]) -> str:
    """The free-run fit at the control horizon k, against the output's mean."""
    fit = scores.get("multistep_fit")
    return "n/a" if fit is None else f"{_percent(fit)} (k={scores.get('multistep_horizon')})"


def print_summary(result: dict[str, Any]) -> None:
    def fmt(value: Any) -> str:
        if value is None:
            return "n/a"
        return f"{value:.4g}" if isinstance(value, float) else str(value)

    print(f"\nsamples assembled: {result['samples']}")
    print(
        f"{'channel':8} {'NMSE':>10} {'persist.':>10} {'skill':>8} "
        f"{'k-step fit':>16} {'vs hold':>8} {'track MAE':>10}"
    )
    for channel, scores in result["identification"].items():
        mae = result["tracking_mae"].get(channel)
        unit = "m" if channel == "depth" else "rad"
        print(
            f"{channel:8} {fmt(scores['nmse']):>10} {fmt(scores['persistence_nmse']):>10} "
            f"{fmt(scores['skill']):>8} {_multistep(scores):>16} "
            f"{_percent(scores.get('horizon_fit')):>8} {fmt(mae):>8} {unit}"
        )
    print(
        f"commands: {result['commands_sent']} sent, acks {result['acks']}; "
        f"control at end: {result['control_reason_at_end'] or 'commanding'}"
    )
    if result["signing"]:
        print(f"signing: {result['signing']}")
    print(f"log: {result['log']}")
