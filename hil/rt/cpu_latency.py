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

It works through the cpuidle driver. Where the kernel runs none (``cpuidle_driver``: the sysfs file
reads ``none``), idle is the architecture's default, a halt, and the request changes nothing; a
real-time run then keeps its idle CPUs busy with idle spinners instead (``hil.rt.idle_spin``).

The cost is said rather than hidden: while held, idle CPUs spin (power, and on a shared host CPU
time of the host). Opening the device needs root (it is ``0600 root``); a refusal is reported and
the run goes on without it.
"""
from __future__ import annotations

import os
import struct

#: the PM QoS CPU latency device
DEVICE = "/dev/cpu_dma_latency"
#: where the kernel names the cpuidle driver that carries out CPU latency requests
CPUIDLE_DRIVER = "/sys/devices/system/cpu/cpuidle/current_driver"


def cpuidle_driver(path: str = CPUIDLE_DRIVER) -> str | None:
    """The cpuidle driver in use (``haltpoll``, ``intel_idle``, ...), or None when there is none (the
    file reads ``none``, or is missing): then idle is the architecture's default (a halt), and a CPU
    latency request changes nothing."""
    try:
        with open(path) as f:
            name = f.read().strip()
    except OSError:  # no cpuidle in sysfs: the architecture's default idle (docstring)
        return None
    return None if name in ("", "none") else name


class CpuLatencyRequest:
    """Hold ``latency_us`` on ``device`` until ``close``; ``held_us`` is the bound held, or None
    (not asked: ``latency_us`` < 0; or refused, which ``log`` is told in one line).  ``driver`` is the
    cpuidle driver that carries a request out (``cpuidle_driver``); where there is none the request
    is held all the same, and ``log`` is told that it changes nothing here."""

    def __init__(self, latency_us: int, log, device: str = DEVICE, driver_path: str = CPUIDLE_DRIVER):
        self.held_us: int | None = None
        self._fd: int | None = None
        self.driver = cpuidle_driver(driver_path)
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
        if self.driver is None:
            log(f"realtime: CPU latency request {latency_us} us held on {device}, but this kernel runs no cpuidle "
                "driver: idle CPUs halt whatever is asked")
            return
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
    except OSError:  # no device here (not Linux, no permission): unknown
        return None
    return struct.unpack("=i", data)[0] if len(data) == 4 else None
