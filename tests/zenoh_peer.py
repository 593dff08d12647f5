"""A Zenoh peer for tests: explicit loopback endpoint, no scouting, collects JSON samples."""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from typing import Any

from hil_service.listeners.zenoh_config import ZenohOptions, open_session


class ZenohProbe:
    """Connects to ``endpoint`` (with ``config_file``'s settings, e.g. TLS and credentials,
    when given) and records every JSON sample under ``key``."""

    def __init__(self, endpoint: str, key: str = "glider/**", config_file: str | None = None):
        self.session = open_session(ZenohOptions(config_file, connect=(endpoint,)))
        self.lock = threading.Lock()
        self.received: dict[str, list[tuple[float, Any]]] = defaultdict(list)
        self.subscriber = self.session.declare_subscriber(key, self._on_sample)
        info = self.session.info
        connected = self.wait_for(
            lambda: any(True for _ in info.peers_zid()) or any(True for _ in info.routers_zid()),
            10,
        )
        assert connected, f"no Zenoh peer at {endpoint}"
        time.sleep(0.3)  # let the subscription reach the peer before anything is published

    def _on_sample(self, sample: Any) -> None:
        payload = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.received[str(sample.key_expr)].append((time.monotonic(), payload))

    def put(self, key: str, payload: Any) -> None:
        self.session.put(key, json.dumps(payload))

    def payloads(self, key: str) -> list[Any]:
        with self.lock:
            return [p for _, p in self.received.get(key, [])]

    def latest(self, key: str, default: Any = None) -> Any:
        """The last payload received on ``key``, or ``default`` before the first."""
        with self.lock:
            samples = self.received.get(key)
            return samples[-1][1] if samples else default

    def count(self, key: str) -> int:
        with self.lock:
            return len(self.received.get(key, []))

    def wait_for(self, predicate, timeout: float, poll: float = 0.05) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(poll)
        return predicate()

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()
