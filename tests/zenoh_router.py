"""A Zenoh router in its own process, for tests that kill and restart it.

Run: python -m tests.zenoh_router ENDPOINT [CONFIG.json5]. It subscribes to ``glider/**``
and prints one
JSON line per 0.2 s with the number of samples received so far; it exits on SIGTERM/SIGINT.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time

from hil_service.zenoh_config import ZenohOptions, open_session


def main(endpoint: str, config_file: str | None = None) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    session = open_session(ZenohOptions(config_file, mode="router", listen=(endpoint,)))
    received = [0]

    def count(_sample: object) -> None:
        received[0] += 1

    subscriber = session.declare_subscriber("glider/**", count)
    while not stop.wait(0.2):
        print(json.dumps({"received": received[0], "t": time.time()}), flush=True)
    subscriber.undeclare()
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
