"""What travels between the service's process and the live view's (server.py).

Service → live view: one ``SOCK_SEQPACKET`` message per batch, ``pickle`` of a list of
entries ``(topic, payload, t_ns)``: ``payload`` the bytes published (or a JSON-ready object,
when the bus encodes nothing), or, with ``topic == MAVLINK``, ``(direction, type, frame,
message)``: a MAVLink frame received (``in``, ``message`` None: the live view decodes the
frame), sent (``out``, with the message object, whose JSON the log records) or refused
(``rejected``, no type). Live view → service: one JSON object per message (its status).
Both ends are this program's, on one machine: pickle is no trust boundary here.
"""

from __future__ import annotations

#: The topic of the entries that are MAVLink frames, not publications (never a Zenoh key).
MAVLINK = "\0mavlink"
#: The largest batch message, bytes: below a Unix socket's default send buffer (212,992),
#: which bounds one SOCK_SEQPACKET message. A larger batch is split.
MAX_MESSAGE = 65_536
#: The largest status message, bytes.
MAX_STATUS = 4096
