"""Warp kernels of warp_buffer: the byte-copy kernel.

Kept in this one module, under a stable name, so Warp's kernel cache (keyed by module name and
source) is built once per machine and reused by every process, children included.

The copy kernel is vectorized, never one thread per byte:

- on the ``cpu`` device each Warp thread copies a 1 MiB chunk; buffers of ``NT_THRESHOLD`` bytes
  or more are copied with 16-byte non-temporal stores (they bypass the cache, which a 64 MiB copy
  would only thrash, and need no read-for-ownership of the destination) followed by a store
  fence, smaller ones with ``memcpy``, whose cache-friendly copy wins while the data fits in cache;
- on CUDA each thread copies 16 bytes (``int4`` loads and stores, coalesced) when both pointers
  are 16-byte aligned, else its 16 bytes one at a time.

``wp.tid()`` is a 32-bit int, so one launch covers at most ``MAX_LAUNCH_THREADS`` threads: larger
copies (over 16 GiB on CUDA) run as several launches, each starting at a 64-bit byte offset.

``benchmarks/copy_bandwidth.py`` measures it against ``np.copyto``.
"""

from __future__ import annotations

import warp as wp

__all__ = ["NT_THRESHOLD", "CPU_CHUNK", "CUDA_CHUNK", "MAX_LAUNCH_THREADS", "copy_bytes",
           "launch_slices"]

#: Copies of at least this many bytes use non-temporal stores on the cpu device.
NT_THRESHOLD = 4 << 20
#: Bytes one Warp thread copies on the cpu device.
CPU_CHUNK = 1 << 20
#: Bytes one Warp thread copies on a CUDA device.
CUDA_CHUNK = 16
#: Threads of one copy launch: ``wp.tid()`` must stay below 2**31 (a 32 GiB CUDA copy would need
#: 2**31 threads); bigger copies are split into launches of at most this many threads.
MAX_LAUNCH_THREADS = 1 << 30

_MODE_PLAIN = 0  # memcpy on cpu, byte loop on CUDA: any alignment
_MODE_VECTOR = 1  # 16-byte aligned: memcpy on cpu, int4 on CUDA
_MODE_STREAM = 2  # 16-byte aligned, large: non-temporal stores on cpu (int4 on CUDA)

_COPY_SNIPPET = r"""
    const long long start = base + (long long)t * chunk;
    long long end = start + chunk;
    if (end > count) end = count;
    if (start >= end) return;
    char* d = (char*)dst.data;
    const char* s = (const char*)src.data;
#if defined(__CUDA_ARCH__)
    if (mode != 0 && end - start == 16) {
        *(int4*)(d + start) = *(const int4*)(s + start);
    } else {
        for (long long i = start; i < end; ++i) d[i] = s[i];
    }
#else
    if (mode == 2) {
        typedef long long wb_v2 __attribute__((vector_size(16)));
        const long long nvec = (end - start) / 16;
        const wb_v2* sv = (const wb_v2*)(s + start);
        wb_v2* dv = (wb_v2*)(d + start);
        for (long long i = 0; i < nvec; ++i) __builtin_nontemporal_store(sv[i], dv + i);
        const long long done = start + nvec * 16;
        if (done < end) __builtin_memcpy(d + done, s + done, (unsigned long)(end - done));
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_sfence();
#else
        __atomic_thread_fence(__ATOMIC_SEQ_CST);
#endif
    } else {
        __builtin_memcpy(d + start, s + start, (unsigned long)(end - start));
    }
#endif
"""


@wp.func_native(_COPY_SNIPPET)
def _copy_range(
    dst: wp.array(dtype=wp.uint8),
    src: wp.array(dtype=wp.uint8),
    t: wp.int32,
    base: wp.int64,
    chunk: wp.int64,
    count: wp.int64,
    mode: wp.int32,
): ...


@wp.kernel
def copy_bytes_kernel(
    dst: wp.array(dtype=wp.uint8),
    src: wp.array(dtype=wp.uint8),
    base: wp.int64,
    chunk: wp.int64,
    count: wp.int64,
    mode: wp.int32,
):
    """Copy bytes ``[base, count)`` of ``src`` to ``dst``; thread ``t`` copies
    ``[base + t*chunk, base + (t+1)*chunk)`` (64-bit offsets: ``t`` alone is 32-bit)."""
    _copy_range(dst, src, wp.tid(), base, chunk, count, mode)


def copy_bytes(dst: wp.array, src: wp.array, stream: wp.Stream | None = None) -> None:
    """Copy all of ``src`` into ``dst``: two contiguous 1-D uint8 arrays on the same device.

    On CUDA the copy is enqueued on ``stream`` (default: the device's current stream) and is
    asynchronous; on the cpu device it has completed when this returns.
    """
    nbytes = src.shape[0]
    if dst.shape[0] != nbytes:
        raise ValueError(f"copy_bytes: destination has {dst.shape[0]} bytes, source {nbytes}")
    if dst.device != src.device:
        raise ValueError(f"copy_bytes: {src.device} -> {dst.device} is not a same-device copy")
    if nbytes == 0:
        return
    aligned = dst.ptr % 16 == 0 and src.ptr % 16 == 0
    device = dst.device
    if device.is_cpu:
        chunk = CPU_CHUNK
        mode = _MODE_STREAM if aligned and nbytes >= NT_THRESHOLD else _MODE_PLAIN
        stream = None
    else:
        chunk = CUDA_CHUNK
        mode = _MODE_VECTOR if aligned else _MODE_PLAIN
    for base, threads in launch_slices(nbytes, chunk):
        wp.launch(
            copy_bytes_kernel, dim=threads, inputs=[dst, src, base, chunk, nbytes, mode],
            device=device, stream=stream,
        )


def launch_slices(nbytes: int, chunk: int) -> list[tuple[int, int]]:
    """The launches that copy ``nbytes`` in ``chunk``-byte threads: ``(first byte, threads)``
    pairs, each launch at most ``MAX_LAUNCH_THREADS`` threads so ``wp.tid()`` cannot overflow."""
    threads = (nbytes + chunk - 1) // chunk
    per_launch = MAX_LAUNCH_THREADS
    return [(first * chunk, min(per_launch, threads - first))
            for first in range(0, threads, per_launch)]

