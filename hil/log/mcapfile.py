"""An MCAP writer whose per-message path is one ``struct`` call: the file ``mcap.writer.Writer``
writes (LZ4 chunks, message indexes, the summary), byte for byte, for the same calls.

Why it exists: a run logs nine rows per 1 ms period, and ``mcap``'s writer spends a dozen Python calls on each
(a ``Message`` object, six buffer writes with a seek, the statistics, a per-entry loop for each
message index when a chunk closes).  In lockstep over two processes the plant writes its rows while
it waits for the TCU, so that time is on the loop's path; in real time the writer process
(``hil/log/writer.py``) shares the machine with the loop.  Everything but the message records and
their indexes is written with ``mcap``'s own record classes, as ``mcap``'s writer does.

Layout (the MCAP specification, https://mcap.dev/spec; the choices are ``mcap.Writer``'s defaults
with LZ4): magic, Header; schemas and channels go into the first chunk, before its first message;
a chunk closes once its uncompressed records pass ``chunk_size`` bytes, followed by one
MessageIndex per channel it holds (in the order of their first message in it); a Metadata record
is written at once, ahead of the chunk still open (which holds earlier messages); at ``finish``:
the last chunk, DataEnd (no data CRC), the summary (schemas, channels, Statistics, ChunkIndexes,
MetadataIndexes, each group with its SummaryOffset), Footer (with the summary's CRC-32) and the
closing magic.

A Message record is ``opcode 0x05 | length u64 | channel_id u16 | sequence u32 | log_time u64 |
publish_time u64 | data``, little-endian; a MessageIndex is ``0x04 | length | channel_id u16 |
records_length u32 | (log_time u64, offset u64)*``, the offsets counted from the start of the
uncompressed chunk.
"""
from __future__ import annotations

import struct
import zlib

import lz4.frame
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Metadata, MetadataIndex, Schema,
                          Statistics, SummaryOffset)
from mcap.writer import MCAP0_MAGIC

_MESSAGE = struct.Struct("<BQHIQQ")          # opcode, record length, channel, sequence, log, publish
_MESSAGE_FIELDS_BYTES = 2 + 4 + 8 + 8
_INDEX_HEAD = struct.Struct("<BQHI")          # opcode, record length, channel, records length


class LeanMcapWriter:
    """``start``, ``register_schema``, ``register_channel``, ``add_message``, ``add_metadata``,
    ``finish``: ``mcap.Writer``'s calls and file (module docstring).  ``stream`` needs ``write`` and
    ``tell``."""

    def __init__(self, stream, chunk_size: int):
        self._stream = stream
        self._chunk_size = chunk_size
        self._records = RecordBuilder()          # records outside chunks, before they are written
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._stats = Statistics(attachment_count=0, channel_count=0, channel_message_counts={}, chunk_count=0,
                                 message_count=0, message_end_time=0, message_start_time=0, metadata_count=0,
                                 schema_count=0)
        self._new_chunk()

    def _new_chunk(self) -> None:
        self._parts: list[bytes] = []              # the open chunk's records, uncompressed
        self._size = 0                             # their bytes
        self._indexes: dict[int, list[int]] = {}   # channel -> [log_time, offset, log_time, offset, ...]
        self._start, self._end = 1 << 64, -1         # its messages' earliest and latest log_time

    def _chunk_record(self, record) -> None:
        b = RecordBuilder()
        record.write(b)
        data = b.end()
        self._parts.append(data)
        self._size += len(data)
        if self._size > self._chunk_size:
            self._close_chunk()

    def _flush(self) -> None:
        self._stream.write(self._records.end())

    # -- mcap.Writer's calls -------------------------------------------------------------------
    def start(self, profile: str = "", library: str = "") -> None:
        self._stream.write(MCAP0_MAGIC)
        Header(profile, library).write(self._records)
        self._flush()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        schema = self._schemas[schema_id] = Schema(id=schema_id, data=data, encoding=encoding, name=name)
        self._stats.schema_count += 1
        self._chunk_record(schema)
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict | None = None) -> int:
        channel_id = len(self._channels) + 1
        channel = self._channels[channel_id] = Channel(id=channel_id, topic=topic, message_encoding=message_encoding,
                                                       schema_id=schema_id, metadata=metadata or {})
        self._stats.channel_count += 1
        self._chunk_record(channel)
        return channel_id

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        """One Message record into the open chunk, and its entry in the chunk's index of its channel
        (the counts and times of the Statistics and the Chunk are taken from those indexes when the
        chunk closes)."""
        index = self._indexes.get(channel_id)
        if index is None:
            index = self._indexes[channel_id] = []
        index += (log_time, self._size)
        if log_time < self._start:
            self._start = log_time
        if log_time > self._end:
            self._end = log_time
        record = _MESSAGE.pack(Opcode.MESSAGE, _MESSAGE_FIELDS_BYTES + len(data), channel_id, sequence, log_time,
                               publish_time) + data
        self._parts.append(record)
        self._size += len(record)
        if self._size > self._chunk_size:
            self._close_chunk()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._flush()
        offset = self._stream.tell()
        self._stats.metadata_count += 1
        Metadata(name=name, metadata=data).write(self._records)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=self._records.count, name=name))
        self._flush()

    def finish(self) -> None:
        """The last chunk, the summary and the footer; the stream stays open."""
        self._close_chunk()
        DataEnd(0).write(self._records)
        self._flush()
        summary_start = self._stream.tell()
        summary = RecordBuilder()
        offsets = []

        def group(opcode, records):
            start = summary.count
            for r in records:
                r.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                         group_length=summary.count - start))

        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        group(Opcode.STATISTICS, [self._stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, [])
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + summary.count
        for o in offsets:
            o.write(summary)
        data = summary.end()
        summary_start = 0 if not data else summary_start
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start, summary_offset_start),
                         zlib.crc32(data))
        self._stream.write(data)
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start,
               summary_crc=crc).write(self._records)
        self._flush()
        self._stream.write(MCAP0_MAGIC)

    # -- chunks --------------------------------------------------------------------------------
    def _close_chunk(self) -> None:
        """The open chunk (if it holds a message) as a Chunk record and its MessageIndex records."""
        if not self._indexes:
            return
        stats, counts = self._stats, self._stats.channel_message_counts
        start, end = self._start, self._end
        stats.message_start_time = start if stats.message_count == 0 else min(start, stats.message_start_time)
        stats.message_end_time = max(end, stats.message_end_time)
        for channel_id, flat in self._indexes.items():
            counts[channel_id] = counts.get(channel_id, 0) + len(flat) // 2
            stats.message_count += len(flat) // 2
        stats.chunk_count += 1
        raw = b"".join(self._parts)
        compressed = lz4.frame.compress(raw)
        chunk = Chunk(compression="lz4", data=compressed, message_start_time=start, message_end_time=end,
                      uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw))
        self._flush()
        chunk_start = self._stream.tell()
        chunk.write(self._records)
        chunk_length = self._records.count
        self._flush()
        index_start = self._stream.tell()
        index_offsets, at, out = {}, 0, []
        for channel_id, flat in self._indexes.items():
            index_offsets[channel_id] = index_start + at
            n = 8 * len(flat)
            out.append(_INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 2 + 4 + n, channel_id, n)
                       + struct.pack(f"<{len(flat)}Q", *flat))
            at += len(out[-1])
        self._stream.write(b"".join(out))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_start,
            chunk_length=chunk_length, message_index_offsets=index_offsets, message_index_length=at,
            compression="lz4", compressed_size=len(compressed), uncompressed_size=len(raw)))
        self._new_chunk()
