"""The bookkeeping of CUDA VMM blocks and of gone publisher sessions, on the cpu device with fakes.

What runs here (no GPU): which block and export kind a CUDA device gets (VMM where it exports
POSIX fds, legacy CUDA IPC otherwise, the fallback logged once); a VMM block's fd travels over
the session's real hand-off socket (SCM_RIGHTS, the same server as the arena) and an import maps
it read-only, once per block, with the process's fd count constant; a gone publisher session
(its hand-off connection closed, its socket refusing, or its last publisher endpoint gone) drops
its cached CUDA imports, their closes ordered after the work queued on the current streams and
after every imported buffer's own release. The real thing is in tests/test_cuda_ipc.py
(cuda-marked): a fake ``VmmMemory`` here is a memfd, so the bytes the importer reads really came
through the fd it was handed.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import socket
import subprocess
import sys
import time
import weakref
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import warp as wp

from tests._reliability_helpers import wait_until
from tests.test_cuda_primitives import FakeEvent, FakeStream
from tests.test_cuda_wiring import FakeDevice
from warp_buffer import cuda, handoff, ipc, memory, pool
from warp_buffer import descriptor as desc
from warp_buffer.arena import Arena, current_arena
from warp_buffer.buffer_impl import WarpBufferImpl
from warp_buffer.errors import CudaDriverError, DeviceMemoryError, ExportUnavailableError
from warp_buffer.errors import StaleBufferError

GRANULE = 64 << 10  # the fake device's VMM granularity (2 MiB on real GPUs)


class FakeVmm:
    """Stands for ``cuda.VmmMemory``: a memfd mapped here. ``export_fd`` dups it (as
    ``cuMemExportToShareableHandle`` makes a new fd); ``import_fd`` maps a received fd."""

    created: list[FakeVmm] = []
    imported: list[FakeVmm] = []

    def __init__(self, fd: int, nbytes: int, read_only: bool) -> None:
        self.fd, self.nbytes, self.read_only = fd, nbytes, read_only
        self.device = wp.get_device("cpu")  # imports are read through Warp's cpu device here
        self.ptr = memory.map_fd(fd, nbytes, writable=not read_only)
        self.closed = False

    @classmethod
    def create(cls, device: Any, nbytes: int) -> FakeVmm:
        fd = os.memfd_create("fake_vmm", os.MFD_CLOEXEC)
        nbytes = -(-nbytes // GRANULE) * GRANULE
        os.ftruncate(fd, nbytes)
        made = cls(fd, nbytes, read_only=False)
        cls.created.append(made)
        return made

    @classmethod
    def import_fd(cls, fd: int, nbytes: int, device: Any, read_only: bool = True) -> FakeVmm:
        made = cls(os.dup(fd), nbytes, read_only)  # the caller closes ``fd``, as with CUDA
        cls.imported.append(made)
        return made

    def export_fd(self) -> int:
        if self.closed:
            raise StaleBufferError("closed")
        return os.dup(self.fd)

    def array(self, offset: int = 0, nbytes: int | None = None) -> wp.array:
        nbytes = self.nbytes - offset if nbytes is None else nbytes
        return wp.array(ptr=self.ptr + offset, dtype=wp.uint8, shape=(nbytes,),
                        device=self.device, deleter=cuda._Keep(self))

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            memory.unmap(self.ptr, self.nbytes)
            os.close(self.fd)

    def __del__(self) -> None:
        self.close()


@pytest.fixture
def vmm_device(monkeypatch: pytest.MonkeyPatch) -> FakeDevice:
    """A CUDA device (fake) that exports VMM memory as POSIX fds, blocks made by FakeVmm."""
    FakeVmm.created, FakeVmm.imported = [], []
    monkeypatch.setattr(cuda, "VmmMemory", FakeVmm)
    monkeypatch.setattr(cuda, "vmm_supported", lambda device: True)
    monkeypatch.setattr(cuda, "vmm_granularity", lambda device: GRANULE)
    monkeypatch.setattr(pool, "_vmm_refused", {})
    device = FakeDevice(uuid="GPU-vmm")
    device.alias = "cuda:7"
    yield device
    for made in FakeVmm.created + FakeVmm.imported:
        made.close()


def _events(monkeypatch: pytest.MonkeyPatch, device: Any) -> tuple[FakeStream, cuda.ReleaseQueue]:
    """Fake current stream and release queue; blocks' IPC events are fakes with fixed handles."""
    stream = FakeStream(5, device)
    queue = cuda.ReleaseQueue(poll_s=0.001)
    monkeypatch.setattr(cuda, "write_stream", lambda dev, s=None: stream)
    monkeypatch.setattr(cuda, "_release_queue", queue)
    monkeypatch.setattr(pool.CudaBlock, "event", property(lambda self: FakeEvent(self.device)))
    monkeypatch.setattr(pool.CudaBlock, "ipc_event_handle", lambda self: b"\x07" * 64)
    return stream, queue


def _exported_impl(block: pool.CudaBlock, device: Any, size: int) -> WarpBufferImpl:
    impl = WarpBufferImpl(None, device, block=block, ptr=block.data_ptr, size=size)
    impl.write_event = FakeEvent(device)  # the write was recorded
    return impl


def _fds_of(block: pool.CudaBlock, session: int) -> set[str]:
    """The fds of this process that a test's hand-offs of ``block`` can leave open: copies of
    the block's memory (sent or received) and connections to ``session``'s hand-off socket on
    the server side, which the server thread closes after the client is done. Not a count of
    every fd: other threads (Zenoh, the session watcher, a garbage collection) open and close
    theirs at any time, and the hand-off server's own closes lag the client by a moment."""
    memory = os.fstat(block.vmm.fd)
    name = "@" + handoff.socket_name(os.getuid(), os.getpid(), session)[1:].decode()
    with open("/proc/net/unix", encoding="ascii") as table:
        rows = [line.split() for line in table.read().splitlines()[1:]]
    served = {row[6] for row in rows if len(row) == 8 and row[7] == name and row[5] == "03"}
    found = set()
    for fd in os.listdir("/proc/self/fd"):
        path = f"/proc/self/fd/{fd}"
        try:
            link, stat = os.readlink(path), os.stat(path)
        except OSError:  # closed meanwhile
            continue
        if ((stat.st_dev, stat.st_ino) == (memory.st_dev, memory.st_ino)
                or link.startswith("socket:[") and link[8:-1] in served):
            found.add(f"{fd} -> {link}")
    return found


def _settles_to(block: pool.CudaBlock, session: int, before: set[str]) -> set[str]:
    """What :func:`_fds_of` holds beyond ``before`` once the hand-off server caught up (5 s)."""
    wait_until(lambda: _fds_of(block, session) <= before, timeout=5.0)
    return _fds_of(block, session) - before


# ------------------------------------------------------------------------- which kind, fallback
def test_a_vmm_capable_device_gets_vmm_blocks_of_at_least_one_granule(vmm_device) -> None:
    blocks = pool.BlockPool(vmm_device)
    lease = blocks.acquire(4096)
    block = lease.block
    try:
        assert isinstance(block, pool.VmmBlock) and block.cuda_kind == desc.KIND_CUDA_VMM
        assert block.capacity == GRANULE  # small buffers share the granule's size class
        assert block.vmm is FakeVmm.created[-1] and block.data_ptr == block.vmm.ptr
        assert block.mem_words() == desc.vmm_words(block.serial, GRANULE)
        with pytest.raises(ExportUnavailableError):
            block.ipc_mem_handle()  # VMM memory has no legacy handle
        other = blocks.acquire(3 * GRANULE).block
        assert other.capacity == 4 * GRANULE and other.serial > block.serial
        other.destroy()
    finally:
        block.destroy()
    assert block.vmm is None and FakeVmm.created[0].closed


def test_without_vmm_blocks_use_legacy_ipc_and_it_is_logged_once(monkeypatch, caplog) -> None:
    monkeypatch.setattr(pool, "_vmm_refused", {})
    monkeypatch.setattr(cuda, "vmm_supported", lambda device: False)
    monkeypatch.setattr(cuda, "alloc_ipc_memory", lambda device, n: SimpleNamespace(ptr=4096))
    device = FakeDevice()
    caplog.set_level(logging.INFO, logger="warp_buffer.pool")
    blocks = [pool.cuda_block(device, n) for n in (4096, 8192, 4096)]
    assert all(type(b) is pool.CudaBlock and b.cuda_kind == desc.KIND_CUDA_IPC for b in blocks)
    said = [r for r in caplog.records if "legacy CUDA IPC" in r.getMessage()]
    assert len(said) == 1 and device.alias in said[0].getMessage()
    assert pool.BlockPool(device).acquire(4096).block.capacity == 4096  # no granule floor


def test_a_driver_that_refuses_cumemcreate_falls_back_once_and_oom_does_not(vmm_device,
                                                                             monkeypatch,
                                                                             caplog) -> None:
    calls: list[int] = []

    def refuse(device: Any, nbytes: int) -> Any:
        calls.append(nbytes)
        raise CudaDriverError("cuMemCreate failed: CUDA error 801 (operation not supported)")

    monkeypatch.setattr(FakeVmm, "create", classmethod(lambda cls, d, n: refuse(d, n)))
    monkeypatch.setattr(cuda, "alloc_ipc_memory", lambda device, n: SimpleNamespace(ptr=4096))
    caplog.set_level(logging.INFO, logger="warp_buffer.pool")
    first, second = pool.cuda_block(vmm_device, 4096), pool.cuda_block(vmm_device, 4096)
    assert type(first) is type(second) is pool.CudaBlock
    assert len(calls) == 1  # judged once: the second block did not try VMM again
    assert sum("cuMemCreate failed" in r.getMessage() for r in caplog.records) == 1
    # Out of device memory is not "VMM unsupported": the pool's trim-and-retry sees it.
    monkeypatch.setattr(pool, "_vmm_refused", {})
    monkeypatch.setattr(FakeVmm, "create",
                        classmethod(lambda cls, d, n: (_ for _ in ()).throw(DeviceMemoryError("full"))))
    with pytest.raises(DeviceMemoryError):
        pool.cuda_block(vmm_device, 4096)
    assert vmm_device.alias not in pool._vmm_refused


def test_the_export_kind_follows_the_block(vmm_device, monkeypatch) -> None:
    _events(monkeypatch, vmm_device)
    vmm = pool.cuda_block(vmm_device, GRANULE)
    monkeypatch.setattr(cuda, "alloc_ipc_memory", lambda device, n: SimpleNamespace(ptr=4096))
    monkeypatch.setattr(pool.CudaBlock, "ipc_mem_handle", lambda self: b"\x05" * 64)
    legacy = pool.CudaBlock(vmm_device, 4096)
    peers = frozenset({vmm_device.uuid})
    try:
        d = ipc._export_local(_exported_impl(vmm, vmm_device, 100), None, peers, None)
        assert d.kind == desc.KIND_CUDA_VMM
        assert (d.mem_handle_0, d.mem_handle_1, d.mem_handle_2) == (vmm.serial, GRANULE, 0)
        assert d.event_handle_0 == int.from_bytes(b"\x07" * 8, "little")  # IPC event handle
        assert current_arena().cuda_exports[d.offset] is vmm  # what the hand-off serves
        assert ipc._export_local(_exported_impl(legacy, vmm_device, 100), None, peers,
                                 None).kind == desc.KIND_CUDA_IPC
        with pytest.raises(ExportUnavailableError):  # asked for the other mechanism
            ipc._export_local(_exported_impl(vmm, vmm_device, 100), desc.KIND_CUDA_IPC, peers,
                              None)
    finally:
        vmm.destroy()
        legacy.destroy()
    assert d.offset not in current_arena().cuda_exports


# ------------------------------------------------------------------------- fds through the hand-off
def test_a_vmm_blocks_fd_travels_over_the_session_socket(vmm_device, monkeypatch) -> None:
    _events(monkeypatch, vmm_device)
    block = pool.cuda_block(vmm_device, GRANULE)
    try:
        d = ipc._export_local(_exported_impl(block, vmm_device, 100), None,
                              frozenset({vmm_device.uuid}), None)
        before = _fds_of(block, d.session)
        for _ in range(20):
            fd, nbytes = handoff.fetch_cuda_block(os.getpid(), d.session, d.offset, block.serial)
            try:
                assert nbytes == GRANULE
                assert os.fstat(fd).st_ino == os.fstat(block.vmm.fd).st_ino  # the very memory
            finally:
                os.close(fd)
        assert not _settles_to(block, d.session, before)  # nothing accumulates, either side
        with pytest.raises(StaleBufferError):  # another allocation at that offset: refused
            handoff.fetch_cuda_block(os.getpid(), d.session, d.offset, block.serial + 1)
        with pytest.raises(StaleBufferError):  # no VMM block there
            handoff.fetch_cuda_block(os.getpid(), d.session, d.offset + 4096, block.serial)
    finally:
        block.destroy()


def test_an_import_maps_the_fd_read_only_once_per_block(vmm_device, monkeypatch) -> None:
    stream, queue = _events(monkeypatch, vmm_device)
    monkeypatch.setattr(ipc, "_cuda_device", lambda word: wp.get_device("cpu"))
    cache = cuda.ImportCache(open_event=lambda handle, device: FakeEvent(device))
    monkeypatch.setattr(ipc, "_cuda_imports", cache)
    block = pool.cuda_block(vmm_device, GRANULE)
    expected = (np.arange(5000) % 253).astype(np.uint8)
    ctypes.memmove(block.data_ptr, expected.ctypes.data, expected.size)  # the publisher writes
    impl = _exported_impl(block, vmm_device, expected.size)
    peers = frozenset({vmm_device.uuid})
    imports = []
    try:
        before = None
        for round_ in range(5):
            d = ipc._export_local(impl, None, peers, None)
            imported = ipc.import_buffer(d)
            np.testing.assert_array_equal(imported.array.numpy(), expected)
            imports.append(imported)
            if round_ == 0:
                before = _fds_of(block, d.session)
        assert len(FakeVmm.imported) == 1 and FakeVmm.imported[0].read_only  # one read-only map
        assert not _settles_to(block, d.session, before)  # the received fds were closed
        for imported in imports:
            imported.release()
        for event in stream.recorded:
            event.is_complete = True
        assert queue.flush(timeout=5)
    finally:
        imports.clear()
        block.destroy()


# ------------------------------------------------------------------------- S5: gone sessions
class _Opened:
    """Stands for an opened CUDA mapping: weak-referenceable, with a device."""

    def __init__(self, device: Any) -> None:
        self.device = device


def test_forgetting_a_session_closes_after_the_queued_work(monkeypatch) -> None:
    device = FakeDevice()
    stream, queue = _events(monkeypatch, device)
    key = (os.getpid(), 0xF0F0)
    opened = [_Opened(device), _Opened(device)]
    for block, value in zip((4096, 8192), opened):
        ipc._cuda_imports._get("memory", (key, block), b"m" * 64, lambda v=value: v)
    ipc._cuda_imports._get("memory", ((1, 2), 4096), b"m" * 64, lambda: _Opened(device))
    closed = [weakref.ref(v) for v in opened]
    del value
    opened.clear()
    assert ipc.forget_session(*key) == 2
    gc.collect()
    assert all(ref() is not None for ref in closed)  # the current stream may still read them
    stream.recorded[-1].is_complete = True
    assert queue.flush(timeout=5)
    gc.collect()
    assert all(ref() is None for ref in closed)  # now closed
    assert ipc._cuda_imports.drop((1, 2)) == 1  # another session's entry was left alone


def test_forgetting_a_session_leaves_a_held_import_to_its_own_release(monkeypatch) -> None:
    device = FakeDevice()
    stream, queue = _events(monkeypatch, device)
    key = (os.getpid(), 0xF1F1)
    base = _Opened(device)
    ipc._cuda_imports._get("memory", (key, 4096), b"m" * 64, lambda: base)
    released: list[bool] = []
    hold = SimpleNamespace(live=True, release=lambda: released.append(True))
    impl = WarpBufferImpl.__new__(WarpBufferImpl)
    reader = FakeStream(6, device)
    impl.cuda_uses = cuda.BlockUses(event_factory=FakeEvent)
    cuda.record_use(impl, reader)  # a read on another stream, still running
    keep = ipc._CudaHold(impl, hold, base, FakeEvent(device))
    ref = weakref.ref(base)
    del base
    ipc.forget_session(*key)
    stream.recorded[-1].is_complete = True  # the session's own close event
    queue.flush(timeout=5)
    gc.collect()
    assert ref() is not None  # the import still holds the mapping
    keep.release()  # the buffer's release: ordered after the reader's use
    assert reader.recorded[-1] in stream.waited
    gc.collect()
    assert ref() is not None and released == []  # its release event is pending
    stream.recorded[-1].is_complete = True
    assert queue.flush(timeout=5)
    del keep
    gc.collect()
    assert released == [True] and ref() is None  # closed after the last use


def _wait_for(predicate: Any, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def test_a_closed_hand_off_connection_reports_the_session_gone(monkeypatch) -> None:
    gone: list[tuple[int, int]] = []
    monkeypatch.setattr(handoff, "session_gone_hooks", [*handoff.session_gone_hooks, gone.append])
    other = Arena(data_bytes=1 << 20)  # a second session, served from this process
    server = handoff.Server(other)
    key = (other.pid, other.session)
    dropped = []
    monkeypatch.setattr(ipc, "forget_session", lambda *k: dropped.append(k))
    try:
        fd, _geometry = handoff.fetch_arena(*key)
        os.close(fd)
        assert _wait_for(lambda: server.peers == 1)
        assert key not in gone  # alive: nothing reported
        server.close()  # the session ends: the kept connection closes
        assert _wait_for(lambda: gone.count(key) == 1)
        assert key in dropped  # ipc's hook forgot the session's cached CUDA imports
        with pytest.raises(StaleBufferError):
            handoff.fetch_arena(*key)  # its socket refuses: reported again
        assert gone.count(key) == 2
    finally:
        server.close()
        memory.unmap(other.base, other.size)
        os.close(other.fd)


def test_the_server_lets_go_of_a_peer_that_closed() -> None:
    other = Arena(data_bytes=1 << 20)
    server = handoff.Server(other)
    try:
        for _ in range(3):
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
                sock.connect(handoff.socket_name(os.getuid(), other.pid, other.session))
                sock.sendall(handoff.REQUEST.pack(handoff.ASK_ARENA, 0, 0))
                _data, fds, _f, _a = socket.recv_fds(sock, 64, 1)
                for fd in fds:
                    os.close(fd)
            time.sleep(0.05)
        assert _wait_for(lambda: server.peers <= 1)  # each accept swept the closed ones
    finally:
        server.close()
        memory.unmap(other.base, other.size)
        os.close(other.fd)


_PUBLISHER = """
import sys
from warp_buffer import allocate_buffer, ipc
buffer = allocate_buffer(4096, "cpu")
d = ipc.export_buffer(buffer)
print(d.owner_pid, d.session, flush=True)
sys.stdin.readline()
"""


def test_a_publisher_process_that_dies_is_reported_gone_at_once(monkeypatch) -> None:
    gone: list[tuple[int, int]] = []
    monkeypatch.setattr(handoff, "session_gone_hooks", [*handoff.session_gone_hooks, gone.append])
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    child = subprocess.Popen([sys.executable, "-c", _PUBLISHER], cwd=root, text=True,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             env={**os.environ, "PYTHONPATH": root})
    try:
        pid, session = map(int, child.stdout.readline().split())
        fd, _geometry = handoff.fetch_arena(pid, session)
        os.close(fd)
        time.sleep(2 * handoff.WATCH_POLL_S)
        assert (pid, session) not in gone  # alive: nothing reported
        child.kill()  # no clean exit: the kernel closes its end
        child.wait(timeout=30)
        assert _wait_for(lambda: (pid, session) in gone)
    finally:
        if child.poll() is None:
            child.kill()
        child.wait(timeout=30)


def test_the_last_gone_publisher_of_a_session_drops_its_imports(monkeypatch) -> None:
    from rosidl_buffer.endpoint import GID_SIZE, EndpointInfo, EndpointType, local_host_id
    from warp_buffer_backend import backend as backend_module

    forgotten: list[tuple[int, int]] = []
    monkeypatch.setattr(backend_module, "forget_session", lambda *key: forgotten.append(key))
    monkeypatch.setattr(backend_module, "import_buffer", lambda descriptor: "imported")
    backend = backend_module.WarpBufferBackend()

    def publisher() -> EndpointInfo:
        return EndpointInfo(gid=os.urandom(GID_SIZE), node_name="p", node_namespace="/",
                            topic_name="/t", topic_type="t", endpoint_type=EndpointType.PUBLISHER,
                            host_id=local_host_id(), process_id=4242, user_id=os.getuid())

    a, b = publisher(), publisher()
    descriptor = SimpleNamespace(owner_pid=4242, session=0xABC)
    for info in (a, b, a):
        assert backend.from_descriptor_with_endpoint(descriptor, info) == "imported"
    backend.on_endpoint_gone(a)
    assert forgotten == []  # b still publishes from that session
    backend.on_endpoint_gone(b)
    assert forgotten == [(4242, 0xABC)]
    backend.on_endpoint_gone(b)  # told twice: nothing more
    assert forgotten == [(4242, 0xABC)]
