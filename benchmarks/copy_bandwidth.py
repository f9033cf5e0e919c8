"""Bandwidth of warp_buffer's copy kernels, as a ratio to ``np.copyto`` (goal: >= 0.9x at 64 MiB).

Measures, per size, the median of ``--repeat`` copies between two page-aligned host buffers on
Warp's ``cpu`` device: ``np.copyto`` (the reference), ``warp_buffer.kernels.copy_bytes`` (the
kernel behind ``to_cpu``, ``clone`` and ``to_buffer``), and ``wp.copy`` for comparison; with a GPU,
also the device-to-device kernel against ``wp.copy``.

    python -m benchmarks.copy_bandwidth [--quick] [--sizes 1M,64M] [--repeat N]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence

import numpy as np

GOAL_SIZE = 64 << 20
GOAL_RATIO = 0.9


def _parse_size(text: str) -> int:
    text = text.strip().upper().removesuffix("B").removesuffix("I")
    scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1:], 1)
    return int(float(text[:-1] if scale > 1 else text) * scale)


def _median_seconds(fn: Callable[[], None], repeat: int) -> float:
    fn()  # warm up: page faults, kernel load
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _aligned(nbytes: int) -> np.ndarray:
    raw = np.empty(nbytes + 4096, dtype=np.uint8)
    offset = -raw.ctypes.data % 4096
    out = raw[offset:offset + nbytes]
    out[:] = np.arange(nbytes, dtype=np.uint64).astype(np.uint8)  # touch every page
    return out


def measure(sizes: Sequence[int], repeat: int) -> list[dict[str, float]]:
    import warp as wp

    from warp_buffer import kernels

    rows = []
    for nbytes in sizes:
        src, dst = _aligned(nbytes), _aligned(nbytes)
        wsrc = wp.array(ptr=src.ctypes.data, dtype=wp.uint8, shape=(nbytes,), device="cpu")
        wdst = wp.array(ptr=dst.ctypes.data, dtype=wp.uint8, shape=(nbytes,), device="cpu")
        reference = _median_seconds(lambda: np.copyto(dst, src), repeat)
        kernel = _median_seconds(lambda: kernels.copy_bytes(wdst, wsrc), repeat)
        if not np.array_equal(dst, src):
            raise RuntimeError(f"copy kernel produced wrong bytes at {nbytes} bytes")
        warp_copy = _median_seconds(lambda: wp.copy(wdst, wsrc), repeat)
        rows.append({"device": "cpu", "bytes": nbytes, "np.copyto GB/s": nbytes / reference / 1e9,
                     "kernel GB/s": nbytes / kernel / 1e9, "wp.copy GB/s": nbytes / warp_copy / 1e9,
                     "ratio": reference / kernel})
    if wp.get_cuda_device_count() > 0:  # pragma: no cover - needs a GPU
        device = wp.get_cuda_devices()[0]
        for nbytes in sizes:
            a = wp.zeros(nbytes, dtype=wp.uint8, device=device)
            b = wp.empty(nbytes, dtype=wp.uint8, device=device)

            def run_kernel() -> None:
                kernels.copy_bytes(b, a)
                wp.synchronize_device(device)

            def run_copy() -> None:
                wp.copy(b, a)
                wp.synchronize_device(device)

            kernel = _median_seconds(run_kernel, repeat)
            warp_copy = _median_seconds(run_copy, repeat)
            rows.append({"device": device.alias, "bytes": nbytes, "np.copyto GB/s": float("nan"),
                         "kernel GB/s": nbytes / kernel / 1e9,
                         "wp.copy GB/s": nbytes / warp_copy / 1e9, "ratio": warp_copy / kernel})
    return rows


def _format(rows: list[dict[str, float]]) -> str:
    lines = [f"{'device':>7} {'size':>9} {'np.copyto':>10} {'kernel':>9} {'wp.copy':>9} "
             f"{'ratio':>7}   (GB/s; ratio = reference time / kernel time, reference = "
             f"np.copyto on cpu, wp.copy on CUDA)"]
    for row in rows:
        size = row["bytes"]
        label = f"{size >> 20} MiB" if size >= 1 << 20 else f"{size >> 10} KiB"
        lines.append(f"{row['device']:>7} {label:>9} {row['np.copyto GB/s']:10.2f} "
                     f"{row['kernel GB/s']:9.2f} {row['wp.copy GB/s']:9.2f} {row['ratio']:6.2f}x")
    goal = [r for r in rows if r["device"] == "cpu" and r["bytes"] == GOAL_SIZE]
    if goal:
        verdict = "meets" if goal[0]["ratio"] >= GOAL_RATIO else "MISSES"
        lines.append(f"64 MiB on cpu: {goal[0]['ratio']:.2f}x np.copyto ({verdict} the "
                     f"{GOAL_RATIO}x goal)")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.copy_bandwidth",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="fewer sizes and repetitions (64 KiB, 4 MiB, 64 MiB; 5 runs)")
    parser.add_argument("--sizes", help="comma-separated sizes, e.g. 64K,1M,64M")
    parser.add_argument("--repeat", type=int, help="copies per measurement (median reported)")
    args = parser.parse_args(argv)
    if args.sizes:
        sizes = [_parse_size(s) for s in args.sizes.split(",") if s.strip()]
    elif args.quick:
        sizes = [64 << 10, 4 << 20, GOAL_SIZE]
    else:
        sizes = [4 << 10, 64 << 10, 1 << 20, 4 << 20, 16 << 20, GOAL_SIZE, 256 << 20]
    repeat = args.repeat or (5 if args.quick else 20)
    from warp_buffer import init_warp

    init_warp()  # no start-up banner in the report
    print(_format(measure(sizes, repeat)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
