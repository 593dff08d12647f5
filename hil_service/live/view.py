"""The live view's side in the service's process: a bounded hand-off to the process that
owns the Foxglove WebSocket server (server.py), off the control path and off its GIL.

The service's thread calls ``offer(topic, payload)`` and ``offer_mavlink(direction, message,
frame)``: one bounded-deque append, or a counted drop when the deque is full; it never
encodes, never waits. While no client subscribes to a MAVLink channel, a MAVLink message of
a type already handed over is not even queued (the live view's process says whether one
does; a viewer that subscribes gets them from the next batch on). Every ``FLUSH_PERIOD`` at
most, the offer that finds the period over sends what the deque holds to the live view's
process as pickled batches (wire.py): a non-blocking socket send per batch, about a
microsecond an entry, on the service's own thread. So no other thread of this process takes
the GIL from it for the live view (a thread that did, 50 times a second, made the service's
thread wait for it and then for a core); a helper thread only looks every ``IDLE_CHECK`` for
entries left when offers stop, and for the live view's status. All the rest (channels, JSON
of MAVLink messages, the SDK's calls, its server's threads) runs in that process, on its
own interpreter and at a lower priority, so that it competes with the service's thread
neither for the GIL nor, when the cores are busy, for a core. When that process falls
behind, batches wait here, within the same bound as the deque, and past it new entries are
dropped and counted (``live_dropped``).
"""

from __future__ import annotations

import contextlib
import json
import pickle
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from typing import Any

from hil_service.live.address import LiveAddress
from hil_service.live.wire import MAVLINK, MAX_MESSAGE, MAX_STATUS
from protocols import keys
from protocols.mavlink_io import MavMessage

#: Entries held between the service and the live view's process (here, unsent); past that
#: they are dropped.
MAX_PENDING = 10_000
#: Between two sends of the deque's entries by the offering thread, s.
FLUSH_PERIOD = 0.02
#: Between two looks of the helper thread (entries left queued once offers stopped; the
#: live view's status while nothing is offered), s: the view's latency when idle.
IDLE_CHECK = 0.05
#: Entries in one batch message at most (also split when its pickle exceeds MAX_MESSAGE).
MAX_BATCH = 256
#: How long the live view's process may take to start its server (a loaded machine), s.
START_TIMEOUT = 60.0
#: How long ``close`` waits for it to send what it holds and end, s.
STOP_TIMEOUT = 10.0
#: Asked of the socket's send buffer (the kernel caps it at net.core.wmem_max, doubled).
SEND_BUFFER = 4 * 1024 * 1024


class LiveView:
    """``start()`` starts the live view's process and its server; ``offer`` from any
    thread; ``close()`` stops both."""

    def __init__(
        self, address: LiveAddress, name: str = "glider-hil", max_pending: int = MAX_PENDING
    ):
        self.address = address
        self.name = name
        self.max_pending = max_pending
        self.offered = 0
        self.dropped = 0  # offered while the deque (with what waits unsent) was full
        self.unwatched = 0  # MAVLink messages not queued: no client watched a MAVLink channel
        self._send_dropped = 0  # entries dropped when sending (refused by pickle, too big, or
        # the live view's process gone)
        self._pending: deque[tuple[str, Any, int]] = deque()
        #: Batches (entries, pickle) the live view's process could not take yet, and how many
        #: entries they hold (read by ``offer`` for the bound).
        self._unsent: deque[tuple[list[Any], bytes]] = deque()
        self._backlog = 0
        self._handed = 0  # entries the live view's process was sent
        #: (direction, type) of every MAVLink message handed over (its channels exist there
        #: or soon will).
        self._known: set[tuple[str, str]] = set()
        #: Whether a client subscribes to a MAVLink channel (the live view's process says);
        #: while none does, the control path queues no MAVLink message it has seen before.
        self._mavlink_watched = False
        #: The live view's process's latest status (server.py ``LiveServer.status``).
        self._status: dict[str, Any] = {}
        self._port = address.port
        self._process: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        self._inputs: list[Any] = []
        #: Held by whichever thread sends (an offering one, the helper, ``sync``, ``close``);
        #: an offer that finds it taken leaves its entry for that one, never waits.
        self._sending = threading.Lock()
        self._flush_due = 0  # time.time_ns() from which an offer sends the queue
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foxglove-live", daemon=True)

    def start(self) -> LiveView:
        """Start the live view's process; return once its server listens. Raises
        RuntimeError with the server's reason if it cannot (e.g. a port in use)."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        with contextlib.suppress(OSError):
            ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        try:
            self._process = subprocess.Popen(
                [
                    sys.executable, "-m", "hil_service.live",
                    "--fd", str(theirs.fileno()), "--host", self.address.host,
                    "--port", str(self.address.port), "--name", self.name,
                ],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,  # the service's stdout carries its JSON summary
            )  # fmt: skip
        finally:
            theirs.close()
        ours.settimeout(START_TIMEOUT)
        try:
            first = ours.recv(MAX_STATUS)
        except TimeoutError:
            first = b'{"error": "no answer within %d s"}' % START_TIMEOUT
        ready = json.loads(first) if first else {"error": "its process ended"}
        if "port" not in ready:
            ours.close()
            self._end_process()
            raise RuntimeError(f"the live view's server did not start: {ready.get('error')}")
        self._port = int(ready["port"])
        ours.setblocking(False)
        self._sock = ours
        self._thread.start()
        return self

    @property
    def port(self) -> int:
        """The port the server listens on (the one chosen when 0 was asked)."""
        return self._port

    @property
    def pid(self) -> int | None:
        """The live view's process (None before ``start``)."""
        return None if self._process is None else self._process.pid

    @property
    def url(self) -> str:
        return f"ws://{self.address.host}:{self.port}"

    # ---- producer side: the control path ------------------------------------------------
    def offer(self, topic: str, payload: Any, t_ns: int = 0) -> None:
        """Hand a payload to the live view; never blocks. ``payload`` is already encoded
        ``bytes``, or a JSON-ready object the caller does not change afterwards."""
        self.offered += 1
        if len(self._pending) + self._backlog >= self.max_pending:
            self.dropped += 1
            return
        if not t_ns:
            t_ns = time.time_ns()
        self._pending.append((topic, payload, t_ns))
        if t_ns >= self._flush_due:
            self._send_queued(False)

    def offer_mavlink(
        self, direction: str, message: MavMessage | None, frame: bytes | None, t_ns: int
    ) -> None:
        """A MAVLink message the service received (``in``) or sent (``out``), or a frame it
        refused (``rejected``, no message): streamed raw and, for a message, decoded. The
        frame defaults to the message's own bytes. Never blocks (as ``offer``)."""
        self.offered += 1  # as offer, inlined: this runs for every frame
        kind = None
        if message is not None:
            kind = message.get_type()
            if not self._mavlink_watched and (direction, kind) in self._known:
                self.unwatched += 1
                return  # nobody watches a MAVLink channel, and this one is advertised already
        if len(self._pending) + self._backlog >= self.max_pending:
            self.dropped += 1
            return
        if kind is not None:
            self._known.add((direction, kind))
        if frame is None:
            frame = message.get_msgbuf()  # type: ignore[union-attr]
        # A received message is decoded again from its frame there; a sent one travels as
        # the object, so that its JSON is the log's (fields before packing).
        sent = message if direction == "out" else None
        self._pending.append((MAVLINK, (direction, kind, frame, sent), t_ns))
        if t_ns >= self._flush_due:
            self._send_queued(False)

    # ---- as a listener of the service's stream (hil_service.listeners) -----------------
    def on_mavlink(
        self, direction: str, message: MavMessage | None, frame: bytes | None, t_ns: int
    ) -> None:
        self.offer_mavlink(direction, message, frame, t_ns)

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        """A publication, as the bytes Zenoh and the log carry."""
        self.offer(key, data, time.time_ns())

    def watched(self) -> bool:
        """Whether a client subscribes to at least one channel (as last reported)."""
        return bool(self._status.get("watched", False))

    def counters(self) -> dict[str, int]:
        """What health's ``service_wide`` carries: messages offered to the live view, passed
        to the server for a subscribed viewer, dropped because the hand-off was full (the
        live view's process fell behind), and the server's reports that a viewer too slow to
        read had its oldest messages dropped (throttled by the SDK: at least one per episode,
        not one per message)."""
        status = self._status
        return {
            "live_offered": self.offered,
            "live_sent": int(status.get("sent", 0)),
            "live_dropped": self.dropped + self._send_dropped,
            "live_viewer_overflows": int(status.get("viewer_overflows", 0)),
        }

    def pending(self) -> int:
        """Entries offered and not yet taken by the live view's process (as last reported)."""
        return (
            len(self._pending) + self._backlog + self._handed - int(self._status.get("received", 0))
        )

    def status(self) -> dict[str, Any]:
        status = self._status
        return {
            "url": self.url,
            "offered": self.offered,
            "sent": int(status.get("sent", 0)),
            "dropped": self.dropped + self._send_dropped,
            "mavlink_unwatched": self.unwatched,
            "received": int(status.get("received", 0)),  # taken by the live view's process
            "encode_errors": int(status.get("encode_errors", 0)),
            "viewer_overflows": int(status.get("viewer_overflows", 0)),
            "pending": self.pending(),
        }

    def sync(self, timeout: float = 60.0) -> bool:
        """Send what is queued now and wait until the live view's process has taken it all
        (a benchmark's end of run); False if it has not within ``timeout``."""
        deadline = time.monotonic() + timeout
        while self._send_queued(True) > 0:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.0005)
        return True

    def watch_inputs(self, session: Any) -> None:
        """Also stream the inputs the service receives (setpoints, control), as the log
        records them: a Zenoh subscriber of our own whose callback only offers the bytes."""

        def on_input(sample: Any) -> None:
            self.offer(str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())

        self._inputs = [
            session.declare_subscriber(key_expr, on_input) for key_expr in keys.INPUT_SUBSCRIPTIONS
        ]

    # ---- sending --------------------------------------------------------------------------
    def _send_queued(self, wait: bool) -> int:
        """Send what is queued and read the live view's status; then the entries pending
        (offered, not yet taken there), or -1 when another thread was sending and
        ``wait`` is False (an offer: that thread sends its entry)."""
        if not self._sending.acquire(wait):
            return -1
        try:
            self._flush_due = time.time_ns() + int(FLUSH_PERIOD * 1e9)
            if self._sock is not None:
                self._flush()
                self._read_status()
            # Exact here: no entry is in a sender's hands while this lock is held.
            return self.pending()
        finally:
            self._sending.release()

    def _run(self) -> None:
        # Only a look, while the service's thread sends: each takes the GIL for an instant.
        while not self._stop.wait(IDLE_CHECK):
            if time.time_ns() >= self._flush_due:  # nobody sent lately
                self._send_queued(False)

    def _flush(self) -> None:
        while self._unsent:  # what the live view's process could not take before, first
            entries, data = self._unsent[0]
            if not self._transmit(entries, data):
                break
            self._unsent.popleft()
            self._backlog -= len(entries)
        pending = self._pending
        count = len(pending)
        if not count:
            return
        popleft = pending.popleft
        taken = [popleft() for _ in range(count)]
        for start in range(0, count, MAX_BATCH):
            for entries, data in self._pieces(taken[start : start + MAX_BATCH]):
                if self._unsent or not self._transmit(entries, data):
                    self._unsent.append((entries, data))
                    self._backlog += len(entries)

    def _pieces(self, batch: list[tuple[str, Any, int]]) -> list[tuple[list[Any], bytes]]:
        """``batch`` pickled, split into halves until each fits a message; an entry that
        pickle refuses or that alone exceeds a message is dropped and counted."""
        try:
            data: bytes | None = pickle.dumps(batch, pickle.HIGHEST_PROTOCOL)
        except Exception:  # an object pickle refuses: halves, down to the one to drop
            data = None
        if data is not None and len(data) <= MAX_MESSAGE:
            return [(batch, data)]
        if len(batch) == 1:
            self._forget(batch)
            return []
        half = len(batch) // 2
        return self._pieces(batch[:half]) + self._pieces(batch[half:])

    def _transmit(self, entries: list[tuple[str, Any, int]], data: bytes) -> bool:
        """One batch message, never waiting: False if the socket is full now (the live
        view's process is behind); a batch that can never go (its process ended) is
        dropped and counted."""
        sock = self._sock
        if sock is None:  # closed meanwhile (``close`` gave up waiting for this thread)
            self._forget(entries)
            return True
        try:
            sock.send(data)
        except BlockingIOError:
            return False
        except OSError:
            self._forget(entries)
            return True
        self._handed += len(entries)
        return True

    def _forget(self, batch: list[tuple[str, Any, int]]) -> None:
        """Count a batch as dropped; its MAVLink types were not advertised after all."""
        self._send_dropped += len(batch)
        for topic, payload, _ in batch:
            if topic == MAVLINK and payload[1] is not None:
                self._known.discard((payload[0], payload[1]))

    def _read_status(self) -> None:
        """Keep the latest status the live view's process sent."""
        sock = self._sock
        latest = None
        while sock is not None:
            try:
                data = sock.recv(MAX_STATUS)
            except (BlockingIOError, ConnectionError):
                break
            if not data:
                break
            latest = data
        if latest is not None:
            self._take_status(latest)

    def _take_status(self, data: bytes) -> None:
        """Keep one status message of the live view's process (a malformed one is ignored)."""
        with contextlib.suppress(ValueError):
            status = json.loads(data)
            self._status = status
            self._mavlink_watched = bool(status.get("mavlink_watched", False))

    # ---- stopping -------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the inputs' subscriber, send what is queued, let the live view's process
        take it and end (its last status kept for ``status()``)."""
        for subscriber in self._inputs:
            subscriber.undeclare()
        self._inputs = []
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(STOP_TIMEOUT)
        deadline = time.monotonic() + STOP_TIMEOUT
        self._send_queued(True)
        while self._unsent and time.monotonic() < deadline:  # let it take what waits
            time.sleep(0.005)
            self._send_queued(True)
        with self._sending:
            sock, self._sock = self._sock, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_WR)  # the live view's process sees the end
            sock.settimeout(STOP_TIMEOUT)
            with contextlib.suppress(OSError):
                while data := sock.recv(MAX_STATUS):  # its statuses, to the last
                    self._take_status(data)
            sock.close()
        self._end_process()

    def _end_process(self) -> None:
        process = self._process
        if process is None:
            return
        try:
            process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(STOP_TIMEOUT)
