"""A relay-free local CAN bus for processes on one machine: a python-can interface (``localbus``).

    bus = can.Bus(interface="localbus", channel="/run/user/1000/hil-bus-x1y2")   # any python-can program

The channel is a directory that only its owner can enter (``create_channel`` makes one, mode 0700).
Every node listens on its own ``AF_UNIX`` ``SOCK_SEQPACKET`` socket there and connects to every node
already present, so each pair of nodes shares one connected, reliable, message-oriented socket: a
full mesh, no relay process.  A frame travels as SocketCAN's ``struct canfd_frame`` (72 bytes: can_id
with the EFF/RTR/ERR flags, len, flags with BRS/ESI/FDF, two reserved bytes, 64 data bytes), so a
frame is delivered whole or not at all, and every other node receives every frame (broadcast, as on
vcan: a third node such as a monitor or a fault injector sees the whole bus).  Each sender's frames
arrive in the order sent; frames of two senders in flight at once may arrive in either order (on a
physical bus arbitration would decide).

Sending never blocks: a peer whose socket buffer is full misses that frame, and the miss is counted
for it (``dropped``, by peer).  A node that dies is noticed (its socket reads end-of-file) and
dropped from the mesh (``peers_lost``).  When two nodes connect to each other at the same moment,
the connection opened by the node with the smaller name survives, so no pair has two connections.

Why not datagrams: unconnected ``AF_UNIX`` datagram sockets drop or block once ten frames are queued
(``net.unix.max_dgram_qlen`` is 10 here); connected SEQPACKET sockets queue by bytes.
"""
from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import struct
import tempfile
import time
from collections import Counter

import can

CANFD_FRAME = struct.Struct("=IBBBB64s")         # struct canfd_frame
EFF_FLAG, RTR_FLAG, ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
EFF_MASK, SFF_MASK = 0x1FFFFFFF, 0x7FF
CANFD_BRS, CANFD_ESI, CANFD_FDF = 0x01, 0x02, 0x04
HELLO = b"hil-localbus-1 "                       # first packet on a connection: protocol and node name
SOCKET_SUFFIX = ".sock"


def create_channel(prefix: str = "hil-bus-") -> str:
    """A new channel directory only this user can enter (removed by ``remove_channel``)."""
    base = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    return tempfile.mkdtemp(prefix=prefix, dir=base)       # mkdtemp: mode 0700


def remove_channel(path: str) -> None:
    """Remove a channel directory and the sockets left in it."""
    try:
        for name in os.listdir(path):
            if name.endswith(SOCKET_SUFFIX):
                try:
                    os.unlink(os.path.join(path, name))
                except FileNotFoundError:  # a peer removed its socket first
                    pass
        os.rmdir(path)
    except OSError:  # the directory is in use or gone already: left for the next cleanup
        pass


def encode(msg: can.Message) -> bytes:
    can_id = (msg.arbitration_id & EFF_MASK) | EFF_FLAG if msg.is_extended_id else msg.arbitration_id & SFF_MASK
    if msg.is_remote_frame:
        can_id |= RTR_FLAG
    if msg.is_error_frame:
        can_id |= ERR_FLAG
    flags = (CANFD_FDF if msg.is_fd else 0) | (CANFD_BRS if msg.bitrate_switch else 0) | \
        (CANFD_ESI if msg.error_state_indicator else 0)
    data = bytes(msg.data)
    return CANFD_FRAME.pack(can_id, len(data), flags, 0, 0, data)


def decode(packet: bytes, channel: str) -> can.Message | None:
    """A frame from a packet, or None for a packet that is not a canfd_frame."""
    if len(packet) != CANFD_FRAME.size:
        return None
    can_id, length, flags, _, _, data = CANFD_FRAME.unpack(packet)
    if length > 64:
        return None
    extended = bool(can_id & EFF_FLAG)
    return can.Message(timestamp=time.time(), arbitration_id=can_id & (EFF_MASK if extended else SFF_MASK),
                       is_extended_id=extended, is_remote_frame=bool(can_id & RTR_FLAG),
                       is_error_frame=bool(can_id & ERR_FLAG), is_fd=bool(flags & CANFD_FDF),
                       bitrate_switch=bool(flags & CANFD_BRS), error_state_indicator=bool(flags & CANFD_ESI),
                       dlc=length, data=data[:length], channel=channel, check=False)


class LocalBus(can.BusABC):
    """One node of a local bus (module docstring).  ``channel``: the bus directory."""

    def __init__(self, channel: str, receive_own_messages: bool = False, fd: bool = True, **kwargs):
        if not channel or not os.path.isdir(channel):
            raise can.CanInitializationError(f"localbus: channel {channel!r} is not a directory")
        st = os.stat(channel)
        if st.st_uid != os.getuid() or st.st_mode & 0o077:
            raise can.CanInitializationError(f"localbus: {channel} must belong to this user and be closed to others "
                                             "(mode 0700)")
        self.channel_info = f"localbus {channel}"
        self._dir = channel
        self._own = receive_own_messages
        self.name = f"{os.getpid()}-{time.monotonic_ns()}"
        self._path = os.path.join(channel, self.name + SOCKET_SUFFIX)
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._peers: dict[int, tuple[socket.socket, str | None, bool]] = {}   # fd -> (sock, peer name, we dialled)
        try:        # a failure (or a signal) half-way leaves no socket open and no socket file behind
            self._listener.bind(self._path)
            self._listener.listen(64)
            self._listener.setblocking(False)
            self._poll = select.poll()
            self._poll.register(self._listener.fileno(), select.POLLIN)
            # the listener alone: ``send`` asks it whether a node is waiting to join (a poll that finds
            # nothing costs a tenth of an accept that fails, which raises)
            self._joining = select.poll()
            self._joining.register(self._listener.fileno(), select.POLLIN)
            self._own_queue: list[can.Message] = []
            self.dropped: Counter = Counter()        # frames a full peer missed, by peer name
            self._closing: set[int] = set()          # peers that closed: not written to, still read to their end
            self.peers_lost = 0
            for name in sorted(os.listdir(channel)):
                if name.endswith(SOCKET_SUFFIX) and name != self.name + SOCKET_SUFFIX:
                    self._dial(os.path.join(channel, name))
            super().__init__(channel=channel, **kwargs)
        except BaseException:
            for sock, _, _ in self._peers.values():
                sock.close()
            self._listener.close()
            with contextlib.suppress(OSError):
                os.unlink(self._path)
            raise

    # -- the mesh ------------------------------------------------------------------------------
    def _add(self, sock: socket.socket, peer: str | None, dialled: bool) -> None:
        sock.setblocking(False)
        self._peers[sock.fileno()] = (sock, peer, dialled)
        self._poll.register(sock.fileno(), select.POLLIN)

    def _drop(self, fd: int) -> None:
        self._closing.discard(fd)
        sock, _, _ = self._peers.pop(fd)
        try:
            self._poll.unregister(fd)
        except KeyError:  # not registered (closed before its first poll)
            pass
        sock.close()

    def _dial(self, path: str) -> None:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            s.connect(path)
            s.send(HELLO + self.name.encode())
        except OSError:           # a node that left its socket behind, or is leaving
            s.close()
            return
        self._add(s, os.path.basename(path)[:-len(SOCKET_SUFFIX)], True)

    def _accept(self) -> None:
        while True:
            try:
                s, _ = self._listener.accept()
            except BlockingIOError:  # no more pending connections
                return
            except OSError:  # the listener was closed (shutdown): nothing to accept
                return
            self._add(s, None, False)      # its name comes in its hello

    def _hello(self, fd: int, packet: bytes) -> None:
        sock, _, dialled = self._peers[fd]
        peer = packet[len(HELLO):].decode(errors="replace")
        self._peers[fd] = (sock, peer, dialled)
        # the same pair connected both ways: keep the connection dialled by the smaller name
        for other_fd, (_, other_peer, other_dialled) in list(self._peers.items()):
            if other_fd != fd and other_peer == peer:
                keep_ours = self.name < peer          # our dialled connection survives
                loser = next(f for f, d in ((fd, dialled), (other_fd, other_dialled)) if d != keep_ours)
                self._drop(loser)
                return

    # -- BusABC --------------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._joining.poll(0):  # a node that joined since: it gets this frame too
            self._accept()
        packet = encode(msg)
        for fd, (sock, peer, _) in list(self._peers.items()):
            if fd in self._closing:
                continue
            try:
                sock.send(packet, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):  # the peer's queue is full: counted as dropped
                self.dropped[peer or str(fd)] += 1
            except OSError as e:
                if e.errno in (errno.EPIPE, errno.ECONNRESET, errno.ENOTCONN):
                    # the peer has closed: nothing more goes to it, but what it sent before closing is
                    # still queued here and is read first (recv drops the connection at end-of-file)
                    self._closing.add(fd)
                else:
                    raise can.CanOperationError(f"localbus: send: {e}") from None
        if self._own:
            self._own_queue.append(decode(packet, self._dir))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """``BusABC.recv``; with no filter set (the nodes set none) straight to ``_recv_internal``, which
        keeps the timeout itself: a lockstep node polls the bus tens of times a period, and python-can's
        loop around it (two clock reads, the filter test, a log call) came on top of each poll."""
        if self._filters is not None:
            return super().recv(timeout)
        return self._recv_internal(timeout)[0]

    def _recv_internal(self, timeout: float | None):
        if self._own_queue:
            return self._own_queue.pop(0), False
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            wait_ms = -1 if end is None else max(0, int((end - time.monotonic()) * 1000 + 0.999))
            try:
                events = self._poll.poll(wait_ms)
            except InterruptedError:  # interrupted: nothing read this round, polled again
                events = []
            for fd, ev in events:
                if fd == self._listener.fileno():
                    self._accept()
                    continue
                if fd not in self._peers:
                    continue
                sock = self._peers[fd][0]
                try:
                    packet = sock.recv(128)
                except BlockingIOError:  # spurious wake-up: nothing to read yet
                    continue
                except OSError:  # a reset connection: read as the peer closing, handled below
                    packet = b""
                if not packet:                       # the peer closed or died
                    self.peers_lost += 1
                    self._drop(fd)
                    continue
                if packet.startswith(HELLO):
                    self._hello(fd, packet)
                    continue
                msg = decode(packet, self._dir)
                if msg is not None:
                    return msg, False
            if end is not None and time.monotonic() >= end:
                return None, False

    def fileno(self) -> int:
        return self._listener.fileno()

    def shutdown(self) -> None:
        for fd in list(self._peers):
            self._drop(fd)
        self._listener.close()
        try:
            os.unlink(self._path)
        except FileNotFoundError:  # removed already (a second shutdown)
            pass
        super().shutdown()

    @staticmethod
    def _detect_available_configs():
        return []
