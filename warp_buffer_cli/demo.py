"""``warp-buffer demo``: a publisher, a Warp subscriber and a CPU subscriber, in three processes.

- the publisher fills ``tensor_msgs/msg/ExperimentalTensor`` frames in Warp memory with a Warp
  kernel (``tensor_conversions.warp``) and publishes them through :mod:`buffer_pubsub`;
- the warp subscriber (``acceptable_buffer_backends="warp"``) views each frame in torch through
  DLPack without a copy (``tensor_conversions.torch``) and checks every element;
- the CPU subscriber (``"cpu"``) gets the same frames as CPU bytes and checks them in NumPy.

Prints the path each subscriber used, messages received and latency percentiles; exits 0 only if
every check passed. Runs on Warp's ``cpu`` device with no set-up (no router, no GPU).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any

import numpy as np

TOPIC = "/warp_buffer_demo/frames"
TENSOR = "tensor_msgs/msg/ExperimentalTensor"
_CHILD = "from warp_buffer_cli.demo import child_main; child_main()"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=50, help="frames to publish (default 50)")
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--rate", type=float, default=50.0, help="frames per second")
    parser.add_argument("--device", default="cpu", help="Warp device of the frames (default cpu)")
    parser.add_argument("--domain", type=int, default=None,
                        help="domain id (default: a private one derived from the process id)")
    parser.add_argument("--timeout", type=float, default=60.0, help="give up after this long")


# --------------------------------------------------------------------------- frame content
def _expected(index: int, height: int, width: int) -> np.ndarray:
    cells = np.arange(height * width, dtype=np.int64).reshape(height, width) % 1000
    # WARP_BUFFER_DEMO_CORRUPT (tests only) makes the subscribers expect other content.
    index += 1 if os.environ.get("WARP_BUFFER_DEMO_CORRUPT") else 0
    return (index * 1000 + cells).astype(np.float32)  # exact in float32 for index < 16000


_fill_kernel = None


def _fill(array: Any, index: int) -> None:
    """Write frame ``index`` into a 2-D float32 Warp array with a Warp kernel."""
    global _fill_kernel
    import warp as wp

    if _fill_kernel is None:
        @wp.kernel
        def fill(out: wp.array2d(dtype=wp.float32), index: int, width: int):
            y, x = wp.tid()
            out[y, x] = float(index * 1000 + (y * width + x) % 1000)

        _fill_kernel = fill
    wp.launch(_fill_kernel, dim=array.shape, inputs=[array, index, array.shape[1]],
              device=array.device)
    wp.synchronize_device(array.device)


# --------------------------------------------------------------------------- children
def _emit(kind: str, payload: Any = None) -> None:
    sys.stdout.write(kind if payload is None else f"{kind} {json.dumps(payload)}")
    sys.stdout.write("\n")
    sys.stdout.flush()


def _publisher(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.quiet = True
    from buffer_pubsub import Node
    from tensor_conversions import warp as tcw

    # Compile the kernel before matching, so the first frame is not late.
    _fill(wp.empty((1, 1), dtype=wp.float32, device=args.device), 0)
    with Node("demo_publisher", domain_id=args.domain) as node:
        pub = node.create_publisher(TENSOR, TOPIC, depth=args.frames)
        matched = pub.wait_for_subscriptions(2, timeout=args.timeout)
        _emit("READY")
        if not matched:
            _emit("RESULT", {"ok": False, "error": "subscribers not found"})
            return 1
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        for index in range(args.frames):
            msg = tcw.allocate_tensor_msg((args.height, args.width), wp.float32,
                                          backend="warp", device=args.device)
            _fill(tcw.from_output_tensor_msg(msg), index)
            _release_output(msg)
            pub.publish(msg)
            time.sleep(period)
        sys.stdin.readline()  # keep the buffers alive until the subscribers are done
    _emit("RESULT", {"ok": True, "published": args.frames,
                     "backend": msg.data.get_backend_type()})
    return 0


def _release_output(msg: Any) -> None:
    import tensor_conversions

    release = getattr(tensor_conversions, "release_output", None)
    if release is not None:
        release(msg)


def _subscriber(args: argparse.Namespace, accept: str) -> int:
    from buffer_pubsub import Node

    # Import the conversion stack before matching: a first import inside the callback (torch
    # takes about a second) would delay every queued frame and skew the latency figures.
    import torch
    from tensor_conversions import numpy as tcn
    from tensor_conversions import torch as tct

    stats: dict[str, Any] = {"received": 0, "bad": 0, "backends": [], "routes": [],
                             "latency_ms": [], "errors": []}

    def check(msg: Any, info: Any) -> None:
        stats["received"] += 1
        backend = msg.data.get_backend_type()
        if backend not in stats["backends"]:
            stats["backends"].append(backend)
        if info.route not in stats["routes"]:
            stats["routes"].append(info.route)
        try:
            if accept == "warp":
                view = tct.from_input_tensor_msg(msg, clone=False)  # DLPack, zero copy
                frame = int(view[0, 0].item()) // 1000
                good = tuple(view.shape) == (args.height, args.width) and bool(torch.equal(
                    view, torch.from_numpy(_expected(frame, args.height, args.width))))
                del view
            else:
                view = tcn.from_input_tensor_msg(msg, clone=False)
                frame = int(view[0, 0]) // 1000
                good = bool(np.array_equal(view, _expected(frame, args.height, args.width)))
        except Exception as exc:  # report, do not stop: the demo must print a verdict
            good = False
            stats["errors"].append(repr(exc))
        if not good:
            stats["bad"] += 1
        stats["latency_ms"].append(
            (time.time_ns() - info.source_timestamp_ns) / 1e6)

    with Node(f"demo_{accept}_subscriber", domain_id=args.domain) as node:
        sub = node.create_subscription(TENSOR, TOPIC, check, depth=args.frames,
                                       acceptable_buffer_backends=accept, with_info=True)
        sub.wait_for_publishers(1, timeout=args.timeout)
        _emit("READY")
        deadline = time.monotonic() + args.timeout
        while stats["received"] + sub.errors < args.frames and time.monotonic() < deadline:
            time.sleep(0.01)
        stats["lost"], stats["transport_errors"] = sub.lost, sub.errors
    _emit("RESULT", stats)
    return 0


def child_main(argv: list[str] | None = None) -> int:
    """Entry of the demo's child processes (run by :func:`run`)."""
    parser = argparse.ArgumentParser(prog="warp-buffer demo (child)")
    parser.add_argument("role", choices=["publisher", "warp", "cpu"])
    add_arguments(parser)
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.role == "publisher":
        code = _publisher(args)
    else:
        code = _subscriber(args, args.role)
    sys.exit(code)


# --------------------------------------------------------------------------- parent
def _spawn(role: str, args: argparse.Namespace) -> subprocess.Popen:
    argv = [sys.executable, "-c", _CHILD, role, "--frames", str(args.frames),
            "--height", str(args.height), "--width", str(args.width), "--rate", str(args.rate),
            "--device", args.device, "--domain", str(args.domain),
            "--timeout", str(args.timeout)]
    return subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def _result(proc: subprocess.Popen, timeout: float) -> dict[str, Any] | None:
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    for line in reversed(out.splitlines()):
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    return None


def _percentiles(values: list[float]) -> str:
    if not values:
        return "n/a"
    p50, p90, p99 = np.percentile(np.asarray(values), [50, 90, 99])
    return f"p50 {p50:.2f} ms  p90 {p90:.2f} ms  p99 {p99:.2f} ms"


def run(args: argparse.Namespace) -> int:
    """Run the demo; 0 only if both subscribers got every frame by the expected path, intact."""
    from rosidl_buffer import RosidlBufferError
    from rosidl_buffer.registry import create_backend_instance

    try:
        create_backend_instance("warp")
    except RosidlBufferError as exc:
        print(f"demo: FAILED: the warp buffer backend is not available: {exc}")
        return 1
    if args.domain is None:
        args.domain = 150 + os.getpid() % 80
    os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.getcwd(), ".warp_cache"))
    print(f"warp-buffer demo: {args.frames} frames of {args.height}x{args.width} float32 on "
          f"Warp device {args.device!r}, domain {args.domain}, topic {TOPIC}")
    procs: dict[str, subprocess.Popen] = {}
    try:
        for role in ("warp", "cpu", "publisher"):
            procs[role] = _spawn(role, args)
        subs = {role: _result(procs[role], args.timeout + 30) for role in ("warp", "cpu")}
        if procs["publisher"].stdin is not None:
            try:
                procs["publisher"].stdin.write("done\n")
                procs["publisher"].stdin.flush()
            except BrokenPipeError:
                pass
        published = _result(procs["publisher"], 30)
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
            proc.wait()
    ok = bool(published and published.get("ok"))
    print(f"publisher: {'published ' + str(published['published']) + ' frames (' + published['backend'] + ' storage)' if ok else 'FAILED ' + str(published)}")
    expected_path = {"warp": "warp", "cpu": "cpu"}
    for role, stats in subs.items():
        if stats is None:
            print(f"{role} subscriber: FAILED (no result)")
            ok = False
            continue
        path_ok = stats["backends"] == [expected_path[role]]
        good = (path_ok and stats["received"] == args.frames and stats["bad"] == 0
                and stats["lost"] == 0 and stats["transport_errors"] == 0)
        ok = ok and good
        print(f"{role} subscriber: path {'+'.join(stats['backends']) or '-'} "
              f"(route {'+'.join(stats['routes']) or '-'}), received {stats['received']}/"
              f"{args.frames}, bad {stats['bad']}, lost {stats['lost']}, "
              f"latency {_percentiles(stats['latency_ms'])}  {'OK' if good else 'FAILED'}")
        for error in stats["errors"][:3]:
            print(f"    error: {error}")
    print("demo: " + ("all checks passed" if ok else "FAILED"))
    return 0 if ok else 1


if __name__ == "__main__":
    demo_parser = argparse.ArgumentParser(prog="warp-buffer demo")
    add_arguments(demo_parser)
    sys.exit(run(demo_parser.parse_args()))
