"""tensor_conversions core: dtype and metadata mapping, validation errors, the DLPack view,
strides/byte_offset, view lifetimes and the CDR round trip (framework-neutral parts)."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import torch
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st

import tensor_conversions as tc
from rosidl_buffer import Buffer
from rosidl_buffer.errors import RosidlBufferError
from rosidl_buffer.messages import deserialize_message, serialize_message
from tensor_conversions import numpy as tc_numpy
from tensor_conversions import torch as tc_torch
from tensor_conversions import warp as tc_warp
from tensor_conversions.testing import MODULES, framework_dtype

DL = tc.DLDataTypeCode


def _host(value):
    """A NumPy array of any framework's value (torch input views refuse ``.numpy()``: a copy)."""
    if isinstance(value, np.ndarray):
        return value
    if isinstance(value, torch.Tensor):
        return value.clone().numpy()
    return value.numpy()


def make_msg(data: np.ndarray, code: int, bits: int, shape, strides=(), byte_offset=0, lanes=1):
    cls = tc.tensor_msg_type()
    return cls(dtype_code=code, dtype_bits=bits, dtype_lanes=lanes,
               shape=np.asarray(shape, np.int64).reshape(-1),
               strides=np.asarray(strides, np.int64).reshape(-1),
               byte_offset=byte_offset, data=Buffer(np.asarray(data, np.uint8)))


# ------------------------------------------------------------------------------ dtype mapping
EXPECTED_CODES = {
    "bool": (6, 8), "int8": (0, 8), "int16": (0, 16), "int32": (0, 32), "int64": (0, 64),
    "uint8": (1, 8), "uint16": (1, 16), "uint32": (1, 32), "uint64": (1, 64),
    "float16": (2, 16), "float32": (2, 32), "float64": (2, 64), "bfloat16": (4, 16),
    "complex64": (5, 64), "complex128": (5, 128),
}


@pytest.mark.parametrize("name", sorted(EXPECTED_CODES))
def test_dtype_codes_follow_dlpack(name):
    dt = tc.dtype_from_name(name)
    assert (dt.code, dt.bits, dt.lanes) == (*EXPECTED_CODES[name], 1)
    assert dt.name == name
    assert tc.dtype_from_metadata(dt.code, dt.bits, 1) is dt


@pytest.mark.parametrize("framework", list(MODULES))
@pytest.mark.parametrize("name", sorted(EXPECTED_CODES))
def test_framework_dtype_maps_both_ways(framework, name):
    """Each framework's dtype maps to the DLPack triple and back, or raises a clear error."""
    module = MODULES[framework]
    supported = {"torch": True, "numpy": name != "bfloat16",
                 "warp": not name.startswith("complex")}[framework]
    if not supported:
        with pytest.raises(tc.UnsupportedDTypeError):
            module.allocate_tensor_msg((2,), name)
        return
    msg = module.allocate_tensor_msg((2,), framework_dtype(framework, name))
    assert (msg.dtype_code, msg.dtype_bits, msg.dtype_lanes) == (*EXPECTED_CODES[name], 1)
    out = module.from_input_tensor_msg(msg)
    assert out.dtype == framework_dtype(framework, name)


def test_torch_dtype_helpers_round_trip():
    for name in EXPECTED_CODES:
        assert tc_torch.dtype_to_torch(tc_torch.torch_to_dtype(getattr(torch, name))) is getattr(
            torch, name)
    with pytest.raises(tc.UnsupportedDTypeError, match="float8"):
        tc_torch.torch_to_dtype(torch.float8_e4m3fn)
    with pytest.raises(tc.UnsupportedDTypeError):
        tc_torch.torch_to_dtype("not-a-dtype")


def test_warp_dtype_helpers_reject_vectors():
    assert tc_warp.dtype_to_warp(tc_warp.warp_to_dtype(wp.bfloat16)) is wp.bfloat16
    with pytest.raises(tc.UnsupportedDTypeError, match="scalar"):
        tc_warp.warp_to_dtype(wp.vec3)
    with pytest.raises(tc.UnsupportedDTypeError, match="complex"):
        tc_warp.dtype_to_warp(tc.dtype_from_name("complex64"))


def test_numpy_dtype_errors():
    with pytest.raises(tc.UnsupportedDTypeError, match="bfloat16"):
        tc_numpy.allocate_tensor_msg((2,), "bfloat16")
    with pytest.raises(tc.UnsupportedDTypeError):
        tc.dtype_from_numpy(np.dtype("U3"))
    with pytest.raises(tc.UnsupportedDTypeError, match="big-endian"):
        tc.dtype_from_numpy(np.dtype(">f4"))


@pytest.mark.parametrize("code, bits, lanes, match", [
    (2, 32, 4, "lanes"),            # vector elements
    (2, 8, 1, "unsupported"),       # float8 is not a plain float code
    (3, 64, 1, "unsupported"),      # opaque handle
    (10, 8, 1, "unsupported"),      # float8_e4m3fn: no common framework dtype
    (6, 1, 1, "unsupported"),       # 1-bit bool
    (99, 32, 1, "unsupported"),     # unknown code
])
def test_unsupported_metadata_raises(code, bits, lanes, match):
    with pytest.raises(tc.UnsupportedDTypeError, match=match):
        tc.dtype_from_metadata(code, bits, lanes)
    msg = make_msg(np.zeros(64), code, bits, (2,), lanes=lanes)
    for module in MODULES.values():
        with pytest.raises(tc.UnsupportedDTypeError):
            module.from_input_tensor_msg(msg)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 255), st.integers(0, 255), st.integers(0, 65535))
def test_metadata_mapping_property(code, bits, lanes):
    """Any (code, bits, lanes) either maps to a DType that maps back to it, or raises typed."""
    try:
        dt = tc.dtype_from_metadata(code, bits, lanes)
    except tc.UnsupportedDTypeError as exc:
        assert isinstance(exc, RosidlBufferError)
        assert (code, bits) not in set(EXPECTED_CODES.values()) or lanes != 1
        return
    assert (dt.code, dt.bits, dt.lanes) == (code, bits, lanes)
    assert tc.dtype_from_name(dt.name) == dt
    if dt.name != "bfloat16":
        assert tc.dtype_from_numpy(dt.numpy_dtype()) == dt


# --------------------------------------------------------------------------- metadata errors
@pytest.mark.parametrize("shape, strides, byte_offset, nbytes, match", [
    ((2, 3), (1,), 0, 24, "one entry per dimension"),
    ((2, 3), (3, -1), 0, 24, "negative strides"),
    ((-1,), (), 0, 24, "negative dimension"),
    ((2, 3), (), 4, 24, "needs 28 bytes"),
    ((2, 3), (), 0, 20, "needs 24 bytes"),
    ((2, 3), (8, 1), 0, 40, "needs 44 bytes"),
])
def test_invalid_layout_raises(shape, strides, byte_offset, nbytes, match):
    msg = make_msg(np.zeros(nbytes), 2, 32, shape, strides, byte_offset)
    with pytest.raises(tc.InvalidTensorMetadataError, match=match):
        tc.layout_of(msg)
    for module in MODULES.values():
        with pytest.raises(tc.InvalidTensorMetadataError):
            module.from_input_tensor_msg(msg, clone=False)
        with pytest.raises(tc.InvalidTensorMetadataError):
            module.from_output_tensor_msg(msg)


def test_layout_properties():
    layout = tc.TensorLayout(tc.dtype_from_name("int16"), (3, 4), (1, 3), 6)
    assert not layout.is_contiguous
    assert layout.span_bytes == 24 and layout.required_nbytes == 30
    assert tc.contiguous_strides((2, 3, 4)) == (12, 4, 1)
    assert tc.contiguous_strides(()) == ()
    empty = tc.TensorLayout.contiguous(tc.dtype_from_name("float32"), (0, 5))
    assert empty.numel == 0 and empty.required_nbytes == 0


# --------------------------------------------------------------------- strides, byte_offset
def _reference(data: np.ndarray, np_dtype, shape, strides, byte_offset) -> np.ndarray:
    itemsize = np.dtype(np_dtype).itemsize
    raw = data[byte_offset:]
    usable = raw[: len(raw) - len(raw) % itemsize].view(np_dtype)
    return np.lib.stride_tricks.as_strided(
        usable, shape=shape, strides=tuple(s * itemsize for s in strides)).copy()


@pytest.mark.parametrize("framework", list(MODULES))
@pytest.mark.parametrize("shape, strides, byte_offset", [
    ((3, 4), (1, 3), 0),            # column-major (a transposed tensor)
    ((3, 4), (6, 1), 8),            # padded rows (row pitch 6) behind an 8-byte header
    ((2, 3, 4), (1, 2, 6), 4),      # fully permuted
    ((4,), (3,), 12),               # every third element
    ((2, 2, 2, 3), (), 4),          # rank-4 contiguous at an offset
    ((3, 2), (0, 1), 0),            # broadcast (zero stride)
    ((1, 4), (2**62, 1), 0),        # a size-1 dimension's stride never steps, however large
])
def test_strided_and_offset_payloads(framework, shape, strides, byte_offset):
    module = MODULES[framework]
    data = np.random.default_rng(1).integers(0, 256, 256, dtype=np.uint8)
    msg = make_msg(data, 2, 32, shape, strides, byte_offset)
    full_strides = tuple(0 if d == 1 else s
                         for d, s in zip(shape, strides or tc.contiguous_strides(shape)))
    expected = _reference(data, np.float32, shape, full_strides, byte_offset)
    for clone in (True, False):
        out = module.from_input_tensor_msg(msg, clone=clone)
        got = _host(out)
        np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))
    if any(s == 0 and d > 1 for d, s in zip(shape, full_strides)):
        return  # a broadcast view aliases elements: frameworks refuse writes, correctly
    # Writing through a strided output view lands on exactly those bytes, and only on them.
    out = module.from_output_tensor_msg(msg)
    if framework == "warp":
        out.fill_(7.0)
    else:
        out[...] = 7.0
    after = msg.data.to_numpy()
    np.testing.assert_array_equal(_reference(after, np.float32, shape, full_strides, byte_offset),
                                  np.full(shape, 7.0, np.float32))
    index = np.indices(shape).reshape(len(shape), -1)
    offsets = byte_offset + 4 * (np.asarray(full_strides)[:, None] * index).sum(axis=0)
    touched = np.zeros(len(data), bool)
    for start in offsets:
        touched[start:start + 4] = True
    np.testing.assert_array_equal(after[~touched], data[~touched])


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_random_layouts_property(data):
    """Random shapes, strides and offsets read identically to an independent NumPy reference."""
    ndim = data.draw(st.integers(0, 4))
    shape = tuple(data.draw(st.lists(st.integers(1, 4), min_size=ndim, max_size=ndim)))
    strides = tuple(data.draw(st.lists(st.integers(0, 7), min_size=ndim, max_size=ndim)))
    name = data.draw(st.sampled_from(["int8", "uint16", "float32", "int64", "float64"]))
    byte_offset = data.draw(st.integers(0, 3)) * np.dtype(name).itemsize
    dt = tc.dtype_from_name(name)
    layout = tc.TensorLayout(dt, shape, strides, byte_offset)
    payload = np.random.default_rng(len(shape)).integers(
        0, 256, layout.required_nbytes + data.draw(st.integers(0, 8)), dtype=np.uint8)
    msg = make_msg(payload, dt.code, dt.bits, shape, strides, byte_offset)
    expected = _reference(payload, np.dtype(name), shape, strides, byte_offset)
    np.testing.assert_array_equal(tc_numpy.from_input_tensor_msg(msg, clone=False), expected)
    np.testing.assert_array_equal(tc_torch.from_input_tensor_msg(msg).numpy(), expected)


def test_tensor_view_is_consumed_by_every_framework_zero_copy():
    data = np.arange(64, dtype=np.uint8)
    msg = make_msg(data, 1, 8, (4, 4), (1, 4), 16)
    view = tc.input_view(msg)
    base = msg.data.get_impl().view().ctypes.data + 16
    t = torch.from_dlpack(view)
    a = np.from_dlpack(view)
    w = wp.from_dlpack(view)
    assert t.data_ptr() == a.ctypes.data == w.ptr == base
    assert t.stride() == (1, 4) and tuple(s // 1 for s in a.strides) == (1, 4)
    assert view.__dlpack_device__() == (1, 0)
    assert "read-only" in repr(view)


# ------------------------------------------------------------------- lifetimes and aliasing
@pytest.mark.parametrize("framework", list(MODULES))
def test_views_outlive_the_message(framework):
    module = MODULES[framework]
    value = np.arange(12, dtype=np.float32).reshape(3, 4)
    msg = tc_numpy.to_tensor_msg(value)
    view = module.from_input_tensor_msg(msg, clone=False)
    out = module.from_output_tensor_msg(msg)
    del msg
    gc.collect()
    for _ in range(3):
        np.empty(4096, np.float32).fill(-1)  # churn the allocator
    np.testing.assert_array_equal(_host(view), value)
    written = out.numpy() if framework != "numpy" else out
    np.testing.assert_array_equal(written, value)


@pytest.mark.parametrize("framework", list(MODULES))
def test_clone_is_independent_and_view_aliases(framework):
    module = MODULES[framework]
    msg = tc_numpy.to_tensor_msg(np.arange(6, dtype=np.int32))
    copy = module.from_input_tensor_msg(msg)
    alias = module.from_input_tensor_msg(msg, clone=False)
    msg.data.numpy()[:4] = 255  # element 0 becomes -1
    assert _host(copy)[0] == 0
    assert _host(alias)[0] == -1


def test_numpy_input_view_is_read_only_and_output_view_writable():
    msg = tc_numpy.to_tensor_msg(np.arange(4, dtype=np.int16))
    view = tc_numpy.from_input_tensor_msg(msg, clone=False)
    assert not view.flags.writeable
    with pytest.raises(ValueError):
        view[0] = 1
    out = tc_numpy.from_output_tensor_msg(msg)
    out[0] = 9
    assert view[0] == 9 and out.flags.writeable


# --------------------------------------------------------------------------- CDR round trip
@pytest.mark.parametrize("as_bytes", [True, False])
def test_cdr_round_trip(as_bytes):
    value = torch.randn(3, 5, dtype=torch.float64)
    msg = tc_torch.to_tensor_msg(value)
    wire = serialize_message(msg)
    received = deserialize_message(bytes(wire) if as_bytes else bytearray(wire),
                                   tc.TENSOR_MSG_TYPE)
    assert torch.equal(tc_torch.from_input_tensor_msg(received), value)
    view = tc_torch.from_input_tensor_msg(received, clone=False)  # aliases the received bytes
    assert torch.equal(view, value)
    np.testing.assert_array_equal(tc_numpy.from_input_tensor_msg(received, clone=False),
                                  value.numpy())
    np.testing.assert_array_equal(tc_warp.from_input_tensor_msg(received, clone=False).numpy(),
                                  value.numpy())
    del received
    gc.collect()
    assert torch.equal(view, value)


def test_cdr_round_trip_keeps_strides_and_offset():
    data = np.random.default_rng(3).integers(0, 256, 80, dtype=np.uint8)
    msg = make_msg(data, 0, 16, (3, 4), (1, 3), 8)
    received = deserialize_message(bytes(serialize_message(msg)), tc.TENSOR_MSG_TYPE)
    np.testing.assert_array_equal(tc_numpy.from_input_tensor_msg(received),
                                  tc_numpy.from_input_tensor_msg(msg))


def test_a_layout_is_validated_once_per_distinct_metadata(monkeypatch):
    from tensor_conversions import metadata

    calls = []
    real = metadata._validate
    monkeypatch.setattr(metadata, "_LAYOUTS", {})
    monkeypatch.setattr(metadata, "_validate", lambda *key: calls.append(key) or real(*key))
    frames = [tc_numpy.to_tensor_msg(np.full((3, 4), i, np.float32)) for i in range(5)]
    calls.clear()
    for i, msg in enumerate(frames):  # new messages, same metadata: validated once
        assert tc_numpy.from_input_tensor_msg(msg, clone=False)[0, 0] == i
    assert len(calls) == 1
    frames[0].shape = np.array([4, 3], np.int64)  # other metadata: validated again
    assert tc_numpy.from_input_tensor_msg(frames[0]).shape == (4, 3)
    assert len(calls) == 2
    frames[1].byte_offset = 8  # and a bad change is still caught
    with pytest.raises(tc.InvalidTensorMetadataError, match="needs 56 bytes"):
        tc_numpy.from_input_tensor_msg(frames[1])
