"""The log's writer process: rows go from the run's loop through a pipe to a forked process that
encodes and writes them, so protobuf and MCAP (microseconds a row, nine rows a period) stay
off the loop.

Contract.  ``WriterProcess(file)`` forks; the child takes ``file`` (a ``hil.log.record.McapFile`` with
everything written so far, its chunk builder and indexes included: fork copies them) and the parent
must not touch ``file`` again.  The parent then hands over *items*: a row ``(topic, log_t_s,
fields)``, ``(META, name, data)`` or ``(CLOSE,)``.  ``put`` only appends to a list; ``ship`` pickles
the list as one length-prefixed batch and writes what the pipe takes without blocking (``push``
with ``block=True`` waits for room).  The child answers on a second pipe with JSON lines:
``{"failed": reason, "written": n}`` when a write fails (later rows are dropped), and
``{"written": n, "failed": reason|null, "orphaned": bool}`` when it ends.

Why fork: the child needs nothing imported or built anew, so it starts in milliseconds; it runs
only code that holds no lock another thread could have held (the file object, ``pickle``,
``os.read``) and leaves with ``os._exit``.  It closes every inherited descriptor but its three, so
a bus socket or a terminal held by the run is not kept open by the writer.

Crash safety. Rows in the pipe outlive the parent: when the parent dies without ``CLOSE`` (SIGKILL),
the child reads to the end of the pipe, calls ``on_orphan(file, last_t_s)`` (the recorder's: an
error event and a ``fault`` record saying so) and finishes the file; what is lost is what the parent
had not yet shipped (the recorder bounds it). The child ignores SIGINT and SIGTERM (a Ctrl-C reaches
the whole process group; the parent decides).

Scheduling.  The child runs on any CPU at normal priority, whatever the loop's real-time priority and
affinity, under ``SCHED_BATCH``: the scheduler then never lets its wake-up preempt the process that
woke it.  Under ``SCHED_OTHER`` a batch written into the pipe wakes the child, which may take the
writer's CPU at once, and the loop's ``os.write`` returns only when the child has encoded the batch
and sleeps again.  Not ``SCHED_IDLE``: on
a busy machine the child would starve and a lockstep loop, which waits for room in the pipe, with it.
"""
from __future__ import annotations

import collections
import contextlib
import fcntl
import json
import os
import pickle
import select
import signal
import struct

META, CLOSE = "\0meta", "\0close"
#: the pipe's capacity asked for (Linux caps it at /proc/sys/fs/pipe-max-size, 1 MiB by default)
PIPE_BYTES = 1 << 20
_LEN = struct.Struct("<I")


class WriterGone(OSError):
    """The writer process is gone (killed, or the pipe to it broke)."""


class WriterProcess:
    """The parent's handle on the writer child (module docstring)."""

    def __init__(self, file, on_orphan):
        rows_r, rows_w = os.pipe()
        status_r, status_w = os.pipe()
        with contextlib.suppress(OSError):
            fcntl.fcntl(rows_w, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        pid = os.fork()
        if pid == 0:                                    # the child: never returns
            code = 1
            try:
                os.close(rows_w)
                os.close(status_r)
                code = _child(file, rows_r, status_w, on_orphan)
            finally:
                os._exit(code)
        os.close(rows_r)
        os.close(status_w)
        os.set_blocking(rows_w, False)
        os.set_blocking(status_r, False)
        self.pid, self._w, self._status_fd = pid, rows_w, status_r
        self._items: list = []
        self._out: collections.deque = collections.deque()    # [memoryview, rows] not yet in the pipe
        self.unshipped = 0           # items put or shipped but not yet in the pipe
        self._status_buf = b""
        self.status: dict = {}
        self.ended = False

    # -- parent side ---------------------------------------------------------------------------------
    @property
    def batched(self) -> int:
        """Items put since the last ``ship``."""
        return len(self._items)

    def put(self, item) -> None:
        self._items.append(item)
        self.unshipped += 1

    def ship(self) -> None:
        """The items put so far as one batch, and as much of the waiting batches as the pipe takes."""
        if self._items:
            data = pickle.dumps(self._items, protocol=pickle.HIGHEST_PROTOCOL)
            self._out.append([memoryview(_LEN.pack(len(data)) + data), len(self._items)])
            self._items = []
        self.push(block=False)

    def push(self, block: bool, timeout_s: float | None = None) -> None:
        """Write waiting batches into the pipe; ``block``: until all are in (or ``timeout_s`` passes)."""
        while self._out:
            head = self._out[0]
            try:
                n = os.write(self._w, head[0])
            except BlockingIOError:
                if not block:
                    return
                self.read_status()
                if self.ended:
                    raise WriterGone("the log's writer process ended") from None
                if not select.select([], [self._w], [], 0.5 if timeout_s is None else timeout_s)[1] \
                        and timeout_s is not None:
                    return
                continue
            except BrokenPipeError:
                raise WriterGone("the log's writer process is gone") from None
            if n == len(head[0]):
                self._out.popleft()
                self.unshipped -= head[1]
            else:
                head[0] = head[0][n:]

    def read_status(self) -> dict:
        """Take whatever the child reported (non-blocking); ``self.status`` is the newest report."""
        while True:
            try:
                chunk = os.read(self._status_fd, 4096)
            except BlockingIOError:  # no report queued (non-blocking read)
                break
            if not chunk:
                self.ended = True
                break
            self._status_buf += chunk
        *lines, self._status_buf = self._status_buf.split(b"\n")
        for line in lines:
            with contextlib.suppress(ValueError):
                self.status = json.loads(line)
        return self.status

    def finish(self, timeout_s: float) -> dict:
        """``CLOSE`` sent (by the caller) and shipped: close the pipe and wait for the child's last
        report; a child that does not end within ``timeout_s`` is killed.  Returns the last report."""
        try:
            self.ship()
            self.push(block=True)
        finally:
            with contextlib.suppress(OSError):
                os.close(self._w)
        os.set_blocking(self._status_fd, True)
        ready = select.select([self._status_fd], [], [], timeout_s)[0]
        while ready:
            chunk = os.read(self._status_fd, 4096)
            if not chunk:
                break
            self._status_buf += chunk
            ready = select.select([self._status_fd], [], [], timeout_s)[0]
        if not ready:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)
        os.set_blocking(self._status_fd, False)
        self.read_status()
        os.close(self._status_fd)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)
        self.ended = True
        if not ready:
            self.status = {**self.status, "failed": f"the log's writer process did not end within {timeout_s:g} s"}
        return self.status

    def kill(self) -> None:
        """End the child at once (the parent is failing anyway)."""
        with contextlib.suppress(OSError):
            os.close(self._w)
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)
        self.ended = True


# -- child side --------------------------------------------------------------------------------------
def _child(file, rows_fd: int, status_fd: int, on_orphan) -> int:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    keep = {rows_fd, status_fd, file.fileno()}
    devnull = os.open(os.devnull, os.O_RDWR)
    for fd in (0, 1, 2):
        os.dup2(devnull, fd)
    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        if fd > 2 and fd not in keep:
            with contextlib.suppress(OSError):
                os.close(fd)
    with contextlib.suppress(OSError, AttributeError):     # SCHED_BATCH: module docstring, "Scheduling"
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))

    def report(**fields) -> None:
        with contextlib.suppress(OSError):
            os.write(status_fd, (json.dumps(fields) + "\n").encode())

    pipe = os.fdopen(rows_fd, "rb", buffering=1 << 16)
    written, failed, closed, last_t = 0, None, False, 0.0
    while not closed:
        head = pipe.read(4)
        if len(head) < 4:
            break                                   # the parent died without CLOSE
        size = _LEN.unpack(head)[0]
        body = pipe.read(size)
        if len(body) < size:
            break                                   # ... halfway through a batch
        items = pickle.loads(body)
        for item in items:
            if failed is not None:
                continue
            try:
                if item[0] == META:
                    file.metadata(item[1], item[2])
                elif item[0] == CLOSE:
                    file.finish()
                    closed = True
                else:
                    file.write(*item)
                    written += 1
                    last_t = item[1]
            except Exception as e:  # noqa: BLE001 - a disk error, or a row the schema refuses: said, not lost
                failed = (e.strerror or str(e)) if isinstance(e, OSError) else f"{type(e).__name__}: {e}"
                file.abandon()
                report(failed=failed, written=written)
    orphaned = not closed and failed is None
    if orphaned:
        try:
            on_orphan(file, last_t)
            file.finish()
        except OSError as e:
            failed = e.strerror or str(e)
            file.abandon()
    report(written=written, failed=failed, orphaned=orphaned)
    return 0
