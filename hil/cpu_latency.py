"""A CPU latency request held for a real-time run, so that idle CPUs poll instead of halting.

Why: in real time each frame wakes a process that sleeps in ``recv`` (the TCU on the sensor frame,
the plant on the command), usually on a CPU that went idle meanwhile. An idle CPU enters the idle
state its cpuidle governor picks; on a virtual machine that is a halt, and a halted vCPU runs again
only when the host schedules it, tens of microseconds later and now and then milliseconds. A
real-time loop pays that on every hop, twice per period over two processes.

How: the kernel's PM QoS interface (``Documentation/power/pm_qos_interface.rst``). A process that
writes a latency bound (microseconds, a native 32-bit integer) to ``/dev/cpu_dma_latency`` and keeps
the file open asks the governor for idle states whose exit latency is within the bound; with 0 only
polling is left (the kernel's ``POLL`` state), the behaviour of ``idle=poll``. The request lasts
while the file is open, and ends when it is closed, also when the process dies. ``cyclictest``
(rt-tests) holds 0 this way by default, and ``rtla timerlat --dma-latency`` for the same reason.

The cost is said rather than hidden: while held, idle CPUs spin (power, and on a shared host CPU
time of the host). Opening the device needs root (it is ``0600 root``); a refusal is reported and
the run goes on without it.
"""
from __future__ import annotations

import os
import struct

#: the PM QoS CPU latency device
DEVICE = "/dev/cpu_dma_latency"


class CpuLatencyRequest:
    """Hold ``latency_us`` on ``device`` until ``close``; ``held_us`` is the bound held, or None
    (not asked: ``latency_us`` < 0; or refused, which ``log`` is told in one line)."""

    def __init__(self, latency_us: int, log, device: str = DEVICE):
        self.held_us: int | None = None
        self._fd: int | None = None
        if latency_us < 0:
            return
        try:
            fd = os.open(device, os.O_WRONLY | os.O_CLOEXEC)
        except OSError as e:
            log(f"realtime: cannot hold a CPU latency request on {device} ({e.strerror or e}): idle CPUs may halt "
                f"and wake late (bus.cpu_latency_us = -1 does not ask)")
            return
        try:
            os.write(fd, struct.pack("=i", latency_us))       # the device takes a native s32 (or hex text)
        except OSError as e:
            os.close(fd)
            log(f"realtime: {device} refused {latency_us} us ({e.strerror or e}): idle CPUs may halt and wake late")
            return
        self._fd, self.held_us = fd, latency_us
        log(f"realtime: CPU latency request {latency_us} us held on {device} for the run "
            f"({'idle CPUs poll instead of halting' if latency_us == 0 else 'shallow idle states only'})")

    def close(self) -> None:
        """End the request (the kernel drops it with the file)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def current_latency_us(device: str = DEVICE) -> int | None:
    """The bound in force now, the least of all requests held (the kernel's default when none is:
    2 000 s); None when the device cannot be read here."""
    try:
        with open(device, "rb") as f:
            data = f.read(4)
    except OSError:
        return None
    return struct.unpack("=i", data)[0] if len(data) == 4 else None
