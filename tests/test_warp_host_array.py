"""``host_array()`` of warp_buffer's handles: a NumPy array over host storage, no copy, that keeps
the handle (and so the storage, or an import's hold) alive; None for device memory."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest

from warp_buffer import allocate_buffer, from_input_buffer, from_output_buffer
from warp_buffer.errors import HandleReleasedError


def _written(nbytes: int = 256):
    buffer = allocate_buffer(nbytes, "cpu")
    with from_output_buffer(buffer) as out:
        out.host_array()[:] = np.arange(nbytes, dtype=np.uint8)
    return buffer


def test_host_array_aliases_the_storage_without_a_copy():
    buffer = _written()
    handle = from_input_buffer(buffer)
    host = handle.host_array()
    assert host.dtype == np.uint8 and host.shape == (256,)
    assert host.ctypes.data == handle.ptr  # the storage itself
    assert np.array_equal(host, np.arange(256, dtype=np.uint8))
    assert np.array_equal(buffer.to_numpy(), host)


def test_host_array_keeps_its_handle_alive_until_it_is_dropped():
    buffer = _written()
    handle = from_input_buffer(buffer)
    alive = weakref.ref(handle)
    host = handle.host_array()
    del handle
    gc.collect()
    assert alive() is not None  # the array holds the handle (and the storage) alive
    assert int(host[7]) == 7
    del host
    gc.collect()
    assert alive() is None


def test_a_released_handle_gives_no_host_array():
    handle = from_input_buffer(_written())
    handle.release()
    with pytest.raises(HandleReleasedError):
        handle.host_array()


@pytest.mark.cuda
def test_device_memory_has_no_host_array():
    buffer = allocate_buffer(256, "cuda:0")
    with from_output_buffer(buffer) as out:
        assert out.host_array() is None
