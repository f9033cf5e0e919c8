"""Cost of tensor_conversions' per-frame operations, against the goals of issue 13.

Per framework (torch, NumPy, Warp) and storage (``cpu``, ``warp`` on Warp's cpu device), the
cost of ``allocate_tensor_msg``, ``from_output_tensor_msg``,
``from_input_tensor_msg(clone=False)`` and ``from_input_tensor_msg(clone=True)`` at 4 KiB, next
to the framework's own zero-copy import of the same memory (``torch.from_dlpack`` /
``np.ndarray`` / ``wp.array(ptr=...)``) as the floor; the ratio to the goal is printed
(goal: input view <= 10 us). Images (``from_input_image_msg(clone=False)``) are measured too.
Each figure is the fastest of many batch means (the least disturbed by other processes on a
shared machine); the input view's median is printed beside it.

    python -m benchmarks.conversions [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

GOAL_INPUT_VIEW_US = 10.0
SHAPE = (32, 32)  # float32: 4 KiB


def _batches_us(fn: Callable[[], Any], repeat: int, inner: int = 20) -> list[float]:
    """``repeat`` batch means of ``inner`` calls, in microseconds."""
    for _ in range(inner):
        fn()  # warm up: imports, caches, kernel loads
    samples = []
    for _ in range(repeat):
        start = time.perf_counter()
        for _ in range(inner):
            fn()
        samples.append((time.perf_counter() - start) / inner * 1e6)
    return samples


def _best_us(fn: Callable[[], Any], repeat: int, inner: int = 20) -> float:
    return min(_batches_us(fn, repeat, inner))


def _floor(framework: str, host: np.ndarray) -> Callable[[], Any]:
    """The framework's own zero-copy import of host memory: what a view cannot beat."""
    if framework == "torch":
        import torch

        return lambda: torch.from_dlpack(host)
    if framework == "numpy":
        return lambda: np.ndarray(SHAPE, np.float32, buffer=host)
    import warp as wp

    return lambda: wp.array(ptr=host.ctypes.data, dtype=wp.float32, shape=SHAPE, device="cpu")


def measure(repeat: int) -> list[dict[str, Any]]:
    import torch
    import warp as wp

    from tensor_conversions import numpy as tc_numpy
    from tensor_conversions import torch as tc_torch
    from tensor_conversions import warp as tc_warp

    modules = {"torch": (tc_torch, torch.float32), "numpy": (tc_numpy, np.float32),
               "warp": (tc_warp, wp.float32)}
    rows = []
    for backend in ("cpu", "warp"):
        device = "cpu" if backend == "warp" else None
        for framework, (module, dtype) in modules.items():
            msg = module.allocate_tensor_msg(SHAPE, dtype, backend=backend, device=device)
            module.from_output_tensor_msg(msg)
            import tensor_conversions as tc

            tc.release_output(msg)
            host = np.zeros(SHAPE, np.float32)
            row = {
                "framework": framework, "backend": backend,
                "allocate_us": _best_us(
                    lambda: module.allocate_tensor_msg(SHAPE, dtype, backend=backend,
                                                       device=device), repeat, 5),
                "output_view_us": _best_us(
                    lambda: module.from_output_tensor_msg(
                        module.allocate_tensor_msg(SHAPE, dtype, backend=backend,
                                                   device=device)), repeat, 5),
                "input_view_samples": _batches_us(
                    lambda: module.from_input_tensor_msg(msg, clone=False), repeat),
                "input_clone_us": _best_us(
                    lambda: module.from_input_tensor_msg(msg, clone=True), repeat),
                "floor_us": _best_us(_floor(framework, host), repeat),
            }
            row["input_view_us"] = min(row["input_view_samples"])
            row["input_view_median_us"] = statistics.median(row.pop("input_view_samples"))
            # output view alone = (allocate + view) - allocate
            row["output_view_us"] = max(row["output_view_us"] - row["allocate_us"], 0.0)
            rows.append(row)
    return rows


def measure_images(repeat: int) -> list[dict[str, Any]]:
    from tensor_conversions import numpy as tc_numpy
    from tensor_conversions import torch as tc_torch

    rows = []
    for name, module in (("torch", tc_torch), ("numpy", tc_numpy)):
        msg = module.allocate_image_msg(480, 640, "rgb8")
        rows.append({"framework": name, "encoding": "rgb8 480x640",
                     "input_view_us": _best_us(
                         lambda: module.from_input_image_msg(msg, clone=False), repeat)})
    return rows


def format_report(rows: list[dict[str, Any]], images: list[dict[str, Any]]) -> str:
    lines = ["tensor_conversions per-frame cost, 4 KiB float32 (us, fastest batch; goal: input "
             f"view <= {GOAL_INPUT_VIEW_US:.0f} us)",
             f"{'framework':<9} {'storage':<7} {'allocate':>9} {'out view':>9} {'in view':>8} "
             f"{'(median)':>9} {'in clone':>9} {'floor':>7} {'view/goal':>10} {'view/floor':>11}"]
    for r in rows:
        lines.append(
            f"{r['framework']:<9} {r['backend']:<7} {r['allocate_us']:9.1f} "
            f"{r['output_view_us']:9.1f} {r['input_view_us']:8.1f} "
            f"{r['input_view_median_us']:9.1f} {r['input_clone_us']:9.1f} "
            f"{r['floor_us']:7.1f} {r['input_view_us'] / GOAL_INPUT_VIEW_US:9.2f}x "
            f"{r['input_view_us'] / max(r['floor_us'], 1e-9):10.1f}x")
    for r in images:
        lines.append(f"image {r['framework']:<7} {r['encoding']}: from_input_image_msg(clone=False) "
                     f"{r['input_view_us']:.1f} us ({r['input_view_us'] / GOAL_INPUT_VIEW_US:.2f}x "
                     "the tensor goal)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.conversions", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_ERROR)  # no start-up banner in the report
    repeat = 15 if args.quick else 60
    print(format_report(measure(repeat), measure_images(repeat)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
