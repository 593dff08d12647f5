"""Whether a connection string can be a link, before the link opens: ``connection_problem``
for ``emulate --connect`` and ``serve --mavlink`` alike.

pymavlink takes much that cannot work and says so late or never: ``udpout:999.1.1.1:14550``
(or a name that does not resolve) runs, and every datagram vanishes (its write swallows the
send error); ``udpout:HOST:0`` sends nowhere; an unknown scheme or a device with a colon in
it reaches its UDP parser ("UDP ports must be specified as host:port", "invalid literal for
int()"); a regular file opens as a log to read. So a vehicle or a service pointed at a
mistyped link would run, "sending", and never reach anyone, or fail with a message about
something else.
"""

from __future__ import annotations

import os
import socket

#: The connection schemes ``Link`` opens as a live network link, each followed by HOST:PORT.
NETWORK_SCHEMES = ("udpin", "udpout", "udpbcast", "udp", "tcp", "tcpin")
#: The schemes that listen (pymavlink's ``udp:`` is ``udpin:``): port 0 takes a free port.
LISTENING_SCHEMES = ("udpin", "udp", "tcpin")
#: What a link can be, for error messages.
ACCEPTED_LINKS = (
    "udpin:HOST:PORT, udpout:HOST:PORT, udpbcast:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT "
    "or a serial device, optionally with its baud rate (e.g. /dev/ttyUSB0 or /dev/ttyUSB0,57600)"
)
#: Names pymavlink would open as a recorded log (or a CSV export), never a live link.
LOG_SUFFIXES = (".tlog", ".bin", ".px4log", ".log", ".mavlink", ".raw", ".csv")


def connection_problem(connection: str, free_port: bool = False) -> str:
    """Why ``connection`` cannot be opened as a link, or "" when it can be tried.

    A link is ``SCHEME:HOST:PORT`` with a scheme of ``NETWORK_SCHEMES``, PORT 1..65535 (0
    too for a listening scheme when ``free_port``: the caller reports the port it got) and
    a HOST that is an address (``address_problem``); or a serial device that exists and is
    not a regular file, with an optional baud rate after a comma (``/dev/ttyUSB0,57600``, as
    pymavlink reads it)."""
    name = connection.strip()
    if not name:
        return f"is empty; it takes {ACCEPTED_LINKS}"
    scheme, colon, rest = name.partition(":")
    if colon and "/" not in scheme and scheme.lower() != "csv":
        return _network_problem(connection, scheme.lower(), rest, free_port)
    device, comma, baud = name.rpartition(",")
    if not comma or os.path.exists(name):
        device, baud = name, ""
    elif not (baud.isdigit() and int(baud) > 0):
        return f"{connection!r}: the baud rate after the comma must be a positive integer"
    kind = recorded_kind(device)
    if kind:
        return f"{connection!r} is {kind}, not a link; it takes {ACCEPTED_LINKS}"
    if not os.path.exists(device):
        return f"{connection!r}: no such serial device; it takes {ACCEPTED_LINKS}"
    return ""


def _network_problem(connection: str, scheme: str, rest: str, free_port: bool) -> str:
    if scheme not in NETWORK_SCHEMES:
        return f"{connection!r}: unknown scheme {scheme!r}; it takes {ACCEPTED_LINKS}"
    host, colon, port = rest.partition(":")
    if not host or not colon or ":" in port:
        return f"{connection!r}: {scheme}: wants HOST:PORT; it takes {ACCEPTED_LINKS}"
    lowest = 0 if free_port and scheme in LISTENING_SCHEMES else 1
    if not (port.isdigit() and lowest <= int(port) <= 65535):
        return f"{connection!r}: port must be an integer {lowest}..65535, got {port!r}"
    unresolved = address_problem(host, int(port))
    return f"{connection!r}: {unresolved}" if unresolved else ""


def normalized(connection: str) -> str:
    """``connection`` with a network scheme in lower case (``UDPIN:…`` → ``udpin:…``), as
    ``connection_problem`` reads it; anything else as given. pymavlink matches schemes case
    by case and would open ``UDPIN:127.0.0.1:14550`` as a serial device of that name."""
    scheme, colon, rest = connection.strip().partition(":")
    if colon and scheme.lower() in NETWORK_SCHEMES:
        return f"{scheme.lower()}:{rest}"
    return connection


def recorded_kind(name: str) -> str:
    """ "a CSV log" or "a file" when pymavlink would open ``name`` as a record to read
    rather than a live link (a ``csv:`` export, a recorded log's name whether it exists or
    not, any regular file); "" for a device, a ``SCHEME:HOST:PORT`` or a name that is none
    of these."""
    lowered = name.strip().lower()
    if lowered.startswith("csv:"):
        return "a CSV log"
    if ":" in lowered.split("/")[0] and not lowered.endswith(LOG_SUFFIXES):
        return ""
    is_device = os.path.exists(name) and not os.path.isfile(name)
    if not is_device and (lowered.endswith(LOG_SUFFIXES) or os.path.isfile(name)):
        return "a file"
    return ""


def address_problem(host: str, port: int) -> str:
    """Why ``host`` cannot be an address to reach or bind, or "". Digits and dots are an IPv4
    address or nothing: parsed, never looked up; a bracketed IPv6 address is parsed too; a
    name is resolved as pymavlink and zenoh would (the hosts file, then DNS)."""
    if host.startswith("[") and host.endswith("]"):
        host, numeric = host[1:-1], True
    else:
        numeric = all(c.isdigit() or c == "." for c in host)
    try:
        socket.getaddrinfo(host, port, flags=socket.AI_NUMERICHOST if numeric else 0)
    except (socket.gaierror, UnicodeError, OverflowError) as error:
        reason = error.strerror if isinstance(error, socket.gaierror) else str(error)
        return f"host {host!r} is not an address ({reason})"
    return ""
