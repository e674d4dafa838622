"""python-can's udp_multicast bus held to this machine (``hil.bus.multicast``): real sockets, a node of
python-can's own class beside this project's, and a network namespace with a second interface to show
what leaves the machine and what does not.  python-can's semantics that the docs rely on (a node receives
its own frames; CAN FD travels) are asserted here against python-can itself."""
import json
import os
import shutil
import subprocess
import sys
import textwrap
import time

import can
import pytest

from hil.bus.link import open_bus
from hil.bus.multicast import LoopbackMulticastBus, new_group
from hil.errors import BusError

from .conftest import ROOT, hil_command, subprocess_env


def frame(i: int, fd: bool) -> can.Message:
    return can.Message(arbitration_id=0x100 + i % 7, data=i.to_bytes(4, "little") * (16 if fd else 2), is_fd=fd,
                       bitrate_switch=fd, is_extended_id=False)


def recv_all(bus, n, timeout=5.0):
    out, end = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < end:
        m = bus.recv(0.1)
        if m is not None:
            out.append(m)
    return out


def stock_node(group, port, hop_limit=0):
    """python-can's own udp_multicast node; a skip (a failure under CI=true) where this host has no route
    for multicast (python-can joins the group on the interface the routing table gives it)."""
    try:
        return can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=hop_limit)
    except can.CanError as e:
        why = f"python-can's udp_multicast cannot join a group here ({e}: no route for 224.0.0.0/4?)"
        assert os.environ.get("CI") != "true", f"CI=true: {why}"
        pytest.skip(why)


def test_sockets_send_with_ttl_0_on_lo_and_a_spec_is_checked():
    group, port = new_group()
    with LoopbackMulticastBus(group, port) as bus:
        assert bus.ttl == 0 and bus.multicast_interface == "127.0.0.1"
    for spec, words in (("udp_multicast:10.0.0.1:4000", "not an IPv4 multicast group"),
                        ("udp_multicast:ff15::1", "not an IPv4 multicast group"),
                        ("udp_multicast:239.255.1.1:port", "not a number"),
                        ("udp_multicast:239.255.1.1:70000", "outside 1-65535")):
        with pytest.raises(BusError) as e:
            open_bus(spec)
        assert str(e.value).startswith(f"bus {spec}: ") and words in str(e.value) and "\n" not in str(e.value)


def test_a_python_can_node_and_a_hil_node_share_classic_and_fd_frames_in_order():
    """Both ways, 200 frames each, classical and FD mixed, each sender's in the order sent; the hil node
    never gets its own frames back, python-can's node does (multicast loops them back to every member on the
    host, whatever receive_own_messages says)."""
    group, port = new_group()
    with LoopbackMulticastBus(group, port) as ours:
        theirs = stock_node(group, port)
        try:
            sent = [frame(i, fd=i % 3 == 0) for i in range(200)]
            for m in sent:
                ours.send(m)
            got = recv_all(theirs, 200)
            assert [(m.arbitration_id, bytes(m.data), m.is_fd) for m in got] == \
                   [(m.arbitration_id, bytes(m.data), m.is_fd) for m in sent]
            for m in sent:
                theirs.send(m)
            got = recv_all(ours, 200)
            assert [(m.arbitration_id, bytes(m.data), m.is_fd) for m in got] == \
                   [(m.arbitration_id, bytes(m.data), m.is_fd) for m in sent]
            assert ours.recv(0.2) is None                              # nothing of its own came back
            own = recv_all(theirs, 200)                                 # python-can's node: its own 200
            assert [bytes(m.data) for m in own] == [bytes(m.data) for m in sent]
            assert ours.dropped == 0 and ours.garbage == 0
        finally:
            theirs.shutdown()


def test_two_hil_nodes_and_garbage_on_the_group():
    """Two nodes of this project see each other's frames; a datagram that is not a python-can frame is
    counted and skipped."""
    group, port = new_group()
    with LoopbackMulticastBus(group, port) as a, LoopbackMulticastBus(group, port) as b:
        import socket
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        s.sendto(b"not msgpack \xc1", (group, port))
        s.close()
        a.send(frame(5, fd=True))
        got = b.recv(2.0)
        assert got is not None and bytes(got.data) == bytes(frame(5, fd=True).data) and got.is_fd
        assert b.garbage == 1 and a.recv(0.1) is None and a.garbage == 1


# -- what leaves the machine: a network namespace with a second interface ----------------------------------
NETNS_PROBE = textwrap.dedent("""
    import json, socket, sys, time
    import can
    from hil.bus.multicast import LoopbackMulticastBus
    from hil.errors import BusError

    group, port = sys.argv[1], int(sys.argv[2])
    # every frame transmitted on v0 arrives at its peer v1: a packet socket there sees what left through v0
    cap = socket.socket(socket.AF_PACKET, socket.SOCK_DGRAM, socket.htons(0x0800))
    cap.bind(("v1", 0))
    cap.settimeout(0.3)

    def transmitted():
        n = 0
        while True:
            try:
                packet = cap.recv(4096)
            except socket.timeout:
                return n
            n += packet[9] == socket.IPPROTO_UDP                # any datagram (python-can's join sends IGMP)

    out = {}
    ours = LoopbackMulticastBus(group, port)
    theirs = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0)
    for i in range(20):
        ours.send(can.Message(arbitration_id=0x100, data=bytes([i]) * 8, is_extended_id=False))
        theirs.send(can.Message(arbitration_id=0x200, data=bytes([i]) * 8, is_extended_id=False))
    got_ours = [m for m in iter(lambda: ours.recv(0.3), None)]
    got_theirs = [m for m in iter(lambda: theirs.recv(0.3), None) if m.arbitration_id == 0x100]
    out["ttl0"] = {"ours_got": len(got_ours), "theirs_got": len(got_theirs), "transmitted": transmitted()}
    leaky = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=1)
    leaky.send(can.Message(arbitration_id=0x300, data=bytes(8), is_extended_id=False))
    try:
        while ours.recv(0.5) is not None:
            pass
        out["refused"] = None
    except BusError as e:
        out["refused"] = str(e)
    out["ttl1_transmitted"] = transmitted()
    for bus in (ours, theirs, leaky):
        bus.shutdown()
    print(json.dumps(out))
""")


def test_nothing_leaves_the_machine_and_a_node_that_sends_out_is_refused(tmp_path):
    """In a network namespace of its own (``unshare -rn``: no root needed where user namespaces are allowed)
    with lo and a veth pair v0/v1, the default route through v0: a hil node and python-can's node with
    hop_limit=0 exchange 20 frames each way and not one UDP datagram is transmitted on v0 (a packet socket
    on its peer v1 sees none; python-can's join of the group there sends IGMP membership reports, which are
    not counted: docs/guide/python-can-tcu.md); python-can's node at hop_limit=1 puts its frame on v0 (seen
    on v1: the capture works), and the hil node refuses the bus, naming the interface and the TTL."""
    unshare, ip = shutil.which("unshare"), shutil.which("ip")
    script = tmp_path / "probe.py"
    script.write_text(NETNS_PROBE)
    group, port = new_group()
    setup = ("ip link set lo up && ip link add v0 type veth peer name v1 && ip link set v0 up && ip link set v1 up "
             "&& ip addr add 10.77.0.1/24 dev v0 && ip route add default via 10.77.0.2 dev v0")
    why = None if unshare and ip else "needs unshare (util-linux) and ip (iproute2)"
    if why is None:
        r = subprocess.run([unshare, "-rn", "sh", "-c", f"{setup} && exec {sys.executable} {script} {group} {port}"],
                           capture_output=True, text=True, env=subprocess_env(), timeout=60)
        if r.returncode != 0 and ("unshare" in r.stderr or "Operation not permitted" in r.stderr
                                  or "RTNETLINK" in r.stderr):
            why = f"no network namespace here: {r.stderr.strip().splitlines()[-1]}"
    if why:
        assert os.environ.get("CI") != "true", f"CI=true: {why}"
        pytest.skip(why)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["ttl0"] == {"ours_got": 20, "theirs_got": 20, "transmitted": 0}, out
    assert out["ttl1_transmitted"] == 1, out
    assert out["refused"] is not None and "came through v0 with TTL 1" in out["refused"] and "hop_limit=0" in \
        out["refused"], out


def test_hil_tcu_hil_run_and_the_plugin_refuse_a_group_drawn_for_the_run(tmp_path):
    r = subprocess.run([*hil_command(), "tcu", str(ROOT / "scenarios/ffcc_a.toml"), "--bus", "udp_multicast"],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 2 and "udp_multicast:GROUP:PORT" in r.stderr, r.stderr
    r = subprocess.run([*hil_command(), "run", str(ROOT / "scenarios/ffcc_a.toml"), "--bus", "udp_multicast",
                        "--tcu", "external", "--out", str(tmp_path)], capture_output=True, text=True,
                       env=subprocess_env(), timeout=120)
    assert r.returncode == 2 and "a group drawn for this run has no external TCU" in r.stderr, r.stderr
    (tmp_path / "test_join.py").write_text(f"def test_answers(hil_run):\n    hil_run({str(ROOT / 'scenarios/ffcc_a.toml')!r})\n")
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "-q",
                        "test_join.py", "--hil-bus", "udp_multicast", "--hil-tcu", "external", "--hil-tcu-cmd", "sleep 9",
                        "--hil-out", str(tmp_path / "out")], cwd=tmp_path, capture_output=True, text=True,
                       env=subprocess_env(), timeout=300)
    assert "1 error" in r.stdout and "--hil-tcu-cmd with --hil-bus udp_multicast: that bus is opened anew by each run" \
        in r.stdout and "udp_multicast:GROUP:PORT (python-can alone)" in r.stdout, r.stdout[-3000:]


def test_a_node_that_does_not_read_loses_frames_and_counts_them():
    """The sender never blocks; a member whose socket buffer is full loses datagrams, and the hil node
    counts them (SO_RXQ_OVFL, stamped on the next datagram it queues): received + dropped = sent."""
    group, port = new_group()
    with LoopbackMulticastBus(group, port) as ours, LoopbackMulticastBus(group, port) as sender:
        n = 5000
        for i in range(n):
            sender.send(frame(i, fd=True))
        got = recv_all(ours, n, timeout=2.0)
        sender.send(frame(n, fd=True))                        # after the drain: it carries the whole count
        last = ours.recv(2.0)
        assert last is not None and bytes(last.data) == bytes(frame(n, fd=True).data)
        assert 0 < len(got) < n and len(got) + ours.dropped == n, (len(got), ours.dropped)
        assert [bytes(m.data) for m in got] == [bytes(frame(i, fd=True).data) for i in
                                                sorted(int.from_bytes(bytes(m.data)[:4], "little") for m in got)]
