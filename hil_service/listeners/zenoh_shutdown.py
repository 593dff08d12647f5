"""Zenoh sessions closed before the interpreter waits for its threads at exit.

zenoh-python runs a subscriber's or queryable's Python callback on a thread that is not a
daemon and ends only when its session closes. A process whose main thread ends with a
session still open (an uncaught exception before the ``finally`` that closes it, a script
that forgets) then waits for those threads forever: the interpreter joins every non-daemon
thread before it runs ``atexit``, so an ``atexit`` hook never gets its turn. ``close_at_exit``
registers the session with a hook that runs before that join
(``threading._register_atexit``, the hook ``concurrent.futures`` uses for its workers), so
such a process ends instead of hanging.
"""

from __future__ import annotations

import atexit
import contextlib
import threading
from typing import Any

import zenoh

#: Sessions opened through ``close_at_exit`` and not seen closed yet (zenoh's Session takes
#: no weak reference: closed ones are dropped from here whenever another is added).
_sessions: list[zenoh.Session] = []
_lock = threading.Lock()


def close_at_exit(session: zenoh.Session) -> zenoh.Session:
    """Close ``session`` at interpreter exit, before the non-daemon threads are joined, if
    nothing closed it before; returns it."""
    with _lock:
        _sessions[:] = [s for s in _sessions if not s.is_closed()]
        _sessions.append(session)
    return session


def _close_open_sessions() -> None:
    with _lock:
        open_sessions = [s for s in _sessions if not s.is_closed()]
        _sessions.clear()
    for session in open_sessions:
        # Exiting anyway: one that fails to close must not keep the others open.
        with contextlib.suppress(Exception):
            session.close()


_register: Any = getattr(threading, "_register_atexit", atexit.register)
_register(_close_open_sessions)
