"""tensor_conversions on warp-backed storage (warp_buffer), on Warp's ``cpu`` device here and on
CUDA where a GPU exists: round trips, the one-write-handle rule, view lifetimes, device errors."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest
import torch
import warp as wp

import tensor_conversions as tc
from tensor_conversions.storage import live_write_handle  
from tensor_conversions.testing import (
    FRAMEWORK_DTYPES,
    MODULES,
    framework_dtype,
    make_value,
    random_bits,
    to_raw,
)

pytestmark = pytest.mark.usefixtures("warp_pool_drained")


DEVICE = "cpu"  # Warp's cpu device: warp storage without a GPU



def _warp_msg(framework, name, raw, device=DEVICE):
    return MODULES[framework].to_tensor_msg(make_value(framework, name, raw), backend="warp",
                                            device=device)


@pytest.mark.parametrize("framework, name", [(f, n) for f in MODULES for n in FRAMEWORK_DTYPES[f]
                                             if not n.startswith("complex")])
def test_warp_backed_round_trip_bit_exact(framework, name):
    raw = random_bits(name, (3, 4), seed=5)
    msg = _warp_msg(framework, name, raw)
    assert msg.data.get_backend_type() == "warp"
    assert str(msg.data.get_impl().device) == DEVICE
    np.testing.assert_array_equal(msg.data.to_numpy(), raw.reshape(-1))
    for clone in (True, False):
        out = MODULES[framework].from_input_tensor_msg(msg, clone=clone)
        assert out.dtype == framework_dtype(framework, name)
        np.testing.assert_array_equal(to_raw(out), raw)


@pytest.mark.parametrize("framework", ["torch", "numpy"])
def test_complex_needs_cpu_storage(framework):
    value = make_value(framework, "complex64", random_bits("complex64", (2,)))
    with pytest.raises(tc.UnsupportedDTypeError, match="complex"):
        MODULES[framework].to_tensor_msg(value, backend="warp", device=DEVICE)


@pytest.mark.parametrize("src", list(MODULES))
@pytest.mark.parametrize("dst", list(MODULES))
def test_cross_framework_through_warp_storage(src, dst):
    raw = random_bits("float16", (2, 3, 2, 2), seed=9)
    msg = _warp_msg(src, "float16", raw)
    np.testing.assert_array_equal(to_raw(MODULES[dst].from_input_tensor_msg(msg)), raw)


@pytest.mark.parametrize("framework", list(MODULES))
def test_allocate_fill_publish_read(framework):
    module = MODULES[framework]
    msg = module.allocate_tensor_msg((4, 5), framework_dtype(framework, "int32"), backend="warp",
                                     device=DEVICE)
    assert msg.data.get_backend_type() == "warp" and len(msg.data) == 80
    out = module.from_output_tensor_msg(msg)
    second = module.from_output_tensor_msg(msg)  # shares the single write handle
    assert live_write_handle(msg) is not None
    values = np.arange(20, dtype=np.int32).reshape(4, 5)
    if framework == "warp":
        wp.copy(out, wp.array(values, dtype=wp.int32, device=DEVICE))
    else:
        out[...] = torch.from_numpy(values) if framework == "torch" else values
    got = second.numpy() if framework != "numpy" else second
    np.testing.assert_array_equal(got, values)  # both views alias the same memory
    del out, second, got
    gc.collect()
    assert live_write_handle(msg) is None  # handle released with the last view
    for reader in MODULES.values():
        got = reader.from_input_tensor_msg(msg)
        np.testing.assert_array_equal(got if isinstance(got, np.ndarray) else got.numpy(), values)


def test_write_after_release_rules():
    module = MODULES["numpy"]
    msg = module.allocate_tensor_msg((8,), np.float32, backend="warp", device=DEVICE)
    out = module.from_output_tensor_msg(msg)
    out[:] = 1.0
    assert tc.release_output(msg) is True
    assert tc.release_output(msg) is False
    # The buffer has used its one write handle: a new in-place view is refused ...
    with pytest.raises(tc.StorageNotWritableError, match="one write") as refused:
        module.from_output_tensor_msg(msg)
    assert isinstance(refused.value, (tc.TensorConversionError, RuntimeError))
    assert isinstance(refused.value, RuntimeError)  # the matching builtin, as every error here
    # ... while to_tensor_msg gives the message a fresh buffer of the same size and device.
    old = msg.data
    module.to_tensor_msg(msg, np.full(8, 2.0, np.float32))
    assert msg.data is not old and len(msg.data) == len(old)
    assert msg.data.get_backend_type() == "warp" and str(msg.data.get_impl().device) == DEVICE
    np.testing.assert_array_equal(module.from_input_tensor_msg(msg), np.full(8, 2.0, np.float32))
    np.testing.assert_array_equal(old.to_numpy().view(np.float32), np.ones(8, np.float32))
    # publisher loop: every iteration rewrites the message
    for i in range(3):
        module.to_tensor_msg(msg, np.full(8, float(i), np.float32))
        np.testing.assert_array_equal(module.from_input_tensor_msg(msg),
                                      np.full(8, float(i), np.float32))


def test_to_tensor_msg_writes_through_live_output_view():
    msg = MODULES["torch"].allocate_tensor_msg((3,), torch.float32, backend="warp", device=DEVICE)
    out = MODULES["torch"].from_output_tensor_msg(msg)
    data_before = msg.data
    MODULES["torch"].to_tensor_msg(msg, torch.tensor([1.0, 2.0, 3.0]))
    assert msg.data is data_before  # the live write handle was reused, not replaced
    assert out.tolist() == [1.0, 2.0, 3.0]
    assert live_write_handle(msg) is not None  # still held by `out`


@pytest.mark.parametrize("framework", list(MODULES))
def test_warp_views_outlive_the_message(framework):
    module = MODULES[framework]
    raw = random_bits("float32", (2, 5), seed=2)
    msg = _warp_msg(framework, "float32", raw)
    view = module.from_input_tensor_msg(msg, clone=False)
    del msg
    gc.collect()
    for _ in range(3):
        wp.zeros(1024, dtype=wp.float32, device=DEVICE)  # churn Warp's allocator
    np.testing.assert_array_equal(to_raw(view), raw)


def test_output_view_outlives_message_and_keeps_handle():
    msg = MODULES["warp"].allocate_tensor_msg((6,), wp.float64, backend="warp", device=DEVICE)
    impl = msg.data.get_impl()
    out = MODULES["warp"].from_output_tensor_msg(msg)
    handle = weakref.ref(live_write_handle(msg))
    del msg
    gc.collect()
    assert handle() is not None  # the view holds the write handle
    out.fill_(3.0)
    np.testing.assert_array_equal(out.numpy(), np.full(6, 3.0))
    np.testing.assert_array_equal(impl.to_cpu().view().view(np.float64), np.full(6, 3.0))
    del out
    gc.collect()
    assert handle() is None  # released with the last view


@pytest.mark.parametrize("framework", list(MODULES))
def test_strided_offset_layout_in_warp_storage(framework):
    payload = np.random.default_rng(4).integers(0, 256, 96, dtype=np.uint8)
    msg = MODULES["numpy"].to_tensor_msg(payload, backend="warp", device=DEVICE)
    layout = tc.TensorLayout(tc.dtype_from_name("float32"), (3, 4), (1, 5), 16)
    tc.write_metadata(msg, layout)
    expected = np.lib.stride_tricks.as_strided(payload[16:].view(np.float32), shape=(3, 4),
                                               strides=(4, 20))
    for clone in (True, False):
        got = MODULES[framework].from_input_tensor_msg(msg, clone=clone)
        np.testing.assert_array_equal(to_raw(got), to_raw(expected))


def test_scalar_in_warp_storage():
    msg = MODULES["torch"].to_tensor_msg(torch.tensor(7, dtype=torch.int64), backend="warp",
                                         device=DEVICE)
    assert list(msg.shape) == []
    assert MODULES["torch"].from_input_tensor_msg(msg, clone=False).shape == ()
    assert MODULES["torch"].from_input_tensor_msg(msg).item() == 7
    assert MODULES["numpy"].from_input_tensor_msg(msg, clone=False)[()] == 7
    assert MODULES["warp"].from_input_tensor_msg(msg).numpy().tolist() == [7]


def test_warp_default_backend_follows_the_array():
    array = wp.array(np.arange(5, dtype=np.float32), dtype=wp.float32, device=DEVICE)
    msg = MODULES["warp"].to_tensor_msg(array)
    assert msg.data.get_backend_type() == "warp"
    assert MODULES["torch"].to_tensor_msg(torch.zeros(2)).data.get_backend_type() == "cpu"


def test_an_empty_tensor_may_use_warp_storage_but_an_empty_image_may_not():
    # A tensor's storage may outgrow its layout (one byte under empty metadata); an image's
    # data is exactly step * height bytes, and a warp buffer is never empty.
    msg = MODULES["numpy"].allocate_tensor_msg((0,), np.float32, backend="warp", device=DEVICE)
    assert msg.data.get_backend_type() == "warp" and len(msg.data) == 1
    with pytest.raises(tc.UnsupportedBackendError, match="empty image"):
        MODULES["numpy"].allocate_image_msg(0, 4, "rgb8", backend="warp", device=DEVICE)


# ------------------------------------------------------------------------------------- CUDA
@pytest.mark.cuda
def test_cuda_storage_with_every_framework():
    msg = MODULES["torch"].allocate_tensor_msg((4, 4), torch.float32, backend="warp",
                                               device="cuda:0")
    assert str(msg.data.get_impl().device) == "cuda:0"
    out = MODULES["torch"].from_output_tensor_msg(msg)
    assert out.device.type == "cuda"
    out.copy_(torch.arange(16, dtype=torch.float32).reshape(4, 4))
    del out
    gc.collect()
    expected = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_array_equal(MODULES["numpy"].from_input_tensor_msg(msg), expected)
    with pytest.raises(tc.UnsupportedBackendError, match="NumPy cannot address"):
        MODULES["numpy"].from_input_tensor_msg(msg, clone=False)
    arr = MODULES["warp"].from_input_tensor_msg(msg, clone=False)
    assert str(arr.device) == "cuda:0"
    np.testing.assert_array_equal(arr.numpy(), expected)


@pytest.mark.cuda
def test_cuda_to_tensor_msg_defaults_and_host_sources():
    value = torch.randn(3, 5, device="cuda").t()
    msg = MODULES["torch"].to_tensor_msg(value)
    assert msg.data.get_backend_type() == "warp"
    assert torch.equal(MODULES["torch"].from_input_tensor_msg(msg), value)
    host = np.arange(15, dtype=np.float32).reshape(5, 3)
    MODULES["numpy"].to_tensor_msg(msg, host)
    np.testing.assert_array_equal(MODULES["numpy"].from_input_tensor_msg(msg), host)
    misaligned = MODULES["numpy"].to_tensor_msg(np.zeros(16, np.uint8), backend="warp",
                                                device="cuda:0")
    tc.write_metadata(misaligned, tc.TensorLayout(tc.dtype_from_name("float32"), (2,), (1,), 2))
    with pytest.raises(tc.InvalidTensorMetadataError, match="misaligned"):
        MODULES["torch"].from_input_tensor_msg(misaligned, clone=False)


def test_a_message_of_ones_own_released_refuses_its_tensor_and_a_view_taken_before_reads_on():
    """``msg.data.release()`` on a message this process allocated ends access through that
    message, as on a received one (it was a no-op: the tensor still came back)."""
    from warp_buffer.errors import HandleReleasedError

    module = MODULES["numpy"]
    msg = module.allocate_tensor_msg((4,), np.float32, backend="warp", device=DEVICE)
    module.to_tensor_msg(msg, np.arange(4, dtype=np.float32))
    before = module.from_input_tensor_msg(msg, clone=False)
    msg.data.release()
    for clone in (False, True):
        with pytest.raises(HandleReleasedError):
            module.from_input_tensor_msg(msg, clone=clone)
    np.testing.assert_array_equal(before, np.arange(4, dtype=np.float32))
