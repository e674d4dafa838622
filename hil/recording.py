"""Streaming MCAP recorder: protobuf channels, small chunks, unbuffered file.

Why small chunks and no file buffering: a writer killed with SIGKILL leaves whatever reached the
file.  With mcap's default 1 MiB chunks that is nothing; with ``CHUNK_SIZE`` bytes per chunk
written straight to an unbuffered file, every finished chunk survives and can be read back with
``mcap.stream_reader.StreamReader`` (see ``hil.logread``).  Memory stays flat because messages
leave the process chunk by chunk; only the small chunk index grows with the run.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
from importlib import metadata as importlib_metadata
from pathlib import Path

from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer

from .schemas import TYPES

CHUNK_SIZE = 32 * 1024
PROFILE = "railway-hil"

#: topic -> protobuf message name
TOPICS = {
    "/plant/state": "PlantState",
    "/plant/sensor": "SensorReading",
    "/tcu/command": "TorqueCommand",
    "/tcu/observer": "ObserverSample",
    "/tcu/status": "TcuStatus",
    "/tcu/identification": "IdentificationEvent",
    "/can/frames": "CanFrame",
    "/loop/timing": "LoopTiming",
    "/run/events": "RunEvent",
    "/run/summary": "RunSummary",
}

VERSIONED_PACKAGES = ("numpy", "scipy", "casadi", "fmpy", "python-can", "cantools", "mcap",
                      "mcap-protobuf-support", "protobuf", "rerun-sdk")


def package_versions() -> dict[str, str]:
    out = {}
    for name in VERSIONED_PACKAGES:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = "not installed"
    try:
        out["railway-hil"] = importlib_metadata.version("railway-hil")
    except importlib_metadata.PackageNotFoundError:
        out["railway-hil"] = "source tree"
    return out


def sim_time_ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


class _InterruptGuard:
    """Ctrl-C and SIGTERM never land inside a write: they raise ``KeyboardInterrupt`` right after it.

    An interrupt raised halfway through mcap's chunk bookkeeping leaves a record the reader
    rejects, and everything after it (the "run interrupted" event included) is lost.
    """

    depth = 0
    pending = False

    @classmethod
    def handler(cls, signum, frame):
        if cls.depth:
            cls.pending = True
        else:
            raise KeyboardInterrupt

    @classmethod
    def leave(cls) -> None:
        cls.depth -= 1
        if cls.pending and not cls.depth:
            cls.pending = False
            raise KeyboardInterrupt


class interrupts_between_writes:
    """Context manager: SIGINT and SIGTERM end the run as ``KeyboardInterrupt``, never mid-write."""

    def __enter__(self):
        self.old = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self.old[sig] = signal.signal(sig, _InterruptGuard.handler)
        return self

    def __exit__(self, *exc):
        for sig, old in self.old.items():
            signal.signal(sig, old)


class _DirectFile:
    """A write-through file: every ``write`` reaches the kernel before it returns.

    mcap wraps a raw (unbuffered) file in an 8 KiB ``BufferedWriter``, which would hold back the
    newest chunks at a SIGKILL; this object is not a ``RawIOBase``, so mcap uses it as it is.
    """

    def __init__(self, path):
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pos = 0

    def write(self, data) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        os.close(self._fd)


class Recorder:
    """``write(topic, t_s, **fields)`` appends one message; ``close(summary)`` finishes the file."""

    def __init__(self, path: str | os.PathLike, chunk_size: int = CHUNK_SIZE):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = _DirectFile(self.path)
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.LZ4)
        self._types = {topic: TYPES[name] for topic, name in TOPICS.items()}
        self.messages = 0
        self.closed = False

    def write(self, topic: str, log_t_s: float, /, **fields) -> None:
        msg = self._types[topic](**fields)
        ns = sim_time_ns(log_t_s)
        _InterruptGuard.depth += 1
        try:
            self._writer.write_message(topic, msg, log_time=ns, publish_time=ns)
            self.messages += 1
        finally:
            _InterruptGuard.leave()

    def metadata(self, name: str, data: dict) -> None:
        with self.atomic():
            self._writer.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in data.items()})

    @contextlib.contextmanager
    def atomic(self):
        """A block of writes that Ctrl-C / SIGTERM cannot split (e.g. the last events and the footer)."""
        _InterruptGuard.depth += 1
        try:
            yield self
        finally:
            _InterruptGuard.leave()

    def event(self, t_s: float, level: str, text: str) -> None:
        self.write("/run/events", t_s, t_s=t_s, level=level, text=text)

    def close(self, summary: dict | None = None) -> None:
        if self.closed:
            return
        with self.atomic():             # summary, metadata and footer go out together
            if summary is not None:
                fields = {k: summary[k] for k in ("identified", "rt_percent", "t_fault_s", "t_serious_s",
                                                  "t_identified_s", "r2", "peak_mu_err_percent",
                                                  "peak_creep_err_percent")
                          if summary.get(k) is not None}
                self.write("/run/summary", summary.get("sim_s", 0.0), json=json.dumps(summary), **fields)
                self.metadata("summary", {"json": json.dumps(summary)})
            self._writer.finish()
            self._file.close()
            self.closed = True
