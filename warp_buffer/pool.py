"""Block pools: where warp buffers get their memory, one pool per Warp device.

Blocks come in power-of-two size classes (at least 4 KiB). A buffer leases one block; when the
buffer and every array viewing it are gone the block returns to its class's free list, and the
next allocation of that class reuses it, so steady-state publishing creates no memory at all.

- ``cpu`` blocks are ranges of this process's arena (:mod:`warp_buffer.arena`: one sealed memfd
  per process, mapped once here and once per peer process), so a same-host peer reads the very
  bytes: exporting costs nothing and no block has an fd or a mapping of its own. Where the arena
  cannot serve (IPC disabled, the arena full) a block is private memory and not exportable.
- CUDA blocks, where the device can export VMM memory as a POSIX fd, are ``cuMemCreate``
  allocations (:class:`VmmBlock`, :class:`warp_buffer.cuda.VmmMemory`): a peer fetches a
  block's fd over the session's hand-off socket and maps it read-only, and the memory outlives
  this process while the peer maps it. Elsewhere (logged once per device) they are allocations
  of the default (non-mempool) allocator, the one legacy CUDA IPC handles work with
  (:class:`CudaBlock`, :func:`warp_buffer.cuda.alloc_ipc_memory`), whose memory dies with this
  process. On first export each CUDA block also gets a 4 KiB range of the arena (never
  touched, so it costs no memory) whose first byte carries the readers' locks and generation.
  A CUDA block is also not reused or freed before every local reader's last-use event
  completed (its ``cuda_uses``).

An exported block is reused or freed only when (a) every peer it was sent to imported it, or a
later descriptor (it dropped this one: keep-last), or is gone (:meth:`warp_buffer.arena.Arena.
delivered`), and (b) no reader holds it: the pool's write-lock probe on the block's lock byte
fails while any reader's read lock is held, and the kernel drops a reader's lock when it dies.
No timer is involved. At most :data:`PROBES` candidates are probed per allocation for reuse, and
as many to hold free memory to its cap (oldest first, the busy ones move to the back), so a
subscriber holding thousands of blocks does not make allocation slow.

Memory goes back to the system when idle: free blocks unused for ``WARP_BUFFER_POOL_IDLE_S``
seconds (default 10) are destroyed by a janitor thread (their arena pages punched out), and free
memory beyond ``WARP_BUFFER_POOL_MAX_IDLE_BYTES`` (default 1 GiB per pool) at once, oldest first.
"""

from __future__ import annotations

import atexit
import collections
import itertools
import logging
import os
import sys
import threading
import time
from typing import Any

import numpy as np
import warp as wp

from . import arena as _arena
from ._env import env_flag, env_float
from . import cuda, handoff
from . import descriptor as _desc
from .errors import EmptyBufferError, ExportError, ExportUnavailableError, InvalidSizeError
from .lease import Exports, Lease

__all__ = [
    "MIN_BLOCK",
    "Block",
    "HostBlock",
    "CudaBlock",
    "VmmBlock",
    "cuda_block",
    "BlockPool",
    "Lease",
    "get_pool",
    "size_class",
    "pool_stats",
    "trim_pools",
    "shutdown",
]

_log = logging.getLogger(__name__)

MIN_BLOCK = _arena.MIN_BLOCK
#: The largest warp buffer: its storage is one 1-D ``wp.array`` of uint8, and Warp allows at
#: most 2**31 - 1 elements per dimension.
MAX_BUFFER_BYTES = 2**31 - 1
PROBES = 8


def ipc_disabled() -> bool:
    """``WARP_BUFFER_DISABLE_IPC=1``: no exports; every peer falls back to CPU bytes."""
    return env_flag("WARP_BUFFER_DISABLE_IPC", False)


def size_class(nbytes: int) -> int:
    """The capacity of the block that holds ``nbytes``: the next power of two, at least 4 KiB."""
    if nbytes <= 0:
        raise EmptyBufferError(f"a warp buffer holds at least one byte, not {nbytes}")
    if nbytes > MAX_BUFFER_BYTES:
        raise InvalidSizeError(
            f"{nbytes} bytes is more than a warp buffer can hold ({MAX_BUFFER_BYTES}: its storage "
            "is one wp.array, and Warp allows 2**31 - 1 elements per dimension); split it")
    return max(MIN_BLOCK, 1 << (nbytes - 1).bit_length())


class Block(Exports):
    """One allocation of a pool; its export state (generation, peers pending, the reclaim probe)
    is :class:`warp_buffer.lease.Exports`. ``offset`` is the block's file offset in the arena
    (0: not in the arena)."""

    device: Any  # wp.Device
    capacity: int
    data_ptr: int
    shared: bool
    cuda_pin: Any = None  # a host block pinned for CUDA staging (cuda.HostRegistration)

    @property
    def host(self) -> np.ndarray | None:
        """A NumPy view of the data (host blocks), for plain host copies."""
        return None

    def destroy(self) -> None:
        raise NotImplementedError


class HostBlock(Block):
    """A block on the cpu device: a range of the arena (shared) or private memory."""

    def __init__(self, capacity: int, shared: bool) -> None:
        super().__init__()
        self.device = wp.get_device("cpu")
        self.capacity = capacity
        self.shared = False
        self._private: Any = None
        if shared:
            try:
                arena = _arena.current_arena()
                offset = arena.alloc(capacity)
            except OSError as exc:
                _log.warning("no shared arena (%s): using private memory; buffers in it "
                             "travel as CPU bytes", exc)
            else:
                _arena_full.note(offset is None, capacity)
                if offset is not None:
                    self.arena, self.offset, self.shared = arena, offset, True
                    self.data_ptr = arena.base + offset
                    self._host = arena.host[offset:offset + capacity]
        if not self.shared:
            self._private = wp.empty(capacity, dtype=wp.uint8, device="cpu")
            self.data_ptr = self._private.ptr
            self._host = self._private.numpy()

    @property
    def host(self) -> np.ndarray:
        return self._host

    def destroy(self) -> None:
        self._host = None  # type: ignore[assignment]
        if self.cuda_pin:  # unpin before the pages are punched out (the GPU must not keep them)
            self.cuda_pin.close()
            self.cuda_pin = None
        if self.shared and self.arena is not None:
            self.arena.free(self.offset, self.capacity)
            self.arena = None
        self._private = None


class _ArenaFull:
    """Whether block sizes found the arena full, to say so once per episode, not per block (a
    subscriber holding every frame fills it at the publishing rate): one warning when a size
    first finds no range, one when every size that did was served again. A size served also
    clears the smaller ones; a smaller one served leaves a larger one full (no flip-flop)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sizes: set[int] = set()

    def note(self, full: bool, capacity: int) -> None:
        with self._lock:
            if full:
                first = not self._sizes
                self._sizes.add(capacity)
                if first:
                    _log.warning("the arena has no %d-byte range left: new buffers use private "
                                 "memory and travel as CPU bytes (no zero copy) until readers "
                                 "let blocks go (WARP_BUFFER_ARENA_GIB sizes the arena; "
                                 "pool_stats() counts them)", capacity)
            elif self._sizes:
                self._sizes = {size for size in self._sizes if size > capacity}
                if not self._sizes:
                    _log.warning("the arena serves again: new buffers are shared (zero copy) "
                                 "once more")

    def after_fork_in_child(self) -> None:
        self._lock = threading.Lock()
        self._sizes = set()  # the child's arena is a new one


_arena_full = _ArenaFull()
os.register_at_fork(after_in_child=_arena_full.after_fork_in_child)


class CudaBlock(Block):
    """A block of CUDA device memory; its arena range (lock byte, generation) comes with its
    first export.

    The memory comes from :func:`warp_buffer.cuda.alloc_ipc_memory` (``cudaMalloc`` for this
    allocation only: no global mempool flip, a user-set allocator neither used nor replaced), so
    CUDA IPC can export it. ``cuda_uses`` keeps the block's last-use events (one per stream that
    read it locally: a read handle's release, a clone's copy, a staging copy); the block is
    reused or freed only once they all completed (:meth:`try_reclaim`).
    """

    def __init__(self, device: Any, capacity: int) -> None:
        super().__init__()
        self.device = device
        self.capacity = capacity
        self.shared = True
        self._ipc_mem_handle: bytes | None = None
        self._event: Any = None
        self.storage = cuda.alloc_ipc_memory(device, capacity)  # raises DeviceMemoryError
        self.data_ptr = self.storage.ptr

    @property
    def ipc_supported(self) -> bool:
        return bool(self.device.is_ipc_supported)

    def ensure_arena_range(self) -> None:
        if self.arena is None:
            arena = _arena.current_arena()
            offset = arena.alloc(MIN_BLOCK)
            if offset is None:
                raise OSError("the arena has no range left for a CUDA block's lock")
            self.arena, self.offset = arena, offset

    def try_reclaim(self) -> bool:
        # Local readers first (cheap event queries): a block a local stream may still read is
        # neither reused nor freed (freeing it would also invalidate peers' mappings).
        if not cuda.ready_for_reuse(self):
            return False
        return super().try_reclaim()

    @property
    def event(self) -> Any:
        """The block's write-completion event, re-recorded per write (interprocess where the
        device supports CUDA IPC, so its handle can travel in a descriptor)."""
        if self._event is None:
            self._event = (cuda.new_ipc_event(self.device) if self.ipc_supported
                           else wp.Event(self.device))
        return self._event

    #: How a same-GPU peer is sent this block (the descriptor kind).
    cuda_kind = _desc.KIND_CUDA_IPC

    def ipc_mem_handle(self) -> bytes:
        """The allocation's CUDA IPC handle (:class:`ExportUnavailableError` if it has none:
        the caller stages instead)."""
        if self._ipc_mem_handle is None:
            self._ipc_mem_handle = cuda.ipc_mem_handle(self.storage)
        return self._ipc_mem_handle

    def mem_words(self) -> tuple[int, ...]:
        """The descriptor's ``mem_handle`` words for this block."""
        return _desc.handle_words(self.ipc_mem_handle())

    def ipc_event_handle(self) -> bytes:
        return cuda.ipc_event_handle(self.event)

    def destroy(self) -> None:
        if self.arena is not None:
            self.arena.free(self.offset, MIN_BLOCK)
            self.arena = None
        self.storage = None
        self._event = None


_vmm_serials = itertools.count(1)


class VmmBlock(CudaBlock):
    """A CUDA block of VMM memory (``cuMemCreate``, rounded up to the device's granularity):
    a peer holding it asks the session's hand-off server for its POSIX fd
    (:func:`warp_buffer.handoff.fetch_cuda_block`, once per block), imports it read-only and
    keeps the physical memory alive after this process exits. ``serial`` (unique in the
    session) tells an importer that a block at a reused arena offset is new memory."""

    cuda_kind = _desc.KIND_CUDA_VMM

    def __init__(self, device: Any, capacity: int) -> None:
        Block.__init__(self)
        self.device = device
        self.capacity = capacity
        self.shared = True
        self._event = None
        self.vmm = cuda.VmmMemory.create(device, capacity)  # DeviceMemoryError, CudaDriverError
        self.vmm_bytes = self.vmm.nbytes
        self.serial = next(_vmm_serials)
        self.storage = self.vmm.array(0, capacity)
        self.data_ptr = self.vmm.ptr

    def ensure_arena_range(self) -> None:
        if self.arena is None:
            super().ensure_arena_range()
            self.arena.cuda_exports[self.offset] = self  # type: ignore[union-attr]

    def ipc_mem_handle(self) -> bytes:
        raise ExportUnavailableError("a VMM block has no legacy CUDA IPC handle")

    def mem_words(self) -> tuple[int, ...]:
        return _desc.vmm_words(self.serial, self.vmm_bytes)

    def export_fd(self) -> int:
        """A new POSIX fd of the allocation (the hand-off server sends and closes it)."""
        return self.vmm.export_fd()

    def destroy(self) -> None:
        if self.arena is not None:
            self.arena.cuda_exports.pop(self.offset, None)  # no more fds handed out
        super().destroy()
        vmm, self.vmm = self.vmm, None
        if vmm is not None:
            vmm.close()  # peers that imported it keep their own handle: their memory stays


_vmm_refused: dict[str, str] = {}  # device alias -> why its CUDA blocks use legacy IPC


def _vmm_refusal(device: Any) -> str | None:
    """Why ``device``'s CUDA blocks cannot be VMM blocks (None: they can)."""
    if not env_flag("WARP_BUFFER_CUDA_VMM", True):
        return "WARP_BUFFER_CUDA_VMM=0"
    if not device.is_ipc_supported:
        return "no CUDA IPC events on the device"  # a VMM block's write event travels by IPC
    if not cuda.vmm_supported(device):
        return ("no VMM with POSIX fd export (CU_DEVICE_ATTRIBUTE_HANDLE_TYPE_POSIX_FILE_"
                "DESCRIPTOR_SUPPORTED)")
    return None


def _refuse_vmm(device: Any, reason: str) -> None:
    if device.alias not in _vmm_refused:
        _vmm_refused[device.alias] = reason
        _log.info("%s: CUDA buffers are exported by legacy CUDA IPC, not VMM (%s): a peer's "
                  "import dies with this process and is mapped writable", device.alias, reason)


def uses_vmm(device: Any) -> bool:
    """Are ``device``'s new CUDA blocks VMM blocks (judged once, the fallback logged once)?"""
    if device.alias in _vmm_refused:
        return False
    reason = _vmm_refusal(device)
    if reason is not None:
        _refuse_vmm(device, reason)
        return False
    return True


def _block_floor(device: Any) -> int:
    """The smallest block capacity on CUDA ``device``: VMM's granularity, else none."""
    if not uses_vmm(device):
        return 0
    try:
        return size_class(cuda.vmm_granularity(device))
    except ExportError:
        return 0


def cuda_block(device: Any, capacity: int) -> CudaBlock:
    """A new CUDA block: VMM where the device exports VMM memory, else legacy CUDA IPC memory.
    Raises :class:`DeviceMemoryError` when the device is full (either way)."""
    if uses_vmm(device):
        try:
            return VmmBlock(device, capacity)
        except cuda.DeviceMemoryError:
            raise
        except ExportError as exc:  # the driver refused VMM after all: never try again here
            _refuse_vmm(device, f"cuMemCreate failed: {exc}")
    return CudaBlock(device, capacity)


class BlockPool:
    """Size-classed blocks of one device (see the module docstring for the reuse rules).

    Blocks come back when their lease's owner is gone (a finalizer), which may run at any
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
        self.private = 0  # blocks made in private memory: the arena was full, or not there
        self._leased = 0  # blocks handed out (returned ones are subtracted when drained)
        # The smallest block (VMM: the allocation granularity, ~2 MiB, so small buffers share
        # one size class); None until the first CUDA allocation judged it.
        self._floor: int | None = 0 if device.is_cpu else None

    # -- allocation ----------------------------------------------------------------------------
    def acquire(self, nbytes: int, rearmable: bool = False) -> Lease:
        """A block of at least ``nbytes``, leased (:class:`warp_buffer.lease.Lease`): free
        blocks first, whose export :meth:`Block.try_reclaim` retires; ``rearmable``: the lease
        may be re-armed after its publish (a loan), so its readers hold tokens."""
        capacity = size_class(nbytes)
        floor = self._floor
        if floor is None:
            floor = self._floor = _block_floor(self.device)
        if capacity < floor:
            capacity = floor
        with self._lock:
            drained = self._drain()
            block = self._take_free(capacity)
            if block is not None:
                self.reused += 1
            self._leased += 1
        if block is None:
            try:
                try:
                    block = self._create(capacity)
                except cuda.DeviceMemoryError:
                    # The device is full: give back what this pool keeps idle, try once more.
                    if not self.trim(0.0):
                        raise
                    block = self._create(capacity)
            except BaseException:
                with self._lock:
                    self._leased -= 1
                raise
            with self._lock:
                self.created += 1
        _janitor.ensure_running()
        if drained:  # free memory grew since the last allocation: hold it to the cap
            self._enforce_idle_cap()
        return Lease(self, block, self.device, rearmable)

    def _take_free(self, capacity: int) -> Block | None:
        queue = self._free.get(capacity)
        if not queue:
            return None
        for _ in range(min(PROBES, len(queue))):
            entry = queue.popleft()
            if entry[0].try_reclaim():
                self.free_bytes -= capacity
                return entry[0]
            queue.append(entry)  # busy: try the others first next time
        arena = queue[0][0].arena
        if arena is not None:
            arena.forget_dead_peers()  # a dead peer's pending deliveries pin nothing
        return None

    def _create(self, capacity: int) -> Block:
        if self.device.is_cpu:
            shared = not ipc_disabled()
            block = HostBlock(capacity, shared=shared)
            if shared and not block.shared:
                with self._lock:
                    self.private += 1
            return block
        return cuda_block(self.device, capacity)

    def _give_back(self, block: Block) -> None:
        # Runs from a finalizer (the lease's): no locks, no threads, nothing that can block.
        if not self._defunct and not sys.is_finalizing():
            self._returned.append((block, time.monotonic()))

    def _drain(self) -> int:
        """Move returned blocks onto the free lists (call with the lock held); returns how
        many."""
        moved = 0
        while True:
            try:
                block, released = self._returned.popleft()
            except IndexError:
                return moved
            moved += 1
            self._leased -= 1
            self._free.setdefault(block.capacity, collections.deque()).append((block, released))
            self.free_bytes += block.capacity

    def _enforce_idle_cap(self) -> None:
        """Free blocks beyond the cap go back, oldest first, at most :data:`PROBES` probed per
        allocation: blocks a reader still holds sit on the free lists too (their lease ended
        here), and probing them all at every allocation made publishing slow (each probe walks
        the arena's lock list, as long as the readers' holds). A held one goes to the back."""
        cap = int(env_float("WARP_BUFFER_POOL_MAX_IDLE_BYTES", 1 << 30))
        if self.free_bytes <= cap:
            return
        victims: list[Block] = []
        with self._lock:
            for _ in range(PROBES):
                if self.free_bytes <= cap:
                    break
                heads = [queue for queue in self._free.values() if queue]
                if not heads:
                    break
                queue = min(heads, key=lambda q: q[0][1])  # the oldest free block
                block, _ = queue.popleft()
                if block.try_reclaim():
                    self.free_bytes -= block.capacity
                    self.destroyed += 1
                    victims.append(block)
                else:  # held: idle from now at the earliest
                    queue.append((block, time.monotonic()))
        for block in victims:
            block.destroy()

    # -- giving memory back ---------------------------------------------------------------------
    def trim(self, idle_s: float = 0.0) -> int:
        """Destroy free blocks idle for ``idle_s`` seconds or more (all with 0). Blocks a reader
        still holds are kept, and so are exported blocks whose descriptors are still on their way
        to a live peer. Returns the bytes given back."""
        now = time.monotonic()
        arena = _arena.existing_arena()
        if arena is not None:
            arena.forget_dead_peers()  # what a dead peer never imported pins nothing
        victims: list[Block] = []
        with self._lock:
            self._drain()
            idle = [(block, released) for queue in self._free.values()
                    for block, released in queue if now - released >= idle_s]
            for block, released in idle:
                if block.try_reclaim():
                    self._free[block.capacity].remove((block, released))
                    self.free_bytes -= block.capacity
                    victims.append(block)
            self.destroyed += len(victims)
        freed = 0
        for block in victims:
            freed += block.capacity
            block.destroy()
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
                "private": self.private,
                "leased": self._leased,
                "free_blocks": sum(len(q) for q in self._free.values()),
                "free_bytes": self.free_bytes,
            }

    def close(self) -> None:
        """Destroy every free block no reader holds now (leased ones are left to their
        buffers, held ones to their readers)."""
        with self._lock:
            self._drain()
            blocks = []
            for queue in self._free.values():
                for entry in list(queue):
                    if entry[0].try_reclaim():
                        queue.remove(entry)
                        blocks.append(entry[0])
                        self.free_bytes -= entry[0].capacity
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
            idle = max(0.0, env_float("WARP_BUFFER_POOL_IDLE_S", 10.0))
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
    """Counters of every pool, by device: created, reused, destroyed, leased, free blocks/bytes,
    and ``private``: blocks made in private memory because the arena was full or could not be
    made (their buffers reach other processes as CPU bytes)."""
    with _pools_lock:
        pools = dict(_pools)
    return {name: pool.stats() for name, pool in pools.items()}


def trim_pools(idle_s: float = 0.0) -> int:
    """Give back the free blocks of every pool idle for ``idle_s`` seconds (all with 0); see
    :meth:`BlockPool.trim`. Returns the bytes given back."""
    with _pools_lock:
        pools = list(_pools.values())
    return sum(pool.trim(idle_s=idle_s) for pool in pools)


def shutdown() -> None:
    """Free every idle block now (buffers still alive keep theirs; peers holding blocks keep
    their mappings). The arena itself goes with the process: nothing is left to remove."""
    with _pools_lock:
        pools = list(_pools.values())
    for pool in pools:
        pool.close()


def _at_exit() -> None:
    """A clean exit: let peers that were sent descriptors but never attached fetch the arena
    (bounded by ``WARP_BUFFER_EXIT_LINGER_S``), then stop serving it."""
    arena = _arena.existing_arena()
    if arena is None or arena.server is None:
        return
    try:
        pids = arena.pending_pids()
        if pids:
            arena.server.linger(pids, handoff.linger_s())
    finally:
        arena.server.close()


atexit.register(_at_exit)


def _after_fork_in_child() -> None:
    global _pools_lock, _janitor
    for pool in _pools.values():
        pool._defunct = True  # blocks inherited from the parent are not ours to recycle
    _pools.clear()
    _pools_lock = threading.Lock()
    _janitor = _Janitor()


os.register_at_fork(after_in_child=_after_fork_in_child)
