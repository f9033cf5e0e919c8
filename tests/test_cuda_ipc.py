"""CUDA defects of issue 14, one test (or more) each; they need a GPU and skip cleanly without.

1. failed IPC opens detected (forged handles, exporter gone): StaleBufferError, no fresh memory;
2. stream-ordered reuse: last-use events per block, deferred release, the public reuse hazard;
3. write completion on the stream that ran the write (torch's current stream, DLPack streams);
4. no device-wide synchronisation (staging returns an event; tensor_conversions doesn't sync);
5. exporter-independent lifetime and read-only imports (VMM, also through the pool and the
   session's hand-off socket; the legacy fallback), devices by UUID, allocation that ignores the
   mempool flip and user allocators, pinned staging, the import cache on real handles, a gone
   session's cached imports dropped at once.

Written against :mod:`warp_buffer.cuda`, the public API and the wired core (pool, ipc,
buffer_impl, api; their cpu bookkeeping is in tests/test_cuda_wiring.py); nothing here has run on
a GPU in the sessions that wrote it (none was lent). The public-API tests (reuse hazard, to_buffer
under a torch stream, publish with a user allocator, tensor_conversions without device syncs)
pass by construction of the wiring, not by a GPU run.
"""

from __future__ import annotations

import gc
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Iterator

import numpy as np
import pytest

pytestmark = pytest.mark.cuda

wp = pytest.importorskip("warp")

import warp_buffer  # noqa: E402
from tests._cuda_child import NBYTES, pattern  # noqa: E402
from warp_buffer import cuda  # noqa: E402
from warp_buffer.errors import ExportUnavailableError, StaleBufferError  # noqa: E402

DEVICE = "cuda:0"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def kernels() -> dict:
    """slow_fill(out, value, spins) and slow_copy(dst, src, spins): the GPU check's kernels."""
    from benchmarks import gpu_check

    return gpu_check.kernels()


@pytest.fixture(scope="module")
def spins(kernels: dict) -> int:
    """Spins that make a slow kernel over NBYTES take ~50 ms here: long enough to race."""
    from benchmarks import gpu_check

    return gpu_check.spins_for(DEVICE, NBYTES, target_ms=50)


def _child(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "tests._cuda_child", *args], cwd=ROOT,
                            env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


@pytest.fixture
def exporter() -> Iterator[tuple[subprocess.Popen, dict]]:
    proc = _child("export")
    try:
        handles = json.loads(proc.stdout.readline())
        yield proc, {k: bytes.fromhex(v) for k, v in handles.items()}
    finally:
        if proc.poll() is None:
            proc.stdin.write("stop\n")
            proc.stdin.flush()
        proc.wait(timeout=60)


# --------------------------------------------------------------------------- 1. checked opens
def test_forged_memory_handle_raises_stale_not_fresh_memory() -> None:
    with pytest.raises(StaleBufferError):
        cuda.open_ipc_memory(os.urandom(cuda.IPC_HANDLE_SIZE), 4096, DEVICE)


def test_forged_event_handle_raises_stale_not_a_new_event() -> None:
    with pytest.raises(StaleBufferError):
        cuda.open_ipc_event(os.urandom(cuda.IPC_HANDLE_SIZE), DEVICE)


def test_import_from_a_live_exporter_reads_its_bytes(exporter: tuple) -> None:
    _proc, handles = exporter
    memory = cuda.open_ipc_memory(handles["mem"], NBYTES, DEVICE)
    event = cuda.open_ipc_event(handles["event"], DEVICE)
    stream = wp.Stream(DEVICE)
    stream.wait_event(event)
    host = wp.empty(NBYTES, dtype=wp.uint8, device="cpu", pinned=True)
    wp.copy(host, memory, stream=stream)
    wp.synchronize_stream(stream)
    assert zlib.crc32(host.numpy().tobytes()) == zlib.crc32(pattern().tobytes())


def test_import_after_the_exporter_exited_raises_stale(exporter: tuple) -> None:
    proc, handles = exporter
    proc.stdin.write("stop\n")
    proc.stdin.flush()
    proc.wait(timeout=60)
    with pytest.raises(StaleBufferError):
        cuda.open_ipc_memory(handles["mem"], NBYTES, DEVICE)


def test_import_cache_opens_a_real_handle_once_and_reopens_after_drop(exporter: tuple) -> None:
    _proc, handles = exporter
    cache = cuda.ImportCache()
    first = cache.memory(1, 1, handles["mem"], NBYTES, DEVICE)
    again = cache.memory(1, 1, handles["mem"], NBYTES, DEVICE)  # import twice
    event = cache.event(1, 1, handles["event"], DEVICE)
    assert again is first and cache.event(1, 1, handles["event"], DEVICE) is event
    assert cache.opens == 2
    view = wp.array(ptr=first.ptr, dtype=wp.uint8, shape=(16,), device=DEVICE)
    del view
    cache.drop(1)
    del first, again
    gc.collect()  # closed (cuIpcCloseMemHandle): a re-import opens it again
    reopened = cache.memory(1, 1, handles["mem"], NBYTES, DEVICE)
    assert cache.opens == 3
    assert zlib.crc32(reopened.numpy().tobytes()) == zlib.crc32(pattern().tobytes())


# --------------------------------------------------------------------------- 2. reuse ordering
def test_block_uses_ready_only_after_the_readers_kernel(kernels: dict, spins: int) -> None:
    device = wp.get_device(DEVICE)
    src = wp.zeros(NBYTES, dtype=wp.uint8, device=device)
    dst = wp.zeros(NBYTES, dtype=wp.uint8, device=device)
    reader = wp.Stream(device)
    wp.launch(kernels["slow_copy"], dim=NBYTES, inputs=[dst, src, spins], device=device,
              stream=reader)
    uses = cuda.BlockUses()
    uses.record_use(reader)
    assert not uses.ready_for_reuse()
    wp.synchronize_stream(reader)
    assert uses.ready_for_reuse()


def test_order_after_keeps_a_slow_reader_from_seeing_the_next_write(kernels: dict,
                                                                   spins: int) -> None:
    device = wp.get_device(DEVICE)
    block = wp.full(NBYTES, 1, dtype=wp.uint8, device=device)
    out = wp.zeros(NBYTES, dtype=wp.uint8, device=device)
    reader, writer = wp.Stream(device), wp.Stream(device)
    wp.synchronize_device(device)
    wp.launch(kernels["slow_copy"], dim=NBYTES, inputs=[out, block, spins], device=device,
              stream=reader)
    uses = cuda.BlockUses()
    uses.record_use(reader)  # the reader's release
    uses.order_after(writer)  # the block's next writer
    wp.launch(kernels["slow_fill"], dim=NBYTES, inputs=[block, 2, 1], device=device,
              stream=writer)
    wp.synchronize_device(device)
    assert int(out.numpy().max()) == 1 == int(out.numpy().min())


def test_release_after_runs_only_once_the_stream_finished(kernels: dict, spins: int) -> None:
    device = wp.get_device(DEVICE)
    data = wp.zeros(NBYTES, dtype=wp.uint8, device=device)
    reader = wp.Stream(device)
    wp.launch(kernels["slow_fill"], dim=NBYTES, inputs=[data, 5, spins * 4], device=device,
              stream=reader)
    queue = cuda.ReleaseQueue()
    seen = []
    cuda.release_after(reader, lambda: seen.append(reader.is_complete), queue)
    assert seen == []  # the kernel is still running: the hold is not dropped yet
    assert queue.flush(timeout=30)
    assert seen == [True]


def test_public_api_reuse_hazard(kernels: dict, spins: int) -> None:
    """A slow reader on stream B; its buffer dropped and a new one of the same size written on
    stream A at once: the reader must still see the old bytes (the pool orders reuse)."""
    device = wp.get_device(DEVICE)
    reader, writer = wp.Stream(device), wp.Stream(device)
    first = warp_buffer.allocate_buffer(NBYTES, DEVICE)
    with warp_buffer.from_output_buffer(first, stream=writer) as out, wp.ScopedStream(writer):
        out.array.fill_(1)  # on the handle's stream (fill_ runs on the current one)
    result = wp.zeros(NBYTES, dtype=wp.uint8, device=device)
    with warp_buffer.from_input_buffer(first, stream=reader) as view:
        wp.launch(kernels["slow_copy"], dim=NBYTES, inputs=[result, view.array, spins * 4],
                  device=device, stream=reader)
    del view, first
    gc.collect()
    second = warp_buffer.allocate_buffer(NBYTES, DEVICE)
    with warp_buffer.from_output_buffer(second, stream=writer) as out:
        wp.launch(kernels["slow_fill"], dim=NBYTES, inputs=[out.array, 2, 1], device=device,
                  stream=writer)
    wp.synchronize_device(device)
    assert int(result.numpy().max()) == 1


# --------------------------------------------------------------------------- 3. write streams
def test_write_stream_covers_a_write_on_a_non_default_torch_stream() -> None:
    torch = pytest.importorskip("torch")
    device = wp.get_device(DEVICE)
    s = torch.cuda.Stream(device=device.ordinal)
    with torch.cuda.stream(s):
        torch.cuda._sleep(int(2e8))
        tensor = torch.full((NBYTES,), 9, dtype=torch.uint8, device=DEVICE)
        event = cuda.write_stream(device).record_event()
    reader = wp.Stream(device)
    reader.wait_event(event)
    host = wp.empty(NBYTES, dtype=wp.uint8, device="cpu", pinned=True)
    wp.copy(host, wp.from_torch(tensor), stream=reader)
    wp.synchronize_stream(reader)
    assert int(host.numpy().min()) == 9


@pytest.mark.parametrize("explicit", [False, True], ids=["handle_stream", "explicit_stream"])
def test_to_buffer_under_a_torch_stream_is_read_complete(explicit: bool) -> None:
    """torch writes under ``torch.cuda.stream(s)``; to_buffer copies on the handle's stream or
    on an explicit other one (``wp.from_dlpack`` orders only Warp's current stream after torch:
    api._order_after_source orders the copy stream too). A reader on a third stream sees it all."""
    torch = pytest.importorskip("torch")
    device = wp.get_device(DEVICE)
    s = torch.cuda.Stream(device=device.ordinal)
    copy_stream = wp.Stream(device) if explicit else None
    buffer = warp_buffer.allocate_buffer(NBYTES, DEVICE)
    with torch.cuda.stream(s):
        torch.cuda._sleep(int(2e8))
        tensor = torch.full((NBYTES,), 4, dtype=torch.uint8, device=DEVICE)
        with warp_buffer.from_output_buffer(buffer) as out:
            warp_buffer.to_buffer(tensor, out, stream=copy_stream)
    reader = wp.Stream(device)
    with warp_buffer.from_input_buffer(buffer, stream=reader) as view:
        host = wp.empty(NBYTES, dtype=wp.uint8, device="cpu", pinned=True)
        wp.copy(host, view.array, stream=reader)
        wp.synchronize_stream(reader)
    assert int(host.numpy().min()) == 4


def test_device_to_host_copies_wait_for_their_own_copy_only(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """to_buffer into a cpu buffer and to_cpu of a CUDA buffer: bytes right, and neither
    synchronises the device or a whole stream (an event on the copy instead)."""
    src = wp.full(NBYTES, 3, dtype=wp.uint8, device=DEVICE)
    cuda_buffer = warp_buffer.allocate_buffer(NBYTES, DEVICE)
    with warp_buffer.from_output_buffer(cuda_buffer) as out:
        warp_buffer.to_buffer(src, out)

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("a device- or stream-wide host wait")

    monkeypatch.setattr(wp, "synchronize_device", refuse)
    monkeypatch.setattr(wp, "synchronize_stream", refuse)
    host = warp_buffer.allocate_buffer(NBYTES, "cpu")
    with warp_buffer.from_output_buffer(host) as out:
        warp_buffer.to_buffer(src, out)
    assert int(host.to_numpy().min()) == 3 == int(cuda_buffer.to_numpy().max())


def test_staged_export_is_read_back_by_an_import() -> None:
    """KIND_CUDA_STAGING: the bytes are in the (pinned) arena block when the descriptor
    leaves; an import reads them on cpu."""
    from warp_buffer import descriptor as desc
    from warp_buffer import ipc

    buffer = warp_buffer.allocate_buffer(NBYTES, DEVICE)
    with warp_buffer.from_output_buffer(buffer) as out:
        out.array.fill_(11)
    descriptor = ipc.export_buffer(buffer, kind=desc.KIND_CUDA_STAGING)
    assert descriptor.kind == desc.KIND_CUDA_STAGING
    assert descriptor.device_uuid == desc.uuid_word(wp.get_device(DEVICE).uuid)
    imported = ipc.import_buffer(descriptor)
    try:
        assert imported.device == "cpu"
        got = imported.to_cpu().view()
        assert int(got.min()) == 11 == int(got.max())
    finally:
        imported.release()


def test_dlpack_stream_values_map_to_cuda_streams() -> None:
    assert int(cuda.stream_from_dlpack(None, DEVICE).cuda_stream or 0) == 0
    assert int(cuda.stream_from_dlpack(1, DEVICE).cuda_stream or 0) == 0
    assert int(cuda.stream_from_dlpack(2, DEVICE).cuda_stream) == 2
    own = wp.Stream(DEVICE)
    assert int(cuda.stream_from_dlpack(int(own.cuda_stream), DEVICE).cuda_stream) == int(
        own.cuda_stream)
    assert cuda.stream_from_handle(int(own.cuda_stream), DEVICE) is cuda.stream_from_handle(
        int(own.cuda_stream), DEVICE)


# --------------------------------------------------------------------------- 4. no device syncs
def test_stage_to_host_does_not_wait(kernels: dict, spins: int) -> None:
    device = wp.get_device(DEVICE)
    src = wp.zeros(NBYTES, dtype=wp.uint8, device=device)
    stream = wp.Stream(device)
    wp.launch(kernels["slow_fill"], dim=NBYTES, inputs=[src, 6, spins * 4], device=device,
              stream=stream)
    host = cuda.pinned_host_array(NBYTES)
    event = cuda.stage_to_host(src, host, stream)
    assert not event.is_complete  # returned while the GPU still works: nothing synchronised
    wp.synchronize_event(event)
    assert int(host.numpy().min()) == 6 == int(host.numpy().max())


def test_staging_into_registered_shared_memory(kernels: dict) -> None:
    import mmap

    region = mmap.mmap(-1, NBYTES)
    addr = np.frombuffer(region, dtype=np.uint8).ctypes.data
    registration = cuda.register_host_memory(addr, NBYTES)
    try:
        host = wp.array(ptr=addr, dtype=wp.uint8, shape=(NBYTES,), device="cpu")
        src = wp.full(NBYTES, 8, dtype=wp.uint8, device=DEVICE)
        wp.synchronize_event(cuda.stage_to_host(src, host))
        assert bytes(region[:4]) == b"\x08" * 4
    finally:
        registration.close()


def test_tensor_conversions_never_synchronise_the_device(monkeypatch: pytest.MonkeyPatch) -> None:
    torch = pytest.importorskip("torch")
    import tensor_conversions
    import tensor_conversions.torch as tct

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("wp.synchronize_device called (a device-wide host wait)")

    msg = tct.allocate_tensor_msg((1024,), torch.float32, backend="warp", device=DEVICE)
    out = tct.from_output_tensor_msg(msg)
    out.copy_(torch.arange(1024, dtype=torch.float32, device=DEVICE))
    del out
    tensor_conversions.release_output(msg)
    monkeypatch.setattr(wp, "synchronize_device", refuse)
    for clone in (True, False):
        got = tct.from_input_tensor_msg(msg, clone=clone)
        assert torch.equal(got, torch.arange(1024, dtype=torch.float32, device=DEVICE))
    tct.to_tensor_msg(torch.ones(16, device=DEVICE))


# --------------------------------------------------------------------------- 5. the rest
def test_find_device_by_uuid_and_capabilities() -> None:
    device = wp.get_device(DEVICE)
    assert cuda.find_device(device.uuid) is device
    caps = cuda.capabilities(device)
    assert caps.uuid == device.uuid and caps.alias == DEVICE
    assert caps.ipc == bool(device.is_ipc_supported)


def test_ipc_allocation_ignores_the_mempool_and_a_user_allocator() -> None:
    device = wp.get_device(DEVICE)
    if not device.is_ipc_supported:
        pytest.skip("no CUDA IPC on this device")

    class Recording:
        def __init__(self) -> None:
            self.calls = 0

        def allocate(self, size: int) -> int:
            self.calls += 1
            return device.default_allocator.allocate(size)

        def deallocate(self, ptr: int, size: int) -> None:
            device.default_allocator.deallocate(ptr, size)

    user = Recording()
    wp.set_device_allocator(device, user)
    try:
        memory = cuda.alloc_ipc_memory(device, 1 << 16)
        assert len(cuda.ipc_mem_handle(memory)) == cuda.IPC_HANDLE_SIZE
        assert user.calls == 0  # the user's allocator was neither used nor replaced
        assert wp.get_device_allocator(device) is user
        theirs = wp.empty(1 << 16, dtype=wp.uint8, device=device)  # the user's memory
        with pytest.raises(ExportUnavailableError):
            cuda.ipc_mem_handle(theirs)  # typed: the caller falls back to staging
    finally:
        wp.set_device_allocator(device, None)
    if device.is_mempool_supported:
        with wp.ScopedMempool(device, True):
            pooled = wp.empty(1 << 16, dtype=wp.uint8, device=device)
        with pytest.raises(ExportUnavailableError):
            cuda.ipc_mem_handle(pooled)
        with pytest.raises(ExportUnavailableError):
            cuda.ipc_mem_handle(memory[16:])  # a view


def test_publish_with_a_user_allocator_does_not_raise() -> None:
    """An allocator set by the user must not make publishing fail: the backend gives a
    descriptor (IPC or staging) or None (CPU bytes), never an uncaught RuntimeError."""
    from rosidl_buffer import registry
    from rosidl_buffer.endpoint import GID_SIZE, EndpointInfo, EndpointType, local_host_id

    device = wp.get_device(DEVICE)

    class UserAllocator:  # not Warp's default allocator: its memory cannot be IPC-exported
        def allocate(self, size: int) -> int:
            return device.default_allocator.allocate(size)

        def deallocate(self, ptr: int, size: int) -> None:
            device.default_allocator.deallocate(ptr, size)

    backend = registry.create_backend_instance("warp")
    peer = EndpointInfo(
        gid=os.urandom(GID_SIZE), node_name="peer", node_namespace="/", topic_name="/t",
        topic_type="tensor_msgs/msg/ExperimentalTensor",
        endpoint_type=EndpointType.SUBSCRIPTION, host_id=local_host_id(),
        process_id=os.getppid(), user_id=os.getuid(),
        supported_backends={"warp": backend.get_backend_metadata()})
    backend.on_discovering_endpoint(peer, [], peer.supported_backends)
    wp.set_device_allocator(device, UserAllocator())
    try:
        buffer = warp_buffer.allocate_buffer(4096, DEVICE)
        with warp_buffer.from_output_buffer(buffer) as out:
            out.array.fill_(3)
        descriptor = backend.create_descriptor_with_endpoint(buffer.get_impl(), peer)
        assert descriptor is not None  # IPC (our own cudaMalloc block) or staging, no error
        assert buffer.to_numpy()[0] == 3
    finally:
        wp.set_device_allocator(device, None)


def _vmm_or_skip() -> None:
    if not cuda.vmm_supported(DEVICE):
        pytest.skip("no VMM with POSIX fd export on this device")


def test_vmm_round_trip_in_process() -> None:
    _vmm_or_skip()
    memory = cuda.VmmMemory.create(DEVICE, NBYTES)
    assert memory.nbytes % cuda.vmm_granularity(DEVICE) == 0
    wp.copy(memory.array(0, NBYTES), wp.array(pattern(), dtype=wp.uint8, device=DEVICE))
    wp.synchronize_device(DEVICE)
    fd = memory.export_fd()
    try:
        imported = cuda.VmmMemory.import_fd(fd, memory.nbytes, DEVICE, read_only=True)
    finally:
        os.close(fd)
    assert imported.read_only and imported.ptr != memory.ptr
    assert zlib.crc32(imported.array(0, NBYTES).numpy().tobytes()) == zlib.crc32(
        pattern().tobytes())
    imported.close()
    memory.close()
    with pytest.raises(StaleBufferError):
        memory.export_fd()


def _serve_once(path: str) -> socket.socket:
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(path)
    server.listen(1)
    server.settimeout(60)
    return server


def test_vmm_import_outlives_its_exporter() -> None:
    _vmm_or_skip()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "s")
        server = _serve_once(path)
        child = _child("vmm_export", path)
        conn, _ = server.accept()
        msg, fds, _, _ = socket.recv_fds(conn, 1024, 1)
        conn.close()
        server.close()
        assert child.wait(timeout=60) == 0  # the exporter is gone
    try:
        memory = cuda.VmmMemory.import_fd(fds[0], json.loads(msg)["nbytes"], DEVICE)
    finally:
        os.close(fds[0])
    assert zlib.crc32(memory.array(0, NBYTES).numpy().tobytes()) == zlib.crc32(
        pattern().tobytes())
    memory.close()


def test_vmm_read_only_import_refuses_writes() -> None:
    _vmm_or_skip()
    memory = cuda.VmmMemory.create(DEVICE, NBYTES)
    wp.copy(memory.array(0, NBYTES), wp.array(pattern(), dtype=wp.uint8, device=DEVICE))
    wp.synchronize_device(DEVICE)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "s")
        server = _serve_once(path)
        child = _child("vmm_write_readonly", path)  # a fault there cannot poison this context
        conn, _ = server.accept()
        fd = memory.export_fd()
        socket.send_fds(conn, [json.dumps({"nbytes": memory.nbytes}).encode()], [fd])
        os.close(fd)
        conn.close()
        server.close()
        out, _ = child.communicate(timeout=120)
    assert json.loads(out.strip().splitlines()[-1])["refused"] is True
    assert zlib.crc32(memory.array(0, NBYTES).numpy().tobytes()) == zlib.crc32(
        pattern().tobytes())  # the exporter's bytes are unchanged
    memory.close()


# --------------------------------------------------------------------------- VMM through the pool
def _vmm_pool_or_skip() -> None:
    _vmm_or_skip()
    from warp_buffer import pool

    if not pool.uses_vmm(wp.get_device(DEVICE)):
        pytest.skip(f"the pool does not use VMM here: {pool._vmm_refused}")


def _reap(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=60)


def test_vmm_block_published_and_imported_by_a_child_read_only() -> None:
    """The pool's VMM block, exported for a same-GPU peer, is imported by a child over the
    session's hand-off socket: right bytes (CRC), and a write kernel through the import fails
    there (read-only mapping) while our bytes stay as they were."""
    _vmm_pool_or_skip()
    from warp_buffer import descriptor, ipc

    device = wp.get_device(DEVICE)
    buffer = warp_buffer.allocate_buffer(NBYTES, DEVICE)
    assert buffer.get_impl().block.cuda_kind == descriptor.KIND_CUDA_VMM
    with warp_buffer.from_output_buffer(buffer) as out:
        wp.copy(out.array, wp.array(pattern(), dtype=wp.uint8, device=DEVICE))
    exported = ipc.export_buffer(buffer, peer_device_uuids={device.uuid})
    assert exported.kind == descriptor.KIND_CUDA_VMM
    child = _child("vmm_import", descriptor.pack(exported).hex())
    try:
        out, _ = child.communicate(timeout=180)
    finally:
        _reap(child)
    read, written = (json.loads(line) for line in out.strip().splitlines()[-2:])
    assert read == {"crc": zlib.crc32(pattern().tobytes()), "device": DEVICE}
    assert written["refused"] is True
    assert zlib.crc32(buffer.to_numpy().tobytes()) == zlib.crc32(pattern().tobytes())


def test_vmm_import_through_the_pool_outlives_its_publisher() -> None:
    """A child publishes a VMM block and exits (SIGKILL: no linger) after we imported it: our
    import still reads its bytes, and the gone session's cached imports are dropped at once
    (the hand-off connection closed) while our buffer keeps its own mapping."""
    _vmm_pool_or_skip()
    from warp_buffer import descriptor, ipc

    child = _child("vmm_publish")
    try:
        line = json.loads(child.stdout.readline())
        assert line["kind"] == descriptor.KIND_CUDA_VMM
        exported = descriptor.unpack(bytes.fromhex(line["descriptor"]))
        imported = ipc.import_buffer(exported)
        key = (exported.owner_pid, exported.session)
        assert any(k[0] == key for k in ipc._cuda_imports._strong["memory"])
        child.kill()
        child.wait(timeout=60)
    finally:
        _reap(child)
    deadline = time.monotonic() + 5
    while any(k[0] == key for k in ipc._cuda_imports._strong["memory"]):
        assert time.monotonic() < deadline, "the gone session's imports were not dropped"
        time.sleep(0.05)
    assert zlib.crc32(imported.to_cpu().view().tobytes()) == zlib.crc32(pattern().tobytes())
    imported.release()
    assert cuda.flush_releases(10)


def test_vmm_switched_off_falls_back_to_legacy_ipc(monkeypatch: pytest.MonkeyPatch) -> None:
    from warp_buffer import descriptor, pool

    monkeypatch.setenv("WARP_BUFFER_CUDA_VMM", "0")
    monkeypatch.setattr(pool, "_vmm_refused", {})
    block = pool.cuda_block(wp.get_device(DEVICE), 4096)
    try:
        assert type(block) is pool.CudaBlock and block.cuda_kind == descriptor.KIND_CUDA_IPC
        assert cuda.is_ipc_allocation(block.storage)
    finally:
        block.destroy()


@pytest.mark.slow
def test_copy_bytes_over_32_gib() -> None:
    from warp_buffer import kernels

    device = wp.get_device(DEVICE)
    nbytes = (32 << 30) + 4099
    if device.free_memory < 2 * nbytes + (4 << 30):
        pytest.skip("needs about 70 GB of free device memory")
    src = wp.empty(nbytes, dtype=wp.uint8, device=device)
    dst = wp.zeros(nbytes, dtype=wp.uint8, device=device)
    tail = wp.array(np.arange(4099, dtype=np.uint8), dtype=wp.uint8, device=device)
    wp.copy(src, tail, dest_offset=nbytes - 4099, count=4099)  # the last bytes, past 2**35
    kernels.copy_bytes(dst, src)
    got = wp.empty(4099, dtype=wp.uint8, device=device)
    wp.copy(got, dst, src_offset=nbytes - 4099, count=4099)
    assert np.array_equal(got.numpy(), np.arange(4099, dtype=np.uint8))
