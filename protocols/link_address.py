"""Whether a network link's HOST can be an address, before the link opens.

pymavlink takes ``udpout:999.1.1.1:14550`` (or a name that does not resolve), and every
datagram to it then vanishes: its write swallows the send error. So a vehicle or a service
pointed at a mistyped host would run, "sending", and never reach anyone.
"""

from __future__ import annotations

import socket

#: The connection schemes ``Link`` opens as a live network link, each followed by HOST:PORT.
NETWORK_SCHEMES = ("udpin", "udpout", "udpbcast", "udp", "tcp", "tcpin")


def host_problem(connection: str) -> str:
    """Why the HOST of ``SCHEME:HOST:PORT`` cannot be an address, or "" when it resolves
    (or when ``connection`` is not a network link of that form: a serial device, or a
    string other checks refuse). A name is resolved as pymavlink would (DNS for a name
    that is not in the hosts file); digits and dots only are parsed, never looked up."""
    scheme, _, rest = connection.strip().partition(":")
    host, _, port = rest.rpartition(":")
    if scheme.lower() not in NETWORK_SCHEMES or not host or ":" in host or not port.isdigit():
        return ""
    # Digits and dots are an IPv4 address or nothing: checked without a DNS query.
    numeric = all(c.isdigit() or c == "." for c in host)
    try:
        socket.getaddrinfo(host, int(port), flags=socket.AI_NUMERICHOST if numeric else 0)
    except (socket.gaierror, UnicodeError, OverflowError) as error:
        reason = error.strerror if isinstance(error, socket.gaierror) else str(error)
        return f"host {host!r} is not an address ({reason})"
    return ""
