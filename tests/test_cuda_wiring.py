"""The bookkeeping of the CUDA wiring, on the cpu device with fake events and streams.

What runs here (no GPU): a CUDA block is neither reused nor freed while a fake reader's last-use
event is incomplete (pool acquisition, trim, close); an imported CUDA buffer's hold is dropped
only once its release event completed, after the reads recorded on it; the export falls back to
staging when CUDA IPC cannot export the memory; devices are found by UUID (two MIG instances
sharing a PCI bus id stay apart); a session that ends is forgotten by the import cache; a cpu
clone is private memory that moves into the arena on its first export, readable by an import.
The same paths on a GPU are in tests/test_cuda_ipc.py (cuda-marked).
"""

from __future__ import annotations

import gc
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from tests.test_cuda_primitives import FakeEvent, FakeStream, Mapping
from warp_buffer import allocate_buffer, attach, cuda, from_output_buffer, ipc, to_buffer
from warp_buffer import descriptor as desc
from warp_buffer.buffer_impl import WarpBufferImpl
from warp_buffer.errors import ExportUnavailableError
from warp_buffer.pool import BlockPool, CudaBlock, MIN_BLOCK


class FakeDevice:
    is_cpu = False
    is_cuda = True
    alias = "cuda:9"
    is_ipc_supported = True

    def __init__(self, uuid: str = "GPU-fake", pci: str = "00000000:41:00") -> None:
        self.uuid = uuid
        self.pci_bus_id = pci


def _fake_block(device: FakeDevice, destroyed: list[Any]) -> CudaBlock:
    """A CudaBlock without device memory (its allocation is the only CUDA call of __init__)."""
    block = CudaBlock.__new__(CudaBlock)
    super(CudaBlock, block).__init__()
    block.device, block.capacity, block.shared = device, MIN_BLOCK, True
    block.cuda_uses = cuda.BlockUses(event_factory=FakeEvent)
    block.destroy = lambda: destroyed.append(block)  # type: ignore[method-assign]
    return block


def test_a_cuda_block_is_not_reused_or_freed_while_a_reader_event_is_pending() -> None:
    device, destroyed = FakeDevice(), []
    pool = BlockPool(device)
    block = _fake_block(device, destroyed)
    reader = FakeStream(7, device)
    cuda.record_use(block, reader)  # a read handle released on stream 7, its kernel still runs
    pending = reader.recorded[-1]
    pool._give_back(block)
    with pool._lock:
        pool._drain()
        assert pool._take_free(MIN_BLOCK) is None  # not handed out again
    assert pool.trim(0.0) == 0 and destroyed == []  # not freed by the janitor's trim
    pool.close()
    assert destroyed == []  # nor by close: a reader may still use it
    pending.is_complete = True  # the reader's work finished
    with pool._lock:
        assert pool._take_free(MIN_BLOCK) is block
    pool._give_back(block)
    pool.close()
    assert destroyed == [block]


def test_a_block_waits_for_every_readers_stream() -> None:
    device, destroyed = FakeDevice(), []
    block = _fake_block(device, destroyed)
    a, b = FakeStream(1, device), FakeStream(2, device)
    cuda.record_use(block, a)
    cuda.record_use(block, b)
    a.recorded[-1].is_complete = True
    assert not block.try_reclaim()  # b still reads
    b.recorded[-1].is_complete = True
    assert block.try_reclaim()


def test_an_imported_cuda_hold_drops_only_after_its_release_event(monkeypatch) -> None:
    device = FakeDevice()
    stream = FakeStream(5, device)
    queue = cuda.ReleaseQueue(poll_s=0.001)
    monkeypatch.setattr(cuda, "write_stream", lambda dev, s=None: stream)
    monkeypatch.setattr(cuda, "_release_queue", queue)
    released: list[bool] = []
    hold = SimpleNamespace(live=True, release=lambda: released.append(True))
    impl = WarpBufferImpl.__new__(WarpBufferImpl)
    reader = FakeStream(6, device)
    impl.cuda_uses = cuda.BlockUses(event_factory=FakeEvent)
    cuda.record_use(impl, reader)  # a read handle's last use on another stream
    keep = ipc._CudaHold(impl, hold, SimpleNamespace(device=device), FakeEvent(device))
    keep.release()
    assert reader.recorded[-1] in stream.waited  # the release is ordered after the read
    assert released == []  # its event is pending: the publisher may not reuse the block yet
    assert not queue.flush(timeout=0.05)
    stream.recorded[-1].is_complete = True
    assert queue.flush(timeout=5)
    assert released == [True]
    keep.release()  # idempotent (deleter and release() both call it)
    assert released == [True]


def _cuda_like_impl(block: Any, device: FakeDevice) -> WarpBufferImpl:
    impl = WarpBufferImpl(None, device, block=block, ptr=1, size=100)
    impl.write_event = FakeEvent(device)  # the write was recorded
    return impl


def test_export_falls_back_to_staging_when_cuda_ipc_cannot_export(monkeypatch) -> None:
    """A user-set allocator or a mempool gives memory CUDA IPC refuses: publish() stages it."""
    device = FakeDevice()
    block = _fake_block(device, [])

    def refuse() -> bytes:
        raise ExportUnavailableError("not a whole default-allocator allocation")

    block.ipc_mem_handle = refuse  # type: ignore[method-assign]
    staged = []

    def stage(impl: WarpBufferImpl) -> WarpBufferImpl:
        staging = WarpBufferImpl.allocate(impl.size(), "cpu")
        staged.append(staging)
        return staging

    monkeypatch.setattr(ipc, "_stage", stage)
    impl = _cuda_like_impl(block, device)
    described = ipc._export_local(impl, None, frozenset({device.uuid}), None)
    assert described.kind == desc.KIND_CUDA_STAGING
    assert described.device_uuid == desc.uuid_word(device.uuid)
    assert len(staged) == 1 and impl.staging is staged[0]
    # Asked for CUDA IPC explicitly, the refusal is the caller's to see.
    with pytest.raises(ExportUnavailableError):
        ipc._export_local(_cuda_like_impl(block, device), desc.KIND_CUDA_IPC, frozenset(), None)


def test_cuda_ipc_only_for_a_peer_with_the_same_device_uuid(monkeypatch) -> None:
    device = FakeDevice(uuid="MIG-a")
    block = _fake_block(device, [])
    staged = []
    monkeypatch.setattr(ipc, "_stage", lambda impl: staged.append(impl) or
                        WarpBufferImpl.allocate(impl.size(), "cpu"))
    # Same PCI bus id, another MIG instance: the peer cannot open our handle.
    ipc._export_local(_cuda_like_impl(block, device), None, frozenset({"MIG-b"}), None)
    assert len(staged) == 1


def test_the_importer_finds_its_device_by_uuid_not_pci_bus_id(monkeypatch) -> None:
    a, b = FakeDevice("MIG-a"), FakeDevice("MIG-b")  # one GPU's two MIG instances: same PCI id
    monkeypatch.setattr(ipc, "_devices_by_word", None)
    monkeypatch.setattr(ipc.wp, "get_cuda_devices", lambda: [a, b])
    assert ipc._cuda_device(desc.uuid_word("MIG-b")) is b
    assert ipc._cuda_device(desc.uuid_word("MIG-a")) is a
    with pytest.raises(ExportUnavailableError):
        ipc._cuda_device(desc.uuid_word("GPU-elsewhere"))


def test_a_session_that_ends_is_dropped_from_the_cuda_import_cache(monkeypatch) -> None:
    key = (2**22 - 3, 0xFEED)  # a pid above any live one: its owner is gone
    monkeypatch.setitem(attach._sessions, key,
                        SimpleNamespace(held=0, owner_pid=key[0], close=lambda: None))
    opened = Mapping(b"h" * 64)  # stands for an opened wp.array (weak-referenceable)
    ipc._cuda_imports._get("memory", (key, 4096), b"h" * 64, lambda: opened)
    assert ipc._cuda_imports.drop(key, 4096) == 1  # it was cached under (session, block)
    ipc._cuda_imports._get("memory", (key, 4096), b"h" * 64, lambda: opened)
    attach.forget_idle()
    assert key not in attach._sessions
    assert ipc._cuda_imports.drop(key) == 0  # the session's entries went with it


# ------------------------------------------------------------------------------ cpu clones
def _written(nbytes: int) -> Any:
    buffer = allocate_buffer(nbytes, "cpu")
    with from_output_buffer(buffer) as out:
        to_buffer((np.arange(nbytes) % 251).astype(np.uint8), out)
    return buffer


def test_a_cpu_clone_takes_no_pool_block_and_moves_into_the_arena_on_export() -> None:
    source = _written(10_000)
    clone = source.get_impl().clone()
    assert clone.block is None and clone.is_exportable  # private memory, exportable
    view = clone.array  # an array made before the move keeps reading the same bytes
    descriptor = ipc.export_buffer(clone)
    assert descriptor.kind == desc.KIND_HOST and clone.block is not None
    assert clone.block.shared and clone.array.ptr == clone.block.data_ptr
    expected = (np.arange(10_000) % 251).astype(np.uint8)
    np.testing.assert_array_equal(view.numpy(), expected)
    imported = ipc.import_buffer(descriptor)
    try:
        np.testing.assert_array_equal(imported.to_cpu().view(), expected)
    finally:
        imported.release()
    again = ipc.export_buffer(clone)  # later exports describe the same block: no more copies
    assert again.offset == descriptor.offset


def test_a_cpu_clone_is_writable_once_and_independent() -> None:
    source = _written(5000)
    clone = source.get_impl().clone()
    from rosidl_buffer import Buffer

    wrapped = Buffer(clone)
    with from_output_buffer(wrapped) as out:
        out.array.fill_(7)
    assert int(source.to_numpy()[0]) == 0 and int(wrapped.to_numpy().max()) == 7
    gc.collect()


def test_a_cpu_clone_without_ipc_falls_back_to_cpu_bytes(monkeypatch) -> None:
    source = _written(4096)
    monkeypatch.setenv("WARP_BUFFER_DISABLE_IPC", "1")
    clone = source.get_impl().clone()
    assert not clone.is_exportable
    with pytest.raises(ExportUnavailableError):
        ipc.export_buffer(clone)
    np.testing.assert_array_equal(clone.to_cpu().view(), source.to_numpy())
