"""One lockstep HIL mission over loopback UDP: the service in a forked process, the emulator
in this one.

The service is ``HilService`` wired by ``hil_service.builder`` as ``serve`` wires it, with
two differences that keep the run reproducible and cheap: setpoints come from the mission's
schedule, keyed by the sample's own timestamp (``ScheduledInbox``), instead of Zenoh, and
there is no Zenoh session: the recorder is the service's only listener. The
emulator is ``Autopilot`` driven by ``LockstepRunner``. A forked child starts in
milliseconds (the modules are already imported), which is what makes a campaign of short
missions fast; the service is a real process, so a test can kill it.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import socket
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.builder import Wired, open_recorder, wire
from hil_service.campaign.mission import Mission, Trace
from hil_service.cli.processes import set_parent_death_signal
from hil_service.config import LogOptions, ServiceConfig
from hil_service.inputs import ControlInputs, Inbox
from hil_service.pipeline import PipelineSettings
from plant_emulator.autopilot import Autopilot, AutopilotConfig
from plant_emulator.lockstep import LockstepRunner
from protocols.mavlink_io import Link
from protocols.samples import TelemetrySample

SERVICE_SUMMARY = "service.json"
SERVICE_ERROR = "service-error.txt"
#: Consecutive lockstep timeouts (the service alive) after which a run is given up.
MAX_CONSECUTIVE_TIMEOUTS = 5
READY_TIMEOUT = 60.0  # wall s for the forked service to open its link and log
STOP_TIMEOUT = 30.0  # wall s for it to close its log and exit once told to stop
#: What the mission process sends its service when the mission is over (it then exits 0).
MISSION_OVER = signal.SIGUSR1
#: Signals that interrupt a mission (Ctrl-C, kill, a batch system's stop, the parent-death
#: signal): a service or mission process stopped by one dies of it after closing its log,
#: and the mission is not recorded, so that ``--resume`` runs it again.
INTERRUPTING = (signal.SIGINT, signal.SIGTERM)


@dataclass(frozen=True)
class Placement:
    """Where a mission's two processes run and how they wait for each other.

    By default both sleep in ``select`` and the kernel places them: what a campaign wants,
    its jobs sharing the cores. With a core each (``service_cpus`` for the service, the
    caller's affinity for the emulator) and ``spin_wait`` s of polling, each side stays warm
    on its core and is woken without the scheduler (docs/lockstep.md, "Two cores"): a faster
    mission that burns both cores."""

    spin_wait: float = 0.0
    service_cpus: frozenset[int] | None = None


#: Both processes where the kernel puts them, sleeping while they wait: a campaign's.
SHARED_CORES = Placement()


class ScheduledInbox(Inbox):
    """Setpoints from the mission's schedule at the sample's own step: deterministic.

    The inputs of every step are made once, here: a step's lookup is an index (one object
    for each run of equal setpoints)."""

    def __init__(self, schedule: dict[str, np.ndarray], period: float):
        super().__init__()
        self.period_ms = period * 1000.0
        columns = {
            channel: [value if math.isfinite(value) else None for value in values.tolist()]
            for channel, values in schedule.items()
        }
        self.steps = len(next(iter(columns.values())))
        self._by_step: list[ControlInputs] = []
        inputs: ControlInputs | None = None
        for k in range(self.steps):
            setpoints = {channel: column[k] for channel, column in columns.items()}
            if inputs is None or inputs.setpoints != setpoints:
                inputs = ControlInputs(setpoints, True)
            self._by_step.append(inputs)

    def inputs_for(self, sample: TelemetrySample) -> ControlInputs:
        k = round(sample.time_boot_ms / self.period_ms)
        return self._by_step[min(max(k, 0), self.steps - 1)]

    def get(self, system_id: int) -> ControlInputs:
        return ControlInputs({"depth": None, "pitch": None}, True)


def service_config(mission: Mission) -> ServiceConfig:
    return ServiceConfig(
        system_ids=(1,),
        control_default=True,
        pipeline=PipelineSettings(seed=mission.seed),
        lockstep=True,
    )


def wire_mission_service(mission: Mission, link: Link, log_dir: Path | None) -> Wired:
    """The mission's service on ``link``, as ``serve`` wires it but with the mission's
    scheduled setpoints and no Zenoh (module docstring); its MCAP log in ``log_dir``
    (None: no log)."""
    config = service_config(mission)
    recorder = open_recorder(
        config,
        LogOptions(directory=None if log_dir is None else str(log_dir)),
        extra={"campaign.mission": json.dumps(mission.__dict__)},
    )
    inbox = ScheduledInbox(mission.schedule(), mission.period)
    return wire(config, link=link, recorder=recorder, inbox=inbox)


def _serve(mission: Mission, run_dir: Path, ready_fd: int, log: bool, placement: Placement) -> int:
    """The forked service: open, say the port on ``ready_fd``, serve until ``MISSION_OVER``
    (0 returned) or an interrupting signal (its number returned), also the SIGTERM it gets
    when the process that forked it dies mid-mission: no orphan service. SIGINT is left
    ignored when it is (a campaign started in the background is not one Ctrl-C stops)."""
    set_parent_death_signal(signal.SIGTERM)
    if placement.service_cpus is not None:
        os.sched_setaffinity(0, placement.service_cpus)
    stop = threading.Event()
    stopped_by: list[int] = []

    def interrupt(signum: int, _frame: object) -> None:
        stopped_by.append(signum)
        stop.set()

    signal.signal(MISSION_OVER, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, interrupt)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, interrupt)
    link = Link("udpin:127.0.0.1:0", 255, 191, spin_wait=placement.spin_wait)
    with socket.socket(fileno=os.dup(link.fileno())) as bound:
        port = bound.getsockname()[1]
    wired = wire_mission_service(mission, link, run_dir if log else None)
    os.write(ready_fd, f"{port}\n".encode())
    os.close(ready_fd)
    try:
        wired.service.run(stop)
        # What the vehicle sent before it stopped (the last acknowledgement) is in the
        # socket already (loopback delivers on send): take it, so every run logs it.
        while link.wait(0.0):
            data = link.recv()
            if not data:
                break
            wired.service.process_datagram(data, datagram=link.datagram)
    finally:
        summary = wired.service.summary()
        report = wired.close()
        summary["log"] = report
        (run_dir / SERVICE_SUMMARY).write_text(json.dumps(summary))
    return stopped_by[0] if stopped_by else 0


def _wait_ready(fd: int, timeout: float) -> int | None:
    """The port the service says it listens on, or None if it died or stayed silent."""
    deadline = time.monotonic() + timeout
    seen = b""
    while b"\n" not in seen:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        ready, _, _ = select.select([fd], [], [], min(remaining, 0.5))
        if ready:
            chunk = os.read(fd, 64)
            if not chunk:
                return None
            seen += chunk
    return int(seen.split(b"\n")[0])


def _exited(pid: int) -> int | None:
    """The wait status if ``pid`` has exited (reaped now), else None."""
    done, status = os.waitpid(pid, os.WNOHANG)
    return status if done == pid else None


def _describe(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"killed by signal {os.WTERMSIG(status)}"
    return f"exited with {os.WEXITSTATUS(status)}"


def interrupted(status: int) -> bool:
    """Whether a wait status is that of a process stopped by an interrupting signal."""
    return os.WIFSIGNALED(status) and os.WTERMSIG(status) in INTERRUPTING


def stop_process(pid: int, signum: int, timeout: float = STOP_TIMEOUT) -> int:
    """Send ``signum`` to the child ``pid``, SIGKILL it when it does not exit within
    ``timeout`` s; its wait status."""
    os.kill(pid, signum)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = _exited(pid)
        if status is not None:
            return status
        time.sleep(0.01)  # a bounded poll for the child's exit, not a pacing sleep
    os.kill(pid, signal.SIGKILL)
    return os.waitpid(pid, 0)[1]


def _stop_if_running(pid: int) -> None:
    """Interrupt the service and wait for it (its log closed), unless it was reaped."""
    try:
        if _exited(pid) is None:
            stop_process(pid, signal.SIGTERM)
    except ChildProcessError:  # reaped already
        pass


@dataclass
class HilOutcome:
    trace: Trace
    wall_s: float
    #: Wall s of the lockstep steps alone, first to last: the mission without its start-up
    #: (the service's readiness, the plant's build).
    steps_wall_s: float = 0.0
    emulator: dict[str, Any] = field(default_factory=dict)
    lockstep: dict[str, int] = field(default_factory=dict)
    service: dict[str, Any] = field(default_factory=dict)
    failure: str | None = None
    #: Why the mission was interrupted (its service stopped by a signal): not a result.
    interrupted: str | None = None
    log_path: str | None = None

    def end(self, status: int, where: str) -> None:
        """The service ended early with ``status``: interrupted or failed, said ``where``."""
        if interrupted(status):
            self.interrupted = f"service {_describe(status)} {where}"
        else:
            self.failure = f"service {_describe(status)} {where}"


def run_hil(
    mission: Mission,
    run_dir: Path,
    timeout: float = 1.0,
    kill_service_at: int | None = None,
    log: bool = True,
    placement: Placement = SHARED_CORES,
) -> HilOutcome:
    """The mission in lockstep over loopback; failures are returned, never raised. An
    exception (KeyboardInterrupt: the mission process was told to stop) interrupts the
    service and waits for it before it propagates."""
    run_dir.mkdir(parents=True, exist_ok=True)
    pid, read_fd = _fork_service(mission, run_dir, log, placement)
    try:
        return _run_with_service(
            mission, run_dir, pid, read_fd, timeout, kill_service_at, placement.spin_wait
        )
    except BaseException:
        _stop_if_running(pid)
        raise


def _run_with_service(
    mission: Mission,
    run_dir: Path,
    pid: int,
    read_fd: int,
    timeout: float,
    kill_service_at: int | None,
    spin_wait: float,
) -> HilOutcome:
    started = time.monotonic()
    trace = Trace.empty(mission.steps)
    try:
        port = _wait_ready(read_fd, READY_TIMEOUT)
    finally:
        os.close(read_fd)
    if port is None:
        outcome = HilOutcome(trace, 0.0)
        status = _exited(pid)
        if status is not None and interrupted(status):
            outcome.end(status, "before it was ready")
        else:
            if status is None:  # silent for READY_TIMEOUT s: a failure, not an interruption
                status = stop_process(pid, signal.SIGTERM, 5.0)
            outcome.failure = _service_failure(run_dir, status)
        outcome.wall_s = time.monotonic() - started
        return outcome
    outcome = HilOutcome(trace, 0.0)
    autopilot, runner, status = _run_emulator(
        mission, port, pid, timeout, kill_service_at, outcome, spin_wait
    )
    outcome.wall_s = time.monotonic() - started
    _end_service(outcome, pid, status, run_dir)
    _collect(outcome, autopilot, runner, run_dir)
    return outcome


def _fork_service(
    mission: Mission, run_dir: Path, log: bool, placement: Placement
) -> tuple[int, int]:
    """Fork the service (``_serve``): its pid, and the pipe end it writes its port to."""
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # the service
        os.close(read_fd)
        code = 1
        try:
            stopped_by = _serve(mission, run_dir, write_fd, log, placement)
            code = 0
            if stopped_by:  # dies of the signal, its log closed: the mission sees why
                signal.signal(stopped_by, signal.SIG_DFL)
                os.kill(os.getpid(), stopped_by)
        except BaseException:
            (run_dir / SERVICE_ERROR).write_text(traceback.format_exc())
        finally:
            os._exit(code)
    os.close(write_fd)
    return pid, read_fd


class _StepWatch:
    """The emulator's step hook: records each sample in the trace, kills the service at step
    ``kill_at`` (fault injection for tests), and stops the run when a lockstep timeout finds
    the service dead or it has stopped answering (``MAX_CONSECUTIVE_TIMEOUTS``)."""

    def __init__(
        self,
        autopilot: Autopilot,
        runner: LockstepRunner,
        pid: int,
        kill_at: int | None,
        outcome: HilOutcome,
        stop: threading.Event,
    ) -> None:
        self.autopilot = autopilot
        self.runner = runner
        self.pid = pid
        self.kill_at = kill_at
        self.outcome = outcome
        self.stop = stop
        self.timeouts = 0  # the runner's count when last looked at
        self.consecutive = 0
        self.status: int | None = None  # the service's wait status, once seen exited

    def __call__(self, sample: TelemetrySample) -> None:
        k = self.autopilot.stats.steps - 1
        self.outcome.trace.record(k, sample)
        if self.kill_at is not None and k == self.kill_at:
            os.kill(self.pid, signal.SIGKILL)  # fault injection (tests): the service dies here
        if self.runner.stats.timeouts > self.timeouts:
            self.timeouts = self.runner.stats.timeouts
            self.consecutive += 1
            status = _exited(self.pid)
            if status is not None:
                self.status = status
                self.outcome.end(status, f"at step {k}")
                self.stop.set()
            elif self.consecutive >= MAX_CONSECUTIVE_TIMEOUTS:
                self.outcome.failure = f"service stopped answering at step {k}"
                self.stop.set()
        else:
            self.consecutive = 0


def _run_emulator(
    mission: Mission,
    port: int,
    pid: int,
    timeout: float,
    kill_service_at: int | None,
    outcome: HilOutcome,
    spin_wait: float,
) -> tuple[Autopilot, LockstepRunner, int | None]:
    """The mission's vehicle in lockstep with the service on ``port``, to its last step or
    until ``_StepWatch`` stops it; the service's wait status if the watch saw it exit."""
    link = Link(f"udpout:127.0.0.1:{port}", 1, 1, spin_wait=spin_wait)
    stop = threading.Event()
    plant = mission.plant()
    autopilot = Autopilot(
        plant,  # type: ignore[arg-type]  # RandomPlant has everything Autopilot uses
        link,
        mission.excitations(),
        AutopilotConfig(system_id=1, duration=mission.steps * mission.period),
    )
    runner = LockstepRunner(autopilot, timeout)
    watch = _StepWatch(autopilot, runner, pid, kill_service_at, outcome, stop)
    autopilot.on_step = watch
    started = time.monotonic()
    try:
        runner.run(stop)
    finally:
        outcome.steps_wall_s = time.monotonic() - started
        link.close()
    return autopilot, runner, watch.status


def _end_service(outcome: HilOutcome, pid: int, status: int | None, run_dir: Path) -> None:
    """Reap the service (telling it the mission is over if it still runs) and fail the
    outcome if it ended early or not cleanly, or mark it interrupted if a signal stopped
    it."""
    if status is None:
        status = _exited(pid)
        if status is not None and outcome.failure is None and outcome.interrupted is None:
            outcome.end(status, "before the end")
    if status is None:
        status = stop_process(pid, MISSION_OVER)
    if outcome.failure is not None or outcome.interrupted is not None:
        return
    if interrupted(status):
        outcome.end(status, "at the end")
    elif not (os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0):
        outcome.failure = _service_failure(run_dir, status)


def _collect(
    outcome: HilOutcome, autopilot: Autopilot, runner: LockstepRunner, run_dir: Path
) -> None:
    """The emulator's, the runner's and the service's summaries, and the log's path."""
    outcome.emulator = autopilot.stats.as_dict(autopilot.codec)
    outcome.lockstep = runner.stats.as_dict()
    summary_path = run_dir / SERVICE_SUMMARY
    if summary_path.exists():
        outcome.service = json.loads(summary_path.read_text())
    counted = outcome.service.get("counters", {})
    served = counted.get("samples", 0)
    if outcome.failure is None and outcome.interrupted is None and served < autopilot.stats.steps:
        # In lockstep the service releases every step, so a step it did not take was
        # released by something else: a process that shares its port and took the vehicle.
        outcome.failure = (
            f"the service took {served} of the {autopilot.stats.steps} samples sent: "
            "another process received the rest"
        )
    dropped = {k: counted.get(k, 0) for k in ("invalid", "incomplete", "out_of_order")}
    if (
        outcome.failure is not None
        and "stopped answering" in outcome.failure
        and any(dropped.values())
    ):
        # A sample the service drops is never released (docs/lockstep.md): say which.
        named = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in dropped.items() if n)
        outcome.failure += f": the service dropped samples ({named})"
    logs = sorted(run_dir.glob("*.mcap"))
    outcome.log_path = str(logs[-1]) if logs else None


def _service_failure(run_dir: Path, status: int) -> str:
    error = run_dir / SERVICE_ERROR
    detail = ""
    if error.exists():
        lines = error.read_text().strip().splitlines()
        detail = f": {lines[-1]}" if lines else ""
    return f"service {_describe(status)}{detail}"
