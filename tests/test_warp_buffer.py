"""warp_buffer in one process: WarpBufferImpl, the user API (handles, promotion, to_buffer),
the copy kernels, write ordering and the pool (reuse, giving memory back)."""

from __future__ import annotations

import gc
import os
import time

import numpy as np
import pytest
import torch
import warp as wp

import warp_buffer
from rosidl_buffer import Buffer, RosidlBufferError
from tests._warp_helpers import expected_pattern, fill_pattern
from warp_buffer import (
    DeviceUnavailableError,
    EmptyBufferError,
    HandleReleasedError,
    InvalidSizeError,
    SizeMismatchError,
    SizeTypeError,
    WarpBufferError,
    UnsupportedSourceError,
    WarpBufferImpl,
    WriteHandleError,
    allocate_buffer,
    from_input_buffer,
    from_output_buffer,
    ipc,
    kernels,
    to_buffer,
)
from warp_buffer.pool import get_pool, size_class

pytestmark = pytest.mark.usefixtures("warp_pool_drained")



def _written(nbytes: int, seed: int = 3) -> Buffer:
    buffer = allocate_buffer(nbytes, "cpu")
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, seed)
    return buffer


def test_allocate_is_a_warp_buffer_on_the_requested_device():
    buffer = allocate_buffer(1000, "cpu")
    impl = buffer.get_impl()
    assert isinstance(impl, WarpBufferImpl)
    assert buffer.get_backend_type() == impl.get_backend_type() == "warp"
    assert impl.size() == len(buffer) == 1000
    assert impl.device == "cpu"
    assert impl.array.dtype == wp.uint8 and impl.array.shape == (1000,)
    assert allocate_buffer(10).get_impl().device == wp.get_device().alias  # follows Warp


@pytest.mark.parametrize("nbytes", [0, -1])
def test_empty_or_negative_sizes_raise_a_typed_error(nbytes):
    with pytest.raises(EmptyBufferError):
        allocate_buffer(nbytes)
    assert issubclass(EmptyBufferError, RosidlBufferError)


def test_unavailable_device_and_bad_size_type():
    with pytest.raises(DeviceUnavailableError):
        allocate_buffer(16, "cuda:7")
    with pytest.raises(SizeTypeError):  # also a TypeError
        allocate_buffer(16.0)  # type: ignore[arg-type]


def test_a_cuda_device_on_a_machine_without_cuda_is_refused_without_native_output(capfd):
    # Warp's native code prints to stderr when asked for "cuda" without a driver; the library
    # refuses the name first, with the same typed error as any device that is not here.
    import tensor_conversions.numpy as tc

    if wp.is_cuda_available():
        assert allocate_buffer(16, "cuda").get_impl().wp_device.is_cuda
        return
    capfd.readouterr()
    for name in ("cuda", "cuda:0"):
        with pytest.raises(DeviceUnavailableError, match="not available here"):
            allocate_buffer(16, name)
        with pytest.raises(tc.UnsupportedBackendError, match="not available here"):
            tc.allocate_tensor_msg((4,), np.float32, backend="warp", device=name)
    assert capfd.readouterr().err == ""


def test_kernel_written_bytes_reach_to_cpu_and_views_reinterpret_without_copy():
    buffer = _written(4096, seed=11)
    np.testing.assert_array_equal(buffer.to_numpy(), expected_pattern(4096, 11))
    with from_input_buffer(buffer) as view:
        floats = view.view(wp.float32, (32, 32))
        assert floats.shape == (32, 32) and floats.ptr == view.ptr == buffer.get_impl().array.ptr
        np.testing.assert_array_equal(floats.numpy().view(np.uint8).reshape(-1),
                                      expected_pattern(4096, 11))
        assert view.view(np.uint16).shape == (2048,)
        assert view.view(wp.vec4, 10).shape == (10,)  # smaller than the buffer is fine
        with pytest.raises(SizeMismatchError):
            view.view(wp.float32, (33, 32))
        with pytest.raises(SizeMismatchError):
            view.view(wp.vec3)  # 4096 is not a whole number of 12-byte elements


@pytest.mark.parametrize("nbytes", [1, 15, 16, 17, 4099, (4 << 20) + 3])
def test_to_cpu_and_clone_copy_every_byte(nbytes):
    buffer = allocate_buffer(nbytes, "cpu")
    data = np.random.default_rng(nbytes).integers(0, 256, nbytes, dtype=np.uint8)
    with from_output_buffer(buffer) as out:
        to_buffer(data, out)
    np.testing.assert_array_equal(buffer.to_numpy(), data)
    clone = buffer.copy()
    assert clone.get_impl() is not buffer.get_impl()
    assert clone.get_backend_type() == "warp" and clone == buffer
    assert clone.get_impl().array.ptr != buffer.get_impl().array.ptr
    with from_output_buffer(clone) as out:  # a clone is a fresh, writable buffer
        out.array.zero_()
    np.testing.assert_array_equal(buffer.to_numpy(), data)
    assert not clone.to_numpy().any()


@pytest.mark.parametrize("offset", [0, 1, 3])
@pytest.mark.parametrize("nbytes", [100, (4 << 20) + 5])
def test_copy_kernel_handles_any_alignment(offset, nbytes):
    src = np.random.default_rng(1).integers(0, 256, nbytes + 8, dtype=np.uint8)
    dst = np.zeros(nbytes + 8, dtype=np.uint8)
    a = wp.array(ptr=src.ctypes.data + offset, dtype=wp.uint8, shape=(nbytes,), device="cpu")
    b = wp.array(ptr=dst.ctypes.data + 8 - offset, dtype=wp.uint8, shape=(nbytes,), device="cpu")
    kernels.copy_bytes(b, a)
    np.testing.assert_array_equal(dst[8 - offset:8 - offset + nbytes], src[offset:offset + nbytes])
    assert not dst[:8 - offset].any() and not dst[8 - offset + nbytes:].any()


def test_one_write_handle_ever():
    buffer = allocate_buffer(64, "cpu")
    with from_output_buffer(buffer):
        with pytest.raises(WriteHandleError):
            from_output_buffer(buffer)
    with pytest.raises(WriteHandleError):
        from_output_buffer(buffer)


def test_no_write_after_publish_or_read():
    published = allocate_buffer(64, "cpu")
    ipc.export_buffer(published)
    with pytest.raises(WriteHandleError):
        from_output_buffer(published)
    read = allocate_buffer(64, "cpu")
    from_input_buffer(read).release()
    with pytest.raises(WriteHandleError):
        from_output_buffer(read)


def test_an_open_write_handle_is_sealed_by_a_read_and_by_a_publish():
    for end in ("read", "publish"):
        buffer = allocate_buffer(64, "cpu")
        handle = from_output_buffer(buffer)
        handle.array.fill_(5)
        if end == "read":
            reader = from_input_buffer(buffer)
            assert (reader.array.numpy() == 5).all()
        else:
            ipc.export_buffer(buffer)
        with pytest.raises(WriteHandleError):
            handle.array  # noqa: B018
        with pytest.raises(WriteHandleError):
            to_buffer(np.zeros(64, np.uint8), handle)
        handle.release()
        assert (buffer.to_numpy() == 5).all()


def test_release_is_idempotent_and_released_handles_refuse_access():
    buffer = allocate_buffer(64, "cpu")
    handle = from_output_buffer(buffer)
    handle.release()
    handle.release()
    for access in (lambda: handle.array, lambda: handle.ptr, lambda: handle.view(wp.uint8)):
        with pytest.raises(HandleReleasedError):
            access()
    reader = from_input_buffer(buffer)
    reader.release()
    reader.release()
    with pytest.raises(HandleReleasedError):
        reader.array  # noqa: B018


def test_a_garbage_collected_write_handle_ends_the_write_and_seal_closes_an_open_one():
    buffer = allocate_buffer(64, "cpu")
    handle = from_output_buffer(buffer)
    handle.array.fill_(9)
    del handle
    gc.collect()
    with from_input_buffer(buffer) as view:
        assert (view.array.numpy() == 9).all()
    sealed = allocate_buffer(64, "cpu")
    open_handle = from_output_buffer(sealed)
    open_handle.array.fill_(4)
    sealed.seal()  # what the transport does on every publish route
    with pytest.raises(WriteHandleError):
        open_handle.array  # noqa: B018
    with pytest.raises(WriteHandleError):
        from_output_buffer(sealed)
    assert (sealed.to_numpy() == 4).all() and sealed.get_impl().is_published


def test_output_handle_promotes_a_cpu_buffer_without_copying():
    cpu = Buffer(np.arange(8, dtype=np.float32), dtype=np.float32)
    with from_output_buffer(cpu) as out:
        promoted = out.get_promoted_buffer()
        assert promoted is out.buffer and promoted is not cpu
        assert promoted.get_backend_type() == "warp" and len(promoted) == cpu.nbytes == 32
        to_buffer(np.full(8, 2.5, np.float32), out)
    assert cpu.get_backend_type() == "cpu" and cpu[0] == 0.0  # the original is untouched
    np.testing.assert_array_equal(promoted.to_numpy().view(np.float32), np.full(8, 2.5))
    native = allocate_buffer(8, "cpu")
    with from_output_buffer(native) as out:
        assert out.get_promoted_buffer() is None and out.buffer is native


def test_input_handle_promotes_a_cpu_buffer_by_copying():
    data = np.random.default_rng(2).integers(0, 256, 300, dtype=np.uint8)
    cpu = Buffer(data)
    with from_input_buffer(cpu) as view:
        promoted = view.get_promoted_buffer()
        assert promoted.get_backend_type() == "warp"
        np.testing.assert_array_equal(view.array.numpy(), data)
        assert view.ptr != cpu.numpy().ctypes.data
    with pytest.raises(WriteHandleError):  # the promoted buffer was read
        from_output_buffer(promoted)
    for empty in (Buffer(), Buffer(b"")):
        with pytest.raises(EmptyBufferError):
            from_input_buffer(empty)
        with pytest.raises(EmptyBufferError):
            from_output_buffer(empty)


def test_to_buffer_takes_dlpack_sources_and_checks_sizes():
    values = np.linspace(-1, 1, 24, dtype=np.float32)
    sources = {
        "numpy": values,
        "torch": torch.from_numpy(values.copy()),
        "torch-strided": torch.from_numpy(np.repeat(values, 2))[::2],
        "warp": wp.array(values.reshape(8, 3), dtype=wp.vec3, device="cpu"),
        "bytes": values.tobytes(),
        "buffer": Buffer(values, dtype=np.float32),
    }
    for name, source in sources.items():
        buffer = allocate_buffer(values.nbytes, "cpu")
        with from_output_buffer(buffer) as out:
            to_buffer(source, out)
        np.testing.assert_array_equal(buffer.to_numpy().view(np.float32), values, err_msg=name)
    buffer = allocate_buffer(values.nbytes + 1, "cpu")
    with from_output_buffer(buffer) as out:
        with pytest.raises(SizeMismatchError):
            to_buffer(values, out)
        with pytest.raises(TypeError):
            to_buffer(object(), out)
        with pytest.raises(UnsupportedSourceError, match="Python objects"):
            to_buffer(np.array([1, "x"], dtype=object), out)
        reader = from_input_buffer(_written(values.nbytes + 1))
        for wrong in ([1, 2, 3], "abc", (1, 2), reader, out):
            with pytest.raises(UnsupportedSourceError) as info:
                to_buffer(wrong, out)
            assert isinstance(info.value, TypeError) and isinstance(info.value, WarpBufferError)
        reader.release()
    assert issubclass(SizeMismatchError, WarpBufferError) and issubclass(SizeMismatchError, ValueError)


def test_a_buffer_larger_than_a_warp_array_is_a_typed_error_at_allocation():
    from warp_buffer.pool import MAX_BUFFER_BYTES

    for nbytes in (MAX_BUFFER_BYTES + 1, 2**31 + 4096, 2**40):
        with pytest.raises(InvalidSizeError, match="2\\*\\*31 - 1"):
            allocate_buffer(nbytes, "cpu")
    assert size_class(MAX_BUFFER_BYTES) == 2**31


def test_size_classes_are_powers_of_two_from_a_page():
    assert [size_class(n) for n in (1, 4096, 4097, 100_000)] == [4096, 4096, 8192, 131072]
    with pytest.raises(EmptyBufferError):
        size_class(0)


def test_steady_state_publishing_reuses_one_block():
    pool = get_pool(wp.get_device("cpu"))
    before = pool.stats()
    for i in range(50):
        buffer = allocate_buffer(3000, "cpu")
        with from_output_buffer(buffer) as out:
            out.array.fill_(i)
        with Buffer(ipc.import_buffer(ipc.export_buffer(buffer))) as received:
            assert received.to_numpy()[0] == i
        del buffer, out, received
    after = pool.stats()
    assert after["created"] - before["created"] == 1
    assert after["reused"] - before["reused"] == 49


def _arena_pages() -> int:
    from warp_buffer.arena import current_arena

    return os.fstat(current_arena().fd).st_blocks  # 512-byte units the arena really holds


def test_idle_memory_goes_back_without_an_explicit_trim(monkeypatch):
    monkeypatch.setenv("WARP_BUFFER_POOL_IDLE_S", "0.2")
    buffer = allocate_buffer(1 << 20, "cpu")
    with from_output_buffer(buffer) as out:
        out.array.fill_(1)  # touch every page
    block = buffer.get_impl().block
    touched = _arena_pages()
    del buffer, out
    gc.collect()
    deadline = time.monotonic() + 10
    while block.arena is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert block.arena is None, "the janitor never gave the idle block back"
    assert touched - _arena_pages() >= (1 << 20) // 512  # its pages went back to the system


def test_idle_bytes_beyond_the_cap_are_freed_at_once(monkeypatch):
    monkeypatch.setenv("WARP_BUFFER_POOL_MAX_IDLE_BYTES", str(8192))
    buffers = [allocate_buffer(8192, "cpu") for _ in range(4)]
    blocks = [b.get_impl().block for b in buffers]
    del buffers
    gc.collect()
    allocate_buffer(10, "cpu")  # any pool operation enforces the cap
    assert sum(b.arena is not None for b in blocks) == 1


def test_the_idle_cap_probes_few_held_blocks_per_allocation(monkeypatch):
    """A subscriber keeping every frame leaves its blocks on the publisher's free lists (their
    leases ended there); the cap probed them all at every allocation, and publishing slowed 10x
    past a GiB of holds. Now at most PROBES per allocation, the held ones moved to the back."""
    import collections

    from warp_buffer import pool as pool_module

    class _Block:
        capacity = 8192

        def __init__(self, reclaimable: bool) -> None:
            self.reclaimable, self.probes, self.destroyed = reclaimable, 0, False

        def try_reclaim(self) -> bool:
            self.probes += 1
            return self.reclaimable

        def destroy(self) -> None:
            self.destroyed = True

    pool = pool_module.BlockPool(wp.get_device("cpu"))
    held = [_Block(False) for _ in range(500)]
    free = [_Block(True) for _ in range(4)]  # the newest: behind every held one
    pool._free[8192] = collections.deque((b, float(i)) for i, b in enumerate(held + free))
    pool.free_bytes = 8192 * 504
    monkeypatch.setenv("WARP_BUFFER_POOL_MAX_IDLE_BYTES", str(8192 * 500))
    calls = 0
    while not all(b.destroyed for b in free):
        before = sum(b.probes for b in held + free)
        pool._enforce_idle_cap()
        assert sum(b.probes for b in held + free) - before <= pool_module.PROBES
        calls += 1
        assert calls < 100, "the free blocks behind the held ones were never reached"
    assert not any(b.destroyed for b in held) and pool.free_bytes == 8192 * 500
    assert len(pool._free[8192]) == 500


def test_a_full_arena_is_said_once_and_counted(monkeypatch, caplog):
    """A subscriber holding every frame filled the arena: the publisher then logged a warning
    per publish (3,209 in 25 s) and nothing counted the blocks that lost zero copy."""
    import logging

    from warp_buffer.arena import current_arena

    arena = current_arena()
    private = get_pool(wp.get_device("cpu")).private
    alloc = arena.alloc
    # no 4 MiB range left; smaller ones still served (they must not say "serves again" each)
    monkeypatch.setattr(arena, "alloc", lambda capacity: None if capacity >= 1 << 22
                        else alloc(capacity))
    with caplog.at_level(logging.WARNING, logger="warp_buffer.pool"):
        full = []
        for _ in range(3):
            full.append(allocate_buffer(1 << 22, "cpu"))
            small = allocate_buffer(1 << 16, "cpu")
            assert small.get_impl().is_exportable
        monkeypatch.undo()
        again = allocate_buffer(1 << 22, "cpu")
    said = [r.getMessage() for r in caplog.records if r.name == "warp_buffer.pool"]
    assert len(said) == 2 and "no 4194304-byte range left" in said[0] and "CPU bytes" in said[0]
    assert "serves again" in said[1]
    assert not any(b.get_impl().is_exportable for b in full) and again.get_impl().is_exportable
    assert get_pool(wp.get_device("cpu")).private == private + 3
    assert warp_buffer.pool_stats()["cpu"]["private"] == private + 3


def test_disabled_ipc_uses_private_memory(monkeypatch):
    monkeypatch.setenv("WARP_BUFFER_DISABLE_IPC", "1")
    buffer = allocate_buffer(5000, "cpu")
    assert not buffer.get_impl().is_exportable and not buffer.get_impl().block.shared
    with pytest.raises(warp_buffer.ExportUnavailableError):
        ipc.export_buffer(buffer)
    with from_output_buffer(allocate_buffer(8, "cpu")) as out:
        to_buffer(b"12345678", out)
        assert bytes(out.array.numpy()) == b"12345678"


# --------------------------------------------------------------------------- CUDA paths
@pytest.mark.cuda
def test_cuda_write_read_on_other_streams_to_cpu_and_clone():  # pragma: no cover - needs a GPU
    device = wp.get_cuda_devices()[0]
    buffer = allocate_buffer(1 << 20, device.alias)
    assert buffer.get_impl().device == device.alias
    writer = wp.Stream(device)
    with from_output_buffer(buffer, stream=writer) as out:
        fill_pattern(out.array, 5)
    reader = wp.Stream(device)
    with from_input_buffer(buffer, stream=reader) as view:
        assert view.stream is reader
    np.testing.assert_array_equal(buffer.to_numpy(), expected_pattern(1 << 20, 5))
    clone = buffer.copy()
    assert clone.get_impl().device == device.alias and clone == buffer
    host = allocate_buffer(64, "cpu")
    with from_output_buffer(host) as out:
        to_buffer(torch.arange(16, dtype=torch.float32, device="cuda"), out)
    np.testing.assert_array_equal(host.to_numpy().view(np.float32), np.arange(16))


def test_a_strided_memoryview_is_copied_in():
    source = bytes(range(32))
    buffer = allocate_buffer(16, "cpu")
    with from_output_buffer(buffer) as out:
        to_buffer(memoryview(source)[::2], out)
    assert buffer.to_numpy().tobytes() == source[::2]


def test_handle_views_and_arguments_raise_typed_errors():
    """Shapes and dtypes a view cannot take are warp_buffer errors that also subclass the
    matching builtin (they were Warp's IndexError, plain ValueError and TypeError, and a
    fractional shape was truncated: (2.9,) gave 2 elements)."""
    import warp_buffer as wb

    with from_output_buffer(allocate_buffer(16, "cpu")) as handle:
        for shape, error in (((), wb.InvalidSizeError), ((-1, 2), wb.InvalidSizeError),
                             ((1, 1, 1, 1, 1), wb.InvalidSizeError), ((2.9,), wb.SizeTypeError),
                             ((True,), wb.SizeTypeError), ("ab", wb.SizeTypeError),
                             (2.0, wb.SizeTypeError)):
            with pytest.raises(error):
                handle.view(wp.float32, shape)
        assert issubclass(wb.InvalidSizeError, ValueError) and issubclass(wb.SizeTypeError,
                                                                         TypeError)
        with pytest.raises(wb.InvalidDTypeError) as refused:
            handle.view("no such dtype")
        assert isinstance(refused.value, TypeError)
        assert handle.view(wp.float32, np.int64(2)).shape == (2,)
        assert handle.view(np.uint8, [2, 8]).shape == (2, 8)
    for not_a_buffer in (b"abc", np.zeros(4, np.uint8), None):
        with pytest.raises(wb.UnsupportedSourceError, match="to_buffer"):
            from_output_buffer(not_a_buffer)
        with pytest.raises(TypeError):
            from_input_buffer(not_a_buffer)
