"""Where the live view listens (``--foxglove [HOST:]PORT``): parsed without importing the
Foxglove SDK, so that every verb reading a configuration does not load it."""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_PORT = 8765


@dataclass(frozen=True)
class LiveAddress:
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT

    @classmethod
    def parse(cls, text: str) -> LiveAddress:
        """``PORT`` (loopback) or ``HOST:PORT``; ValueError names what is wrong."""
        host, colon, port_text = text.rpartition(":")
        if not colon:
            host, port_text = "127.0.0.1", text
        host = host.strip("[]") or "127.0.0.1"
        try:
            port = int(port_text)
        except ValueError:
            raise ValueError(f"--foxglove {text!r}: expected [HOST:]PORT") from None
        if not 0 <= port <= 65535:
            raise ValueError(f"--foxglove {text!r}: port out of range")
        return cls(host, port)

    def __str__(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"
