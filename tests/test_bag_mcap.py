"""The recorder's MCAP writer (rosbags' with large messages written directly): what it writes
reads back identically with rosbags' reader and with Foxglove's reference MCAP reader (indexed,
CRCs checked, and record by record), whatever mix of large and small messages."""

from __future__ import annotations

import pathlib
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from warp_buffer_cli.bag.writer import DIRECT_BYTES, BagWriter

TENSOR = "tensor_msgs/msg/ExperimentalTensor"
STRING = "std_msgs/msg/String"


def _write(path: pathlib.Path, sizes: list[int]) -> list[tuple[str, int, bytes]]:
    """A bag of tensors of ``sizes`` bytes, each followed by a small text; what was written."""
    from rosbags.rosbag2 import StoragePlugin

    from rosidl_buffer.messages import get_message_type, get_typestore, serialize_message

    tensor, text = get_message_type(TENSOR), get_message_type(STRING)
    written = []
    with BagWriter(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        big = writer.add_connection("/frames", TENSOR, typestore=get_typestore())
        small = writer.add_connection("/text", STRING, typestore=get_typestore())
        for index, size in enumerate(sizes):
            stamp = 1_000_000_000 + index * 1_000_000
            data = bytes(serialize_message(tensor(data=np.full(size, index % 251, np.uint8))))
            writer.write(big, stamp, data)
            note = bytes(serialize_message(text(data=f"after {index}")))
            writer.write(small, stamp + 1, note)
            written += [("/frames", stamp, data), ("/text", stamp + 1, note)]
    return written


def _read_back(path: pathlib.Path) -> tuple[list, list, list]:
    from mcap.reader import make_reader
    from mcap.records import Message
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2 import Reader

    with Reader(path) as reader:
        by_rosbags = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
    (storage,) = path.glob("*.mcap")
    with open(storage, "rb") as handle:
        indexed = make_reader(handle, validate_crcs=True)
        summary = indexed.get_summary()
        assert summary is not None and summary.statistics.message_count == len(by_rosbags)
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        by_mcap = [(ch.topic, m.log_time, m.data) for _, ch, m in indexed.iter_messages()]
    with open(storage, "rb") as handle:
        records = [r for r in StreamReader(handle, validate_crcs=True).records
                   if isinstance(r, Message)]
    channels = {c.id: c.topic for c in summary.channels.values()}
    by_stream = [(channels[m.channel_id], m.log_time, m.data) for m in records]
    with open(storage, "rb") as handle:
        _check_message_indexes(StreamReader(handle, emit_chunks=True).records)
    return by_rosbags, by_mcap, by_stream


def _check_message_indexes(records) -> None:
    """Every message index entry (what ros2's MCAP plugin seeks by, in log-time order) points at
    a message record of its channel and time inside the chunk before it."""
    import struct

    from mcap.records import Chunk, MessageIndex

    chunk, checked = None, 0
    for record in records:
        if isinstance(record, Chunk):
            assert record.compression == "" and record.uncompressed_size == len(record.data)
            chunk = record
        elif isinstance(record, MessageIndex):
            for log_time, offset in record.records:
                op, _length, channel, _seq, stamp = struct.unpack_from("<BQHIQ", chunk.data,
                                                                        offset)
                assert (op, channel, stamp) == (0x05, record.channel_id, log_time)
                assert chunk.message_start_time <= stamp <= chunk.message_end_time
                checked += 1
    assert checked


def test_large_and_small_messages_read_back_identically(tmp_path):
    sizes = [DIRECT_BYTES + 5, 10, 3 * DIRECT_BYTES, 200_000, 700_000, DIRECT_BYTES - 100, 1]
    written = _write(tmp_path / "bag", sizes)
    by_rosbags, by_mcap, by_stream = _read_back(tmp_path / "bag")
    assert by_rosbags == written and by_mcap == written
    assert sorted(by_stream, key=lambda m: m[1]) == written


@settings(max_examples=15, deadline=None)
@given(st.lists(st.sampled_from([0, 7, 4096, DIRECT_BYTES - 64, DIRECT_BYTES, 2 * DIRECT_BYTES]),
                min_size=1, max_size=6))
def test_any_mix_of_sizes_reads_back(tmp_path_factory, sizes):
    path = tmp_path_factory.mktemp("mix") / "bag"
    written = _write(path, sizes)
    by_rosbags, by_mcap, _ = _read_back(path)
    assert by_rosbags == written and by_mcap == written


def test_the_direct_path_is_what_writes_large_messages(tmp_path, monkeypatch):
    """(So the tests above test it.) rosbags' own chunking never sees a large message."""
    from rosbags.rosbag2.storage_mcap import McapWriter

    seen: list[int] = []
    original = McapWriter.write
    monkeypatch.setattr(McapWriter, "write",
                        lambda self, c, t, d: (seen.append(len(d)), original(self, c, t, d))[1])
    _write(tmp_path / "bag", [2 * DIRECT_BYTES, 100])
    assert seen and max(seen) < DIRECT_BYTES


def test_sqlite3_storage_is_rosbags_own_committed_each_second(tmp_path, monkeypatch):
    import sqlite3

    from rosbags.rosbag2 import StoragePlugin, Writer

    from rosidl_buffer.messages import get_typestore
    from warp_buffer_cli.bag import writer as writer_module

    storage = BagWriter.STORAGE_PLUGINS[StoragePlugin.SQLITE3]
    assert issubclass(storage, Writer.STORAGE_PLUGINS[StoragePlugin.SQLITE3])
    monkeypatch.setattr(writer_module, "COMMIT_S", 0.0)  # every write committed
    bag = BagWriter(tmp_path / "bag", version=BagWriter.VERSION_LATEST,
                    storage_plugin=StoragePlugin.SQLITE3)
    bag.open()
    connection = bag.add_connection("/t", "std_msgs/msg/String", typestore=get_typestore())
    bag.write(connection, 1, b"\x00\x01\x00\x00\x01\x00\x00\x00\x00")
    # Seen by another connection before the writer closes: committed.
    other = sqlite3.connect(tmp_path / "bag" / "bag.db3")
    try:
        assert other.execute("SELECT COUNT(*) FROM messages").fetchone() == (1,)
    finally:
        other.close()
    bag.close()


def test_small_mcap_messages_reach_the_file_within_commit_s(tmp_path, monkeypatch):
    from rosbags.rosbag2 import StoragePlugin

    from rosidl_buffer.messages import get_typestore
    from warp_buffer_cli.bag import writer as writer_module

    monkeypatch.setattr(writer_module, "COMMIT_S", 0.2)
    path = tmp_path / "bag"
    bag = BagWriter(path, version=BagWriter.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    bag.open()
    try:
        connection = bag.add_connection("/t", "std_msgs/msg/String", typestore=get_typestore())
        first, second = b"first-message-body", b"second-message-body"
        bag.write(connection, 1, first)  # nothing written for COMMIT_S before: in the file now
        bag.write(connection, 2, second)  # 0.2 s not passed: still in rosbags' pending chunk
        on_disk = (path / "bag.mcap").read_bytes()
        assert first in on_disk and second not in on_disk
        bag.flush_if_due()
        assert second not in (path / "bag.mcap").read_bytes()  # not due yet
        time.sleep(0.25)
        bag.flush_if_due()  # what the recorder's writer thread calls when nothing comes
        assert second in (path / "bag.mcap").read_bytes()
    finally:
        bag.close()


def test_reindex_refuses_a_bag_its_writer_still_holds(tmp_path):
    from rosbags.rosbag2 import StoragePlugin

    from rosidl_buffer.messages import get_typestore
    from warp_buffer_cli.bag.errors import BagReadError
    from warp_buffer_cli.bag.reindex import reindex

    path = tmp_path / "bag"
    writer = BagWriter(path, version=BagWriter.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    try:
        connection = writer.add_connection("/t", "std_msgs/msg/String", typestore=get_typestore())
        writer.write(connection, 1, bytes(2 * DIRECT_BYTES))  # on disk already (direct)
        before = (path / "bag.mcap").read_bytes()
        with pytest.raises(BagReadError, match="held by another process"):
            reindex(path)
        assert (path / "bag.mcap").read_bytes() == before  # not cut, no footer added
        assert not (path / "metadata.yaml").exists()
    finally:
        writer.close()
    assert reindex(path) == {"file": "bag.mcap", "messages": 1, "topics": 1, "cut_bytes": 0,
                             "unchanged": True}  # closed by its writer: left as it is


# --------------------------------------------------------------------------- damage, info
def _text_bag(path: pathlib.Path, count: int, stamps: list[int] | None = None) -> list[bytes]:
    """A closed MCAP bag of ``count`` small texts on /t (one rosbags chunk); their CDR."""
    from rosbags.rosbag2 import StoragePlugin

    from rosidl_buffer.messages import get_message_type, get_typestore, serialize_message

    text = get_message_type(STRING)
    payloads = [bytes(serialize_message(text(data=f"text {i:04d}"))) for i in range(count)]
    with BagWriter(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/t", STRING, typestore=get_typestore())
        for i, payload in enumerate(payloads):
            writer.write(connection, stamps[i] if stamps else 1_000_000 + i * 1000, payload)
    return payloads


@pytest.mark.parametrize("field", ["opcode", "length", "channel", "log time"])
def test_damage_to_any_message_records_head_is_found_when_the_bag_opens(tmp_path, field):
    """rosbags' reader raises OverflowError or struct.error mid-playback on such damage, or
    skips the message silently; the check at open names the file instead."""
    from warp_buffer_cli.bag.errors import BagDamagedError
    from warp_buffer_cli.bag.play import open_bag

    bag = tmp_path / "bag"
    payloads = _text_bag(bag, 12)
    mcap = bag / "bag.mcap"
    clean = mcap.read_bytes()
    open_bag(bag).close()  # intact: no complaint
    at, size = {"opcode": (0, 1), "length": (1, 8), "channel": (9, 2), "log time": (15, 8)}[field]
    for payload in payloads:
        head = clean.index(payload) - 31  # opcode, length, channel, sequence, two times
        damaged = bytearray(clean)
        damaged[head + at:head + at + size] = b"\xfe" * size
        mcap.write_bytes(bytes(damaged))
        with pytest.raises(BagDamagedError, match=f"{mcap}.* damaged at byte"):
            open_bag(bag)


def test_info_shows_metadatas_duration_and_end_and_sizes_in_a_fitting_unit(tmp_path, capsys):
    """As ros2 bag info: Duration is metadata.yaml's, End = Start + Duration (rosbags' reader
    counts one past the last stamp), and a small bag's size is no "0.0 MiB"."""
    import argparse

    from ruamel.yaml import YAML

    from warp_buffer_cli.bag import info
    from warp_buffer_cli.bag.progress import size_text

    bag = tmp_path / "bag"
    _text_bag(bag, 3, stamps=[5_000_000_000, 5_000_000_100, 7_000_000_123])
    meta = YAML(typ="safe").load((bag / "metadata.yaml").read_text())
    assert meta["rosbag2_bagfile_information"]["duration"]["nanoseconds"] == 2_000_000_123
    report = info.describe(bag)
    assert (report["start_ns"], report["duration_ns"], report["end_ns"]) == (
        5_000_000_000, 2_000_000_123, 7_000_000_123)
    info.run(argparse.Namespace(bag=str(bag), json=False))
    lines = capsys.readouterr().out.splitlines()
    assert "Duration:          2.000000123s" in lines
    assert any(line.startswith("End:") and line.endswith("(7.000000123)") for line in lines)
    assert f"Bag size:          {size_text(report['size_bytes'])}" in lines
    assert "KiB" in size_text(report["size_bytes"])
    assert [size_text(n) for n in (0, 1023, 1536, 5 << 20, 3 << 30, 5 << 40, 9 << 50)] == [
        "0 B", "1023 B", "1.5 KiB", "5.0 MiB", "3.0 GiB", "5.0 TiB", "9216.0 TiB"]
