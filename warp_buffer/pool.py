"""Block pools: where warp buffers get their memory, one pool per Warp device.

Blocks come in power-of-two size classes (at least 4 KiB). A buffer leases one block; when the
buffer and every array viewing it are gone the block returns to its class's free list, and the
next allocation of that class reuses it, so steady-state publishing creates no memory at all.

- ``cpu`` blocks are files in ``/dev/shm`` (a 4 KiB header, then the data), so a same-host peer
  can map the very bytes: exporting costs nothing. Where shared memory cannot be had (IPC
  disabled, /dev/shm full) a block falls back to private memory and is simply not exportable.
- CUDA blocks are device allocations made with the default (non-mempool) allocator, the one CUDA
  IPC handles work with; their header (uid, acknowledgements, the readers' locks) is a
  header-only shm file created on first export.

Reuse of an exported block waits until (a) every descriptor issued for it was acknowledged by an
import, or ``WARP_BUFFER_INFLIGHT_GRACE_S`` passed since the last one was issued (a descriptor
the peer dropped is never imported), and (b) no reader holds it: the pool takes ``LOCK_EX |
LOCK_NB`` on the block file, which fails while any reader's ``LOCK_SH`` is held, and the kernel
drops a reader's lock when the reader dies. Blocks are tried oldest-released first.

Memory goes back to the system when idle: free blocks unused for ``WARP_BUFFER_POOL_IDLE_S``
seconds (default 10) are destroyed by a janitor thread, and free memory beyond
``WARP_BUFFER_POOL_MAX_IDLE_BYTES`` (default 1 GiB per pool) is destroyed at once, oldest first.
"""

from __future__ import annotations

import atexit
import collections
import ctypes
import fcntl
import logging
import os
import secrets
import sys
import threading
import time
from typing import Any

import warp as wp

from . import shm
from .errors import EmptyBufferError, InvalidSizeError

__all__ = [
    "MIN_BLOCK",
    "Block",
    "HostBlock",
    "CudaBlock",
    "BlockPool",
    "Lease",
    "get_pool",
    "size_class",
    "pool_stats",
    "trim_pools",
    "shutdown",
]

_log = logging.getLogger(__name__)

MIN_BLOCK = 4096
MAX_BLOCK = 1 << 40


def _env_float(name: str, default: float) -> float:
    try:
        return float(os.environ.get(name, default))
    except ValueError:
        return default


def ipc_disabled() -> bool:
    """``WARP_BUFFER_DISABLE_IPC=1``: no exports; every peer falls back to CPU bytes."""
    return os.environ.get("WARP_BUFFER_DISABLE_IPC", "").strip().lower() in ("1", "true", "yes", "on")


def size_class(nbytes: int) -> int:
    """The capacity of the block that holds ``nbytes``: the next power of two, at least 4 KiB."""
    if nbytes <= 0:
        raise EmptyBufferError(f"a warp buffer holds at least one byte, not {nbytes}")
    if nbytes > MAX_BLOCK:
        raise InvalidSizeError(f"{nbytes} bytes is more than a warp buffer can hold ({MAX_BLOCK})")
    return max(MIN_BLOCK, 1 << (nbytes - 1).bit_length())


class Block:
    """One allocation of a pool, with the state of its current export."""

    device: Any  # wp.Device
    capacity: int
    data_ptr: int
    block_id: int
    header: shm.BlockHeader | None
    shared: bool

    def __init__(self) -> None:
        self.uid = 0  # uid of the current export, 0 when not exported
        self.issued = 0  # descriptors issued for the current uid
        self.last_issue = 0.0
        self.path: str | None = None
        self.fd: int | None = None

    # -- export bookkeeping (called with the owning impl's lock held) --------------------------
    def begin_export(self) -> int:
        """The uid of the current export, drawn on the first export of the leased buffer."""
        if self.uid == 0:
            header = self.ensure_header()
            self.uid = secrets.randbits(64) or 1
            self.issued = 0
            ctypes.memset(ctypes.addressof(header.acks), 0, shm.ACK_SLOTS)
            header.uid = self.uid
        return self.uid

    def issue_slot(self) -> int:
        """A fresh acknowledgement slot for one descriptor (NO_ACK_SLOT past the 64th)."""
        slot = self.issued if self.issued < shm.ACK_SLOTS else shm.NO_ACK_SLOT
        self.issued += 1
        self.last_issue = time.monotonic()
        return slot

    def _acks_complete(self) -> bool:
        if self.issued > shm.ACK_SLOTS:
            return False
        acks = self.header.acks  # type: ignore[union-attr]
        return all(acks[i] for i in range(self.issued))

    def try_reclaim(self, now: float, grace: float) -> bool:
        """May the block be reused or freed now? Invalidates its export if so."""
        if self.uid == 0:
            return True
        if not self._acks_complete() and now - self.last_issue < grace:
            return False  # a descriptor may still be in flight
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # type: ignore[arg-type]
        except BlockingIOError:
            return False  # a reader holds it
        try:
            # Under LOCK_EX no reader is inside; later ones see uid 0 and raise StaleBufferError.
            self.header.uid = 0  # type: ignore[union-attr]
            self.uid = 0
            self.issued = 0
        finally:
            fcntl.flock(self.fd, fcntl.LOCK_UN)  # type: ignore[arg-type]
        return True

    def ensure_header(self) -> shm.BlockHeader:
        raise NotImplementedError

    def reset_for_lease(self) -> None:
        """Called when the block is handed to a new buffer."""

    def destroy(self) -> None:
        raise NotImplementedError

    def _init_header(self, header: shm.BlockHeader, session: shm.Session, kind: int) -> None:
        header.magic = shm.MAGIC
        header.version = shm.HEADER_VERSION
        header.header_size = shm.HEADER_SIZE
        header.capacity = self.capacity
        header.session = session.session
        header.owner_pid = session.pid
        header.block_id = self.block_id
        header.kind = kind


class HostBlock(Block):
    """A block on the cpu device: shared (header + data in a /dev/shm file) or private."""

    def __init__(self, capacity: int, shared: bool) -> None:
        super().__init__()
        self.device = wp.get_device("cpu")
        self.capacity = capacity
        self.shared = False
        self._map: tuple[int, int] | None = None
        self._private: Any = None
        if shared:
            try:
                self._create_shared()
            except OSError as exc:
                _log.warning("no shared memory for a %d-byte block (%s): using private memory; "
                             "buffers in it travel as CPU bytes", capacity, exc)
        if not self.shared:
            self.block_id = 0
            # Private memory: a header-sized prefix keeps the layout (and the stamp) identical.
            raw = wp.empty(shm.HEADER_SIZE + capacity, dtype=wp.uint8, device="cpu")
            self._private = raw
            base = raw.ptr
            self.header = shm.BlockHeader.from_address(base)
            self.data_ptr = base + shm.HEADER_SIZE
        self.stamp_array = wp.array(
            ptr=ctypes.addressof(self.header) + shm.GENERATION_OFFSET, dtype=wp.uint64,
            shape=(1,), device="cpu",
        )

    def _create_shared(self) -> None:
        total = shm.HEADER_SIZE + self.capacity
        session, self.block_id, self.path, self.fd, addr = _create_mapped_block_file(total)
        self._map = (addr, total)
        self.header = shm.BlockHeader.from_address(addr)
        self._init_header(self.header, session, shm.KIND_HOST_DATA)
        self.data_ptr = addr + shm.HEADER_SIZE
        self.shared = True

    def ensure_header(self) -> shm.BlockHeader:
        return self.header

    def reset_for_lease(self) -> None:
        self.header.generation = 0

    def destroy(self) -> None:
        self.stamp_array = None
        self.header = None  # type: ignore[assignment]
        if self._map is not None:
            shm.unmap(*self._map)
            self._map = None
        _close_block_file(self.fd, self.path)
        self.fd = self.path = None
        self._private = None


def _create_mapped_block_file(nbytes: int) -> tuple[Any, int, str, int, int]:
    """Create a block file of ``nbytes`` and map it: ``(session, block_id, path, fd, address)``.
    On failure the file is closed and removed again."""
    session, block_id, path, fd = shm.create_block_file(nbytes)
    try:
        addr = shm.map_fd(fd, nbytes)
    except BaseException:
        os.close(fd)
        session.remove_file(path)
        raise
    return session, block_id, path, fd, addr


def _close_block_file(fd: int | None, path: str | None) -> None:
    """Close a block's fd and remove its /dev/shm file from this process's session."""
    if fd is not None:
        os.close(fd)
    if path is not None:
        with shm._session_lock:
            session = shm._session
            if session is not None and path in session.files:
                session.remove_file(path)


_mempool_lock = threading.Lock()


class CudaBlock(Block):
    """A block of CUDA device memory; its shm header file is made on first export."""

    def __init__(self, device: Any, capacity: int) -> None:
        super().__init__()
        self.device = device
        self.capacity = capacity
        self.shared = True
        self.header = None
        self.block_id = 0
        self._header_map: tuple[int, int] | None = None
        self._ipc_mem_handle: bytes | None = None
        self._event: Any = None
        with _mempool_lock:
            if device.is_mempool_supported:
                with wp.ScopedMempool(device, False):  # CUDA IPC needs the default allocator
                    self.storage = wp.empty(capacity, dtype=wp.uint8, device=device)
            else:
                self.storage = wp.empty(capacity, dtype=wp.uint8, device=device)
        self.data_ptr = self.storage.ptr

    @property
    def ipc_supported(self) -> bool:
        return bool(self.device.is_ipc_supported)

    def ensure_header(self) -> shm.BlockHeader:
        if self.header is None:
            session, self.block_id, self.path, self.fd, addr = _create_mapped_block_file(
                shm.HEADER_SIZE)
            self._header_map = (addr, shm.HEADER_SIZE)
            header = shm.BlockHeader.from_address(addr)
            self._init_header(header, session, shm.KIND_HEADER_ONLY)
            self.header = header
        return self.header

    @property
    def event(self) -> Any:
        """The block's CUDA event (interprocess where the device supports IPC)."""
        if self._event is None:
            self._event = wp.Event(self.device, interprocess=self.ipc_supported)
        return self._event

    def ipc_mem_handle(self) -> bytes:
        if self._ipc_mem_handle is None:
            self._ipc_mem_handle = self.storage.ipc_handle()
        return self._ipc_mem_handle

    def ipc_event_handle(self) -> bytes:
        return self.event.ipc_handle()

    def destroy(self) -> None:
        if self._header_map is not None:
            shm.unmap(*self._header_map)
            self._header_map = None
        self.header = None
        _close_block_file(self.fd, self.path)
        self.fd = self.path = None
        self.storage = None
        self._event = None


class Lease:
    """One buffer's use of one block. Used as the ``deleter`` of the buffer's base ``wp.array``,
    so the block returns to the pool exactly when the last array over it is collected."""

    __slots__ = ("pool", "block", "_done", "__weakref__")

    def __init__(self, pool: BlockPool, block: Block) -> None:
        self.pool = pool
        self.block = block
        self._done = False

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        if not self._done:
            self._done = True
            self.pool._give_back(self.block)


class BlockPool:
    """Size-classed blocks of one device (see the module docstring for the reuse rules).

    Blocks come back from garbage collection (a ``wp.array`` deleter), which may run at any
    allocation, on any thread, even while this pool's lock is held by the same thread: so a
    returned block only goes onto a lock-free queue, drained under the lock by the next pool
    operation.
    """

    def __init__(self, device: Any) -> None:
        self.device = device
        self._lock = threading.Lock()
        self._free: dict[int, collections.deque[tuple[Block, float]]] = {}
        self._returned: collections.deque[tuple[Block, float]] = collections.deque()
        self._defunct = False
        self.created = 0
        self.reused = 0
        self.destroyed = 0
        self.free_bytes = 0
        self._leased = 0  # blocks handed out (returned ones are subtracted when drained)

    # -- allocation ----------------------------------------------------------------------------
    def acquire(self, nbytes: int) -> Lease:
        capacity = size_class(nbytes)
        grace = _env_float("WARP_BUFFER_INFLIGHT_GRACE_S", 2.0)
        with self._lock:
            self._drain()
            block = self._take_free(capacity, time.monotonic(), grace)
            if block is not None:
                self.reused += 1
            self._leased += 1
        if block is None:
            try:
                block = self._create(capacity)
            except BaseException:
                with self._lock:
                    self._leased -= 1
                raise
            with self._lock:
                self.created += 1
        block.reset_for_lease()
        _janitor.ensure_running()
        self._enforce_idle_cap()
        return Lease(self, block)

    def _take_free(self, capacity: int, now: float, grace: float) -> Block | None:
        queue = self._free.get(capacity)
        if not queue:
            return None
        for index, (block, _released) in enumerate(queue):
            if block.try_reclaim(now, grace):
                del queue[index]
                self.free_bytes -= block.capacity
                return block
        return None

    def _create(self, capacity: int) -> Block:
        if self.device.is_cpu:
            return HostBlock(capacity, shared=not ipc_disabled())
        return CudaBlock(self.device, capacity)

    def _give_back(self, block: Block) -> None:
        # Runs from a deleter: no locks, no threads, nothing that can block (see the class doc).
        if not self._defunct and not sys.is_finalizing():
            self._returned.append((block, time.monotonic()))

    def _drain(self) -> None:
        """Move returned blocks onto the free lists (call with the lock held)."""
        while True:
            try:
                block, released = self._returned.popleft()
            except IndexError:
                return
            self._leased -= 1
            self._free.setdefault(block.capacity, collections.deque()).append((block, released))
            self.free_bytes += block.capacity

    def _enforce_idle_cap(self) -> None:
        cap = int(_env_float("WARP_BUFFER_POOL_MAX_IDLE_BYTES", 1 << 30))
        if self.free_bytes > cap:
            self.trim(max_free_bytes=cap)

    # -- giving memory back ---------------------------------------------------------------------
    def trim(self, idle_s: float = 0.0, max_free_bytes: int | None = None,
             inflight_grace: float | None = None) -> int:
        """Destroy free blocks idle for ``idle_s`` seconds or more (all with 0), or, with
        ``max_free_bytes``, the oldest ones until free memory fits. Blocks a reader still holds
        are kept, and so are exported blocks whose descriptors may still be in flight
        (``inflight_grace``, default ``WARP_BUFFER_INFLIGHT_GRACE_S``). Returns the bytes given
        back."""
        now = time.monotonic()
        grace = (_env_float("WARP_BUFFER_INFLIGHT_GRACE_S", 2.0) if inflight_grace is None
                 else inflight_grace)
        victims: list[Block] = []
        with self._lock:
            self._drain()
            entries = sorted(
                ((released, block) for queue in self._free.values() for block, released in queue),
                key=lambda item: item[0],
            )
            free = self.free_bytes
            for released, block in entries:
                if max_free_bytes is not None:
                    if free <= max_free_bytes:
                        break
                elif now - released < idle_s:
                    continue
                if block.try_reclaim(now, grace):
                    self._free[block.capacity].remove((block, released))
                    free -= block.capacity
                    victims.append(block)
            self.free_bytes = free
            self.destroyed += len(victims)
        freed = 0
        for block in victims:
            freed += block.capacity
            block.destroy()
        if victims:
            shm.close_session_if_empty()
        return freed

    def is_idle(self) -> bool:
        """No block leased or free: nothing for the janitor to watch."""
        with self._lock:
            self._drain()
            return self._leased == 0 and not any(self._free.values())

    def stats(self) -> dict[str, int]:
        with self._lock:
            self._drain()
            return {
                "created": self.created,
                "reused": self.reused,
                "destroyed": self.destroyed,
                "leased": self._leased,
                "free_blocks": sum(len(q) for q in self._free.values()),
                "free_bytes": self.free_bytes,
            }

    def close(self) -> None:
        """Destroy every free block now (leased ones are left to their buffers)."""
        with self._lock:
            self._drain()
            blocks = [block for queue in self._free.values() for block, _ in queue]
            self._free.clear()
            self.free_bytes = 0
            self.destroyed += len(blocks)
        for block in blocks:
            try:
                block.destroy()
            except Exception:  # pragma: no cover - best effort at shutdown
                pass


class _Janitor:
    """A daemon thread that gives idle free blocks back; it runs while any pool holds blocks
    and is started by allocations (never from a deleter)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def ensure_running(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="warp_buffer-pool-janitor")
                self._thread.start()

    def _run(self) -> None:
        while True:
            idle = max(0.0, _env_float("WARP_BUFFER_POOL_IDLE_S", 10.0))
            time.sleep(min(1.0, max(0.05, idle / 4)))
            with _pools_lock:
                pools = list(_pools.values())
            busy = False
            for pool in pools:
                try:
                    pool.trim(idle_s=idle)
                    pool._enforce_idle_cap()
                    busy = busy or not pool.is_idle()
                except Exception:  # pragma: no cover - never let the janitor die noisily
                    _log.exception("warp_buffer pool janitor")
            if not busy:
                with self._lock:
                    self._thread = None
                return


_janitor = _Janitor()
_pools: dict[str, BlockPool] = {}
_pools_lock = threading.Lock()


def get_pool(device: Any) -> BlockPool:
    """The pool of Warp device ``device`` (a ``wp.Device``)."""
    key = device.alias
    with _pools_lock:
        pool = _pools.get(key)
        if pool is None:
            pool = _pools[key] = BlockPool(device)
        return pool


def pool_stats() -> dict[str, dict[str, int]]:
    """Counters of every pool, by device: created, reused, destroyed, leased, free blocks/bytes."""
    with _pools_lock:
        pools = dict(_pools)
    return {name: pool.stats() for name, pool in pools.items()}


def trim_pools(idle_s: float = 0.0, inflight_grace: float | None = None) -> int:
    """Give back the free blocks of every pool idle for ``idle_s`` seconds (all with 0); see
    :meth:`BlockPool.trim`. Returns the bytes given back."""
    with _pools_lock:
        pools = list(_pools.values())
    return sum(pool.trim(idle_s=idle_s, inflight_grace=inflight_grace) for pool in pools)


def shutdown() -> None:
    """Clean shutdown: free every idle block and remove every shared-memory file of this
    process (buffers still alive keep their mappings; peers holding them keep theirs)."""
    with _pools_lock:
        pools = list(_pools.values())
    for pool in pools:
        pool.close()
    shm.close_session()


def _at_exit() -> None:
    if shm._session is not None and shm._session.pid == os.getpid():
        shm.close_session()


atexit.register(_at_exit)


def _after_fork_in_child() -> None:
    global _pools_lock, _janitor
    for pool in _pools.values():
        pool._defunct = True  # blocks inherited from the parent are not ours to recycle
    _pools.clear()
    _pools_lock = threading.Lock()
    _janitor = _Janitor()


os.register_at_fork(after_in_child=_after_fork_in_child)
