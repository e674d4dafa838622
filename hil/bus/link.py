"""The link between plant and TCU: opening a bus by name from a table of backends (``open_bus``), a
thread-safe sender, and the timing rules both nodes share (heartbeat period, silence limit).

Bus specs:
  ``auto``               ``socketcan:vcan0`` when this kernel has it, otherwise ``local``
  ``socketcan:<ch>``     SocketCAN (vcan0, can0 ...), CAN FD enabled
  ``local``              a new relay-free local bus (``hil.bus.localbus``: Unix sockets in a directory only
                         this user can enter), removed at the end; processes join it as ``localbus:<dir>``
  ``localbus:<dir>``     a node on an existing local bus
  ``hub``                a python-can-remote loopback hub that ``hil`` starts on 127.0.0.1 with a free
                         port and stops at the end (processes connect with ``remote:ws://127.0.0.1:P/``);
                         for crossing machines.  Its HTTP side serves files to any local user: never
                         the default
  ``remote:<url>``       an existing python-can-remote server
  ``inprocess``          no bus and no second process: the TCU node answers in the plant's thread,
                         still through the same DBC encode/decode (see ``InprocessTcuBus``)
  ``udp_multicast``      python-can's ``udp_multicast`` bus held to this machine (``hil.bus.multicast``) on a new
                         group and port drawn for the run; processes join it as ``udp_multicast:GROUP:PORT``
  ``udp_multicast:GROUP[:PORT]``  a node on that group (IPv4; port 43113, python-can's, when not given): the bus
                         a TCU joins with python-can alone (``hop_limit=0``); TTL 0, loopback interface only
  ``<interface>:<ch>``   any python-can interface (pcan:PCAN_USBBUS1, kvaser:0, vector:0 ...); bitrates
                         and timing come from python-can's own configuration (``~/.canrc``)

``BusHandle.peer_spec`` is what a second process passes to ``open_bus`` to reach the same bus.
Backends are looked up by name in ``BACKENDS`` (as python-can's ``BACKENDS``).  Errors are ``BusError``: one line naming the bus and what is available here.
"""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
import threading
from typing import Callable

import can

from ..errors import BusError, HilError, PeerSilent

HUB_START_TIMEOUT_S = 15.0
HUB_SWITCH_INTERVAL_S = 1e-4
MODES = ("lockstep", "realtime")


# -- what this machine offers ---------------------------------------------------------------------
def socketcan_support() -> tuple[bool, str]:
    """(True, "") when the kernel can open AF_CAN raw sockets, else (False, why)."""
    if not hasattr(socket, "AF_CAN"):
        return False, "this Python has no AF_CAN"
    try:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as e:
        return False, f"this kernel has no SocketCAN (socket(AF_CAN) failed: errno {e.errno} {os.strerror(e.errno)})"
    s.close()
    return True, ""


def can_interfaces() -> list[str]:
    """SocketCAN network interfaces present (ARPHRD_CAN = 280), e.g. ['vcan0']."""
    out = []
    for p in sorted(Path("/sys/class/net").glob("*")):
        try:
            if (p / "type").read_text().strip() == "280":
                out.append(p.name)
        except OSError:  # an interface that went away while listed
            continue
    return out


def vcan_available(channel: str = "vcan0") -> tuple[bool, str]:
    ok, why = socketcan_support()
    if not ok:
        return False, why
    if channel not in can_interfaces():
        return False, f"no CAN interface {channel!r} (present: {', '.join(can_interfaces()) or 'none'})"
    return True, ""


def available_here() -> str:
    names = ["auto", "local", "hub", "inprocess", "udp_multicast[:GROUP:PORT]"]
    ok, _ = socketcan_support()
    if ok:
        names += [f"socketcan:{ch}" for ch in can_interfaces()]
    return ", ".join(names) + "; or any python-can interface:channel (" + ", ".join(sorted(can.VALID_INTERFACES)) + ")"


# -- the in-process "bus" ---------------------------------------------------------------------------
class InprocessTcuBus(can.BusABC):
    """A bus with a TCU node on the other end, in this thread: ``send`` hands the frame (as bytes,
    through a copy) to ``node.handle`` and queues the node's replies for ``recv``."""

    def __init__(self, node, channel="inprocess", **kwargs):
        self.node = node
        self.channel_info = "inprocess TCU node"
        self._rx: deque[can.Message] = deque()
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout=None) -> None:
        now = time.time()
        copy = can.Message(timestamp=now, arbitration_id=msg.arbitration_id, data=bytes(msg.data),
                           is_extended_id=msg.is_extended_id, is_fd=msg.is_fd, bitrate_switch=msg.bitrate_switch,
                           is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, dlc=msg.dlc)
        for reply in self.node.handle(copy):
            reply.timestamp = time.time()
            self._rx.append(reply)

    def _recv_internal(self, timeout):
        if self._rx:
            return self._rx.popleft(), False
        if timeout:               # nothing can arrive before the next send: wait without spinning
            time.sleep(timeout)
        return None, False

    def shutdown(self) -> None:
        super().shutdown()


# -- the hub -------------------------------------------------------------------------------------
def die_with_parent() -> None:
    """``preexec_fn`` for helper processes: SIGTERM when the process that started them dies (Linux),
    so a plant killed with SIGKILL leaves no hub or TCU behind."""
    try:
        import ctypes
        import signal
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # no prctl (not Linux): the child is still stopped by close()
        pass


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Hub:
    """python-can-remote server on 127.0.0.1 (a virtual bus behind a websocket), as a child process."""

    def __init__(self, port: int | None = None):
        self.port = port or free_port()
        self.url = f"ws://127.0.0.1:{self.port}/"
        # python-can-remote relays each client in its own threads: a short GIL switch interval keeps
        # a frame from waiting up to 5 ms (the default) for another thread
        argv = ["can_remote", "--interface", "virtual", "--channel", f"hil-hub-{self.port}", "--host", "127.0.0.1",
                "--port", str(self.port)]
        # python-can-remote 0.3.0 serves any file the user can read to any HTTP GET that is not a
        # websocket upgrade (GET /../../etc/passwd; SECURITY.md, the advisory): this hub answers 404
        code = (f"import runpy, sys; sys.setswitchinterval({HUB_SWITCH_INTERVAL_S!r}); sys.argv = {argv!r}; "
                "import can_remote.server as s; s.ClientRequestHandler.send_trace_webpage = "
                "lambda self: self.send_error(404); "
                "runpy.run_module('can_remote', run_name='__main__')")
        # its own session: a Ctrl-C at the terminal reaches the plant, which closes its bus and then
        # stops the hub (a hub killed first breaks both clients' connections mid-shutdown)
        self.proc = subprocess.Popen([sys.executable, "-c", code], preexec_fn=die_with_parent, start_new_session=True,
                                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + HUB_START_TIMEOUT_S
        while True:
            if self.proc.poll() is not None:
                raise BusError(f"hub: python-can-remote exited with code {self.proc.returncode} on port {self.port}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    break
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise BusError(f"hub: python-can-remote did not listen on 127.0.0.1:{self.port} "
                                   f"within {HUB_START_TIMEOUT_S:g} s") from None
                time.sleep(0.05)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:  # a hub that ignores SIGTERM is killed
                self.proc.kill()
                self.proc.wait()


# -- the factory ---------------------------------------------------------------------------------
@dataclass
class BusHandle:
    """An open bus plus what it took to open it; ``close()`` shuts the bus and any hub down."""
    spec: str                     # as asked ("auto")
    name: str                     # as resolved ("hub", "socketcan:vcan0")
    bus: can.BusABC | None        # None for inprocess until a node is attached
    peer_spec: str | None         # what another process opens to reach this bus (None: in-process only)
    hub: Hub | None = None
    extra: dict = field(default_factory=dict)
    cleanup: Callable[[], None] | None = None     # after the bus is closed (e.g. remove a local bus's directory)

    def close(self) -> None:
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except BaseException as e:  # noqa: BLE001 - closing a dead connection must not hide the real error
                # python-can retries (and warns "was not properly shut down") at garbage collection
                # unless the bus counts as shut down; there is nothing left to close
                self.bus._is_shutdown = True
                if not isinstance(e, Exception):
                    raise
            self.bus = None
        if self.hub is not None:
            self.hub.stop()
            self.hub = None
        if self.cleanup is not None:
            self.cleanup()
            self.cleanup = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def resolve(spec: str) -> str:
    """``auto`` -> ``socketcan:vcan0`` or ``local``; other specs unchanged (checked by ``open_bus``)."""
    if spec == "auto":
        ok, _ = vcan_available("vcan0")
        return "socketcan:vcan0" if ok else "local"
    return spec


def open_python_can(interface: str, channel: str) -> can.BusABC:
    if interface not in can.VALID_INTERFACES:
        raise BusError(f"bus {interface}:{channel}: unknown python-can interface {interface!r}; "
                       f"available here: {available_here()}")
    if interface == "socketcan":
        ok, why = vcan_available(channel)
        if not ok:
            raise BusError(f"bus socketcan:{channel}: {why}; available here: {available_here()}")
    if interface == "remote":
        kwargs = {}
    else:
        kwargs = {"fd": True}
    try:
        return can.Bus(interface=interface, channel=channel, receive_own_messages=False, **kwargs)
    except (can.CanError, OSError, ImportError, ValueError, TypeError) as e:
        raise BusError(f"bus {interface}:{channel}: cannot open: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
                       f"; available here: {available_here()}") from None


def _open_inprocess(spec, name, channel, inprocess_node=None) -> BusHandle:
    if inprocess_node is None:
        raise BusError("bus inprocess: needs the TCU node to answer in this process")
    return BusHandle(spec, name, InprocessTcuBus(inprocess_node), None)


def _open_hub(spec, name, channel, inprocess_node=None) -> BusHandle:
    hub = Hub()
    try:
        bus = can.Bus(interface="remote", channel=hub.url, receive_own_messages=False)
    except Exception as e:  # noqa: BLE001
        hub.stop()
        raise BusError(f"bus hub: cannot connect to {hub.url}: {e}") from None
    return BusHandle(spec, "hub", bus, f"remote:{hub.url}", hub=hub)


def _open_local(spec, name, channel, inprocess_node=None) -> BusHandle:
    """``local``: a new local bus (``hil.bus.localbus``) in a directory of its own, removed at close."""
    from .localbus import create_channel, remove_channel

    path = create_channel()
    try:
        handle = _open_localbus(spec, f"localbus:{path}", path)
    except BaseException:
        remove_channel(path)
        raise
    handle.name = "local"
    handle.cleanup = lambda: remove_channel(path)
    return handle


def _open_localbus(spec, name, channel, inprocess_node=None) -> BusHandle:
    """``localbus:<dir>``: a node on an existing local bus (another process's ``local``)."""
    from .localbus import LocalBus

    try:
        bus = LocalBus(channel)
    except (can.CanError, OSError) as e:
        raise BusError(f"bus localbus:{channel}: cannot open: {e}") from None
    return BusHandle(spec, name, bus, f"localbus:{channel}")


def _open_udp_multicast(spec, name, channel, inprocess_node=None) -> BusHandle:
    """``udp_multicast[:GROUP[:PORT]]``: a node on python-can's udp_multicast bus, on this machine only
    (``hil.bus.multicast``); without a group, one drawn for this run (a few draws when a port is taken)."""
    from .multicast import new_group, open_loopback, parse_channel

    if channel:
        try:
            group, port = parse_channel(channel)
        except ValueError as e:
            raise BusError(f"bus {name}: {e}; udp_multicast:GROUP:PORT, e.g. "
                           "udp_multicast:239.255.42.17:43117") from None
        bus = open_loopback(group, port)
    else:
        for attempt in range(5):
            group, port = new_group()
            try:
                bus = open_loopback(group, port)
                break
            except BusError:
                if attempt == 4:
                    raise
    peer = f"udp_multicast:{group}:{port}"
    return BusHandle(spec, peer if channel else "udp_multicast", bus, peer,
                     extra={"open_to": "any process of any user on this machine can join it"
                                       f"{'' if channel else f' ({group}:{port})'}; this side sends with TTL 0 on "
                                       "lo (nothing of it leaves the machine)"})


def _open_local_only(spec, name, channel, inprocess_node=None) -> BusHandle:
    interface = name.split(":", 1)[0]
    return BusHandle(spec, name, open_python_can(interface, channel), None)


def _open_python_can(spec, name, channel, inprocess_node=None) -> BusHandle:
    interface = name.split(":", 1)[0]
    return BusHandle(spec, name, open_python_can(interface, channel), name)


Opener = Callable[..., BusHandle]
#: backend name -> opener(spec, resolved name, channel, inprocess_node=None); any other
#: ``interface:channel`` goes to python-can
BACKENDS: dict[str, Opener] = {
    "inprocess": _open_inprocess,
    "local": _open_local,
    "localbus": _open_localbus,
    "hub": _open_hub,
    "udp_multicast": _open_udp_multicast,
    "virtual": _open_local_only,      # python-can's virtual bus lives inside one process
}


def open_bus(spec: str, inprocess_node=None) -> BusHandle:
    """Open the bus named by ``spec`` (see the module docstring); raises BusError with one line."""
    if not isinstance(spec, str) or not spec:
        raise BusError(f"bus {spec!r}: empty bus name; available here: {available_here()}")
    name = resolve(spec)
    backend, _, channel = name.partition(":")
    if backend in BACKENDS:
        return BACKENDS[backend](spec, name, channel, inprocess_node=inprocess_node)
    if not channel:
        raise BusError(f"unknown bus {spec!r}; available here: {available_here()}")
    return _open_python_can(spec, name, channel)


# -- a bus that fails ----------------------------------------------------------------------------------
def is_bus_failure(e: BaseException) -> bool:
    """An exception raised by the bus itself: python-can, python-can-remote, or the OS under them (the
    hub process killed, the interface gone), not by the code a bus runs in-process."""
    return isinstance(e, (can.CanError, OSError)) or type(e).__module__.split(".")[0] in ("can", "can_remote")


class GuardedBus:
    """``bus`` whose ``recv`` and ``send`` turn a failure of the bus itself (``is_bus_failure``) into
    ``PeerSilent`` naming the bus, so a dead hub ends a run in one line (exit 3) with the usual fault
    handling; ``send``'s ``CanOperationError`` (a full transmit queue) passes through for
    ``Sender`` to retry.  Everything else is the bus's own."""

    def __init__(self, bus, name: str):
        self._bus, self.name = bus, name

    def _failed(self, e: Exception) -> PeerSilent:
        return PeerSilent(f"bus {self.name} failed ({type(e).__name__}: {str(e)[:120]}): its hub process or "
                          "interface is gone")

    def recv(self, timeout=None):
        try:
            return self._bus.recv(timeout=timeout)
        except HilError:
            raise
        except Exception as e:
            if not is_bus_failure(e):
                raise
            raise self._failed(e) from None

    def send(self, msg, timeout=None):
        try:
            return self._bus.send(msg, timeout=timeout)
        except (HilError, can.CanOperationError):
            raise
        except Exception as e:
            if not is_bus_failure(e):
                raise
            raise self._failed(e) from None

    def __getattr__(self, name):
        return getattr(self._bus, name)


# -- sending and timing -------------------------------------------------------------------------------
class Sender:
    """Thread-safe ``send`` (a heartbeat thread and the main loop share the bus); a full transmit
    queue (ENOBUFS) is retried for up to ~25 ms, then the error propagates."""

    def __init__(self, bus: can.BusABC):
        self.bus = bus
        self._lock = threading.Lock()
        self.sent = 0

    def send(self, msg: can.Message) -> None:
        with self._lock:
            for attempt in range(50):
                try:
                    self.bus.send(msg, timeout=0.1)
                    self.sent += 1
                    return
                except can.CanOperationError:
                    if attempt == 49:
                        raise
                    time.sleep(0.0005)


def poll_until(bus: can.BusABC, until: float) -> can.Message | None:
    """A frame from ``bus``, polled without sleeping until one comes or ``until`` (perf_counter)
    passes: lockstep's wait before sleeping in the bus (``[bus] lockstep_spin_s``; a node woken by
    the kernel answers later than one that is awake)."""
    recv, clock = bus.recv, time.perf_counter
    while (msg := recv(timeout=0.0)) is None and clock() < until:
        pass
    return msg


def silence_limit_s(settings, mode: str, period_s: float) -> float:
    """How long the peer may send nothing before it counts as silent (wall seconds).

    Realtime: ``silence_periods`` periods of the heartbeat, the one frame a node sends however busy
    it is (``max(heartbeat_period_s, period_s)``).  Lockstep: ``lockstep_silence_s`` (a lockstep
    period has no wall-clock length, and a TCU busy fitting is not silent)."""
    if mode == "realtime":
        return settings.silence_periods * max(settings.heartbeat_period_s, period_s)
    return settings.lockstep_silence_s


def heartbeat_period_s(settings, mode: str) -> float:
    """Realtime: ``[bus] heartbeat_period_s``.  Lockstep: a quarter of the silence limit (the peers wait
    for each other by design; frequent heartbeats would only cost syscalls, which are dear in UML)."""
    return settings.heartbeat_period_s if mode == "realtime" else settings.lockstep_silence_s / 4
