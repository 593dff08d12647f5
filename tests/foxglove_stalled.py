"""A Foxglove WebSocket viewer that subscribes to every channel and then stops reading.

Raw sockets and the WebSocket handshake by hand (RFC 6455): the viewer that every slow or
hung browser tab becomes. Its receive buffer is made small so that the server's writes back
up after a few messages.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time


class StalledViewer:
    def __init__(self, host: str, port: int, timeout: float = 30.0):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self.sock.settimeout(timeout)
        self.sock.connect((host, port))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
            ).encode()
        )
        self._buffer = b""
        while b"\r\n\r\n" not in self._buffer:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("the server closed the handshake")
            self._buffer += chunk
        head, _, self._buffer = self._buffer.partition(b"\r\n\r\n")
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ConnectionError(head.decode(errors="replace"))
        self.subscribed: dict[int, str] = {}
        self.advertised: dict[str, dict[str, object]] = {}  # topic → channel (wait_advertised)

    def _read_exact(self, n: int) -> bytes:
        while len(self._buffer) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("closed")
            self._buffer += chunk
        data, self._buffer = self._buffer[:n], self._buffer[n:]
        return data

    def _frame(self) -> tuple[int, bytes]:
        first, second = self._read_exact(2)
        length = second & 0x7F
        if length == 126:
            (length,) = struct.unpack("!H", self._read_exact(2))
        elif length == 127:
            (length,) = struct.unpack("!Q", self._read_exact(8))
        return first & 0x0F, self._read_exact(length)

    def _send_text(self, text: str) -> None:
        payload = text.encode()
        mask = os.urandom(4)
        header = bytes([0x81])
        if len(payload) < 126:
            header += bytes([0x80 | len(payload)])
        else:
            header += bytes([0x80 | 126]) + struct.pack("!H", len(payload))
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(header + mask + masked)

    def subscribe_until(self, topic_prefix: str, count: int, timeout: float = 30.0) -> None:
        """Read advertisements, subscribing to every channel under ``topic_prefix``, until
        ``count`` channels are subscribed; then the viewer reads nothing more."""
        deadline = time.monotonic() + timeout
        next_id = 1
        while len(self.subscribed) < count:
            if time.monotonic() > deadline:
                raise TimeoutError(f"subscribed to {sorted(self.subscribed.values())} only")
            opcode, payload = self._frame()
            if opcode != 1:
                continue  # binary message data, pings
            message = json.loads(payload)
            if message.get("op") != "advertise":
                continue
            subscriptions = []
            for channel in message["channels"]:
                if channel["topic"].startswith(topic_prefix):
                    subscriptions.append({"id": next_id, "channelId": channel["id"]})
                    self.subscribed[next_id] = channel["topic"]
                    next_id += 1
            if subscriptions:
                self._send_text(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def wait_advertised(self, topic: str, timeout: float = 30.0) -> dict[str, object]:
        """Read advertisements, subscribing to nothing, until ``topic``'s arrives; its
        channel description."""
        deadline = time.monotonic() + timeout
        while topic not in self.advertised and time.monotonic() < deadline:
            opcode, payload = self._frame()
            if opcode != 1:
                continue
            message = json.loads(payload)
            if message.get("op") == "advertise":
                for channel in message["channels"]:
                    self.advertised[channel["topic"]] = channel
        if topic in self.advertised:
            return self.advertised[topic]
        raise TimeoutError(f"{topic} was not advertised within {timeout:.0f} s")

    def close(self) -> None:
        self.sock.close()
