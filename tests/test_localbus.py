"""The relay-free local bus (``hil.bus.localbus``) as any python-can program uses it: real sockets, real
processes."""
import os
import stat
import subprocess
import sys
import time

import can
import pytest

from hil.bus.localbus import create_channel, remove_channel

from .conftest import subprocess_env


@pytest.fixture
def channel():
    path = create_channel()
    yield path
    remove_channel(path)


def frame(i: int, fd: bool = True) -> can.Message:
    return can.Message(arbitration_id=0x100 + i % 7, data=i.to_bytes(4, "little") * (16 if fd else 2), is_fd=fd,
                       bitrate_switch=fd, is_extended_id=False)


def recv_all(bus, n, timeout=5.0):
    out, end = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < end:
        m = bus.recv(0.1)
        if m is not None:
            out.append(m)
    return out


def test_channel_is_closed_to_other_users_and_a_python_can_interface(channel):
    assert stat.S_IMODE(os.stat(channel).st_mode) == 0o700
    assert "localbus" in can.VALID_INTERFACES                    # registered through the can.interface entry point
    a = can.Bus(interface="localbus", channel=channel)
    b = can.Bus(interface="localbus", channel=channel)
    try:
        a.send(frame(3))
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 0x103 and got.is_fd and got.bitrate_switch
        assert bytes(got.data) == bytes(frame(3).data) and got.dlc == 64
        assert a.recv(0.2) is None                               # no echo of its own frames
        b.send(frame(4, fd=False))
        got = a.recv(2.0)
        assert got is not None and not got.is_fd and not got.bitrate_switch and got.dlc == 8
    finally:
        a.shutdown()
        b.shutdown()
    os.chmod(channel, 0o755)
    with pytest.raises(can.CanInitializationError, match="mode 0700"):
        can.Bus(interface="localbus", channel=channel)


def test_three_nodes_see_every_frame_in_order_classic_and_fd(channel):
    nodes = [can.Bus(interface="localbus", channel=channel) for _ in range(3)]
    try:
        time.sleep(0.05)
        for i in range(300):
            nodes[i % 3].send(frame(i, fd=i % 2 == 0))
        for k, bus in enumerate(nodes):
            got = [int.from_bytes(bytes(m.data[:4]), "little") for m in recv_all(bus, 200)]
            assert sorted(got) == [i for i in range(300) if i % 3 != k]       # every other node's frames
            for sender in {0, 1, 2} - {k}:                                    # each sender's order kept
                assert [i for i in got if i % 3 == sender] == list(range(sender, 300, 3))
            assert bus.recv(0.05) is None
    finally:
        for bus in nodes:
            bus.shutdown()


def test_a_node_that_dies_is_noticed_and_a_slow_one_never_blocks_the_sender(channel):
    code = ("import can, time, sys; b = can.Bus(interface='localbus', channel=sys.argv[1]); "
            "b.send(can.Message(arbitration_id=0x701, data=b'x' * 8, is_extended_id=False)); time.sleep(30)")
    peer = subprocess.Popen([sys.executable, "-c", code, channel], env=subprocess_env())
    bus = can.Bus(interface="localbus", channel=channel)
    try:
        assert bus.recv(20.0) is not None                      # the peer is there
        t0 = time.perf_counter()
        for i in range(20000):                                  # the peer reads nothing: its buffer fills
            bus.send(frame(i))
        assert time.perf_counter() - t0 < 10.0
        assert sum(bus.dropped.values()) > 0                    # counted, not blocked
        peer.kill()
        peer.wait(10)
        bus.recv(0.5)
        bus.send(frame(1))
        assert bus.peers_lost == 1
    finally:
        if peer.poll() is None:
            peer.kill()
        bus.shutdown()


def test_what_a_peer_sent_before_closing_is_read_even_after_a_send_to_it_fails(channel):
    """A TCU that answers and exits at once: the plant's next send to it fails (EPIPE), yet the frames
    the TCU sent before closing are still delivered (a lockstep run's last TcuStatus was lost so)."""
    a = can.Bus(interface="localbus", channel=channel)
    b = can.Bus(interface="localbus", channel=channel)
    try:
        a.send(can.Message(arbitration_id=0x701, data=b"\x01", is_extended_id=False))   # a accepts b's connection
        assert b.recv(timeout=2.0) is not None
        for i in range(3):
            b.send(can.Message(arbitration_id=0x120, data=bytes([i]), is_extended_id=False))
        b.shutdown()
        b = None
        for _ in range(2):      # the first send may still be taken by the kernel; the next fails (EPIPE)
            a.send(can.Message(arbitration_id=0x701, data=b"\x02", is_extended_id=False))
        got = []
        while (m := a.recv(timeout=0.5)) is not None:
            got.append(bytes(m.data))
        assert got == [b"\x00", b"\x01", b"\x02"]
        assert a.peers_lost == 1
    finally:
        a.shutdown()
        if b is not None:
            b.shutdown()


def test_a_node_with_filters_receives_only_the_frames_they_let_through(channel):
    """``recv`` skips python-can's filter loop only when no filter is set: a node that sets filters still
    gets only the matching frames, and a node without them every frame, in order."""
    with can.Bus(interface="localbus", channel=channel) as a, \
            can.Bus(interface="localbus", channel=channel, can_filters=[{"can_id": 0x102, "can_mask": 0x7FF}]) as b, \
            can.Bus(interface="localbus", channel=channel) as c:
        for i in range(14):
            a.send(frame(i))
        got_b = recv_all(b, 2, timeout=3.0)
        got_c = recv_all(c, 14, timeout=3.0)
        assert [m.arbitration_id for m in got_b] == [0x102, 0x102]
        assert b.recv(0.05) is None
        assert [bytes(m.data) for m in got_c] == [bytes(frame(i).data) for i in range(14)]
