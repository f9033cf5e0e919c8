"""More consumers through DLPack: JAX, ONNX Runtime and CuPy modules of the same shape.

Each framework is optional (extras ``jax``, ``onnx``, ``cupy``): its tests skip, with the reason,
when it is not installed; CuPy's also without a CUDA device.
"""

from __future__ import annotations

import numpy as np
import pytest

import tensor_conversions as tc
from rosidl_buffer.messages import deserialize_message, serialize_message
from tensor_conversions import numpy as tc_numpy

pytestmark = pytest.mark.usefixtures("warp_pool_drained")


def _msg(values: np.ndarray, backend: str = "cpu"):
    msg = tc_numpy.allocate_tensor_msg(values.shape, values.dtype, backend=backend,
                                       device="cpu" if backend == "warp" else None)
    tc_numpy.to_tensor_msg(msg, values)
    return msg


def _host_ptr(msg) -> int:
    if msg.data.get_backend_type() == "cpu":
        return msg.data.numpy(writable=False).ctypes.data
    return msg.data.get_impl().array.ptr


# ------------------------------------------------------------------------------------- JAX
@pytest.fixture(scope="module")
def tc_jax():
    pytest.importorskip("jax", reason="jax not installed (pip install warp-buffer[jax])")
    from tensor_conversions import jax as module

    return module


@pytest.mark.parametrize("backend", ["cpu", "warp"])
def test_jax_input_view_is_zero_copy(tc_jax, backend):
    values = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    msg = _msg(values, backend)
    view = tc_jax.from_input_tensor_msg(msg, clone=False)
    assert view.shape == (2, 3, 4) and view.dtype == np.float32
    assert view.unsafe_buffer_pointer() == _host_ptr(msg)
    np.testing.assert_array_equal(np.asarray(view), values)
    copy = tc_jax.from_input_tensor_msg(msg)
    assert copy.unsafe_buffer_pointer() != _host_ptr(msg)
    np.testing.assert_array_equal(np.asarray(copy), values)


def test_jax_reads_received_read_only_bytes(tc_jax):
    received = deserialize_message(serialize_message(_msg(np.arange(6, dtype=np.int32))),
                                   type(_msg(np.zeros(1))))
    np.testing.assert_array_equal(np.asarray(tc_jax.from_input_tensor_msg(received)),
                                  np.arange(6))


def test_jax_to_msg_and_back(tc_jax):
    import jax.numpy as jnp

    value = jnp.arange(12, dtype=jnp.int16).reshape(3, 4) * 3
    msg = tc_jax.to_tensor_msg(value)
    np.testing.assert_array_equal(tc_numpy.from_input_tensor_msg(msg), np.asarray(value))
    bf = tc_jax.to_tensor_msg(jnp.ones((2,), jnp.bfloat16))
    assert (bf.dtype_code, bf.dtype_bits) == (tc.DLDataTypeCode.BFLOAT, 16)
    into = tc_jax.allocate_tensor_msg((3, 4), jnp.int16)
    tc_jax.to_tensor_msg(into, value)
    np.testing.assert_array_equal(tc_numpy.from_input_tensor_msg(into), np.asarray(value))


def test_jax_strided_needs_clone_and_no_output_view(tc_jax):
    msg = _msg(np.arange(12, dtype=np.float32).reshape(3, 4))
    tc.write_metadata(msg, tc.TensorLayout(tc.dtype_from_name("float32"), (3, 2), (4, 2), 0))
    with pytest.raises(tc.InvalidTensorMetadataError, match="contiguous"):
        tc_jax.from_input_tensor_msg(msg, clone=False)
    np.testing.assert_array_equal(np.asarray(tc_jax.from_input_tensor_msg(msg)),
                                  np.arange(12, dtype=np.float32).reshape(3, 4)[:, ::2])
    with pytest.raises(tc.UnsupportedBackendError, match="immutable"):
        tc_jax.from_output_tensor_msg(msg)
    with pytest.raises(tc.UnsupportedValueError, match="list"):
        tc_jax.to_tensor_msg([1, 2])


# ---------------------------------------------------------------------------- ONNX Runtime
@pytest.fixture(scope="module")
def tc_onnx():
    pytest.importorskip("onnxruntime",
                        reason="onnxruntime not installed (pip install warp-buffer[onnx])")
    from tensor_conversions import onnx as module

    return module


@pytest.mark.parametrize("backend", ["cpu", "warp"])
def test_ortvalue_input_view_is_zero_copy(tc_onnx, backend):
    values = np.arange(6, dtype=np.float32).reshape(2, 3)
    msg = _msg(values, backend)
    view = tc_onnx.from_input_tensor_msg(msg, clone=False)
    assert view.shape() == [2, 3] and view.data_type() == "tensor(float)"
    assert view.data_ptr() == _host_ptr(msg)
    np.testing.assert_array_equal(view.numpy(), values)
    copy = tc_onnx.from_input_tensor_msg(msg)
    assert copy.data_ptr() != _host_ptr(msg)
    np.testing.assert_array_equal(copy.numpy(), values)


def test_ortvalue_to_msg(tc_onnx):
    import onnxruntime as ort

    for dtype in (np.float32, np.float64, np.int64, np.uint8, np.bool_):
        values = (np.arange(5) % 2).astype(dtype)
        msg = tc_onnx.to_tensor_msg(ort.OrtValue.ortvalue_from_numpy(values))
        np.testing.assert_array_equal(tc_numpy.from_input_tensor_msg(msg), values)
    with pytest.raises(tc.UnsupportedBackendError, match="in place"):
        tc_onnx.from_output_tensor_msg(msg)
    with pytest.raises(tc.UnsupportedValueError):
        tc_onnx.to_tensor_msg(np.zeros(2))


def test_ortvalue_refuses_complex_with_the_typed_error(tc_onnx):
    """ONNX Runtime's bridges refuse complex with raw RuntimeErrors (1.30)."""
    msg = tc_numpy.to_tensor_msg(np.ones(3, np.complex64))
    for clone in (True, False):
        with pytest.raises(tc.UnsupportedDTypeError, match="complex64"):
            tc_onnx.from_input_tensor_msg(msg, clone=clone)
    with pytest.raises(tc.UnsupportedDTypeError, match="complex128"):
        tc_onnx.allocate_tensor_msg((2,), np.complex128)


# ------------------------------------------------------------------------------------ CuPy
@pytest.mark.cuda
def test_cupy_round_trip_on_cuda():
    cupy = pytest.importorskip("cupy", reason="cupy not installed (pip install warp-buffer[cupy])")
    from tensor_conversions import cupy as tc_cupy

    value = cupy.arange(12, dtype=cupy.float32).reshape(3, 4)
    msg = tc_cupy.to_tensor_msg(value)
    assert msg.data.get_backend_type() == "warp" and str(msg.data.get_impl().device) == "cuda:0"
    view = tc_cupy.from_input_tensor_msg(msg, clone=False)
    assert view.data.ptr == msg.data.get_impl().array.ptr
    assert bool((view == value).all())
    out_msg = tc_cupy.allocate_tensor_msg((3, 4), cupy.float32, backend="warp", device="cuda:0")
    stream = cupy.cuda.Stream(non_blocking=True)
    with stream:  # written on a non-default CuPy stream: the handle follows it
        tc_cupy.from_output_tensor_msg(out_msg)[...] = value * 2
    tc.release_output(out_msg)
    np.testing.assert_array_equal(tc_numpy.from_input_tensor_msg(out_msg), cupy.asnumpy(value) * 2)
    with pytest.raises(tc.UnsupportedBackendError, match="host memory"):
        tc_cupy.from_input_tensor_msg(_msg(np.zeros(2, np.float32)), clone=False)


@pytest.mark.parametrize("module, package", [("jax", "jax"), ("onnx", "onnxruntime"),
                                             ("cupy", "cupy")])
def test_a_missing_optional_framework_names_the_extra_to_install(module, package):
    import importlib
    import importlib.util

    if importlib.util.find_spec(package) is not None:
        pytest.skip(f"{package} is installed here")
    with pytest.raises(ImportError, match=rf"warp-buffer\[{module}\]"):
        importlib.import_module(f"tensor_conversions.{module}")
