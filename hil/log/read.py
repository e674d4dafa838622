"""Reading MCAP logs back, whole or damaged (a run killed mid-write, a file cut at any byte, bytes
changed anywhere).

``read_log`` reads every record it can trust and steps over the rest:

- A log that ends with its footer and an intact summary section (its CRC checks) is read by its
  indexes: every chunk and metadata record at the offset the summary gives, each chunk checked
  against its CRC.  A damaged chunk or record is skipped on its own; every other one is read.
- Otherwise (a log cut short, or its summary damaged) records are read one after the other from the
  start; at a record that cannot be read (a wrong opcode, a length past the end, a chunk whose CRC
  does not match) the reader searches on for the next chunk whose CRC matches (or metadata record
  that parses exactly) and continues there.

Every skipped stretch is reported with its byte range and what was wrong (``LogContents.damaged``,
``damage``).  The channels and schemas of a ``railway-hil`` log (header profile ``PROFILE``) are
registered in ``hil.log.schemas.TOPICS`` order, so when the damaged part held them they are rebuilt from
``hil.log.schemas``.  A log closed properly after a run that did not finish
(a fault, an interrupt) is not damaged: ``ended_early`` says why it ended.

``read_log(..., on_message=f)`` streams instead of collecting: each decoded message goes to
``f(topic, log_time_ns, message)`` as its chunk is read, nothing is kept in ``messages``, and the
file's pages are released after each chunk, so the memory a read needs does not grow with the log.
"""
from __future__ import annotations

import mmap
import struct
import zlib
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Footer, Header, Message, Metadata, MetadataIndex, Schema
from mcap.stream_reader import breakup_chunk
from mcap_protobuf.decoder import DecoderFactory

from ..errors import LogError
from .schemas import PROFILE, TOPICS, TYPES

MAGIC = b"\x89MCAP0\r\n"
_OPCODES = {int(op) for op in Opcode}
_RECORD_HEAD = 9                      # opcode (1 byte) + length (8 bytes)
_FOOTER_LENGTH = 8 + 8 + 4
_COMPRESSIONS = (b"", b"lz4", b"zstd")


@dataclass
class LogContents:
    path: str
    messages: list = field(default_factory=list)     # (topic, log_time_ns, decoded protobuf message)
    message_count: int = 0                           # every message record read, whatever its topic
    metadata: dict = field(default_factory=dict)     # name -> dict
    complete: bool = True                            # whole, closed, and the run finished (summary)
    damage: str = ""                                 # what was damaged or missing, with byte positions
    cut: bool = False                                # the file does not end with the log's end (footer)
    damaged: list = field(default_factory=list)      # (first byte, end byte, what) of every skipped stretch
    skipped_bytes: int = 0
    ended_early: str = ""                            # closed properly, but the run did not finish: why
    rebuilt_channels: int = 0                        # channels rebuilt from hil.log.schemas.TOPICS

    def topic(self, name: str) -> list:
        return [m for t, _, m in self.messages if t == name]

    def problem(self) -> str:
        """What a reader of this log should be told (damage first, else why the run ended early)."""
        if self.damage:
            return self.damage
        return f"the run did not finish ({self.ended_early}); the log was closed properly" if self.ended_early else ""


def scenario_from_log(log: LogContents, hint: str = "", overrides: dict | None = None):
    """The scenario a ``hil run`` log was recorded with (its TOML text and ``--set`` overrides, from
    the metadata), or one LogError line; ``hint`` ends the line that says the log has none;
    ``overrides``: more ``--set`` keys on top of the logged ones."""
    import json

    from ..config import ScenarioError, parse_scenario

    if (log.cut or log.damaged) and not log.metadata and not log.message_count:
        raise LogError(f"{log.path}: nothing readable ({log.damage})")
    sc = log.metadata.get("scenario") or {}
    if "toml" not in sc:
        if log.damaged:
            raise LogError(f"{log.path}: its scenario metadata is lost to the damage ({log.damage}){hint}")
        raise LogError(f"{log.path}: no scenario metadata: not a 'hil run' log (another tool's MCAP?){hint}")
    try:
        logged = json.loads(sc["overrides"]) if sc.get("overrides") else None
    except ValueError:  # damaged overrides: none applied, as with a log that has none
        logged = None
    logged = logged if isinstance(logged, dict) else {}
    try:
        return parse_scenario(sc["toml"], f"{log.path}: scenario metadata", {**logged, **(overrides or {})} or None,
                              check_dbc=False)
    except ScenarioError as e:
        raise LogError(str(e)) from None


class _Damaged(Exception):
    """A record that cannot be trusted; the message says why."""


def _stream(body) -> ReadDataStream:
    return ReadDataStream(BytesIO(bytes(body)))


class _Reader:
    """Turns trusted records into ``LogContents``; ``record_at`` reads (and checks) one record."""

    def __init__(self, buf, out: LogContents, topics, on_message=None):
        self.buf, self.out, self.topics, self.on_message = buf, out, topics, on_message
        self.size = len(buf)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.decoders: dict[int, object] = {}
        self.factory = DecoderFactory()
        self.profile = None
        self.footer = False

    # -- one record ---------------------------------------------------------------------------------
    def head(self, pos: int) -> tuple[int, int]:
        """(opcode, end) of the record at ``pos``; _Damaged when it cannot be one."""
        if pos + _RECORD_HEAD > self.size:
            raise _Damaged("the file ends inside a record's head")
        op = self.buf[pos]
        length = struct.unpack_from("<Q", self.buf, pos + 1)[0]
        if op not in _OPCODES:
            raise _Damaged(f"no record starts here (opcode 0x{op:02x})")
        end = pos + _RECORD_HEAD + length
        if end > self.size:
            raise _Damaged(f"a {Opcode(op).name.lower()} record of {length} bytes runs past the end of the file")
        return op, end

    def record_at(self, pos: int, strict: bool = False) -> int:
        """Read the record at ``pos`` into the contents; its end.  ``strict``: a record outside a chunk
        must also parse to exactly its length (used to find a place to go on after damage)."""
        op, end = self.head(pos)
        body = self.buf[pos + _RECORD_HEAD:end]
        try:
            if op == Opcode.CHUNK:
                self._chunk(body)
                if self.on_message is not None:
                    self._release(pos, end)
            else:
                stream = _stream(body)
                record = self._read(op, stream, len(body))
                if strict and stream.count != len(body):
                    raise _Damaged("the record's fields do not fill its length")
                if record is not None:
                    self.take(record)
        except _Damaged:
            raise
        except Exception as e:  # noqa: BLE001 - whatever the parser makes of damaged bytes
            raise _Damaged(f"unreadable {Opcode(op).name.lower()} record ({type(e).__name__}: {e})") from None
        return end

    def _release(self, start: int, end: int) -> None:
        """Drop the mapped pages of bytes [start, end) from this process's memory (they are read again
        from the file if needed): a streamed read stays flat however long the log."""
        start -= start % mmap.PAGESIZE
        if hasattr(self.buf, "madvise") and end > start:
            try:
                self.buf.madvise(mmap.MADV_DONTNEED, start, end - start)
            except (OSError, ValueError):  # madvise is advice: without it the read uses more memory, same bytes
                pass

    @staticmethod
    def _read(op: int, stream: ReadDataStream, length: int):
        if op == Opcode.HEADER:
            return Header.read(stream)
        if op == Opcode.SCHEMA:
            return Schema.read(stream)
        if op == Opcode.CHANNEL:
            return Channel.read(stream)
        if op == Opcode.MESSAGE:
            return Message.read(stream, length)
        if op == Opcode.METADATA:
            return Metadata.read(stream)
        if op == Opcode.FOOTER:
            return Footer.read(stream)
        stream.read(length)          # indexes, statistics, attachments, data end: nothing to take
        return None

    def _chunk(self, body) -> None:
        stream = _stream(body)
        chunk = Chunk.read(stream)
        if chunk.compression not in ("", "lz4", "zstd"):
            raise _Damaged(f"chunk compressed with unknown {chunk.compression[:20]!r}")
        try:
            records = breakup_chunk(chunk, validate_crc=True)
        except Exception as e:  # noqa: BLE001 - CRC mismatch, broken compression, garbage inside
            raise _Damaged(f"chunk fails its CRC or decompression ({type(e).__name__}: {e})") from None
        for record in records:
            self.take(record)

    # -- what a record adds -------------------------------------------------------------------------
    def take(self, record) -> None:
        out = self.out
        if isinstance(record, Header):
            self.profile = record.profile
        elif isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, Metadata):
            out.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Footer):
            self.footer = True
        elif isinstance(record, Message):
            out.message_count += 1
            ch = self.channels.get(record.channel_id) or self._rebuilt(record.channel_id)
            if ch is None or (self.topics is not None and ch.topic not in self.topics):
                return
            if record.channel_id not in self.decoders:
                self.decoders[record.channel_id] = self.factory.decoder_for(ch.message_encoding,
                                                                            self.schemas.get(ch.schema_id))
            decode = self.decoders[record.channel_id]
            if decode is None:
                return
            if self.on_message is not None:
                self.on_message(ch.topic, record.log_time, decode(record.data))
            else:
                out.messages.append((ch.topic, record.log_time, decode(record.data)))

    def _rebuilt(self, channel_id: int):
        """The channel (and its schema) ``hil.log.record`` registers as number ``channel_id``, for a
        ``railway-hil`` log whose channel records were lost; None for another log."""
        from mcap_protobuf.schema import build_file_descriptor_set

        if self.profile != PROFILE or not 1 <= channel_id <= len(TOPICS):
            return None
        topic, name = list(TOPICS.items())[channel_id - 1]
        cls = TYPES[name]
        self.schemas.setdefault(channel_id, Schema(id=channel_id, name=cls.DESCRIPTOR.full_name, encoding="protobuf",
                                                   data=build_file_descriptor_set(cls).SerializeToString()))
        channel = Channel(id=channel_id, topic=topic, message_encoding="protobuf", schema_id=channel_id, metadata={})
        self.channels[channel_id] = channel
        self.out.rebuilt_channels += 1
        return channel

    # -- finding the next good record ---------------------------------------------------------------
    def _chunk_candidate(self, q: int) -> bool:
        """Cheap test that a chunk record could start at ``q``: its fields agree with its length and it
        carries a CRC."""
        if q + _RECORD_HEAD + 32 > self.size:
            return False
        if struct.unpack_from("<I", self.buf, q + _RECORD_HEAD + 24)[0] == 0:
            return False                     # no CRC: nothing would tell a chunk from chance bytes
        length = struct.unpack_from("<Q", self.buf, q + 1)[0]
        clen = struct.unpack_from("<I", self.buf, q + _RECORD_HEAD + 28)[0]
        if clen > 4 or q + _RECORD_HEAD + 32 + clen + 8 > self.size:
            return False
        if bytes(self.buf[q + _RECORD_HEAD + 32:q + _RECORD_HEAD + 32 + clen]) not in _COMPRESSIONS:
            return False
        dlen = struct.unpack_from("<Q", self.buf, q + _RECORD_HEAD + 32 + clen)[0]
        return length == 32 + clen + 8 + dlen and q + _RECORD_HEAD + length <= self.size

    def resync(self, start: int) -> int | None:
        """The first position >= ``start`` where a chunk whose CRC matches, or a metadata record that
        parses exactly, begins (and is read); None when there is none."""
        q = start
        while q < self.size:
            c, m = self.buf.find(b"\x06", q), self.buf.find(b"\x0c", q)
            hits = [x for x in (c, m) if x >= 0]
            if not hits:
                return None
            q = min(hits)
            if self.buf[q] == Opcode.CHUNK and not self._chunk_candidate(q):
                q += 1
                continue
            try:
                self.record_at(q, strict=True)
                return q
            except _Damaged:  # damaged here too: the scan goes on to the next offset
                q += 1
        return None


def _summary(buf) -> tuple[list, list, list] | None:
    """(schemas + channels, chunk indexes, metadata indexes) from the summary section of a log that
    ends with its footer and magic and whose summary CRC matches; None otherwise."""
    size = len(buf)
    footer_at = size - len(MAGIC) - _RECORD_HEAD - _FOOTER_LENGTH
    if footer_at < len(MAGIC) or bytes(buf[size - len(MAGIC):]) != MAGIC or buf[footer_at] != Opcode.FOOTER:
        return None
    if struct.unpack_from("<Q", buf, footer_at + 1)[0] != _FOOTER_LENGTH:
        return None
    summary_start, _, crc = struct.unpack_from("<QQI", buf, footer_at + _RECORD_HEAD)
    if not len(MAGIC) <= summary_start <= footer_at:
        return None
    if crc != 0 and zlib.crc32(buf[summary_start:footer_at + _RECORD_HEAD + 16]) != crc:
        return None
    known, chunks, metas = [], [], []
    pos = summary_start
    try:
        while pos < footer_at:
            op = buf[pos]
            length = struct.unpack_from("<Q", buf, pos + 1)[0]
            end = pos + _RECORD_HEAD + length
            stream = _stream(buf[pos + _RECORD_HEAD:end])
            if op in (Opcode.SCHEMA, Opcode.CHANNEL):
                known.append(_Reader._read(op, stream, length))
            elif op == Opcode.CHUNK_INDEX:
                chunks.append(ChunkIndex.read(stream))
            elif op == Opcode.METADATA_INDEX:
                metas.append(MetadataIndex.read(stream))
            pos = end
    except Exception:  # noqa: BLE001 - a summary that does not parse is not used
        return None
    return known, chunks, metas


def _read_indexed(reader: _Reader, summary) -> None:
    known, chunks, metas = summary
    try:
        reader.record_at(len(MAGIC))             # the header, for the profile
    except _Damaged as e:
        reader.out.damaged.append((len(MAGIC), len(MAGIC), f"header: {e}"))
    for record in known:
        reader.take(record)
    places = sorted([(c.chunk_start_offset, c.chunk_length, "chunk") for c in chunks]
                    + [(m.offset, m.length, f"metadata {m.name!r}") for m in metas])
    for offset, length, what in places:
        try:
            if offset + length > reader.size:
                raise _Damaged("outside the file")
            end = reader.record_at(offset, strict=what != "chunk")
            if end != offset + length:
                raise _Damaged(f"the record is {end - offset} bytes, the index says {length}")
        except _Damaged as e:
            reader.out.damaged.append((offset, offset + length, str(e) if what == "chunk" else f"{what}: {e}"))
    reader.footer = True


def _read_linear(reader: _Reader) -> None:
    out, pos = reader.out, len(MAGIC)
    while pos < reader.size and not reader.footer:
        try:
            pos = reader.record_at(pos)
            continue
        except _Damaged as e:
            why = str(e)
        if reader.footer:
            break
        nxt = reader.resync(pos + 1)
        if nxt is None:
            if pos + _RECORD_HEAD > reader.size or "runs past the end" in why:
                out.cut = True
                out.damaged.append((pos, reader.size, f"the file ends inside a record ({why})"))
            else:
                out.damaged.append((pos, reader.size, f"{why}; nothing readable after it"))
            return
        out.damaged.append((pos, nxt, why))
        pos = reader.head(nxt)[1]            # resync has read the record at nxt: go on after it
    if reader.footer and bytes(reader.buf[pos:]) != MAGIC:
        out.cut = True
        out.damaged.append((pos, reader.size, "the closing magic after the footer is missing or wrong"))


def read_log(path, topics: set[str] | None = None, on_message=None) -> LogContents:
    """Read every message that can be trusted (module docstring); damage is reported, not raised.
    ``on_message(topic, log_time_ns, message)``: messages are streamed to it, not collected.
    LogError (one line) for a file that cannot be read or is not MCAP at all."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            head = f.read(len(MAGIC))
            if head != MAGIC:
                raise LogError(f"{path}: not an MCAP file (no MCAP magic at the start)")
            buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except OSError as e:
        raise LogError(f"{path}: cannot read: {e.strerror or e}") from None
    out = LogContents(str(path))
    with buf:
        reader = _Reader(buf, out, topics, on_message)
        summary = _summary(buf)
        if summary is not None:
            _read_indexed(reader, summary)
        else:
            _read_linear(reader)
            if not reader.footer and not out.cut:
                out.cut = True
                out.damaged.append((reader.size, reader.size, "the file ends without the log's end (footer)"))
        size = reader.size
    out.skipped_bytes = sum(b - a for a, b, _ in out.damaged)
    if out.damaged:
        out.complete = False
        parts = [f"bytes {a}-{b}: {what}" if b > a else f"at byte {a}: {what}" for a, b, what in out.damaged[:3]]
        more = f"; and {len(out.damaged) - 3} more" if len(out.damaged) > 3 else ""
        out.damage = (f"damaged in {len(out.damaged)} place(s) of {size} bytes, {out.skipped_bytes} bytes skipped: "
                      + "; ".join(parts) + more)
        if out.rebuilt_channels:
            out.damage += f"; {out.rebuilt_channels} channel(s) rebuilt from hil.log.schemas.TOPICS"
    if "summary" not in out.metadata:
        out.complete = False
        if not out.damaged:
            fault = out.metadata.get("fault") or {}
            out.ended_early = (f"fault at step {fault.get('step', '?')}: {fault['reason']}" if "reason" in fault
                               else "no summary: interrupted or aborted")
    return out
