"""tensor_conversions on CUDA: writes complete on the stream that ran them (torch's current
stream, also a non-default one), reads are ordered on the consumer's stream, and no conversion
waits for the whole device (issue 14 point 3 and 4). Skipped without a CUDA device."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import torch
import warp as wp

import tensor_conversions as tc
from tensor_conversions import numpy as tc_numpy
from tensor_conversions import torch as tc_torch
from tensor_conversions import warp as tc_warp

pytestmark = [pytest.mark.cuda, pytest.mark.usefixtures("warp_pool_drained")]

N = 1 << 22  # 16 MiB of float32: a write long enough to race if ordering were wrong
SLOW = 50_000_000  # torch.cuda._sleep cycles (~25 ms): the writer is still busy when we read


@pytest.fixture
def no_device_sync(monkeypatch):
    """Fail any conversion that waits for the whole device."""
    def refuse(*args, **kwargs):
        raise AssertionError("wp.synchronize_device called by a conversion")

    monkeypatch.setattr(wp, "synchronize_device", refuse)
    monkeypatch.setattr(torch.cuda, "synchronize", refuse)


def _alloc():
    return tc_torch.allocate_tensor_msg((N,), torch.float32, backend="warp", device="cuda:0")


def test_write_under_a_non_default_torch_stream_is_seen_by_a_reader(no_device_sync):
    msg = _alloc()
    writer = torch.cuda.Stream()
    with torch.cuda.stream(writer):
        out = tc_torch.from_output_tensor_msg(msg)
        torch.cuda._sleep(SLOW)  # the fill below is queued behind a slow kernel on `writer`
        out.fill_(7.0)
    del out
    gc.collect()
    assert tc.release_output(msg) is False  # the view's death released the handle
    reader = torch.cuda.Stream()
    with torch.cuda.stream(reader):  # another stream: must wait for the writer's event
        got = tc_torch.from_input_tensor_msg(msg)
        total = got.sum()
    assert total.item() == 7.0 * N


def test_to_tensor_msg_records_completion_on_torchs_current_stream(no_device_sync):
    msg = _alloc()
    stream = torch.cuda.Stream()
    with torch.cuda.stream(stream):
        value = torch.empty(N, device="cuda")
        torch.cuda._sleep(SLOW)
        value.fill_(3.0)
        tc_torch.to_tensor_msg(msg, value)  # copy queued on `stream`, completion recorded there
    view = tc_warp.from_input_tensor_msg(msg, clone=False)  # Warp's stream waits for it
    assert float(view.numpy().sum()) == 3.0 * N


def test_input_view_is_ordered_on_the_consumer_stream(no_device_sync):
    msg = _alloc()
    writer = torch.cuda.Stream()
    with torch.cuda.stream(writer):
        out = tc_torch.from_output_tensor_msg(msg)
        torch.cuda._sleep(SLOW)
        out.fill_(5.0)
        del out
    consumer = torch.cuda.Stream()
    with torch.cuda.stream(consumer):
        view = tc_torch.from_input_tensor_msg(msg, clone=False)
        total = view.sum()
    assert total.item() == 5.0 * N


def test_dlpack_consumer_stream_waits_for_the_handle_stream():
    msg = _alloc()
    with torch.cuda.stream(torch.cuda.Stream()):
        out = tc_torch.from_output_tensor_msg(msg)
        torch.cuda._sleep(SLOW)
        out.fill_(2.0)
        del out
    view = tc.input_view(msg)  # read handle on Warp's current stream
    consumer = torch.cuda.Stream()
    with torch.cuda.stream(consumer):
        tensor = torch.from_dlpack(view)  # passes `consumer` to __dlpack__
        total = tensor.sum()
    assert total.item() == 2.0 * N


def test_clone_paths_never_synchronize_the_device(no_device_sync):
    value = torch.arange(1024, dtype=torch.float32, device="cuda").reshape(32, 32)
    msg = tc_torch.to_tensor_msg(value)
    assert torch.equal(tc_torch.from_input_tensor_msg(msg), value)
    assert np.array_equal(tc_numpy.from_input_tensor_msg(msg), value.cpu().numpy())
    arr = tc_warp.from_input_tensor_msg(msg)
    assert np.array_equal(arr.numpy(), value.cpu().numpy())
    msg2 = tc_warp.to_tensor_msg(arr)
    assert torch.equal(tc_torch.from_input_tensor_msg(msg2), value)


def test_image_on_cuda_keeps_step_as_stride():
    msg = tc_torch.allocate_image_msg(4, 5, "rgba8", backend="warp", device="cuda:0", step=32)
    out = tc_torch.from_output_image_msg(msg)
    assert out.device.type == "cuda" and out.stride() == (32, 4, 1)
    out.fill_(9)
    del out
    got = tc_torch.from_input_image_msg(msg)
    assert got.shape == (4, 5, 4) and bool((got == 9).all())
