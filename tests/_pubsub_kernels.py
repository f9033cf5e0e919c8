"""Warp kernels used by the pub/sub test children (an importable module, so the kernel cache is
shared across processes)."""

from __future__ import annotations

import numpy as np
import warp as wp


@wp.kernel
def _xor_bytes(src: wp.array(dtype=wp.uint8), dst: wp.array(dtype=wp.uint8), key: wp.uint8):
    i = wp.tid()
    dst[i] = src[i] ^ key


def xor_buffer(buffer, key: int):
    """A new buffer, in the same backend as ``buffer``, holding ``buffer ^ key`` computed by a
    Warp kernel on the backend's own memory (Warp arrays for ``warp``, host arrays otherwise)."""
    backend = buffer.get_backend_type()
    n = len(buffer)
    if backend == "warp":
        from warp_buffer import allocate_buffer, from_input_buffer, from_output_buffer

        src = from_input_buffer(buffer)
        out = allocate_buffer(n)
        dst = from_output_buffer(out)
        wp.launch(_xor_bytes, dim=n, inputs=[src.array, dst.array, wp.uint8(key)],
                  device=dst.array.device)
        wp.synchronize_device(dst.array.device)
        for handle in (src, dst):
            for name in ("close", "release"):
                if hasattr(handle, name):
                    getattr(handle, name)()
                    break
        return out
    host = buffer.to_numpy()
    src = wp.array(host, dtype=wp.uint8, device="cpu")
    dst = wp.empty(n, dtype=wp.uint8, device="cpu")
    wp.launch(_xor_bytes, dim=n, inputs=[src, dst, wp.uint8(key)], device="cpu")
    result = dst.numpy()
    if backend == "fake":
        from fake_buffer_backend import FakeBufferImpl
        from rosidl_buffer import Buffer

        return Buffer(FakeBufferImpl(result))
    from rosidl_buffer import Buffer

    return Buffer(np.asarray(result))
