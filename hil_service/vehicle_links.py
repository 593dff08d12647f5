"""Several MAVLink links on one service, and who a vehicle is when each has its own ids.

A fleet of hundreds of gliders does not share one MAVLink network: each shore gateway or
Iridium/RUDICS forwarder brings its own vehicles, with a system-id space of its own (a
system id is one byte). ``serve --mavlink`` given several times opens one ``Link`` per
endpoint (``LinkSet``, links numbered 1, 2, … in the order given); a vehicle's commands,
heartbeats and releases go back on the link (and to the peer address) its frames last
came from.

How vehicles are told apart (``serve --vehicle-ids``, docs/fleet.md):

* ``sysid`` (the default): a system id is one vehicle whichever link it is heard on, as on
  one link (where its frames last came from is where its commands go); key id ``7``.
* ``link``: a vehicle is (link, system id). ``LinkIdentity`` renumbers each received message
  to its vehicle id (``keys.vehicle_id``: ``link * 256 + sysid``; key id ``2-7``) before the
  service sees it, and what the service sends back to its wire system id.
"""

from __future__ import annotations

from collections.abc import Sequence

from protocols import keys
from protocols.mavlink_io import Address, Link, MavMessage, readable


class LinkSet:
    """Several datagram links with the part of ``Link``'s interface the service uses. A
    received datagram's address is ``(link number, peer address)``; ``send_to`` takes it
    back. Datagram links only: each datagram holds whole frames, so frames of different
    links never mix in one parser's buffer."""

    datagram = True

    def __init__(self, connections: Sequence[str], source_system: int = 255,
                 source_component: int = 0, spin_wait: float = 0.0):  # fmt: skip
        if not 1 <= len(connections) <= keys.MAX_LINKS:
            raise ValueError(f"--mavlink: 1..{keys.MAX_LINKS} links, got {len(connections)}")
        self.connection = ", ".join(connections)
        self.spin_wait = spin_wait
        self.links: list[Link] = []
        try:
            for connection in connections:
                link = Link(connection, source_system, source_component, spin_wait)
                self.links.append(link)
                if not link.datagram:
                    raise ValueError(
                        f"{connection}: several --mavlink links must be UDP (udpin:, udpout:)"
                    )
        except Exception:
            self.close()
            raise
        self._ready: list[int] = []  # link indexes select found readable, not yet drained
        self._fds = [link.fileno() for link in self.links]
        self._index_of = {fd: index for index, fd in enumerate(self._fds)}

    def fileno(self) -> int:
        return self.links[0].fileno()

    def bound(self) -> str:
        """Each link's connection string with the port it listens on (``Link.bound``)."""
        return ", ".join(link.bound() for link in self.links)

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a datagram on any link; True when one may be there."""
        if self._ready:
            return True
        try:
            ready = readable(self._fds, timeout, self.spin_wait)
        except (OSError, ValueError):
            return False
        self._ready = [self._index_of[fd] for fd in ready]
        return bool(self._ready)

    def recv_from(self) -> tuple[bytes, Address]:
        """One datagram of a link ``wait`` found readable, with ``(link number, peer)``. A
        link stays ready until a read finds nothing (the sockets do not block): a burst is
        read without a ``select`` per datagram; the ready links take turns, so a busy one
        does not hold the others back."""
        while self._ready:
            index = self._ready.pop()
            data, peer = self.links[index].recv_from()
            if data:
                self._ready.insert(0, index)
                return data, (index + 1, peer)
        return b"", None

    def recv(self) -> bytes:
        return self.recv_from()[0]

    def send(self, frame: bytes) -> None:
        """To every link's peer (no address: nobody has spoken yet)."""
        for link in self.links:
            link.send(frame)

    def send_to(self, frame: bytes, address: Address) -> None:
        """To ``(link number, peer)`` as ``recv_from`` gave it; without one, as ``send``."""
        if address is None:
            self.send(frame)
            return
        number, peer = address
        self.links[number - 1].send_to(frame, peer)

    def close(self) -> None:
        for link in self.links:
            link.close()


class LinkIdentity:
    """``--vehicle-ids link``: each message of link ``n`` renumbered to its vehicle id (its
    header's system id, and a target system naming its own sender, as an acknowledgement
    to the vehicle's companion does), and each message sent framed with the wire system
    id. Pure: no I/O."""

    def __init__(self) -> None:
        #: Messages that came with no link number (replay of raw frames, a bare ``Link``):
        #: left as they are, i.e. link 0.
        self.unlinked = 0

    def admit(self, messages: list[MavMessage], source: Address) -> None:
        """Renumber ``messages`` (as decoded from one datagram of ``source``) in place."""
        if source is None or len(source) != 2 or not isinstance(source[0], int):
            self.unlinked += len(messages)
            return
        link = source[0]
        for message in messages:
            header = message.get_header()
            wire = header.srcSystem
            if not 1 <= wire <= 255:
                continue  # broadcast id 0: nobody's vehicle
            vehicle = keys.vehicle_id(link, wire)
            header.srcSystem = vehicle
            if getattr(message, "target_system", None) == wire:
                message.target_system = vehicle

    @staticmethod
    def outgoing(message: MavMessage, vehicle: int) -> int:
        """The wire system id of ``vehicle``; a target system naming the vehicle id becomes
        it too (``message`` changed in place, before it is packed)."""
        wire = keys.split_vehicle_id(vehicle)[1]
        if getattr(message, "target_system", None) == vehicle:
            message.target_system = wire
        return wire


def identity_for(mode: str) -> LinkIdentity | None:
    """The renumbering ``--vehicle-ids`` (``ServiceConfig.vehicle_ids``) asks for: None
    for ``sysid`` (system ids as they are)."""
    return LinkIdentity() if mode == "link" else None
