"""hil/log/mcapfile.py writes the file mcap's own writer writes, byte for byte, and mcap's reader reads it."""
import io
import random

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from hil.log.mcapfile import LeanMcapWriter

from .conftest import case_seed


def calls(rng: random.Random, messages: int) -> list[tuple]:
    """Schemas, channels, then messages on random channels (times that sometimes go back, empty and
    long payloads) with metadata in between."""
    out = [("register_schema", f"s{i}", "protobuf", rng.randbytes(rng.randrange(0, 3000))) for i in range(3)]
    out += [("register_channel", f"/t{i}", "protobuf", rng.randrange(1, 4)) for i in range(6)]
    t = rng.randrange(0, 10**12)
    for i in range(messages):
        if rng.random() < 0.01:
            out.append(("add_metadata", f"m{i}", {"k": str(i), "text": "x" * rng.randrange(0, 50)}))
            continue
        t = max(0, t + rng.randrange(-50_000, 2_000_000))
        out.append(("add_message", rng.randrange(1, 6), t, rng.randbytes(rng.choice([0, 1, rng.randrange(2, 300)])),
                    t + rng.randrange(0, 5)))
    return out


def write(writer, sequence) -> None:
    writer.start(profile="railway-hil", library="test")
    for name, *args in sequence:
        if name == "add_message":
            writer.add_message(args[0], log_time=args[1], data=args[2], publish_time=args[3])
        else:
            getattr(writer, name)(*args)
    writer.finish()


@pytest.mark.parametrize("messages, chunk_size", [(0, 32768), (1, 500), (4000, 700), (4000, 32768)])
def test_the_same_bytes_as_mcaps_writer_and_readable_by_its_reader(messages, chunk_size):
    seed = case_seed()
    sequence = calls(random.Random(seed), messages)
    theirs, ours = io.BytesIO(), io.BytesIO()
    write(Writer(theirs, chunk_size=chunk_size, compression=CompressionType.LZ4), sequence)
    write(LeanMcapWriter(ours, chunk_size), sequence)
    assert ours.getvalue() == theirs.getvalue(), f"seed {seed}"

    sent = [(s[1], s[2], s[3]) for s in sequence if s[0] == "add_message"]
    ours.seek(0)
    reader = make_reader(ours, validate_crcs=True)
    got = [(m.channel_id, m.log_time, m.data) for _, _, m in reader.iter_messages(log_time_order=False)]
    assert got == sent
    summary = reader.get_summary()
    assert summary.statistics.message_count == len(sent)
    assert sum(1 for s in sequence if s[0] == "add_metadata") == len(summary.metadata_indexes)


def test_rows_of_scalars_encode_as_a_message_made_for_each(tmp_path):
    """``McapFile.write``'s kept message per topic (every field set anew from each row) gives the bytes of a
    message made from the row's fields, row after row, fields at their defaults included."""
    import os

    from google.protobuf.descriptor import FieldDescriptor as F

    from hil.log.record import McapFile
    from hil.log.schemas import FIELDS

    rng = random.Random(case_seed("rows"))
    f = McapFile(os.open(tmp_path / "x.mcap", os.O_WRONLY | os.O_CREAT), 32 * 1024)
    assert {"/can/frames", "/plant/state", "/loop/timing"} <= set(f._fill)
    ints = {F.TYPE_INT32: (-2**31, 2**31 - 1), F.TYPE_SINT32: (-2**31, 2**31 - 1), F.TYPE_UINT32: (0, 2**32 - 1),
            F.TYPE_INT64: (-2**63, 2**63 - 1), F.TYPE_SINT64: (-2**63, 2**63 - 1), F.TYPE_UINT64: (0, 2**64 - 1)}

    def draw(fd):
        if fd.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT):
            return rng.choice([0.0, -0.0, rng.uniform(-1e6, 1e6), float("nan"), float("inf")])
        if fd.type == F.TYPE_BOOL:
            return rng.random() < 0.5
        if fd.type == F.TYPE_BYTES:
            return rng.randbytes(rng.choice([0, 8, 24]))
        if fd.type == F.TYPE_STRING:
            return rng.choice(["", "rx", "ok", "monitoring"])
        lo, hi = ints[fd.type]
        return rng.choice([0, lo, hi, rng.randint(lo, hi)])

    for topic, fill in f._fill.items():
        cls, names = f._types[topic], FIELDS[topic]
        for _ in range(50):
            row = tuple(draw(cls.DESCRIPTOR.fields_by_name[n]) for n in names)
            assert fill(row) == cls(**dict(zip(names, row))).SerializeToString(), (topic, row)
    f.finish()
