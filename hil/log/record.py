"""The run's MCAP log: where it goes (``log_path``), the recorder, and ONE writer per topic.

Every part of a run that logs (the plant node for its states, sensors, frames and the TCU's decoded
frames; the exchange loop for its timing) calls the ``write_*`` function of the topic, so a log has
the same topics and fields whatever the transport.

Streaming: protobuf channels, small chunks, unbuffered file.

Why small chunks and no file buffering: a writer killed with SIGKILL leaves whatever reached the
file.  With mcap's default 1 MiB chunks that is nothing; with ``CHUNK_SIZE`` bytes per chunk
written straight to an unbuffered file, every finished chunk survives and can be read back (see
``hil.log.read``, which also steps over damaged chunks).  Memory stays flat because messages
leave the process chunk by chunk; only the small chunk index grows with the run.
"""
from __future__ import annotations

import collections
import contextlib
import hashlib
import json
import os
import re
import signal
import threading
import time
from importlib import metadata as importlib_metadata
from pathlib import Path

from mcap.writer import LIBRARY_IDENTIFIER
from mcap_protobuf.schema import build_file_descriptor_set

from identifier.messages import STAGE_NAMES

from ..errors import ConfigError, LogWriteError
from .writer import CLOSE, META, WriterGone, WriterProcess
from .mcapfile import LeanMcapWriter
from .schemas import FIELDS, PROFILE, TOPICS, TYPES

CHUNK_SIZE = 32 * 1024

VERSIONED_PACKAGES = ("numpy", "scipy", "casadi", "fmpy", "python-can", "cantools", "mcap",
                      "mcap-protobuf-support", "protobuf", "rerun-sdk")


def package_versions() -> dict[str, str]:
    out = {}
    for name in VERSIONED_PACKAGES:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:  # an optional package: its absence is recorded
            out[name] = "not installed"
    try:
        out["railway-hil"] = importlib_metadata.version("railway-hil")
    except importlib_metadata.PackageNotFoundError:  # run from a checkout without installing
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
    remember = None     # the command's handler (hil.cli): told of every interrupt, so none is lost to a
                        # library that catches KeyboardInterrupt (seen in CI: a run went on to exit 0)

    @classmethod
    def handler(cls, signum, frame):
        if getattr(cls.remember, "interrupted", None) is False:
            cls.remember.interrupted = True
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
            _InterruptGuard.remember = self.old[signal.SIGINT]
            if getattr(self.old[signal.SIGINT], "interrupted", False):
                # an interrupt the command's handler saw (hil.cli) but something swallowed: no run
                self.__exit__()
                raise KeyboardInterrupt
        return self

    def __exit__(self, *exc):
        for sig, old in self.old.items():
            signal.signal(sig, old)
        _InterruptGuard.remember = None


class _DirectFile:
    """A write-through file: every ``write`` reaches the kernel before it returns.

    mcap wraps a raw (unbuffered) file in an 8 KiB ``BufferedWriter``, which would hold back the
    newest chunks at a SIGKILL; this object is not a ``RawIOBase``, so mcap uses it as it is.
    """

    def __init__(self, fd: int):
        self._fd = fd
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


class McapFile:
    """The log file itself: one protobuf message per row, LZ4 chunks of ``chunk_size`` bytes written
    straight to the file descriptor ``fd`` (by ``hil.log.mcapfile``: mcap's writer's file, with a leaner
    path per row).

    The header's profile is ``PROFILE`` and every topic's schema and channel are registered before
    the first message, in ``TOPICS`` order (ids 1, 2, ...), so a reader can rebuild them from
    ``TOPICS`` when the chunk that held them is damaged (``hil.log.read``)."""

    def __init__(self, fd: int, chunk_size: int):
        self._file = _DirectFile(fd)
        self._writer = LeanMcapWriter(self._file, chunk_size)
        self._writer.start(profile=PROFILE, library=f"railway-hil hil.log.mcapfile ({LIBRARY_IDENTIFIER} records)")
        self._types, self._channels, self._fill = {}, {}, {}
        for topic, name in TOPICS.items():
            cls = TYPES[name]
            schema_id = self._writer.register_schema(cls.DESCRIPTOR.full_name, "protobuf",
                                                     build_file_descriptor_set(cls).SerializeToString())
            self._channels[topic] = self._writer.register_channel(topic, "protobuf", schema_id)
            self._types[topic] = cls
            if topic in FIELDS and not any(getattr(f, "is_repeated", True) or f.type == f.TYPE_MESSAGE
                                           for f in cls.DESCRIPTOR.fields):
                self._fill[topic] = _filler(cls, FIELDS[topic])

    def write(self, topic: str, log_t_s: float, fields: dict | tuple) -> None:
        """One row: ``fields`` by name, or (a tuple) every field's value in ``FIELDS[topic]`` order."""
        ns = sim_time_ns(log_t_s)
        fill = self._fill.get(topic) if type(fields) is tuple else None
        if fill is not None:        # a row of scalars: one message of the topic, every field set anew
            self._writer.add_message(self._channels[topic], log_time=ns, data=fill(fields), publish_time=ns)
            return
        if type(fields) is tuple:
            names = FIELDS[topic]
            if len(fields) != len(names):
                raise ValueError(f"{topic}: a row of {len(fields)} values for {len(names)} fields")
            fields = dict(zip(names, fields))
        data = self._types[topic](**fields).SerializeToString()
        self._writer.add_message(self._channels[topic], log_time=ns, data=data, publish_time=ns)

    def metadata(self, name: str, data: dict) -> None:
        self._writer.add_metadata(name, data)

    def fileno(self) -> int:
        return self._file._fd

    def finish(self) -> None:
        self._writer.finish()
        self._file.close()

    def abandon(self) -> None:
        """Close the file as it is (after a write failed: the writer's state is not to be trusted)."""
        with contextlib.suppress(OSError):
            self._file.close()


def _filler(cls, names: tuple):
    """``McapFile.write``'s encoder of a tuple row of a topic whose fields are all scalars: one message kept
    per topic, every field set from the row, serialised.  The bytes of ``cls(**dict(zip(names, row)))``
    (every field is set each time, and proto3 writes a field at its default value the same way: not at
    all), without a dict and a message made per row."""
    msg, n, topic = cls(), len(names), cls.DESCRIPTOR.full_name

    def fill(values: tuple) -> bytes:
        if len(values) != n:
            raise ValueError(f"{topic}: a row of {len(values)} values for {n} fields")
        for name, value in zip(names, values):
            setattr(msg, name, value)
        return msg.SerializeToString()
    return fill


#: what the writer process records when the run's process dies without closing the log
ORPHANED = ("the run's process ended without closing its log (killed?); the rows it had not handed to the "
            "log's writer are lost")


def _orphaned(file: McapFile, t_s: float) -> None:
    """The writer process's last rows when the run died (``hil.log.writer``): an error event, a fault."""
    file.write("/run/events", t_s, {"t_s": t_s, "level": "ERROR", "text": ORPHANED})
    file.metadata("fault", {"reason": ORPHANED, "t_s": repr(t_s)})


class Recorder:
    """``write(topic, t_s, **fields)`` appends one message; ``close(summary)`` finishes the file.

    In line (as created): every ``write`` encodes and writes its row.  Deferred
    (``defer(queue_limit, block_when_full, writer)``), ``write`` only appends the row (about a
    microsecond) and the encoding happens off the loop's path, in one of two places:

    - ``writer="process"``: a writer process takes the file over (``hil.log.writer``) and encodes
      beside the loop; ``work`` (in a wait) ships the rows through a pipe, a batch at a time.  Rows in the
      pipe outlive a SIGKILL of this process (the child writes them and finishes the file with an
      error event).  Best where a CPU is free for it (real time, a single-process run).
    - ``writer="inline"``: this process writes queued rows while it waits (``work(until)`` writes
      until then).  Best where no CPU is free (two lockstep nodes polling on two CPUs: a third busy
      process takes its CPU from them).

    Rows not yet written or shipped are ``pending``; they are what a SIGKILL of this process loses,
    so ``queue_limit`` bounds that loss.  At ``queue_limit`` ``write`` either writes or waits for
    room (``block_when_full``: lockstep, where nothing is late) or drops the row and counts it
    (``overflow``: real time, where the loop must not wait).  A failed write (a full disk) raises
    ``LogWriteError`` (from the writer process: at the next ``write`` or ``work`` after it said
    so); later rows are dropped (``dropped``)."""

    #: rows appended before ``work`` ships them to the writer process (one pickle and one pipe write,
    #: in a wait of the loop); ``write`` ships them itself at SHIP_IN_LINE_ROWS (a loop that never waits)
    BATCH_ROWS = 64
    SHIP_IN_LINE_ROWS = 4 * BATCH_ROWS
    #: how long ``close`` waits for the writer process to finish the file
    CLOSE_TIMEOUT_S = 120.0
    WRITERS = ("process", "inline")

    def __init__(self, path: str | os.PathLike, chunk_size: int = CHUNK_SIZE):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as e:
            raise ConfigError(f"{self.path}: cannot write the log: {e.strerror or e}") from None
        try:
            self._file = McapFile(fd, chunk_size)
        except OSError as e:
            with contextlib.suppress(OSError):
                os.close(fd)
            self._remove_if_empty()
            raise LogWriteError(f"{self.path}: cannot write the log: {e.strerror or e}") from None
        self._written = 0
        self.closed = False
        self.failed: str | None = None      # why writing failed; from then on rows are dropped
        self.dropped = 0
        self._proc: WriterProcess | None = None
        self._queue: collections.deque | None = None
        self._queue_limit = 0
        self._block_when_full = True
        self.overflow = 0
        self.queued_max = 0

    def defer(self, queue_limit: int, block_when_full: bool, writer: str = "process") -> None:
        """From now on rows are written off the loop's path (class docstring)."""
        if writer not in self.WRITERS:
            raise ValueError(f"writer {writer!r}: one of {', '.join(self.WRITERS)}")
        if self._proc is not None or self._queue is not None or self.failed:
            return
        self._queue_limit = max(int(queue_limit), 1)
        self._block_when_full = block_when_full
        if writer == "inline":
            self._queue = collections.deque()
            return
        with self.atomic():     # a Ctrl-C waits until the fork is done (at-fork handlers would swallow it)
            self._proc = WriterProcess(self._file, _orphaned)
        self._file = None

    @property
    def writer_pid(self) -> int | None:
        """The writer process (None: rows are written in this process)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def pending(self) -> int:
        """Rows appended but not yet written (in line) or handed to the writer process."""
        if self._proc is not None:
            return self._proc.unshipped
        return len(self._queue) if self._queue is not None else 0

    @property
    def work_due(self) -> bool:
        """``work`` has something to do: a batch of ``BATCH_ROWS`` rows to ship to the writer process,
        or queued rows to write in line."""
        if self._proc is not None:
            return self._proc.batched >= self.BATCH_ROWS
        return bool(self._queue)

    @property
    def messages(self) -> int:
        """Rows written, queued or handed to the writer so far."""
        return self._written + (len(self._queue) if self._queue is not None else 0)

    def write(self, topic: str, log_t_s: float, /, **fields) -> None:
        self._add(topic, log_t_s, fields)

    def row(self, topic: str, log_t_s: float, values: tuple) -> None:
        """``write`` with every field's value in ``FIELDS[topic]`` order: the loop's rows, a few a period,
        without a dict to build and pickle for each (the names are put back in the writer)."""
        self._add(topic, log_t_s, values)

    def _add(self, topic: str, log_t_s: float, fields: dict | tuple) -> None:
        proc = self._proc
        if proc is not None and not self.failed and proc.unshipped < self._queue_limit:    # the usual case
            proc.put((topic, log_t_s, fields))
            self._written += 1
            if proc.batched >= self.SHIP_IN_LINE_ROWS:    # no wait came to ship them in
                self._ship(block=False)
            if proc.unshipped > self.queued_max:
                self.queued_max = proc.unshipped
            return
        if proc is None and self._queue is None:
            self._write(topic, log_t_s, fields)
            return
        if self.failed:
            self.dropped += 1
            return
        if self.pending >= self._queue_limit:
            self._make_room(block=self._block_when_full)
            if self.pending >= self._queue_limit:
                self.overflow += 1
                return
        if self._proc is not None:
            self._proc.put((topic, log_t_s, fields))
            self._written += 1
            if self._proc.batched >= self.SHIP_IN_LINE_ROWS:    # no wait came to ship them in
                self._ship(block=False)
        else:
            self._queue.append((topic, log_t_s, fields))
        if self.pending > self.queued_max:
            self.queued_max = self.pending

    def work(self, until: float | None = None) -> int:
        """Use a wait for the log: ship the appended rows to the writer process (as far as the pipe
        takes them without waiting), or write queued rows in line until ``time.perf_counter()``
        passes ``until`` (None: all; at least one row is written).  Returns how many rows are still
        pending."""
        if self.failed:
            return self.pending
        if self._proc is not None:
            self._ship(block=False)
        elif self._queue:
            self._write_queued(until)
        return self.pending

    def _make_room(self, block: bool) -> None:
        if self._proc is not None:
            self._ship(block)
        elif block:       # a batch, not the one row the next append needs: the appends after it go straight in
            self._write_queued(None, max_rows=len(self._queue) - self._queue_limit + self.BATCH_ROWS)

    def _write_queued(self, until: float | None, max_rows: int | None = None) -> None:
        """Queued rows written in line, in one batch: one interrupt guard around them, not one a row (as
        ``_write``, which it is row by row)."""
        q, n = self._queue, 0
        if self.failed:
            while q and (max_rows is None or n < max_rows):
                q.popleft()
                self.dropped += 1
                n += 1
            return
        write, clock = self._file.write, time.perf_counter
        _InterruptGuard.depth += 1
        try:
            while q and (max_rows is None or n < max_rows):
                if until is not None and n and clock() >= until:
                    break
                write(*q.popleft())
                n += 1
        except OSError as e:
            self._written, n = self._written + n, 0      # the rows before the failing one reached the file
            raise self._fail(e) from None
        finally:
            self._written += n
            _InterruptGuard.leave()

    def _ship(self, block: bool) -> None:
        proc = self._proc
        _InterruptGuard.depth += 1
        try:
            proc.ship()
            if block:
                while proc.unshipped >= self._queue_limit:
                    proc.push(block=True, timeout_s=0.5)
                    self._check_writer()
            self._check_writer()
        except WriterGone as e:
            self._check_writer()            # a failure it reported first says more
            raise self._fail(OSError(0, str(e))) from None
        finally:
            _InterruptGuard.leave()

    def _check_writer(self) -> None:
        status = self._proc.read_status()
        if status.get("failed") and not self.failed:
            self._written = status.get("written", self._written)
            raise self._fail(OSError(0, status["failed"]))

    def _write(self, topic: str, log_t_s: float, fields: dict) -> None:
        if self.failed:
            self.dropped += 1
            return
        _InterruptGuard.depth += 1
        try:
            self._file.write(topic, log_t_s, fields)
            self._written += 1
        except OSError as e:
            raise self._fail(e) from None
        finally:
            _InterruptGuard.leave()

    def _fail(self, e: OSError) -> LogWriteError:
        """Writing failed: later rows are dropped, the file is closed as it is; the error to raise."""
        self.failed = e.strerror or str(e)
        if self._proc is not None:
            self._proc.kill()
        else:
            self._file.abandon()
        return LogWriteError(f"{self.path}: cannot write the log: {self.failed} (after {self._written} messages; "
                             "what reached the file stays readable)")

    def _remove_if_empty(self) -> None:
        with contextlib.suppress(OSError):
            if self.path.stat().st_size == 0:
                self.path.unlink()

    def metadata(self, name: str, data: dict) -> None:
        data = {k: v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
        with self.atomic():
            if self.failed:
                return
            if self._queue:
                self._write_queued(None)
            if self._proc is not None:
                self._proc.put((META, name, data))
                return
            try:
                self._file.metadata(name, data)
            except OSError as e:
                raise self._fail(e) from None

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
        """Write the pending rows, the summary and the footer.  After a failed write (``failed``) the
        file is only closed (what reached it stays readable; an empty file is removed); a failure here
        raises ``LogWriteError``, after the file is closed."""
        if self.closed:
            return
        try:
            with self.atomic():         # the pending rows, summary, metadata and footer go out together
                if summary is not None and not self.failed:
                    fields = {k: summary[k] for k in ("identified", "rt_percent", "t_fault_s", "t_serious_s",
                                                      "t_identified_s", "r2", "peak_mu_err_percent",
                                                      "peak_creep_err_percent")
                              if summary.get(k) is not None}
                    self._queue_limit = max(self._queue_limit, self.pending + 2)   # the end is never dropped
                    self.write("/run/summary", summary.get("sim_s", 0.0), json=json.dumps(summary), **fields)
                    self.metadata("summary", {"json": json.dumps(summary)})
                if not self.failed:
                    self._finish()
        finally:
            self.closed = True
            if self._proc is not None and not self._proc.ended:
                self._proc.kill()
            if self.failed:
                self._remove_if_empty()

    def _finish(self) -> None:
        if self._proc is None:
            if self._queue:
                self._write_queued(None)
            self._queue = None
            try:
                self._file.finish()
            except OSError as e:
                raise self._fail(e) from None
            return
        self._proc.put((CLOSE,))
        try:
            status = self._proc.finish(self.CLOSE_TIMEOUT_S)
        except WriterGone as e:
            status = {**self._proc.read_status(), "failed": self._proc.status.get("failed") or str(e)}
        if status.get("failed") or "written" not in status:
            self._written = status.get("written", self._written)
            raise self._fail(OSError(0, status.get("failed") or "the log's writer process ended without a word"))


# -- where a log goes -----------------------------------------------------------------------------------
#: the longest slug a log name part takes (a scenario name beyond it is cut)
SLUG_MAX = 60


def slug(text: str, what: str) -> str:
    """``text`` as a file-name part: letters, digits, ``.``, ``_``, ``-`` (any run of other characters
    becomes one ``_``, a run of dots one ``.``), at most ``SLUG_MAX`` characters, never starting or ending
    with ``.``, ``_`` or ``-``: it holds no path separator and is never ``.`` or ``..``, so a log named
    from it stays in its directory.  Refused in one line when nothing usable is left (empty, only dots)."""
    out = re.sub(r"\.{2,}", ".", re.sub(r"[^A-Za-z0-9._-]+", "_", str(text))).strip("._-")
    out = out[:SLUG_MAX].rstrip("._-")
    if not out:
        shown = repr(str(text)[:80]) + ("..." if len(str(text)) > 80 else "")
        raise ConfigError(f"{what} {shown}: cannot be part of a log file name (use letters, digits, . _ -)")
    return out


def log_path(scenario, strategy: str, seed: int, out_dir=None, plant: str | None = None,
             reality: dict | None = None) -> Path:
    """``<out>/<scenario>-<strategy>[-<law>]-<seed>[-<plant>][-real-<digest>].mcap``, every part slugged so
    the file stays inside ``out_dir`` (default ``logs``); ``plant`` is None for the CasADi model; the control
    law is named unless it is the open-loop ``demand`` (whose logs keep their old names).

    ``reality`` (the ``[reality]`` effects) adds a digest of the effects and their parameters, not
    their names: a "real" run never takes a nominal run's name, and the name does not tell the gap
    diagnosis what it is asked to find."""
    parts = [slug(scenario.name, "scenario name"), slug(strategy, "strategy"), str(int(seed))]
    law = scenario.control.law
    if law != "demand":
        parts.insert(2, slug(law, "control law"))
    if plant:
        parts.append(slug(plant, "plant"))
    if reality:
        digest = hashlib.sha256(json.dumps(reality, sort_keys=True, default=str).encode()).hexdigest()[:8]
        parts.append(f"real-{digest}")
    return Path(out_dir or "logs") / ("-".join(parts) + ".mcap")


def prepare_out_dir(out_dir) -> Path:
    """The ``--out`` directory, created if needed; ConfigError (one line) when it cannot be."""
    out = Path(out_dir or "logs")
    if out.suffix.lower() in (".mcap", ".rrd"):
        raise ConfigError(f"--out {out}: names a directory for the logs, not a log file")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out {out}: cannot create the directory: {e.strerror or e}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {out}: not writable")
    return out


def start_recording(scenario, strategy: str, seed: int, bus: str, mode: str, path, plant_meta=None,
                    bus_meta=None, dbc=None) -> Recorder:
    """A recorder with the metadata every run log carries: the scenario as written plus its --set
    overrides (so replay and view rebuild exactly this scenario), versions, the run's settings."""
    rec = Recorder(path)
    try:
        rec.metadata("scenario", {"name": scenario.name, "path": scenario.path, "toml": scenario.source_text,
                                  "overrides": scenario.overrides})
        rec.metadata("versions", package_versions())
        rec.metadata("run", {"strategy": strategy, "seed": str(seed), "bus": bus, "mode": mode,
                             "exchange_period_s": repr(scenario.run.exchange_period_s),
                             # behaviour newer than some logs: replay runs a log without
                             # these keys as it ran (hil/replay.py, NEWER_THAN_SOME_LOGS)
                             "gp_rail_changes": "dated in closed loop",
                             "identified_rail_climb": "a drop and a climb at each change of rail",
                             "identified_past_a_peak": "a drop and a climb when the dither finds it past a peak",
                             "identified_rise": "a drop and a climb when mu^ rises above its level at the creep held",
                             "identified_creep_bounds": "the creep held at most max_kmh 1.6 km/h; drops to cap_kmh 0.7",
                             "identified_peak_estimate": "set-point, ceiling and drop from the peak estimate",
                             "identified_relative_drop": "drops to a fraction of the set-point held; the new rail's "
                                                         "estimate bounds it, its median sets it",
                             "peak_estimate_per_update": "the peak estimate's memory and hazard per update",
                             "gp_closed_loop_tracking": "gp's train-speed line refitted every sample, interval floors",
                             "gp_open_loop_edge": "gp confirms no maximum at the lowest creep seen in open loop either",
                             "gp_one_rail": "gp confirms in closed loop only from a window that holds one rail"})
        if dbc is not None:
            rec.metadata("dbc", dbc)
        if bus_meta is not None:
            rec.metadata("bus", bus_meta)
        if plant_meta is not None:
            rec.metadata("plant", plant_meta)
    except BaseException:
        rec.close()
        raise
    return rec


# -- one writer per topic ----------------------------------------------------------------------------
def write_plant_state(rec: Recorder, step: int, s, stage: str) -> None:
    rec.row("/plant/state", s.t_s, (step, s.t_s, s.motor_speed_rad_s, s.train_speed_ms, s.creep_speed_kmh, s.mu,
                                    s.load_torque_nm, s.torque_nm, s.fault_active, stage))


def write_rail_truth(rec: Recorder, step: int, t_s: float, peak_mu: float, peak_creep_kmh: float, demand_mu: float,
                     segment: int) -> None:
    rec.row("/plant/rail", t_s, (step, t_s, peak_mu, peak_creep_kmh, demand_mu, segment))


def write_control_metrics(rec: Recorder, t_s: float, control: str, m: dict) -> None:
    """``/control/metrics``: the run's closed-loop figures (hil/traction.py), once, at its end (NaN: none)."""
    def num(k):
        x = m.get(k)
        return float("nan") if x is None else float(x)
    rec.write("/control/metrics", t_s, t_s=t_s, control=control, adhesion_utilisation=num("adhesion_utilisation"),
              adhesion_utilisation_low=num("adhesion_utilisation_low"), macro_slip_s=num("macro_slip_s"),
              macro_slip_count=int(m.get("macro_slip_count") or 0), reaction_ms=num("reaction_ms"),
              recovery_s=num("recovery_s"), torque_ripple_percent=num("torque_ripple_percent"))


def write_sensor(rec: Recorder, t_s: float, step: int, motor_speed_rad_s: float, train_speed_ms: float) -> None:
    rec.row("/plant/sensor", t_s, (step, t_s, motor_speed_rad_s, train_speed_ms))


def write_command(rec: Recorder, command, period_s: float) -> None:
    t = command.step * period_s
    rec.row("/tcu/command", t, (command.step, t, command.torque_nm))


def write_status(rec: Recorder, status, observer, period_s: float) -> None:
    """``/tcu/observer`` (when the TCU had a valid reading) and ``/tcu/status``."""
    if observer is not None:
        rec.row("/tcu/observer", observer.t_s, (observer.step, observer.t_s, observer.creep_speed_kmh, observer.mu_hat,
                                                observer.load_torque_nm))
    t = status.step * period_s
    rec.row("/tcu/status", t, (status.step, t, status.stage, STAGE_NAMES[status.stage], status.correction))


def write_estimate(rec: Recorder, e) -> None:
    """``/tcu/estimate``: the TCU's estimate of the current rail's peak (a TcuEstimate frame's ``EstimateReport``)."""
    rec.row("/tcu/estimate", e.t_s, (e.step, e.t_s, e.peak_creep_kmh, e.peak_creep_ci[0], e.peak_creep_ci[1],
                                     e.peak_mu, e.peak_mu_ci[0], e.peak_mu_ci[1], e.since_step))


def write_identification(rec: Recorder, e, strategy: str) -> None:
    """``/tcu/identification`` and its line on ``/run/events``."""
    rec.write("/tcu/identification", e.t_s, step=e.step, t_s=e.t_s, kind=e.kind, correction=e.correction,
              params=list(e.params), j_ef=e.j_ef, samples=e.samples, strategy=strategy,
              peak_mu_ci=list(e.peak_mu_ci), peak_creep_ci=list(e.peak_creep_ci),
              peak_open=bool(e.peak_open), samples_from_s=float(e.samples_from_s),
              samples_to_s=float(e.samples_to_s))
    rec.event(e.t_s, "INFO", f"{e.kind} Q={e.correction} after {e.samples} samples: "
              + ", ".join(f"{x:.5g}" for x in e.params))


def write_frame(rec: Recorder, t_s: float, msg, direction: str, status: str, wall_ns: int) -> None:
    rec.row("/can/frames", t_s, (t_s, wall_ns, int(round((msg.timestamp or 0.0) * 1e9)), msg.arbitration_id,
                                 bool(msg.is_extended_id), bool(msg.is_fd), bool(msg.is_error_frame),
                                 bool(msg.is_remote_frame), bool(msg.bitrate_switch), int(msg.dlc), bytes(msg.data),
                                 direction, status))


def write_timing(rec: Recorder, step: int, t_s: float, period_us: float, round_trip_us: float, lateness_us: float,
                 missed: bool) -> None:
    rec.row("/loop/timing", t_s, (step, t_s, period_us, round_trip_us, lateness_us, missed))
