"""The service's Zenoh side, a listener of its stream (``hil_service.listeners``).

``ZenohPublisher`` puts every publication's bytes on its key (commands with congestion
control BLOCK, the rest with DROP), declares each vehicle's liveliness token and state
queryable, and hands received setpoints and control messages to an ``Inbox`` without
blocking Zenoh's callback threads; each received input is also told to ``record`` (the
notifier's, so that the log keeps it; refused ones apart, with the reason).

Before it declares a vehicle's token it asks the network whether another service already
holds it (overlapping ``--sysid`` ranges behind one router): one warning line on stderr and
a count (``counters``), both services kept running. The question is asked without waiting
for the answer, which comes on a Zenoh thread, so a vehicle's first sample never waits on
the network.
"""

from __future__ import annotations

import json
import sys
import threading
from collections.abc import Callable
from typing import Any

import zenoh
from zenoh.handlers import Callback

from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from hil_service.listeners.notifier import PublisherTable
from protocols import keys, payload_json

#: Where a received input goes besides the inbox: (key, payload, direction).
Record = Callable[[str, Any, str], None]

#: How long, at most, the question "does another service hold this vehicle's token?" waits
#: for its answers (s). A router answers from its own table, in about a millisecond; the
#: bound is for a network that does not answer, and nothing waits on it but the question.
HOLDER_QUERY_TIMEOUT = 2.0


def warn_on_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class ZenohPublisher(Listener):
    def __init__(
        self,
        session: zenoh.Session,
        inbox: Inbox,
        record: Record | None = None,
        warn: Callable[[str], None] = warn_on_stderr,
        program: str = "glider-hil serve",
    ):
        self.session = session
        self.inbox = inbox
        self.record = record
        self.warn = warn
        self.program = program  # names the warning's sender
        # The publications go through a compiled table (notifier.PublisherTable): this
        # instance's ``on_publish`` is the table's, which the notifier calls for every
        # publication without a Python frame (``handler_of`` takes it from the instance).
        self._table = PublisherTable(self._declare)
        self._publishers: dict[str, zenoh.Publisher] = self._table.publishers
        self.on_publish = self._table.on_publish  # type: ignore[method-assign]
        self._declared: dict[int, list[Any]] = {}
        # Vehicles whose token another service held, and those whose question has had
        # every answer: written on Zenoh threads, read by the service (under the lock).
        self._lock = threading.Lock()
        self._served_elsewhere: set[int] = set()
        self._answered: set[int] = set()
        self._subscribers: list[Any] = [
            session.declare_subscriber(key_expr, self._on_input)
            for key_expr in keys.INPUT_SUBSCRIPTIONS
        ]

    def _on_input(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: parse and store only, never block.
        key = str(sample.key_expr)
        raw = sample.payload.to_bytes()
        reason = self.inbox.accept(key, raw)
        if self.record is None:
            return
        if reason:  # kept apart, so each input channel holds only what its schema allows
            text = raw.decode("utf-8", "replace")
            refused = {"key": key, "text": text, "reason": reason}
            self.record(keys.rejected_inputs(), refused, "in")
        else:
            self.record(key, json.loads(raw), "in")

    def _declare(self, key: str, reliable: bool) -> zenoh.Publisher:
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        publisher = self.session.declare_publisher(
            key, congestion_control=congestion, encoding=zenoh.Encoding.APPLICATION_JSON
        )
        self._publishers[key] = publisher
        return publisher

    def on_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        """Liveliness token and state queryable for a newly seen vehicle, and the
        publishers of its keys: declaring one costs in proportion to the keys already
        declared (about 1 ms each with 1,000 vehicles), so a fleet pays it when its
        vehicles appear, not on the sample its control starts."""
        if system_id in self._declared:
            return
        for key, reliable in keys.VehicleKeys.of(system_id).publications():
            if key not in self._publishers:
                self._declare(key, reliable)

        def answer(query: zenoh.Query) -> None:
            query.reply(keys.state(system_id), payload_json.encode(state()))

        self._ask_for_other_holders(system_id)
        self._declared[system_id] = [
            self.session.liveliness().declare_token(keys.service(system_id)),
            self.session.declare_queryable(keys.state(system_id), answer),
        ]

    def _ask_for_other_holders(self, system_id: int) -> None:
        """Ask for the tokens of ``system_id`` already held, without waiting for the answer.

        Asked before this service declares its own: a token counts only if it is another's
        (the question reaches this session's tables and the router before the declaration
        does). Two services that start serving a vehicle at the same moment may both be
        answered before either token is declared, and neither warns."""

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._served_elsewhere_too(system_id)

        def on_answered() -> None:
            with self._lock:
                self._answered.add(system_id)

        self.session.liveliness().get(
            keys.service(system_id),
            Callback(on_reply, on_answered),
            timeout=HOLDER_QUERY_TIMEOUT,
        )

    def _served_elsewhere_too(self, system_id: int) -> None:
        """Counted and said once per vehicle, however many answers name it (a router
        answers once for its clients' tokens, peers each for their own)."""
        with self._lock:
            if system_id in self._served_elsewhere:
                return
            self._served_elsewhere.add(system_id)
        self.warn(
            f"{self.program}: vehicle {keys.key_id(system_id)} is also served by another "
            "service on this Zenoh network (overlapping --sysid ranges?)"
        )

    def served_elsewhere(self, system_id: int) -> bool | None:
        """Whether another service held ``system_id``'s token when this one started
        serving it; None until the network has answered (or the question timed out)."""
        with self._lock:
            if system_id in self._served_elsewhere:
                return True
            return False if system_id in self._answered else None

    def counters(self) -> dict[str, int]:
        """For health's ``service_wide``: ``vehicles_served_elsewhere``, this service's
        vehicles whose token another service already held when it started serving them."""
        with self._lock:
            return {"vehicles_served_elsewhere": len(self._served_elsewhere)}

    def stop(self) -> None:
        for declared in [*self._subscribers, *self._publishers.values()]:
            declared.undeclare()
        for items in self._declared.values():
            for item in items:
                item.undeclare()
        self._publishers.clear()
        self._declared.clear()
