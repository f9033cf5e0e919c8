"""The lane's native core (buffer_pubsub._ring) against a hostile same-user peer: garbage in the
ring it shares (tails, stamps, lengths, the reader's words), and malformed hand-overs on the
reader's socket. Nothing may crash, hang, read out of bounds or leak a descriptor; an honest
peer is served afterwards.

Bounded for CI (300 scribbles per seed); ``-m slow`` adds a long run (20,000 per seed), which
docs/native.md runs under AddressSanitizer.
"""

from __future__ import annotations

import mmap
import os
import random
import socket
import struct

import pytest

from buffer_pubsub import _ring, fast_lane

ROUNDS, LONG_ROUNDS = 300, 20_000
SLOT = 256
ROOM = SLOT - _ring.SLOT_HEAD
#: Offsets of the ring header's words (buffer_pubsub/_ring.h)
TAIL, WRITER_CLOSED, HEAD, WAITING, READER_CLOSED = 64, 72, 128, 136, 140


def _pair(depth: int = 8, keep: int = 8) -> tuple[_ring.RingWriter, _ring.RingReader, mmap.mmap]:
    """A writer, its reader, and a third mapping of the ring: the hostile peer's pen."""
    writer = _ring.RingWriter(depth, SLOT)
    memfd = writer.take_memfd()
    try:
        reader = _ring.RingReader(memfd, writer.doorbell, depth, SLOT, keep)
        pen = mmap.mmap(memfd, writer.size)
    finally:
        os.close(memfd)
    return writer, reader, pen


def _scribble(pen: mmap.mmap, rng: random.Random, depth: int) -> None:
    """One hostile edit: a header word, a slot's stamp or length, or raw bytes anywhere."""
    what = rng.randrange(6)
    word = rng.choice([0, 1, 2, depth, 2**32, 2**63, 2**64 - 1, rng.getrandbits(64)])
    slot = 4096 + rng.randrange(depth) * SLOT
    if what == 0:
        struct.pack_into("<Q", pen, TAIL, word)
    elif what == 1:
        struct.pack_into("<Q", pen, slot, word)  # stamp
    elif what == 2:
        struct.pack_into("<I", pen, slot + 8, word & 0xFFFFFFFF)  # length
    elif what == 3:  # a plausible stamp for the next frames, with any length
        n = rng.randrange(64)
        struct.pack_into("<QI", pen, 4096 + (n % depth) * SLOT, 2 * n + 2,
                         rng.choice([0, ROOM, ROOM + 1, 2**31]))
        struct.pack_into("<Q", pen, TAIL, n + 1)
    elif what == 4:
        at = rng.randrange(len(pen) - 16)
        pen[at:at + 16] = rng.randbytes(16)
    else:
        pen[:64] = rng.randbytes(64)  # magic and geometry: read once, at attach


@pytest.mark.parametrize("seed", range(4))
def test_hostile_ring_contents_never_crash_or_overrun_the_reader(seed: int) -> None:
    _hostile_ring(seed, ROUNDS)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(4, 8))
def test_hostile_ring_contents_long(seed: int) -> None:
    _hostile_ring(seed, LONG_ROUNDS)


def _hostile_ring(seed: int, rounds: int) -> None:
    rng = random.Random(seed)
    writer, reader, pen = _pair()
    got: list[bytes] = []
    waker = _ring.Waker(None)
    try:
        waker.watch([(reader, got.append, "hostile")], [])
        for _ in range(rounds):
            for _ in range(rng.randrange(1, 4)):
                _scribble(pen, rng, reader.depth)
            if rng.random() < 0.5:
                for _ in range(reader.depth + 2):  # bounded: at most keep frames per pass
                    frame = reader.take()
                    if frame is not None:
                        assert len(frame) <= ROOM
            else:
                waker.wait(0)
            assert all(len(frame) <= ROOM for frame in got)
            got.clear()
    finally:
        waker.close()
        pen.close()
        writer.close()


def test_an_honest_ring_after_hostile_reader_words_still_delivers() -> None:
    """The writer trusts nothing the reader writes either: garbage in the reader's words never
    stops it from writing, and the reader's own count decides what it takes."""
    writer, reader, pen = _pair(depth=4, keep=4)
    try:
        rng = random.Random(7)
        for i in range(200):
            struct.pack_into("<QI", pen, HEAD, rng.getrandbits(64), rng.getrandbits(32))
            assert writer.write(b"frame %d" % i)
            assert reader.take() == b"frame %d" % i
        struct.pack_into("<I", pen, READER_CLOSED, 1)  # the reader's word for "closed"
        assert not writer.write(b"to nobody")
    finally:
        pen.close()
        writer.close()


def _memfd(size: int, seals: int, header: bool = True) -> int:
    """A memfd of ``size`` bytes with ``seals``, holding a well-formed ring header (8 slots of
    SLOT bytes) unless ``header`` is False: each case fails one check only."""
    fd = os.memfd_create("hostile", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    os.ftruncate(fd, size)
    if header:
        os.pwrite(fd, b"WBLANE\x00\x01" + struct.pack("<IIII", 1, 8, SLOT, os.getpid()), 0)
    if seals:
        import fcntl

        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, seals)
    return fd


def _hostile_hellos() -> list[tuple[str, bytes, list[int]]]:
    """(what, hello, fds) a broken or hostile writer may send; each must be refused."""
    import fcntl

    seals = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL
    size = 4096 + 8 * SLOT

    def hello(depth: int = 8, slot: int = SLOT, magic: bytes = fast_lane.MAGIC,
              version: int = fast_lane.VERSION) -> bytes:
        return fast_lane.HELLO.pack(magic, version, os.getpid(), depth, slot, ROOM)

    read_end, write_end = os.pipe()
    os.close(write_end)
    cases = [
        ("no fds", hello(), []),
        ("one fd", hello(), [_memfd(size, seals)]),
        ("short hello", hello()[:-3], [_memfd(size, seals), os.eventfd(0)]),
        ("wrong magic", hello(magic=b"XXXXXXXX"), [_memfd(size, seals), os.eventfd(0)]),
        ("wrong version", hello(version=99), [_memfd(size, seals), os.eventfd(0)]),
        ("zero depth", hello(depth=0), [_memfd(4096, seals), os.eventfd(0)]),
        ("huge slot", hello(slot=1 << 30), [_memfd(size, seals), os.eventfd(0)]),
        ("unsealed", hello(), [_memfd(size, 0), os.eventfd(0)]),
        ("too small", hello(), [_memfd(4096, seals), os.eventfd(0)]),
        ("a pipe for a ring", hello(), [os.dup(read_end), os.eventfd(0)]),
        ("no ring header", hello(), [_memfd(size, seals, header=False), os.eventfd(0)]),
    ]
    os.close(read_end)
    return cases


def test_malformed_hand_overs_are_refused_and_an_honest_writer_is_served() -> None:
    name = f"warp_buffer/hostile/{os.urandom(6).hex()}"
    reader = fast_lane.LaneReader(name, depth=4)
    try:
        reader.take()  # settle
        before = len(os.listdir("/proc/self/fd"))
        for what, hello, fds in _hostile_hellos():
            conn = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            conn.connect(fast_lane.address(name))
            try:
                socket.send_fds(conn, [hello], fds) if fds else conn.send(hello)
            finally:
                for fd in fds:
                    os.close(fd)
            assert reader.take() is None, what
            assert not reader.rings(), what  # refused, its connection dropped
            conn.close()
        # a writer that connects and says nothing is kept waiting, and dropped when it leaves
        silent = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        silent.connect(fast_lane.address(name))
        assert reader.take() is None
        assert len(reader.watched()) == 2  # the listener and the silent writer's connection
        silent.close()
        reader.take()  # its hello never comes: dropped
        assert len(reader.watched()) == 1
        assert len(os.listdir("/proc/self/fd")) == before  # nothing of the refused kept
        honest = fast_lane.LaneWriter(name)
        try:
            assert honest.write(b"served") and reader.take() == b"served"
        finally:
            honest.close()
    finally:
        reader.close()


def test_a_frame_stuck_half_written_behind_the_tail_does_not_spin_the_waker() -> None:
    """A broken writer that published its tail past a frame whose stamp still says "being
    written" must not keep the ring pending (the waker would never sleep): the frame is
    skipped as garbage and the next wait sleeps."""
    import time

    writer, reader, pen = _pair()
    waker = _ring.Waker(None)
    try:
        waker.watch([(reader, lambda frame: None, "stuck")], [])
        struct.pack_into("<Q", pen, 4096, 1)  # frame 0: stamp 2*0+1, "being written"
        struct.pack_into("<Q", pen, TAIL, 1)  # ... and the tail past it
        waker.wait(0)
        assert not reader.pending and reader.lost == 1
        started = time.monotonic()
        waker.wait(0.2)  # nothing pending: it sleeps its timeout
        assert time.monotonic() - started >= 0.15
    finally:
        waker.close()
        pen.close()
        writer.close()


def test_notify_racing_close_never_writes_a_closed_or_reused_descriptor() -> None:
    # notify() writes the eventfd without the GIL (the woken waiter takes it at once): close()
    # must wait for such a write and no later notify may reach the fd number once it is closed
    # (the kernel hands it to the next file this process opens).
    import threading

    for _ in range(20):
        waker = _ring.Waker(None)
        stop = threading.Event()

        def hammer() -> None:
            while not stop.is_set():
                waker.notify()

        threads = [threading.Thread(target=hammer) for _ in range(3)]
        for thread in threads:
            thread.start()
        try:
            for _ in range(50):
                waker.wait(0.0005)  # asleep part of the time: notifies write then
            number = waker.fd
            waker.close()
            assert waker.fd == -1
            reused = os.eventfd(0, os.EFD_NONBLOCK)  # likely the number just closed
            try:
                for _ in range(2000):
                    waker.notify()  # after close: a no-op, whatever fd has that number now
                with pytest.raises(BlockingIOError):
                    os.eventfd_read(reused)  # nothing was written to it
            finally:
                os.close(reused)
        finally:
            stop.set()
            for thread in threads:
                thread.join()
        assert number >= 0


def test_a_closed_waker_is_not_initialized_again_and_watch_takes_only_a_descriptor() -> None:
    waker = _ring.Waker(None)
    waker.close()
    with pytest.raises(RuntimeError, match="twice"):
        waker.__init__(None)  # (leaked its first buffers and callback before)
    writer = _ring.RingWriter(4, SLOT)
    try:
        for bad in (2**40, -2):
            with pytest.raises(ValueError, match="not a file descriptor"):
                writer.watch(bad)  # (truncated to an int before)
        writer.watch(-1)
    finally:
        writer.close()
