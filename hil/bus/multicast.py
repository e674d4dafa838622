"""python-can's ``udp_multicast`` bus held to this machine: a bus that a TCU program joins with python-can
alone, no root, no kernel module and nothing of this project:

    bus = can.Bus(interface="udp_multicast", channel="239.255.42.17", port=43117, hop_limit=0)

``LoopbackMulticastBus`` is this project's node on it (the plant's, the built-in TCU's).  The wire is
python-can's own (``can.interfaces.udp_multicast.utils``: one UDP datagram per frame, a msgpack map of
the frame's fields, CAN FD included), so its frames and python-can's ``UdpMulticastBus`` frames are one bus.

What python-can's class does (python-can 4.x, ``can/interfaces/udp_multicast/bus.py``), and what this node
does instead:

- it binds ``("", port)`` and joins the group on the interface the routing table gives the group (the
  default route's), and sends with the TTL it is given (``hop_limit``, default 1: one hop, i.e. onto the
  network of that interface).  **This node** sends from a socket bound to 127.0.0.1 with
  ``IP_MULTICAST_IF`` 127.0.0.1 (the loopback interface) and ``IP_MULTICAST_TTL`` 0, and joins the group on
  the loopback interface only: its frames never leave the machine twice over (a multicast datagram of TTL
  0 is delivered to this host's members and never transmitted, RFC 1112 section 6.1; Linux drops it after
  the loopback copy), and it needs no route (a host with only ``lo`` runs it).
- a python-can node given ``hop_limit=0`` sends through the default route's interface, but with TTL 0:
  the kernel hands this host's members their copy and transmits nothing.  A frame that arrives through
  an interface other than ``lo`` with a TTL above 0 was sent onto that interface's network too (a node
  left at python-can's default ``hop_limit=1``, or another machine): this node refuses the bus with
  ``BusError`` naming the sender, the interface and the TTL (read from ``IP_PKTINFO`` and ``IP_RECVTTL``).
- multicast loops every datagram back to every member on the host, **the sender included**: python-can's
  class receives its own frames whatever ``receive_own_messages`` says (``True`` raises there).  This node
  drops the datagrams whose source is its own send socket (``receive_own_messages=True`` keeps them).
- python-can promises neither delivery nor order.  On loopback a datagram is handed to every member
  within the sender's ``sendto`` call, so each sender's frames arrive in the order sent; a member whose
  receive buffer is full loses datagrams: this node asks for a 1 MiB buffer and counts what its socket
  lost (``SO_RXQ_OVFL``) in ``dropped``.

Any process of any user on the machine can join a group (as with the hub): the frames are not
authenticated unless both sides hold a key (``[bus] auth``, ``docs/security.md``).  IPv4 groups only.
"""
from __future__ import annotations

import ipaddress
import secrets
import select
import socket
import struct
import time

import can
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from ..errors import BusError

#: python-can's ``UdpMulticastBus`` default port: the port of a spec that names none
DEFAULT_PORT = 43113
LOOPBACK = "127.0.0.1"
RECV_BUFFER_BYTES = 1 << 20
# Linux values (the socket module of Python 3.11 does not name them all)
IP_PKTINFO = getattr(socket, "IP_PKTINFO", 8)
IP_RECVTTL = getattr(socket, "IP_RECVTTL", 12)
IP_TTL = getattr(socket, "IP_TTL", 2)
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
PKTINFO = struct.Struct("=i4s4s")                  # struct in_pktinfo: ifindex, local address, destination
#: the groups ``new_group`` draws from: 239.255.0.0/16, the IPv4 Local Scope (RFC 2365)
DRAWN_GROUPS = ipaddress.ip_network("239.255.0.0/16")
DRAWN_PORTS = (49152, 65535)


def parse_channel(channel: str) -> tuple[str, int]:
    """(group, port) of ``GROUP`` or ``GROUP:PORT`` (an IPv4 multicast address, 224.0.0.0/4; the port
    python-can's default when not given); ``ValueError`` saying what is wrong."""
    group, _, port_text = channel.partition(":")
    try:
        address = ipaddress.ip_address(group)
    except ValueError:
        raise ValueError(f"{group!r} is not an IPv4 multicast group (e.g. 239.255.42.17)") from None
    if address.version != 4 or not address.is_multicast:
        raise ValueError(f"{group} is not an IPv4 multicast group (224.0.0.0/4, e.g. 239.255.42.17)")
    try:
        port = int(port_text) if port_text else DEFAULT_PORT
    except ValueError:
        raise ValueError(f"port {port_text!r} is not a number") from None
    if not 1 <= port <= 65535:
        raise ValueError(f"port {port} is outside 1-65535")
    return str(address), port


def new_group() -> tuple[str, int]:
    """A group in 239.255.0.0/16 and a port above 49151, drawn at random: a run's own bus, so that two
    runs on one machine do not share one."""
    host = secrets.randbelow(DRAWN_GROUPS.num_addresses - 2) + 1
    return str(DRAWN_GROUPS[host]), DRAWN_PORTS[0] + secrets.randbelow(DRAWN_PORTS[1] - DRAWN_PORTS[0] + 1)


class LoopbackMulticastBus(can.BusABC):
    """A node of a ``udp_multicast`` bus on this machine only (module docstring).  ``channel``: the IPv4
    multicast group; ``port``: its UDP port.  ``dropped``: datagrams this node's socket lost (full buffer);
    ``garbage``: datagrams that were not python-can frames (skipped)."""

    def __init__(self, channel: str, port: int = DEFAULT_PORT, receive_own_messages: bool = False, fd: bool = True,
                 **kwargs):
        group, port = parse_channel(f"{channel}:{port}")
        self.group, self.port = group, port
        self.channel_info = f"udp_multicast {group}:{port} on lo"
        self._own = receive_own_messages
        self._fd = fd
        self._lo = socket.if_nametoindex("lo")
        self.dropped = 0
        self.garbage = 0
        self._rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            rx = self._rx
            rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)     # as python-can's: many members, one port
            if hasattr(socket, "SO_REUSEPORT"):
                rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            try:
                rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
            except OSError:
                pass                                  # the system's default buffer, capped by net.core.rmem_max
            rx.bind((group, port))                    # datagrams to other addresses never reach it
            rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                          socket.inet_aton(group) + socket.inet_aton(LOOPBACK))      # a member on lo only
            rx.setsockopt(socket.IPPROTO_IP, IP_PKTINFO, 1)
            rx.setsockopt(socket.IPPROTO_IP, IP_RECVTTL, 1)
            rx.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
            rx.setblocking(False)
            tx = self._tx
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(LOOPBACK))
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            tx.bind((LOOPBACK, 0))
            self._me = tx.getsockname()               # the source of this node's own datagrams
            self._poll = select.poll()
            self._poll.register(rx.fileno(), select.POLLIN)
            super().__init__(channel=group, **kwargs)
        except BaseException:
            self._rx.close()
            self._tx.close()
            raise

    @property
    def ttl(self) -> int:
        """The TTL this node's datagrams are sent with (0: never transmitted)."""
        return self._tx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)

    @property
    def multicast_interface(self) -> str:
        """The address of the interface this node's datagrams go out on (127.0.0.1: lo)."""
        return socket.inet_ntoa(self._tx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_fd and not self._fd:
            raise can.CanOperationError("udp_multicast: cannot send a CAN FD frame with fd=False")
        try:
            self._tx.sendto(pack_message(msg), (self.group, self.port))
        except OSError as e:
            raise can.CanOperationError(f"udp_multicast: send: {e}") from None

    def _read(self) -> tuple[bytes, tuple, int | None, int | None] | None:
        """One datagram (data, source, arrival interface index, TTL), None when none is queued."""
        try:
            data, ancillary, _, source = self._rx.recvmsg(4096, 256)
        except (BlockingIOError, InterruptedError):  # nothing queued
            return None
        ifindex = ttl = None
        for level, kind, value in ancillary:
            if level == socket.IPPROTO_IP and kind == IP_PKTINFO and len(value) >= PKTINFO.size:
                ifindex = PKTINFO.unpack_from(value)[0]
            elif level == socket.IPPROTO_IP and kind == IP_TTL and len(value) >= 4:
                ttl = struct.unpack_from("=i", value)[0]
            elif level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= 4:
                self.dropped = struct.unpack_from("=I", value)[0]
        return data, source, ifindex, ttl

    def _recv_internal(self, timeout: float | None):
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            got = self._read()
            if got is not None:
                data, source, ifindex, ttl = got
                if source == self._me and not self._own:
                    continue
                if ifindex is not None and ifindex != self._lo and ttl:
                    name = _interface_name(ifindex)
                    raise BusError(f"bus udp_multicast:{self.group}:{self.port}: a frame from "
                                   f"{source[0]}:{source[1]} came through {name} with TTL {ttl}: its sender's frames "
                                   f"go out on {name}'s network too (python-can: open it with hop_limit=0, which "
                                   "keeps them on this machine)")
                try:
                    msg = unpack_message(data, replace={"timestamp": time.time(), "channel": self.group}, check=True)
                except Exception:  # noqa: BLE001 - anything on the group that is not a python-can frame
                    self.garbage += 1
                    continue
                if msg.is_fd and not self._fd:
                    continue
                return msg, False
            wait_s = None if end is None else end - time.monotonic()
            if wait_s is not None and wait_s <= 0:
                return None, False
            try:
                self._poll.poll(-1 if wait_s is None else max(1, int(wait_s * 1000 + 0.999)))
            except InterruptedError:  # a signal: the loop checks the deadline and polls again
                pass

    def fileno(self) -> int:
        return self._rx.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._rx.close()
        self._tx.close()

    @staticmethod
    def _detect_available_configs():
        return []


def _interface_name(ifindex: int) -> str:
    try:
        return socket.if_indextoname(ifindex)
    except OSError:  # the interface went away: named by its index
        return f"interface {ifindex}"


def open_loopback(group: str, port: int) -> LoopbackMulticastBus:
    """A node on ``group:port``; ``BusError`` naming the bus when the sockets cannot be set up."""
    try:
        return LoopbackMulticastBus(group, port)
    except (OSError, can.CanError) as e:
        raise BusError(f"bus udp_multicast:{group}:{port}: cannot open: {e}") from None
