"""``buffer_pubsub._streams`` (C): the attachment parser and the per-subscription stream judge.

The rules are checked on hand-worked cases, then against an independent Python model of them
(``tests/_sequence_model.py``) on random streams; the parser is fed hostile bytes.
"""

from __future__ import annotations

import random
import struct

import pytest

from buffer_pubsub import _streams, wire
from buffer_pubsub._streams import Streams

from tests._sequence_model import LOST_WINDOW, MAX_TRACKED, RECENT_STAMPS, Deduplicator, SequenceTracker

GID = b"\x01" * 16
OTHER = b"\x02" * 16


def lost_of(verdict) -> int:
    return 0 if verdict is None else verdict[1]


def run(streams, numbers, exact):
    verdicts = [streams.track("own", GID, n, exact) for n in numbers]
    return (sum(lost_of(v) for v in verdicts), [v is not None and v[2] for v in verdicts],
            sum(v is not None and v[3] for v in verdicts))


# ------------------------------------------------------------------------------- hand-worked rules
def test_our_streams_count_every_gap():
    assert run(Streams(), [1, 2, 4, 5, 9], True) == (1 + 3, [False] * 5, 0)


def test_an_upstream_fan_out_is_not_loss():
    # one publish to three streams: this one sees every third number
    assert run(Streams(), [2, 5, 8, 11, 14], False)[0] == 0


def test_a_loss_under_an_upstream_fan_out_counts_whole_messages():
    # stride 3; 11 -> 17 skips one message of this stream (14)
    assert run(Streams(), [2, 5, 8, 11, 17, 20, 23], False)[0] == 1


def test_a_fan_out_that_grows_costs_no_false_loss():
    # a subscription joined: the stride goes from 2 to 3 and stays
    assert run(Streams(), [1, 3, 5, 7, 10, 13, 16, 19], False)[0] == 0


def test_late_and_jumps():
    lost, late, jumps = run(Streams(), [1, 2, 3, 2, 2**40, 4], True)
    assert late == [False, False, False, True, False, False] and jumps == 2 and lost == 0


def test_the_int64_extremes_resynchronize_instead_of_overflowing():
    streams = Streams()
    assert streams.track("own", GID, -2**63, True) is None
    assert streams.track("own", GID, 2**63 - 1, True) == (False, 0, False, True)
    assert streams.last("own", GID) == 2**63 - 1
    assert streams.track("own", GID, -2**63, True) == (False, 0, False, True)
    with pytest.raises(OverflowError):
        streams.track("own", GID, 2**63, True)


def test_streams_and_publishers_are_judged_apart():
    streams = Streams()
    for n in (1, 2, 3):
        assert lost_of(streams.track("base", GID, n, True)) == 0
        assert lost_of(streams.track("own", GID, n, True)) == 0
        assert lost_of(streams.track("base", OTHER, n * 10, True)) == (0 if n == 1 else 9)
    assert streams.last("base", OTHER) == 30 and streams.last("cpu", GID) is None


def test_duplicates_by_publisher_and_stamp():
    streams = Streams()
    assert not streams.seen_before(GID, 100)
    assert not streams.seen_before(OTHER, 100)  # another publisher
    assert streams.seen_before(GID, 100)
    assert not streams.seen_before(GID, 101)
    streams.forget(GID)
    assert not streams.seen_before(GID, 100)
    streams.forget(b"\x09" * 16)  # never seen: nothing to forget


def test_admit_judges_the_stamp_then_the_number():
    streams = Streams()
    assert streams.admit("own", GID, 1, 500, True, True, False) is None
    # the same message again: a second copy, and its number is judged too (late here)
    assert streams.admit("own", GID, 1, 500, True, True, False) == (True, 0, True, False)
    assert streams.admit("own", GID, 3, 501, True, True, False) == (False, 1, False, False)
    # no stamp: no duplicate check
    assert streams.admit("own", GID, 4, None, True, True, False) is None
    assert streams.admit("own", GID, 5, None, True, True, False) is None


def test_a_publisher_that_restarts_is_followed_not_refused():
    # rmw_zenoh numbers again from 1 after a restart (same gid: a pinned Zenoh id) and drops
    # nothing for it (rmw_subscription_data.cpp add_new_message): a resync, then in order
    streams = Streams()
    for n in range(1, 101):
        assert streams.track("base", GID, n, True, False, True) is None
    assert streams.track("base", GID, 1, True, False, True) == (False, 0, False, True)
    assert all(streams.track("base", GID, n, True, False, True) is None for n in range(2, 11))
    # ours: the same step back is a message a later one overtook (late)
    assert streams.track("base", OTHER, 5, True) is None
    assert streams.track("base", OTHER, 4, True) == (False, 0, True, False)


def test_a_stream_of_its_own_counts_what_came_before_its_first_message():
    # a lane overwrote 1..4 before the reader's first read: 4 missed, then in order
    streams = Streams()
    assert sum(lost_of(streams.track("own", GID, n, True, True)) for n in (5, 6, 8)) == 4 + 1
    # a shared stream (base key, intra) is joined at any number: nothing missed
    assert run(Streams(), [5, 6, 8], True)[0] == 1
    # a stride-judged stream (rmw_zenoh's numbers count every put) is not numbered from 1
    assert lost_of(Streams().track("own", GID, 7, False, True)) == 0


def test_the_tables_forget_their_oldest_entries():
    streams = Streams()
    for n in range(MAX_TRACKED + 10):
        gid = n.to_bytes(16, "little")
        streams.track("own", gid, 1, True)
        streams.seen_before(gid, 1)
    assert streams.sizes() == (MAX_TRACKED, MAX_TRACKED)
    assert streams.last("own", (0).to_bytes(16, "little")) is None
    assert streams.last("own", (MAX_TRACKED + 9).to_bytes(16, "little")) == 1


def test_bad_arguments_are_typed_errors():
    streams = Streams()
    with pytest.raises(TypeError):
        streams.track("own", "not bytes", 1, True)
    with pytest.raises(TypeError):
        streams.track(b"own", GID, 1, True)
    with pytest.raises(TypeError):
        streams.track("own", GID, 1.5, True)
    with pytest.raises(TypeError):
        streams.admit("own", GID, 1, "stamp", True, True, False)
    with pytest.raises(TypeError):
        Streams(1)

    class Refuses:
        def __bool__(self):
            raise ZeroDivisionError("no truth value")

    # the first failing flag's own error, never a SystemError from a call made after it
    with pytest.raises(ZeroDivisionError):
        streams.admit("own", GID, 1, None, Refuses(), Refuses(), False)
    with pytest.raises(ZeroDivisionError):
        streams.track("own", GID, 1, Refuses(), Refuses())


# ------------------------------------------------------------------------------- against the model
def model_verdict(tracker, dedupe, stream, gid, sequence, stamp, exact, from_one, restarts):
    duplicate = stamp is not None and dedupe.seen_before(gid, stamp)
    v = tracker.track(stream, gid, sequence, exact, from_one, restarts)
    if not duplicate and v.lost == 0 and not v.late and not v.jump:
        return None
    return (duplicate, v.lost, v.late, v.jump)


@pytest.mark.parametrize("seed", range(8))
def test_random_streams_match_the_model(seed):
    rng = random.Random(seed)
    streams, tracker, dedupe = Streams(), SequenceTracker(), Deduplicator()
    gids = [bytes([g]) * 16 for g in range(4)]
    last = {g: rng.randrange(1, 50) for g in gids}
    stamps = {g: 0 for g in gids}
    for _ in range(4000):
        gid = rng.choice(gids)
        stream = rng.choice(("own", "base", "cpu"))
        roll = rng.random()
        if roll < 0.6:
            last[gid] += rng.choice((1, 1, 1, 2, 3))
        elif roll < 0.8:
            last[gid] += rng.choice((2, 3, 4)) * rng.randrange(1, 4)
        elif roll < 0.9:
            last[gid] -= rng.randrange(0, 5)
        elif roll < 0.95:
            last[gid] += rng.choice((LOST_WINDOW, LOST_WINDOW + 1, -LOST_WINDOW, 2**40))
        else:
            last[gid] = rng.randrange(-2**63, 2**63)
        if rng.random() < 0.8:
            stamps[gid] += 1
        stamp = None if rng.random() < 0.3 else stamps[gid] - rng.choice((0, 0, 0, 1, RECENT_STAMPS))
        exact, from_one, restarts = (rng.random() < 0.5 for _ in range(3))
        args = (stream, gid, last[gid], stamp, exact, from_one, restarts)
        assert streams.admit(*args) == model_verdict(tracker, dedupe, *args), args
        if rng.random() < 0.01:
            streams.forget(gid)
            dedupe.forget(gid)
    for gid in gids:
        for stream in ("own", "base", "cpu"):
            assert streams.last(stream, gid) == tracker.last(stream, gid)


# ------------------------------------------------------------------------------- the attachment
def test_an_attachment_parses_as_rmw_zenoh_writes_it():
    raw = struct.pack("<qqB", -3, 2**62, 0x10) + bytes(range(16))
    assert wire.parse_attachment(raw) == wire.Attachment(-3, 2**62, bytes(range(16)))
    assert type(wire.parse_attachment(bytearray(raw))) is wire.Attachment
    head, payload = wire.split_frame(raw + b"cdr bytes")
    assert head == wire.Attachment(-3, 2**62, bytes(range(16)))
    assert bytes(payload) == b"cdr bytes" and payload.readonly
    assert bytes(wire.split_frame(raw)[1]) == b""


def test_bytes_past_the_attachment_are_ignored_as_rmw_zenoh_ignores_them():
    # attachment_helpers.cpp reads the sequence, the stamp and the gid, then stops
    raw = struct.pack("<qqB", 5, 6, 0x10) + bytes(range(16))
    assert wire.parse_attachment(raw + b"a later field") == wire.Attachment(5, 6, bytes(range(16)))


@pytest.mark.parametrize("raw", [None, b"", b"\x00" * 32, b"\x00" * 34,
                                 struct.pack("<qqB", 1, 2, 0x0F) + bytes(16)])
def test_a_malformed_attachment_is_a_wire_format_error(raw):
    with pytest.raises(wire.WireFormatError):
        wire.parse_attachment(raw)


def test_a_short_or_foreign_lane_frame_is_refused():
    with pytest.raises(wire.WireFormatError):
        wire.split_frame(b"short")
    with pytest.raises(wire.WireFormatError):
        wire.split_frame(struct.pack("<qqB", 1, 2, 0x11) + bytes(16) + b"x")
    with pytest.raises(TypeError):
        wire.split_frame(bytearray(40))


def test_random_bytes_never_crash_the_parser():
    rng = random.Random(7)
    for _ in range(3000):
        raw = rng.randbytes(rng.randrange(0, 80))
        if rng.random() < 0.5 and len(raw) >= 17:
            raw = raw[:16] + b"\x10" + raw[17:]
        try:
            head, payload = wire.split_frame(raw)
        except wire.WireFormatError:
            assert len(raw) < _streams.ATTACHMENT_SIZE or raw[16] != 0x10
        else:
            assert head.encode() == raw[:33] and bytes(payload) == raw[33:]


def test_an_attachment_packs_as_rmw_zenoh_reads_it():
    gid = bytes(range(16))
    raw = wire.pack_attachment(-3, 2**62, gid)
    assert raw == struct.pack("<qqB", -3, 2**62, 0x10) + gid
    assert wire.Attachment(-3, 2**62, gid).encode() == raw
    with pytest.raises(ValueError):
        wire.pack_attachment(1, 2, b"short")
    with pytest.raises(OverflowError):
        wire.pack_attachment(2**63, 2, gid)
