"""Reading MCAP logs back, whole or damaged (a run killed mid-write, a file cut at any byte)."""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Message, Metadata, Schema
from mcap.exceptions import EndOfFile
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory

from .errors import LogError

MAGIC = b"\x89MCAP0\r\n"


@dataclass
class LogContents:
    path: str
    messages: list = field(default_factory=list)     # (topic, log_time_ns, decoded protobuf message)
    message_count: int = 0                           # every message record read, whatever its topic
    metadata: dict = field(default_factory=dict)     # name -> dict
    complete: bool = True
    damage: str = ""
    cut: bool = False                                # reading stopped at a damaged or missing record

    def topic(self, name: str) -> list:
        return [m for t, _, m in self.messages if t == name]


def scenario_from_log(log: LogContents, hint: str = ""):
    """The scenario a ``hil run`` log was recorded with (its TOML text and ``--set`` overrides, from
    the metadata), or one LogError line; ``hint`` ends the line that says the log has none."""
    import json

    from .config import ScenarioError, parse_scenario

    if log.cut and not log.metadata and not log.message_count:
        raise LogError(f"{log.path}: nothing readable before the damage ({log.damage})")
    sc = log.metadata.get("scenario") or {}
    if "toml" not in sc:
        raise LogError(f"{log.path}: no scenario metadata: not a 'hil run' log (another tool's MCAP?){hint}")
    try:
        overrides = json.loads(sc["overrides"]) if sc.get("overrides") else None
    except ValueError:
        overrides = None
    try:
        return parse_scenario(sc["toml"], f"{log.path}: scenario metadata",
                              overrides if isinstance(overrides, dict) else None)
    except ScenarioError as e:
        raise LogError(str(e)) from None


def read_log(path, topics: set[str] | None = None) -> LogContents:
    """Read every message that can be read; a damaged tail is reported, not raised."""
    p = Path(path)
    try:
        head = p.open("rb").read(len(MAGIC))
    except OSError as e:
        raise LogError(f"{path}: cannot read: {e.strerror}") from None
    if head != MAGIC:
        raise LogError(f"{path}: not an MCAP file (no MCAP magic at the start)")
    out = LogContents(str(path))
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    decoders: dict[int, object] = {}
    factory = DecoderFactory()
    with p.open("rb") as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True,
                              record_size_limit=1 << 30)
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata):
                    out.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Message):
                    out.message_count += 1
                    ch = channels.get(record.channel_id)
                    if ch is None or (topics is not None and ch.topic not in topics):
                        continue
                    if record.channel_id not in decoders:
                        decoders[record.channel_id] = factory.decoder_for(ch.message_encoding,
                                                                          schemas.get(ch.schema_id))
                    decode = decoders[record.channel_id]
                    if decode is None:
                        continue
                    out.messages.append((ch.topic, record.log_time, decode(record.data)))
        except Exception as e:  # noqa: BLE001 - any failure past this point is damage to report
            out.complete = False
            out.cut = True
            size = p.stat().st_size
            if isinstance(e, (EndOfFile, struct.error)):
                out.damage = f"the file ends inside a record (cut at byte {size})"
            else:
                out.damage = f"unreadable record before byte {size} ({type(e).__name__}: {e})"
    if out.complete and "summary" not in out.metadata:
        out.complete = False
        out.damage = out.damage or "no summary record (the run did not finish)"
    return out
