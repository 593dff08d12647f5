"""Interpreter settings for a process that runs the per-sample path for a long time.

``serve`` and ``replay`` call :func:`tune_for_service` once, after start-up; the benchmarks
call it too, so that they measure the path as those commands run it.

* Switch interval 0.5 ms: the recorder's thread must not hold the GIL for the default
  5 ms while a telemetry datagram waits, so a short interval bounds the control path's wait.
* ``gc.freeze()`` after start-up: the modules and objects that exist then (numpy, scipy,
  Zenoh, pymavlink's dialect: hundreds of thousands of objects) live as long as the process,
  and without the freeze every full collection traverses them again.
* Thresholds for a fleet's state. Each sample allocates a few hundred container objects
  (decoded messages, payload dicts, log records, the model's multi-step map), and a
  vehicle's replace the previous sample's a vehicle cycle later: with 1,000 gliders at 1 Hz,
  about 60,000 of them are alive at any time, and a young collection traverses all of them
  whatever its threshold (50-70 ms). With the older generations collected every 10 young
  collections, those survivors fill them, and their collections take 160-460 ms every few
  seconds and find no garbage (the per-sample path makes no reference cycles: 0 collected in
  every collection measured). So young collections every 20,000 net allocations (every few
  seconds in such a fleet, rarely for one vehicle), the middle generation every 100 of them
  and the full one every 10 of those (about an hour in that fleet): reference cycles are
  still reclaimed, and the long pauses are rare instead of constant
  (``benchmarks/fleet_inprocess.py``, docs/benchmarks.md).
"""

from __future__ import annotations

import gc
import os
import sys
from collections.abc import Callable

SWITCH_INTERVAL_S = 0.0005
GC_THRESHOLDS = (20_000, 100, 10)


def tune_for_service() -> None:
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


def one_cpu_child() -> tuple[int, Callable[[], None]]:
    """(cpu, preexec_fn) that pins a child process and every thread it will start (Zenoh's
    runtime included) to the first CPU this process may use: "on one core", literally."""
    cpu = min(os.sched_getaffinity(0))
    return cpu, lambda: os.sched_setaffinity(0, {cpu})
