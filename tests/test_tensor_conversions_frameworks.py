"""tensor_conversions.torch / .numpy / .warp on CPU storage: shapes, every dtype bit-exactly,
strided sources, to_tensor_msg rules, cross-framework exchange and backend/device errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

import tensor_conversions as tc
from tensor_conversions.testing import (
    FRAMEWORK_DTYPES,
    MODULES,
    SHARED_DTYPES,
    framework_dtype,
    make_value,
    random_bits,
    to_raw,
)

SHAPES = [(), (7,), (3, 5), (2, 3, 4, 5)]
CASES = [(f, n) for f in MODULES for n in FRAMEWORK_DTYPES[f]]


def _expected_shape(framework, shape):
    return (1,) if framework == "warp" and shape == () else shape  # Warp has no 0-d arrays


@pytest.mark.parametrize("framework, name", CASES)
def test_every_dtype_round_trips_bit_exactly(framework, name):
    module = MODULES[framework]
    for shape in SHAPES:
        if framework == "warp" and shape == ():
            continue  # no 0-d Warp values; scalar messages are covered below
        raw = random_bits(name, shape, seed=len(shape))
        msg = module.to_tensor_msg(make_value(framework, name, raw), backend="cpu")
        assert list(msg.shape) == list(shape) and len(msg.strides) == 0
        assert msg.data.get_backend_type() == "cpu"
        np.testing.assert_array_equal(msg.data.to_numpy(), raw.reshape(-1))
        for clone in (True, False):
            out = module.from_input_tensor_msg(msg, clone=clone)
            assert tuple(out.shape) == shape
            np.testing.assert_array_equal(to_raw(out), raw)


@pytest.mark.parametrize("framework", list(MODULES))
@pytest.mark.parametrize("shape", SHAPES)
def test_allocate_fill_read(framework, shape):
    module = MODULES[framework]
    msg = module.allocate_tensor_msg(shape, framework_dtype(framework, "float32"))
    n = int(np.prod(shape))
    assert len(msg.data) == 4 * n and msg.data.get_backend_type() == "cpu"
    assert (msg.dtype_code, msg.dtype_bits, msg.dtype_lanes) == (2, 32, 1)
    out = module.from_output_tensor_msg(msg)
    assert tuple(out.shape) == _expected_shape(framework, shape)
    source = np.asarray(np.arange(n, dtype=np.float32).reshape(shape) + 0.5)
    if framework == "warp":
        wp.copy(out, wp.array(source.reshape(-1), dtype=wp.float32, device="cpu"))
    else:
        out[...] = torch.from_numpy(source) if framework == "torch" else source
    del out
    np.testing.assert_array_equal(msg.data.to_numpy().view(np.float32), source.reshape(-1))
    for reader in MODULES.values():  # cross-framework read of what this framework wrote
        got = reader.from_input_tensor_msg(msg)
        got = got if isinstance(got, np.ndarray) else got.numpy()
        np.testing.assert_array_equal(got.reshape(shape), source)


def _strided_sources(framework):
    base = np.arange(4 * 6, dtype=np.int32).reshape(4, 6)
    t = torch.from_numpy(base.copy())
    if framework == "torch":
        return [t.t(), t[:, ::2], t[1:3, 1:5], t.reshape(2, 2, 6).permute(2, 0, 1)]
    if framework == "numpy":
        return [base.T, base[:, ::2], base[1:3, 1:5], base[::-1], np.asfortranarray(base)]
    return [wp.from_dlpack(t.t()), wp.from_dlpack(t[:, ::2]), wp.from_dlpack(t[1:3, 1:5])]


@pytest.mark.parametrize("framework", list(MODULES))
def test_strided_sources_are_normalized(framework):
    """Transposed/sliced sources are copied into a contiguous row-major payload (empty strides)."""
    module = MODULES[framework]
    for source in _strided_sources(framework):
        expected = to_raw(source)
        msg = module.to_tensor_msg(source, backend="cpu")
        assert len(msg.strides) == 0 and msg.byte_offset == 0
        assert len(msg.data) == expected.size
        np.testing.assert_array_equal(msg.data.to_numpy(), expected.reshape(-1))
        np.testing.assert_array_equal(to_raw(module.from_input_tensor_msg(msg)), expected)


@pytest.mark.parametrize("framework", list(MODULES))
def test_to_tensor_msg_into_preallocated(framework):
    module = MODULES[framework]
    msg = module.allocate_tensor_msg((4, 4), framework_dtype(framework, "float64"))
    raw = random_bits("float32", (2, 3))
    value = make_value(framework, "float32", raw)
    assert module.to_tensor_msg(msg, value) is msg
    assert (msg.dtype_code, msg.dtype_bits) == (2, 32) and list(msg.shape) == [2, 3]
    assert len(msg.data) == 128  # storage kept, larger than needed
    np.testing.assert_array_equal(to_raw(module.from_input_tensor_msg(msg)), raw)
    # the output view follows the refreshed metadata
    assert tuple(module.from_output_tensor_msg(msg).shape) == (2, 3)


@pytest.mark.parametrize("framework", list(MODULES))
def test_to_tensor_msg_too_small_raises_and_changes_nothing(framework):
    module = MODULES[framework]
    msg = module.allocate_tensor_msg((2,), framework_dtype(framework, "int8"))
    before = (msg.dtype_code, msg.dtype_bits, list(msg.shape), msg.data.to_numpy().tolist())
    value = make_value(framework, "int32", random_bits("int32", (3,)))
    with pytest.raises(tc.TensorSizeError, match="needs 12 bytes"):
        module.to_tensor_msg(msg, value)
    assert (msg.dtype_code, msg.dtype_bits, list(msg.shape), msg.data.to_numpy().tolist()) == before
    with pytest.raises(tc.UnsupportedBackendError):
        module.to_tensor_msg(msg, value, backend="cpu")


@pytest.mark.parametrize("src", list(MODULES))
@pytest.mark.parametrize("dst", list(MODULES))
def test_cross_framework_exchange(src, dst):
    """A tensor sent from one framework is received bit-exactly by another (shared dtypes)."""
    for i, name in enumerate(SHARED_DTYPES):
        raw = random_bits(name, (3, 4), seed=i)
        msg = MODULES[src].to_tensor_msg(make_value(src, name, raw), backend="cpu")
        received = MODULES[dst].from_input_tensor_msg(msg, clone=bool(i % 2))
        assert received.dtype == framework_dtype(dst, name)
        np.testing.assert_array_equal(to_raw(received), raw)


@pytest.mark.parametrize("framework", ["torch", "warp"])
def test_bfloat16_between_torch_and_warp(framework):
    raw = random_bits("bfloat16", (5, 3))
    msg = MODULES[framework].to_tensor_msg(make_value(framework, "bfloat16", raw), backend="cpu")
    assert (msg.dtype_code, msg.dtype_bits) == (4, 16)
    for reader in ("torch", "warp"):
        np.testing.assert_array_equal(to_raw(MODULES[reader].from_input_tensor_msg(msg)), raw)
    with pytest.raises(tc.UnsupportedDTypeError, match="bfloat16"):
        MODULES["numpy"].from_input_tensor_msg(msg)


def test_scalar_messages():
    msg = MODULES["torch"].to_tensor_msg(torch.tensor(2.5, dtype=torch.float32))
    assert list(msg.shape) == [] and len(msg.data) == 4
    assert MODULES["numpy"].from_input_tensor_msg(msg).shape == ()
    assert MODULES["numpy"].from_input_tensor_msg(msg, clone=False)[()] == 2.5
    assert MODULES["torch"].from_input_tensor_msg(msg, clone=False).item() == 2.5
    warp_view = MODULES["warp"].from_input_tensor_msg(msg, clone=False)
    assert warp_view.shape == (1,) and warp_view.numpy()[0] == 2.5
    MODULES["warp"].to_tensor_msg(msg, wp.array([4.0], dtype=wp.float32, device="cpu"))
    assert MODULES["numpy"].from_input_tensor_msg(msg).tolist() == [4.0]


@pytest.mark.parametrize("framework", list(MODULES))
def test_empty_tensors(framework):
    module = MODULES[framework]
    msg = module.allocate_tensor_msg((0, 3), framework_dtype(framework, "float32"))
    assert len(msg.data) == 0
    assert tuple(module.from_input_tensor_msg(msg).shape) == (0, 3)
    assert tuple(module.from_input_tensor_msg(msg, clone=False).shape) == (0, 3)


@pytest.mark.parametrize("framework", list(MODULES))
def test_unservable_backend_or_device_raises(framework):
    module = MODULES[framework]
    dtype = framework_dtype(framework, "float32")
    with pytest.raises(tc.UnsupportedBackendError, match="unknown backend"):
        module.allocate_tensor_msg((2,), dtype, backend="cuda")
    with pytest.raises(tc.UnsupportedBackendError, match="host memory"):
        module.allocate_tensor_msg((2,), dtype, backend="cpu", device="cuda:0")
    with pytest.raises(tc.UnsupportedBackendError, match="not available"):
        module.allocate_tensor_msg((2,), dtype, backend="warp", device="cuda:97")
    with pytest.raises(tc.InvalidTensorMetadataError):
        module.allocate_tensor_msg((2, -1), dtype)


def test_unknown_storage_backend_raises():
    from rosidl_buffer import Buffer, BufferImplBase

    class Elsewhere(BufferImplBase):
        def get_backend_type(self):
            return "elsewhere"

        def size(self):
            return 8

        def to_cpu(self):
            raise NotImplementedError

        def clone(self):
            return self

    msg = MODULES["numpy"].allocate_tensor_msg((2,), np.float32)
    msg.data = Buffer(Elsewhere())
    for module in MODULES.values():
        with pytest.raises(tc.UnsupportedBackendError, match="elsewhere"):
            module.from_input_tensor_msg(msg)


def test_wrong_value_types_raise():
    with pytest.raises(TypeError):
        MODULES["torch"].to_tensor_msg(np.zeros(3))
    with pytest.raises(TypeError):
        MODULES["warp"].to_tensor_msg(np.zeros(3))
    msg = MODULES["numpy"].allocate_tensor_msg((3,), np.float32)
    with pytest.raises(TypeError):
        MODULES["numpy"].to_tensor_msg(msg)
