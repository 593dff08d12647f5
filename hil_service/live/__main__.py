"""``python -m hil_service.live --fd N …``: the live view's process (server.py), started by
``LiveView.start``. Its priority is lowered first, before any thread exists (the SDK's
server threads, and one an import starts, inherit it): nice +``NICE``, and ``SCHED_BATCH``,
whose threads never preempt a running one when they wake (the service's thread, busy with a
sample, keeps its core while a batch arrives here)."""

from __future__ import annotations

import contextlib
import os
import sys

NICE = 5


def lower_priority() -> None:
    with contextlib.suppress(AttributeError, OSError):  # not Linux: nice alone
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    with contextlib.suppress(OSError):
        os.nice(NICE)


if __name__ == "__main__":
    lower_priority()
    from hil_service.live.server import main

    sys.exit(main())
