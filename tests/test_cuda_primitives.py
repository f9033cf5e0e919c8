"""The plumbing of warp_buffer.cuda that runs without a GPU: the import cache, the reuse
bookkeeping and the deferred releases (with fake events and streams), device lookup by UUID,
the typed errors of the checked opens, and the VMM structures against cuda.h.

The CUDA behaviour itself is in tests/test_cuda_ipc.py (cuda-marked)."""

from __future__ import annotations

import gc
import os
import shutil
import subprocess
import threading
import time
from types import SimpleNamespace

import pytest
import warp as wp

from warp_buffer import cuda
from warp_buffer.errors import (
    DescriptorError,
    ExportUnavailableError,
    StaleBufferError,
    WarpBufferError,
)


# --------------------------------------------------------------------------- fakes
class FakeEvent:
    def __init__(self, device: object = None) -> None:
        self.device = device
        self.is_complete = True
        self.records = 0


class FakeStream:
    def __init__(self, handle: int, device: object = "dev") -> None:
        self.cuda_stream = handle
        self.device = device
        self.waited: list[FakeEvent] = []
        self.recorded: list[FakeEvent] = []

    def record_event(self, event: FakeEvent | None = None) -> FakeEvent:
        event = event or FakeEvent(self.device)
        self.recorded.append(event)
        event.records += 1
        event.is_complete = False  # recorded work is pending until the test completes it
        return event

    def wait_event(self, event: FakeEvent) -> None:
        self.waited.append(event)


class Mapping:
    """Stands for an opened wp.array (weak-referenceable)."""

    def __init__(self, handle: bytes) -> None:
        self.handle = handle


def _handle(n: int) -> bytes:
    return bytes([n]) * cuda.IPC_HANDLE_SIZE


def _cache(**kw: object) -> tuple[cuda.ImportCache, list[bytes]]:
    opened: list[bytes] = []

    def open_memory(handle: bytes, nbytes: int, device: object) -> Mapping:
        opened.append(handle)
        return Mapping(handle)

    def open_event(handle: bytes, device: object) -> Mapping:
        opened.append(handle)
        return Mapping(handle)

    return cuda.ImportCache(open_memory, open_event, **kw), opened


# --------------------------------------------------------------------------- import cache
def test_import_cache_opens_each_block_once() -> None:
    cache, opened = _cache()
    a = cache.memory(7, 1, _handle(1), 4096, None)
    assert cache.memory(7, 1, _handle(1), 4096, None) is a
    b = cache.memory(7, 2, _handle(2), 4096, None)
    other_session = cache.memory(8, 1, _handle(1), 4096, None)
    assert b is not a and other_session is not a
    event = cache.event(7, 1, _handle(9), None)
    assert cache.event(7, 1, _handle(9), None) is event
    assert opened == [_handle(1), _handle(2), _handle(1), _handle(9)]
    assert cache.opens == 4 and len(cache) == 4


def test_import_cache_reopens_when_the_block_has_a_new_handle() -> None:
    cache, opened = _cache()
    first = cache.memory(7, 1, _handle(1), 4096, None)
    second = cache.memory(7, 1, _handle(3), 4096, None)  # the publisher re-made block 1
    assert second is not first and second.handle == _handle(3)
    assert opened == [_handle(1), _handle(3)]


def test_import_cache_evicts_lru_but_never_reopens_a_live_mapping() -> None:
    cache, opened = _cache(max_entries=2)
    held = cache.memory(1, 1, _handle(1), 4096, None)
    cache.memory(1, 2, _handle(2), 4096, None)
    cache.memory(1, 3, _handle(3), 4096, None)  # evicts block 1 from the strong entries
    assert len(cache) == 2
    assert cache.memory(1, 1, _handle(1), 4096, None) is held  # still viewed: no second open
    assert opened == [_handle(1), _handle(2), _handle(3)]
    cache.drop(1)
    del held
    gc.collect()
    cache.memory(1, 1, _handle(1), 4096, None)  # gone everywhere: opened again
    assert opened[-1] == _handle(1) and len(opened) == 4


def test_import_cache_failed_open_is_not_cached() -> None:
    calls = []

    def failing(handle: bytes, nbytes: int, device: object) -> Mapping:
        calls.append(handle)
        if len(calls) == 1:
            raise StaleBufferError("exporter gone")
        return Mapping(handle)

    cache = cuda.ImportCache(failing, lambda h, d: Mapping(h))
    with pytest.raises(StaleBufferError):
        cache.memory(1, 1, _handle(1), 4096, None)
    assert len(cache) == 0
    assert cache.memory(1, 1, _handle(1), 4096, None).handle == _handle(1)
    assert len(calls) == 2


def test_import_cache_drop_by_session_and_block() -> None:
    cache, _ = _cache()
    keep = [cache.memory(1, b, _handle(b), 4096, None) for b in (1, 2, 3)]
    keep.append(cache.memory(2, 1, _handle(1), 4096, None))
    assert cache.drop(1, 2) == 1
    assert cache.drop(1) == 2
    assert len(cache) == 1
    cache.clear()
    assert len(cache) == 0


def test_import_cache_is_thread_safe_one_open_per_key() -> None:
    cache, opened = _cache()
    results: list[object] = []

    def worker() -> None:
        for _ in range(200):
            results.append(cache.memory(5, 5, _handle(5), 4096, None))

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(opened) == 1 and len({id(r) for r in results}) == 1


# --------------------------------------------------------------------------- reuse ordering
def test_block_uses_one_event_per_stream_and_ready_only_when_all_complete() -> None:
    uses = cuda.BlockUses(event_factory=FakeEvent)
    a, b = FakeStream(11), FakeStream(12)
    assert uses.ready_for_reuse()  # never used
    uses.record_use(a)
    uses.record_use(a)  # re-records the same event: later work on a supersedes
    uses.record_use(b)
    assert uses.pending == 2
    assert not uses.ready_for_reuse()
    events = list(uses._events.values())
    assert events[0].records == 2 and events[1].records == 1
    events[0].is_complete = True
    assert not uses.ready_for_reuse() and uses.pending == 1
    events[1].is_complete = True
    assert uses.ready_for_reuse() and uses.pending == 0


def test_block_uses_order_after_waits_on_every_pending_use() -> None:
    uses = cuda.BlockUses(event_factory=FakeEvent)
    uses.record_use(FakeStream(1))
    uses.record_use(FakeStream(2))
    writer = FakeStream(3)
    uses.order_after(writer)
    assert len(writer.waited) == 2
    uses.record_use(None)  # cpu: nothing to order
    assert uses.pending == 2


def test_record_use_and_ready_for_reuse_on_a_block_object() -> None:
    block = SimpleNamespace()
    assert cuda.ready_for_reuse(block)
    block.cuda_uses = cuda.BlockUses(event_factory=FakeEvent)
    cuda.record_use(block, FakeStream(4))
    assert not cuda.ready_for_reuse(block)
    next(iter(block.cuda_uses._events.values())).is_complete = True
    assert cuda.ready_for_reuse(block)


# --------------------------------------------------------------------------- deferred release
def test_release_queue_runs_callbacks_only_after_their_event() -> None:
    queue = cuda.ReleaseQueue(poll_s=0.001)
    ran: list[str] = []
    done = FakeEvent()
    queue.defer(done, lambda: ran.append("now"))
    assert ran == ["now"]  # already complete: no deferral
    pending = FakeEvent()
    pending.is_complete = False
    queue.defer(pending, lambda: ran.append("later"))
    time.sleep(0.02)
    assert ran == ["now"] and len(queue) == 1
    pending.is_complete = True
    assert queue.flush(timeout=2.0)
    assert ran == ["now", "later"] and len(queue) == 0


def test_release_queue_flush_times_out_and_survives_a_failing_callback() -> None:
    queue = cuda.ReleaseQueue(poll_s=0.001)
    stuck = FakeEvent()
    stuck.is_complete = False
    queue.defer(stuck, lambda: None)
    assert not queue.flush(timeout=0.05)
    ok = []
    bad = FakeEvent()
    bad.is_complete = False
    queue.defer(bad, lambda: 1 / 0)
    good = FakeEvent()
    good.is_complete = False
    queue.defer(good, lambda: ok.append(1))
    bad.is_complete = good.is_complete = True
    stuck.is_complete = True
    assert queue.flush(timeout=2.0)
    assert ok == [1]


def test_release_after_records_on_the_readers_stream() -> None:
    queue = cuda.ReleaseQueue(poll_s=0.001)
    ran = []
    cuda.release_after(None, lambda: ran.append("cpu"), queue)
    assert ran == ["cpu"]
    stream = FakeStream(21)
    cuda.release_after(stream, lambda: ran.append("gpu"), queue)
    assert ran == ["cpu"] and len(queue) == 1
    stream.recorded[-1].is_complete = True
    assert queue.flush(2.0) and ran == ["cpu", "gpu"]


def test_flush_releases_waits_for_the_module_queue() -> None:
    ran = []
    stream = FakeStream(22)
    cuda.release_after(stream, lambda: ran.append(1))
    assert cuda.flush_releases(timeout=0.05) is False and ran == []
    stream.recorded[-1].is_complete = True
    assert cuda.flush_releases(timeout=2.0) and ran == [1]


# --------------------------------------------------------------------------- device identity
def test_find_device_matches_uuid_not_pci_bus_id() -> None:
    # Two MIG instances of one GPU: same PCI bus id, different UUIDs.
    mig_a = SimpleNamespace(uuid="MIG-aaaa", pci_bus_id="00000000:41:00", alias="cuda:0")
    mig_b = SimpleNamespace(uuid="MIG-bbbb", pci_bus_id="00000000:41:00", alias="cuda:1")
    assert cuda.find_device("MIG-bbbb", [mig_a, mig_b]) is mig_b
    assert cuda.find_device("MIG-aaaa", [mig_a, mig_b]) is mig_a
    with pytest.raises(ExportUnavailableError):
        cuda.find_device("GPU-cccc", [mig_a, mig_b])
    with pytest.raises(DescriptorError):
        cuda.find_device("", [mig_a])


# --------------------------------------------------------------------------- typed errors
@pytest.mark.parametrize("handle", [b"", b"\x01" * 63, bytes(64), "x" * 64])
def test_checked_opens_reject_malformed_handles(handle: object) -> None:
    with pytest.raises(DescriptorError):
        cuda.open_ipc_memory(handle, 4096, "cpu")  # type: ignore[arg-type]
    with pytest.raises(DescriptorError):
        cuda.open_ipc_event(handle, "cpu")  # type: ignore[arg-type]


def test_cuda_calls_on_the_cpu_device_raise_typed_errors() -> None:
    with pytest.raises(ExportUnavailableError):
        cuda.open_ipc_memory(_handle(1), 4096, "cpu")
    with pytest.raises(ExportUnavailableError):
        cuda.open_ipc_event(_handle(1), "cpu")
    with pytest.raises(ExportUnavailableError):
        cuda.alloc_ipc_memory("cpu", 4096)
    with pytest.raises(ExportUnavailableError):
        cuda.ipc_mem_handle(wp.zeros(16, dtype=wp.uint8, device="cpu"))
    with pytest.raises(ExportUnavailableError):
        cuda.capabilities("cpu")
    with pytest.raises(ExportUnavailableError):
        cuda.new_ipc_event("cpu")
    assert not cuda.is_ipc_allocation(wp.zeros(16, dtype=wp.uint8, device="cpu"))
    assert cuda.vmm_supported("cpu") is False
    assert issubclass(cuda.DeviceMemoryError, (WarpBufferError, MemoryError))
    assert issubclass(cuda.CudaDriverError, ExportUnavailableError)


def test_stage_to_host_needs_a_cuda_source() -> None:
    host = wp.zeros(16, dtype=wp.uint8, device="cpu")
    with pytest.raises(ValueError):
        cuda.stage_to_host(host, host)


def test_dlpack_no_sync_stream() -> None:
    assert cuda.stream_from_dlpack(-1, "cpu") is None
    with pytest.raises((ValueError, ExportUnavailableError)):
        cuda.stream_from_dlpack(-5, "cpu")


def test_torch_current_stream_is_none_without_torch_cuda() -> None:
    # No CUDA here: torch has not initialised it, so torch has written nothing on a GPU.
    assert cuda.torch_current_stream("cpu") is None


@pytest.mark.skipif(os.path.exists("/dev/nvidia0") or shutil.which("nvidia-smi") is not None,
                    reason="a CUDA driver may be present")
def test_no_driver_is_a_typed_error() -> None:
    try:
        import ctypes

        ctypes.CDLL("libcuda.so.1")
    except OSError:
        pass
    else:  # pragma: no cover - a driver without a device
        pytest.skip("libcuda.so.1 is present")
    with pytest.raises(cuda.CudaDriverError):
        cuda.vmm_granularity  # noqa: B018 - attribute exists
        cuda._driver()
    with pytest.raises(cuda.CudaDriverError):
        cuda.register_host_memory(0x1000, 4096)


# --------------------------------------------------------------------------- VMM structures
def test_vmm_structures_match_the_cuda_header_layout() -> None:
    import ctypes

    prop = cuda._MemAllocationProp
    assert ctypes.sizeof(prop) == 32
    assert prop.location.offset == 8
    assert prop.win32HandleMetaData.offset == 16
    assert prop.allocFlags.offset == 24
    assert ctypes.sizeof(cuda._MemAccessDesc) == 12
    assert cuda._MemAccessDesc.flags.offset == 8


_HEADER_DIRS = ["/usr/local/cuda/include", "/usr/local/cuda-13.0/include",
                "/usr/local/cuda-12/include"]


@pytest.mark.skipif(shutil.which("gcc") is None or not any(
    os.path.exists(os.path.join(d, "cuda.h")) for d in _HEADER_DIRS),
    reason="needs gcc and the CUDA headers")
def test_vmm_constants_and_layout_against_cuda_h(tmp_path: object) -> None:
    import ctypes

    include = next(d for d in _HEADER_DIRS if os.path.exists(os.path.join(d, "cuda.h")))
    source = tmp_path / "layout.c"  # type: ignore[operator]
    source.write_text(r"""
#include <stdio.h>
#include <stddef.h>
#include <cuda.h>
int main(void) {
  printf("%zu %zu %zu %zu %zu %zu\n", sizeof(CUmemAllocationProp),
         offsetof(CUmemAllocationProp, location),
         offsetof(CUmemAllocationProp, win32HandleMetaData),
         offsetof(CUmemAllocationProp, allocFlags), sizeof(CUmemAccessDesc),
         offsetof(CUmemAccessDesc, flags));
  printf("%d %d %d %d %d %d %d %d %d\n", CU_MEM_ALLOCATION_TYPE_PINNED,
         CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR, CU_MEM_LOCATION_TYPE_DEVICE,
         CU_MEM_ACCESS_FLAGS_PROT_READ, CU_MEM_ACCESS_FLAGS_PROT_READWRITE,
         CU_DEVICE_ATTRIBUTE_VIRTUAL_MEMORY_MANAGEMENT_SUPPORTED,
         CU_DEVICE_ATTRIBUTE_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR_SUPPORTED,
         CU_MEMHOSTREGISTER_PORTABLE, CU_IPC_HANDLE_SIZE);
  return 0;
}
""")
    exe = tmp_path / "layout"  # type: ignore[operator]
    subprocess.run(["gcc", f"-I{include}", str(source), "-o", str(exe)], check=True,
                   capture_output=True, timeout=60)
    sizes, constants = subprocess.run([str(exe)], check=True, capture_output=True, text=True,
                                      timeout=10).stdout.splitlines()
    assert [int(x) for x in sizes.split()] == [
        ctypes.sizeof(cuda._MemAllocationProp), cuda._MemAllocationProp.location.offset,
        cuda._MemAllocationProp.win32HandleMetaData.offset,
        cuda._MemAllocationProp.allocFlags.offset, ctypes.sizeof(cuda._MemAccessDesc),
        cuda._MemAccessDesc.flags.offset]
    assert [int(x) for x in constants.split()] == [
        cuda._CU_MEM_ALLOCATION_TYPE_PINNED, cuda._CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR,
        cuda._CU_MEM_LOCATION_TYPE_DEVICE, cuda._CU_MEM_ACCESS_FLAGS_PROT_READ,
        cuda._CU_MEM_ACCESS_FLAGS_PROT_READWRITE,
        cuda._CU_DEVICE_ATTRIBUTE_VIRTUAL_MEMORY_MANAGEMENT_SUPPORTED,
        cuda._CU_DEVICE_ATTRIBUTE_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR_SUPPORTED,
        cuda._CU_MEMHOSTREGISTER_PORTABLE, cuda.IPC_HANDLE_SIZE]
