"""The NumPy host-view fast path of ``from_input_tensor_msg(msg, clone=False)``: a read-only
ndarray built straight over CPU storage or warp storage on Warp's ``cpu`` device, checked against
the general path (``input_native``) for layouts, fallbacks, metadata forms and lifetimes."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import warp_buffer

import tensor_conversions as tc
from rosidl_buffer.messages import deserialize_message, serialize_message
from tensor_conversions import _api, metadata
from tensor_conversions import numpy as tn
from tensor_conversions.storage import live_write_handle

pytestmark = pytest.mark.usefixtures("warp_pool_drained")

STORAGES = [("cpu", None), ("warp", "cpu")]
IDS = ["cpu", "warp-cpu"]
_INPUT_NATIVE = _api.input_native  # the general path (the fixture below replaces the name)


def _filled(backend, device, values):
    """A message of ``values`` (written through the output view, write complete)."""
    msg = tn.allocate_tensor_msg(values.shape, values.dtype, backend=backend, device=device)
    out = tn.from_output_tensor_msg(msg)
    out[...] = values
    del out
    tc.release_output(msg)
    return msg


def _raw_msg(backend, device, raw, dtype, shape, strides, byte_offset):
    """Storage holding the bytes ``raw``, with metadata for ``dtype``/shape/strides/offset."""
    msg = _filled(backend, device, raw)
    dt = tn._ADAPTER.to_dtype(dtype)
    msg.dtype_code, msg.dtype_bits, msg.dtype_lanes = dt.code, dt.bits, dt.lanes
    msg.shape = np.asarray(shape, np.int64).reshape(-1)
    msg.strides = np.asarray(strides, np.int64).reshape(-1)
    msg.byte_offset = byte_offset
    return msg


def _storage_span(msg):
    """``(first byte address, size)`` of the message's storage."""
    if msg.data.get_backend_type() == "cpu":
        return msg.data.get_impl().view().ctypes.data, len(msg.data)
    handle = warp_buffer.from_input_buffer(msg.data)
    ptr = handle.ptr
    handle.release()
    return ptr, len(msg.data)


@pytest.fixture
def general_calls(monkeypatch):
    """The ``clone`` of each call that took the general path (a fast-path read adds none)."""
    calls = []

    def spy(adapter, msg, layout, clone):
        calls.append(clone)
        return _INPUT_NATIVE(adapter, msg, layout, clone)
    monkeypatch.setattr(_api, "input_native", spy)
    return calls


@pytest.mark.parametrize("backend, device", STORAGES, ids=IDS)
def test_zero_copy_read_only_view(backend, device, general_calls):
    values = np.arange(12, dtype=np.float32).reshape(3, 4) * 1.5
    msg = _filled(backend, device, values)
    arr = tn.from_input_tensor_msg(msg, clone=False)
    base, size = _storage_span(msg)
    assert arr.ctypes.data == base and arr.nbytes == size
    np.testing.assert_array_equal(arr, values)
    assert arr.flags.writeable is False
    with pytest.raises(ValueError):
        arr[0, 0] = 7.0
    with pytest.raises(ValueError):
        np.copyto(arr, 0.0)
    assert general_calls == []  # the fast path, no TensorView
    np.testing.assert_array_equal(tn.from_input_tensor_msg(msg), values)  # nothing was written


def test_zero_copy_of_a_received_cpu_message(general_calls):
    values = np.arange(-6, 6, dtype=np.int16).reshape(2, 2, 3)
    sent = _filled("cpu", None, values)
    msg = deserialize_message(serialize_message(sent), type(sent))
    assert type(msg.data.get_impl()).__name__ == "CpuBufferImpl"
    arr = tn.from_input_tensor_msg(msg, clone=False)
    base, size = _storage_span(msg)
    assert arr.ctypes.data == base and arr.nbytes == size
    assert arr.ctypes.data != _storage_span(sent)[0]  # the received bytes, not the sender's
    np.testing.assert_array_equal(arr, values)
    assert arr.flags.writeable is False
    with pytest.raises(ValueError):
        arr[0, 0, 0] = 1
    assert general_calls == []


DTYPES = ["uint8", "int16", "float32", "float64", "complex64", "bool"]
# (shape, strides in elements or () for contiguous, byte offset)
LAYOUTS = [
    ((2, 3, 4), (), 0),
    ((3, 5), (1, 3), 16),         # transposed 2-D (column-major)
    ((2, 3, 4), (1, 2, 6), 8),    # permuted 3-D
    ((4, 3), (0, 1), 24),         # broadcast rows (zero stride)
    ((3, 2), (4, 1), 3),          # row padding (row stride > width), unaligned offset
    ((), (), 40),                 # 0-d scalar
]


@pytest.mark.parametrize("backend, device", STORAGES, ids=IDS)
@pytest.mark.parametrize("shape, strides, byte_offset", LAYOUTS)
def test_layouts_match_the_general_path(backend, device, shape, strides, byte_offset,
                                        general_calls):
    for dtype in DTYPES:  # one case per layout: the leak guard runs once, not per dtype
        _check_layout(backend, device, dtype, shape, strides, byte_offset, general_calls)


def _check_layout(backend, device, dtype, shape, strides, byte_offset, general_calls):
    raw = np.random.default_rng(byte_offset).integers(0, 256, 256, dtype=np.uint8)
    if dtype == "bool":
        raw %= 2  # only 0/1 are valid NumPy bools
    msg = _raw_msg(backend, device, raw, dtype, shape, strides, byte_offset)
    layout = metadata.layout_of(msg)
    fast = tn.from_input_tensor_msg(msg, clone=False)
    general = _INPUT_NATIVE(tn._ADAPTER, msg, layout, False)
    expected = np.ndarray(shape, np.dtype(dtype), buffer=raw.copy(), offset=byte_offset,
                          strides=layout.byte_strides)
    for got in (fast, general):
        assert got.dtype == np.dtype(dtype)
        assert got.shape == tuple(shape) and got.strides == layout.byte_strides
        np.testing.assert_array_equal(got, expected)
    assert fast.ctypes.data == general.ctypes.data == _storage_span(msg)[0] + byte_offset
    assert fast.flags.writeable is False and general.flags.writeable is False
    assert general_calls == []


@pytest.mark.parametrize("backend, device", STORAGES, ids=IDS)
@pytest.mark.parametrize("clone", [False, True])
def test_bfloat16_still_raises_the_typed_error(backend, device, clone, general_calls):
    msg = _filled(backend, device, np.arange(16, dtype=np.uint8))
    msg.dtype_code, msg.dtype_bits, msg.dtype_lanes = int(tc.DLDataTypeCode.BFLOAT), 16, 1
    msg.shape = np.array([8], np.int64)
    assert metadata.layout_of(msg).numpy_args is None
    with pytest.raises(tc.UnsupportedDTypeError, match="bfloat16"):
        tn.from_input_tensor_msg(msg, clone=clone)
    assert general_calls == [clone]


@pytest.mark.parametrize("backend, device", STORAGES, ids=IDS)
@pytest.mark.parametrize("shape", [(0,), (2, 0, 3)])
def test_empty_tensor_takes_the_general_path(backend, device, shape, general_calls):
    if backend == "cpu":  # warp buffers are never empty: empty metadata over 8 bytes instead
        msg = tn.allocate_tensor_msg(shape, "float64")
    else:
        msg = _raw_msg(backend, device, np.zeros(8, np.uint8), "float64", shape, (), 0)
    arr = tn.from_input_tensor_msg(msg, clone=False)
    assert arr.shape == shape and arr.dtype == np.float64 and arr.size == 0
    assert general_calls == [False]


@pytest.mark.parametrize("shape, strides", [
    ([2, 3], [1, 2]), ((2, 3), (1, 2)),
    (np.array([2, 3], np.int32), np.array([1, 2], np.int32)),
    ([2, 3], np.array([1, 2], np.int64)), (np.array([2, 3], np.int64), [1, 2]),
    (np.array([[2, 3]], np.int64), np.array([[1, 2]], np.int64)),  # 2-D: flattened
    (np.array([2, 3], np.uint16), np.array([1, 2], np.uint64)),
])
def test_layout_of_accepts_other_int_forms(shape, strides):
    values = np.arange(6, dtype=np.int16)
    msg = _filled("cpu", None, values)
    msg.shape, msg.strides = np.array([2, 3], np.int64), np.array([1, 2], np.int64)
    reference = metadata.layout_of(msg)
    want = tn.from_input_tensor_msg(msg, clone=False)
    msg.shape, msg.strides = shape, strides
    assert metadata.layout_of(msg) == reference
    assert reference.shape == (2, 3) and reference.strides == (1, 2)
    got = tn.from_input_tensor_msg(msg, clone=False)
    np.testing.assert_array_equal(got, values.reshape(3, 2).T)
    assert got.strides == want.strides and got.ctypes.data == want.ctypes.data


def test_layout_of_list_with_empty_strides_is_contiguous():
    msg = _filled("cpu", None, np.arange(6, dtype=np.int16))
    msg.shape, msg.strides = [3, 2], []
    assert metadata.layout_of(msg) == metadata.TensorLayout.contiguous(
        tn._ADAPTER.to_dtype("int16"), (3, 2))


@pytest.mark.parametrize("shape, strides, match", [
    ([-2, 3], [], "negative"),
    (np.array([2, -3], np.int32), np.array([], np.int32), "negative"),
    (np.array([-1], np.int64), np.array([], np.int64), "negative"),
    ([2, 3], [1], "one entry per dimension"),
    (np.array([2, 3], np.int64), np.array([3, 1, 1], np.int64), "one entry per dimension"),
    (np.array([2, 3], np.int32), np.array([1], np.int32), "one entry per dimension"),
    (["a", 3], [], "sequence of ints"),
    ([2, 3], [1, -1], "negative strides"),
])
def test_wrong_metadata_still_raises(shape, strides, match):
    msg = _filled("cpu", None, np.arange(6, dtype=np.int16))
    msg.shape, msg.strides = shape, strides
    with pytest.raises(tc.InvalidTensorMetadataError, match=match):
        metadata.layout_of(msg)
    with pytest.raises(tc.InvalidTensorMetadataError, match=match):
        tn.from_input_tensor_msg(msg, clone=False)


@pytest.mark.parametrize("backend, device", STORAGES, ids=IDS)
def test_view_keeps_the_storage_alive(backend, device, general_calls):
    values = np.linspace(0.0, 1.0, 64, dtype=np.float64).reshape(8, 8)
    msg = _filled(backend, device, values)
    arr = tn.from_input_tensor_msg(msg, clone=False)[::2, 1:]
    del msg
    gc.collect()
    if backend == "warp":
        warp_buffer.trim_pools(0.0)
        assert sum(s["leased"] for s in warp_buffer.pool_stats().values()) >= 1
        scratch = tn.allocate_tensor_msg((8, 8), np.float64, backend="warp", device="cpu")
        tn.from_output_tensor_msg(scratch)[...] = -1.0  # must not land in the viewed block
        tc.release_output(scratch)
        del scratch
    np.testing.assert_array_equal(arr, values[::2, 1:])
    assert general_calls == []


def test_read_through_the_live_write_handle(general_calls):
    msg = tn.allocate_tensor_msg((4, 4), "int32", backend="warp", device="cpu")
    out = tn.from_output_tensor_msg(msg)
    out[...] = np.arange(16, dtype=np.int32).reshape(4, 4)
    handle = live_write_handle(msg)
    assert handle is not None
    arr = tn.from_input_tensor_msg(msg, clone=False)
    assert arr.ctypes.data == out.ctypes.data  # the same memory, read through the write handle
    np.testing.assert_array_equal(arr, np.arange(16).reshape(4, 4))
    assert live_write_handle(msg) is handle  # still writable: no read handle sealed the buffer
    out[0, 0] = 99
    assert arr[0, 0] == 99
    assert arr.flags.writeable is False
    assert general_calls == []
    assert tc.release_output(msg) is True
    del out, arr, handle
    np.testing.assert_array_equal(tn.from_input_tensor_msg(msg, clone=False).ravel()[:3],
                                  [99, 1, 2])


@pytest.mark.parametrize("backend, device", STORAGES, ids=IDS)
@pytest.mark.parametrize("strides", [(), (1, 3)])
def test_clone_true_returns_a_writable_contiguous_copy(backend, device, strides):
    raw = np.arange(64, dtype=np.uint8)
    msg = _raw_msg(backend, device, raw, "float32", (3, 3), strides, 4)
    view = tn.from_input_tensor_msg(msg, clone=False)
    for copy in (tn.from_input_tensor_msg(msg), tn.from_input_tensor_msg(msg, clone=True)):
        assert copy.flags.writeable and copy.flags.c_contiguous
        base, size = _storage_span(msg)
        assert not base <= copy.ctypes.data < base + size
        np.testing.assert_array_equal(copy, view)
        copy[...] = 0
        assert view.any()  # the storage was not touched
    np.testing.assert_array_equal(view, np.ndarray((3, 3), np.float32, buffer=raw.copy(),
                                                   offset=4, strides=view.strides))


# ------------------------------------------------------------------------------------ torch
def test_torch_view_of_warp_host_storage_is_zero_copy_and_typed_for_missing_dtypes(
        general_calls):
    torch = pytest.importorskip("torch")
    from tensor_conversions import torch as tt

    values = np.arange(12, dtype=np.float32).reshape(3, 4)
    msg = _filled("warp", "cpu", values)
    view = tt.from_input_tensor_msg(msg, clone=False)
    base, _ = _storage_span(msg)
    assert view.const_data_ptr() == base and view.dtype == torch.float32
    assert view.shape == (3, 4) and torch.equal(view, torch.from_numpy(values))
    assert False not in general_calls  # the fast path, not input_native
    del view
    # a dtype torch lacks: the general path's typed error, and no read handle left open
    raw = _raw_msg("warp", "cpu", np.zeros(16, np.uint8), np.uint32, (4,), (), 0)
    try:
        tt.dtype_to_torch(tt.torch_to_dtype("uint32"))
    except tc.errors.UnsupportedDTypeError:
        with pytest.raises(tc.errors.UnsupportedDTypeError):
            tt.from_input_tensor_msg(raw, clone=False)
    else:
        assert tt.from_input_tensor_msg(raw, clone=False).dtype == torch.uint32


def test_torch_view_of_received_cpu_bytes_takes_dlpack_without_a_warning(general_calls):
    pytest.importorskip("torch")
    import warnings

    from tensor_conversions import torch as tt

    values = np.arange(8, dtype=np.int16)
    sent = _filled("cpu", None, values)
    received = deserialize_message(bytes(serialize_message(sent)), type(sent))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # torch.from_numpy of read-only bytes would warn
        view = tt.from_input_tensor_msg(received, clone=False)
    assert view.tolist() == values.tolist()
    assert general_calls == [False]  # read-only bytes: the general (DLPack) path


def test_fractional_metadata_is_an_error_not_a_truncated_layout():
    msg = _filled("cpu", None, np.zeros(24, np.uint8))
    for bad in ([2.5, 3], [True, "x"], [float("nan")]):
        msg.shape = bad
        with pytest.raises(tc.errors.InvalidTensorMetadataError):
            metadata.layout_of(msg)
    msg.shape, msg.strides = [2.0, 3], []  # integral floats are the ints they name
    assert metadata.layout_of(msg).shape == (2, 3)
