"""A minimal ground-station peer for tests: a UDP socket on a free loopback port + our codec."""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass, field

from protocols.mavlink_io import MavlinkCodec, MavMessage


@dataclass
class Received:
    message: MavMessage
    arrival: float


@dataclass
class UdpPeer:
    system_id: int = 255
    component_id: int = 190
    sock: socket.socket = field(init=False)
    codec: MavlinkCodec = field(init=False)
    remote: tuple[str, int] | None = None

    def __post_init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.codec = MavlinkCodec(self.system_id, self.component_id)

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def receive_for(self, seconds: float) -> list[Received]:
        return self.receive_until(lambda _: False, seconds)

    def receive_until(self, done, timeout: float) -> list[Received]:
        """Collect messages until ``done(all_so_far)`` is true or ``timeout`` s pass."""
        received: list[Received] = []
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                data, address = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            self.remote = address
            now = time.monotonic()
            received.extend(Received(m, now) for m in self.codec.parse(data, datagram=True))
            if done(received):
                break
        return received

    def send(self, message: MavMessage) -> None:
        assert self.remote is not None, "no datagram received yet: peer address unknown"
        self.sock.sendto(self.codec.pack(message), self.remote)

    def send_raw(self, data: bytes) -> None:
        assert self.remote is not None
        self.sock.sendto(data, self.remote)

    def close(self) -> None:
        self.sock.close()
