"""The publisher session's arena: one sealed anonymous ``memfd`` that holds every shared block.

A process that exports cpu memory creates one arena (its *session*, named by a random 64-bit
tag), ``ftruncate``\\s it once to a large virtual size (``WARP_BUFFER_ARENA_GIB``, default 64:
pages exist only once touched), seals it against shrinking and growing (``F_SEAL_SHRINK |
F_SEAL_GROW | F_SEAL_SEAL``) and maps it once. Blocks are offset ranges inside it, handed out by a
buddy allocator; idle blocks give their pages back with ``FALLOCATE_PUNCH_HOLE``. Peers receive the
fd over a Unix socket (:mod:`warp_buffer.handoff`) and map it once too. Nothing has a name in
``/dev/shm``: the memory is gone when the last process that maps it or holds its fd is gone,
whatever way it ended (clean exit, SIGTERM, SIGKILL).

File layout (little endian)::

    [0, 4096)                 arena header (HELLO layout of :mod:`warp_buffer.handoff`)
    [ACKS_OFFSET, +64 KiB)    one 64-byte slot per peer subscription: the last delivery
                              sequence that peer's process imported (written by that peer only)
    [GENS_OFFSET, ...)        one uint64 per 4 KiB of data: the generation of the export that
                              starts there (0: none); checked by an importer under its lock
    [data_offset, file_size)  the blocks

Holds: a reader process takes a read lock on a block's lock range, its first :data:`LOCK_SPAN`
bytes in the file (OFD lock, by its native core while it holds the block, see
:mod:`warp_buffer.attach`); the publisher recycles a block only once its non-blocking write-lock
probe on that range succeeds, and clears the block's generation under that lock, so a late
import of a recycled block finds another generation and raises
:class:`~warp_buffer.errors.StaleBufferError`. The per-message part of the arena (generations,
peer slots, the probe) is native: :attr:`Arena.core`, a :class:`warp_buffer._core.ArenaCore`.
"""

from __future__ import annotations

import ctypes
import dataclasses
import fcntl
import logging
import os
import secrets
import struct
import threading
import time
from typing import Any

from rosidl_buffer.buffer_impl import array_at

from . import memory
from .descriptor import _core
from ._env import env_float

__all__ = [
    "MIN_BLOCK",
    "MAX_PEERS",
    "NO_PEER",
    "SEALS",
    "Geometry",
    "Arena",
    "PeerSlot",
    "current_arena",
    "existing_arena",
    "arena_bytes",
    "alive",
]

_log = logging.getLogger(__name__)

MIN_BLOCK = 4096
#: The bytes of a block's lock range (at the block's file offset; a CUDA block's is a range of
#: its own): a reader process read-locks it while it holds the block.
LOCK_SPAN = MIN_BLOCK
HEADER_PAGE = 4096
MAX_PEERS = 1024
SLOT_STRIDE = 64  # one cache line per peer: peers never share a line they write
NO_PEER = 0xFFFF
ACKS_OFFSET = HEADER_PAGE
GENS_OFFSET = ACKS_OFFSET + MAX_PEERS * SLOT_STRIDE
SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL
MAGIC = b"WARPARN\x02"
VERSION = 2
#: The header page, and the hello a peer receives with the fd: magic, version, owner pid,
#: session tag, data offset, data bytes, file size.
HELLO = struct.Struct("<8sIIQQQQ")
SEQ_BITS = 40  # a delivery sequence is epoch << SEQ_BITS | number


def arena_bytes() -> int:
    """Data bytes of a new arena: ``WARP_BUFFER_ARENA_GIB`` (default 64) GiB, a power of two."""
    gib = env_float("WARP_BUFFER_ARENA_GIB", 64.0)
    wanted = max(MIN_BLOCK * 16, int(gib * (1 << 30)))
    return 1 << (wanted.bit_length() - 1)


@dataclasses.dataclass(frozen=True)
class Geometry:
    """Where things are in an arena of ``data_bytes`` data bytes (both sides compute it)."""

    data_bytes: int
    data_offset: int = dataclasses.field(init=False)
    file_size: int = dataclasses.field(init=False)

    def __post_init__(self) -> None:
        gens = self.data_bytes // MIN_BLOCK * 8
        offset = -(-(GENS_OFFSET + gens) // MIN_BLOCK) * MIN_BLOCK
        object.__setattr__(self, "data_offset", offset)
        object.__setattr__(self, "file_size", offset + self.data_bytes)

    def check_block(self, offset: int, capacity: int) -> str | None:
        """Why ``(offset, capacity)`` cannot be a block of this arena, or None."""
        if capacity < MIN_BLOCK or capacity & (capacity - 1) or capacity > self.data_bytes:
            return f"capacity {capacity} is not a block size of this arena"
        rel = offset - self.data_offset
        if rel < 0 or rel % capacity or rel + capacity > self.data_bytes:
            return f"offset {offset} is not the start of a {capacity}-byte block"
        return None


class _Buddy:
    """Power-of-two ranges of ``[0, size)``, naturally aligned, merged again when freed."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._free: dict[int, set[int]] = {size: {0}}

    def alloc(self, capacity: int) -> int | None:
        order = capacity
        while order <= self.size and not self._free.get(order):
            order <<= 1
        if order > self.size:
            return None
        offset = self._free[order].pop()
        while order > capacity:  # split, keep the upper halves free
            order >>= 1
            self._free.setdefault(order, set()).add(offset + order)
        return offset

    def free(self, offset: int, capacity: int) -> None:
        while capacity < self.size:
            buddy = offset ^ capacity
            peers = self._free.get(capacity)
            if peers is None or buddy not in peers:
                break
            peers.remove(buddy)
            offset = min(offset, buddy)
            capacity <<= 1
        self._free.setdefault(capacity, set()).add(offset)


#: One peer subscription's delivery accounting in this session (native): ``index``, ``epoch``,
#: ``pid``, ``issued`` (the last number sent) and ``window`` (how many of its latest descriptors
#: the peer can still import: its delivery queue and a few in hand; older ones it can never read,
#: they pin nothing; 0: no limit). The publisher numbers the descriptors it sends the peer
#: (:meth:`warp_buffer.lease.Lease.export`); the peer's process writes the last number it
#: imported into the slot.
PeerSlot = _core.PeerSlot


class Arena:
    """This process's session: the sealed memfd, its one mapping, the allocator, the peer slots
    and the hand-off server (started on first export)."""

    def __init__(self, data_bytes: int | None = None) -> None:
        self.geometry = Geometry(data_bytes or arena_bytes())
        self.pid = os.getpid()
        self.session = secrets.randbits(64) or 1
        size = self.geometry.file_size
        fd = os.memfd_create("warp_buffer", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
        try:
            os.fchmod(fd, 0o600)  # a memfd starts as 0777; ours is readable by its owner only
            os.ftruncate(fd, size)
            fcntl.fcntl(fd, fcntl.F_ADD_SEALS, SEALS)
            self.base = memory.map_fd(fd, size)
        except BaseException:
            os.close(fd)
            raise
        self.fd = fd
        self.size = size
        self.data_offset = self.geometry.data_offset
        ctypes.memmove(self.base, self.hello(), HELLO.size)
        #: The per-message state (generations, peer slots, the retire probe), native.
        self.core = _core.ArenaCore(self.base, fd, self.data_offset, self.geometry.data_bytes)
        self.host = array_at(self.base, size)
        self._lock = threading.Lock()
        self._buddy = _Buddy(self.geometry.data_bytes)
        self._slots: dict[Any, PeerSlot] = {}
        self._free_slots = list(range(MAX_PEERS - 1, -1, -1))
        self._last_liveness = 0.0
        self.server: Any = None
        # CUDA VMM blocks by the offset of their lock range: the server hands a peer holding
        # one of them its fd (warp_buffer.handoff.ASK_CUDA_VMM).
        self.cuda_exports: dict[int, Any] = {}

    def hello(self) -> bytes:
        g = self.geometry
        return HELLO.pack(MAGIC, VERSION, self.pid, self.session, g.data_offset, g.data_bytes,
                          g.file_size)

    # -- blocks -----------------------------------------------------------------------------
    def alloc(self, capacity: int) -> int | None:
        """File offset of a new ``capacity``-byte block, or None when the arena is full."""
        with self._lock:
            rel = self._buddy.alloc(capacity)
        return None if rel is None else self.data_offset + rel

    def free(self, offset: int, capacity: int) -> None:
        """Give a block's pages back to the system and its range back to the allocator."""
        try:
            memory.punch_hole(self.fd, offset, capacity)
        except OSError as exc:  # pragma: no cover - tmpfs always supports it
            _log.warning("could not give %d bytes back: %s", capacity, exc)
        with self._lock:
            self._buddy.free(offset - self.data_offset, capacity)

    def new_generation(self, offset: int, capacity: int) -> int:
        """Start an export of the ``capacity``-byte block at ``offset``: a generation never used
        before, whose low bits hold log2(capacity), so an importer can tell that a descriptor's
        capacity is the block's own (a generation word says nothing of the bytes after a
        block's first 4 KiB: a forged larger capacity would read the next block)."""
        return self.core.new_generation(offset, capacity)

    def try_retire(self, offset: int) -> bool:
        """End the export of the block at ``offset`` if no reader holds it (a write-lock probe
        on its lock range); later imports of it then find generation 0 and fail as stale."""
        return self.core.try_retire(offset)

    # -- peers ------------------------------------------------------------------------------
    def peer_slot(self, key: Any, pid: int, window: int = 0) -> PeerSlot | None:
        """The delivery slot of peer ``key`` (its subscription gid), assigned on first use;
        None when every slot is taken (the peer is then served by CPU). ``window``: see
        :class:`PeerSlot` (a keep-last peer's depth, plus what it may hold in hand)."""
        if not self._free_slots and key not in self._slots:
            self._last_liveness = 0.0
            self.forget_dead_peers()  # make room: dead peers first
        with self._lock:
            slot = self._slots.get(key)
            if slot is None:
                if not self._free_slots:
                    return None
                index = self._free_slots.pop()
                slot = self._slots[key] = self.core.open_slot(index, pid, max(0, window))
            return slot

    def forget_peer(self, key: Any) -> None:
        """The peer is gone: its pending deliveries no longer pin anything; the slot is reused."""
        with self._lock:
            slot = self._slots.pop(key, None)
            if slot is not None:
                self.core.close_slot(slot.index)
                self._free_slots.append(slot.index)

    def forget_dead_peers(self) -> None:
        """Forget peers whose process died (checked at most every 100 ms)."""
        now = time.monotonic()
        if now - self._last_liveness < 0.1:
            return
        self._last_liveness = now
        with self._lock:
            dead = [key for key, slot in self._slots.items() if not alive(slot.pid)]
        for key in dead:
            self.forget_peer(key)

    def pending_pids(self) -> set[int]:
        """Pids of peers that have descriptors they did not import yet (for the exit linger)."""
        with self._lock:
            slots = list(self._slots.values())
        ack = self.core.ack
        return {s.pid for s in slots if s.issued and ack(s.index) < (s.epoch << SEQ_BITS | s.issued)}


def alive(pid: int) -> bool:
    """Does process ``pid`` exist (it may be another user's)?"""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


_arena: Arena | None = None
_arena_lock = threading.Lock()


def current_arena() -> Arena:
    """This process's arena, created on first use."""
    global _arena
    arena = _arena
    if arena is not None and arena.pid == _core.pid():
        return arena
    with _arena_lock:
        if _arena is None or _arena.pid != _core.pid():
            _arena = Arena()
        return _arena


def existing_arena() -> Arena | None:
    arena = _arena
    return arena if arena is not None and arena.pid == _core.pid() else None


def _after_fork_in_child() -> None:
    # The parent's arena is not ours to allocate from: a child starts its own session. Nor is
    # its hand-off socket ours to hold: inherited, it would stay bound after the parent died,
    # and peers connecting to it would wait for an answer that never comes.
    global _arena, _arena_lock
    if _arena is not None and _arena.server is not None:
        _arena.server.abandon()
    _arena = None
    _arena_lock = threading.Lock()


os.register_at_fork(after_in_child=_after_fork_in_child)
