"""Interpreter settings for a process that runs the per-sample path for a long time.

``serve`` and ``replay`` call :func:`tune_for_service` once, after start-up; the benchmarks
call it too, so that they measure the path as those commands run it. Every ``glider-hil``
command calls :func:`single_threaded_blas` before anything loads numpy.

* Switch interval 0.5 ms: the recorder's thread must not hold the GIL for the default
  5 ms while a telemetry datagram waits, so a short interval bounds the control path's wait.
* ``gc.freeze()`` after start-up: the modules and objects that exist then (numpy, scipy,
  Zenoh, pymavlink's dialect: hundreds of thousands of objects) live as long as the process,
  and without the freeze every full collection traverses them again.
* A full collection every hour, on the clock, and no automatic collections. Each sample
  allocates a few hundred container objects (decoded messages, payload dicts, log records,
  the model's multi-step map), and a vehicle's replace the previous sample's a vehicle
  cycle later: with 1,000 gliders at 1 Hz about 60,000 of them are alive at any time, and
  counted allocations set off a young collection every few seconds that traverses them all
  whatever its threshold (50-100 ms), and, the first time, every vehicle's long-lived
  identifiers and controllers too (0.44 s). Each is a stall of every vehicle's sample. The
  per-sample path makes no reference cycles (no collection measured found garbage; and
  ``benchmarks/fleet_inprocess.py`` prints what one collection finds after a run with
  collections off), so objects are freed by their reference counts as they are replaced,
  and the hourly collection (0.4-0.9 s with 1,000 vehicles as their windows fill,
  docs/fleet.md) reclaims any reference cycle within the hour.
"""

from __future__ import annotations

import gc
import os
import sys
import threading
from collections.abc import Callable

#: The variables through which OpenBLAS (numpy's and scipy's wheels) and MKL take their
#: thread count, once, when they load.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
SWITCH_INTERVAL_S = 0.0005
COLLECTION_PERIOD_S = 3600.0

_collector: Collector | None = None


class Collector:
    """A daemon thread that runs a full garbage collection every ``period`` seconds."""

    def __init__(self, period: float) -> None:
        if not period > 0:
            raise ValueError(f"collection period must be positive, not {period}")
        self.period = period
        self.collections = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gc-collector", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            gc.collect()
            self.collections += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def tune_for_service() -> None:
    """Idempotent: a second call freezes what exists then and keeps the one collector."""
    global _collector
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    gc.collect()
    gc.freeze()
    gc.disable()
    if _collector is None:
        _collector = Collector(COLLECTION_PERIOD_S)


def single_threaded_blas() -> None:
    """BLAS and LAPACK on the calling thread, unless the user set a thread count: in effect
    for the libraries loaded after the call, and for child processes.

    Their matrices here are small (a structure choice's least squares, 400 × 29; the
    oracle's bases), where a thread pool only adds its hand-offs, and its threads spin on
    the cores the service, the emulator and a campaign's missions need: on a 2-core machine
    with both cores busy, one channel's structure choice took up to 0.3-0.5 s with numpy's
    default of a thread per core, 33-50 ms on one thread (``benchmarks/choice_cost.py``;
    docs/benchmarks.md, "The structure choices of a fleet that started together")."""
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")


def one_cpu_child() -> tuple[int, Callable[[], None]]:
    """(cpu, preexec_fn) that pins a child process and every thread it will start (Zenoh's
    runtime included) to the first CPU this process may use: "on one core", literally."""
    cpu = min(os.sched_getaffinity(0))
    return cpu, lambda: os.sched_setaffinity(0, {cpu})
