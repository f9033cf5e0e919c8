"""``warp-buffer demo``: a publisher, a Warp subscriber and a CPU subscriber, in three processes.

- the publisher fills ``tensor_msgs/msg/ExperimentalTensor`` frames in Warp memory with a Warp
  kernel (``tensor_conversions.warp``) and publishes them through :mod:`buffer_pubsub`;
- the warp subscriber (``acceptable_buffer_backends="warp"``) views each frame in torch through
  DLPack without a copy (``tensor_conversions.torch``; through ``tensor_conversions.warp`` where
  torch, an optional extra, is not installed) and checks every element;
- the CPU subscriber (``"cpu"``) gets the same frames as CPU bytes and checks them in NumPy.

Prints the path each subscriber used, messages received, the latency percentiles (publish to
callback entry: the transport's) and, apart, the time each subscriber's check of every element
took; exits 0 only if every check passed. Runs with no set-up (no router); on Warp's preferred device by default
(``cuda:0`` where a GPU is usable, else ``cpu``). A device this machine lacks fails at once.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ._arguments import number, topic_name

TOPIC = "/warp_buffer_demo/frames"
TENSOR = "tensor_msgs/msg/ExperimentalTensor"
#: The node names of the demo's subscribers (the publisher waits for these two).
DEMO_SUBSCRIBERS = frozenset({"demo_warp_subscriber", "demo_cpu_subscriber"})
_CHILD = "from warp_buffer_cli.demo import child_main; child_main()"
_PR_SET_PDEATHSIG = 1  # prctl(2)


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows every default; a None default is described in the option's own help instead."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        return action.help if action.default is None else super()._get_help_string(action)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = _HelpFormatter
    parser.add_argument("--frames", type=number(int, 1), default=50, help="frames to publish")
    parser.add_argument("--height", type=number(int, 1), default=240, help="frame height")
    parser.add_argument("--width", type=number(int, 1), default=320, help="frame width")
    parser.add_argument("--rate", type=number(float, 0.01, zero=True), default=50.0,
                        help="frames per second (0: as fast as possible)")
    parser.add_argument("--device", default=None,
                        help="Warp device of the frames, e.g. cpu or cuda:0 (default: Warp's "
                             "preferred device, cuda:0 where a GPU is usable, else cpu)")
    parser.add_argument("--domain", type=number(int, 0, high=2**31 - 1), default=None,
                        help="domain id (default: ROS_DOMAIN_ID when set, else one derived "
                             "from the process id)")
    parser.add_argument("--topic", default=None, type=topic_name,
                        help=f"topic (default: {TOPIC}_<process id>: two demos never share one)")
    parser.add_argument("--timeout", type=number(float, 0, inclusive=False, high=86_400.0),
                        default=60.0,
                        help="seconds before the demo gives up")


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
    try:
        return _publish(args)
    except Exception as exc:  # the parent prints the verdict: hand it the typed error's message
        _emit("RESULT", {"ok": False, "error": f"{type(exc).__name__}: {exc}"})
        return 1


def _publish(args: argparse.Namespace) -> int:
    import warp as wp

    from buffer_pubsub import Node
    from tensor_conversions import warp as tcw

    # Compile the kernel before matching, so the first frame is not late.
    _fill(wp.empty((1, 1), dtype=wp.float32, device=args.device), 0)
    with Node("demo_publisher", domain_id=args.domain) as node:
        pub = node.create_publisher(TENSOR, args.topic, depth=args.frames)
        matched = _wait_for_demo_subscribers(node, pub, args.topic, args.timeout)
        _emit("READY")
        if not matched:
            _emit("RESULT", {"ok": False, "error": "subscribers not found"})
            return 1
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        deadline = time.monotonic() + args.timeout  # the subscribers stop waiting then too
        published = 0
        for index in range(args.frames):
            if time.monotonic() > deadline:
                break
            msg = tcw.allocate_tensor_msg((args.height, args.width), wp.float32,
                                          backend="warp", device=args.device)
            _fill(tcw.from_output_tensor_msg(msg), index)
            _release_output(msg)
            pub.publish(msg)
            published += 1
            if period and published < args.frames:  # none after the last; never past --timeout
                time.sleep(max(0.0, min(period, deadline - time.monotonic())))
        sys.stdin.readline()  # keep the buffers alive until the subscribers are done
    if published < args.frames:
        _emit("RESULT", {"ok": False, "published": published,
                         "error": f"--timeout {args.timeout:g} s passed after {published} of "
                                  f"{args.frames} frames"})
        return 1
    _emit("RESULT", {"ok": True, "published": args.frames,
                     "backend": msg.data.get_backend_type()})
    return 0


def _wait_for_demo_subscribers(node: Any, pub: Any, topic: str, timeout: float) -> bool:
    """Whether the demo's own two subscriptions matched within ``timeout``. Another subscriber of
    the topic (a recorder, ``topic echo``) may match first: a count of two would then start the
    frames before one of ours listens, and it would miss the first ones."""
    deadline = time.monotonic() + timeout
    while True:
        served = {route.subscription_gid for route in pub.routes()}
        names = {info.node_name for info in node.get_subscriptions_info_by_topic(topic)
                 if info.endpoint_gid in served}
        if DEMO_SUBSCRIBERS <= names:
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)


def _release_output(msg: Any) -> None:
    import tensor_conversions

    release = getattr(tensor_conversions, "release_output", None)
    if release is not None:
        release(msg)


def _subscriber(args: argparse.Namespace, accept: str) -> int:
    try:
        return _subscribe(args, accept)
    except Exception as exc:  # as _publisher: the parent prints the typed error's message
        _emit("RESULT", {"failed": f"{type(exc).__name__}: {exc}"})
        return 1


def _new_stats() -> dict[str, Any]:
    return {"received": 0, "bad": 0, "backends": [], "routes": [], "latency_ms": [],
            "check_ms": [], "errors": []}


def record_frame(stats: dict[str, Any], msg: Any, info: Any,
                 frame_is_right: Callable[[Any], bool]) -> None:
    """Count one received frame in ``stats``: its latency (publish to callback entry: the
    transport's), then its check, timed apart (reading every element takes longer than the
    delivery on a large frame, and is no part of it)."""
    arrived_ns = time.time_ns()
    check_start = time.perf_counter()
    stats["received"] += 1
    backend = msg.data.get_backend_type()
    if backend not in stats["backends"]:
        stats["backends"].append(backend)
    if info.route not in stats["routes"]:
        stats["routes"].append(info.route)
    try:
        good = frame_is_right(msg)
    except Exception as exc:  # report, do not stop: the demo must print a verdict
        good = False
        stats["errors"].append(repr(exc))
    if not good:
        stats["bad"] += 1
    stats["latency_ms"].append((arrived_ns - info.source_timestamp_ns) / 1e6)
    stats["check_ms"].append((time.perf_counter() - check_start) * 1e3)


def _torch_frame_check(args: argparse.Namespace) -> Callable[[Any], bool] | None:
    """The warp subscriber's check of a frame viewed in torch through DLPack (zero copy), or
    None when torch (an optional extra) is not installed."""
    try:
        import torch

        from tensor_conversions import torch as tct
    except ImportError:
        return None

    def frame_is_right(msg: Any) -> bool:
        view = tct.from_input_tensor_msg(msg, clone=False)
        frame = int(view[0, 0].item()) // 1000
        expected = torch.from_numpy(_expected(frame, args.height, args.width))
        return tuple(view.shape) == (args.height, args.width) and bool(torch.equal(
            view, expected.to(view.device)))  # the frame may live on a GPU
    return frame_is_right


def _subscribe(args: argparse.Namespace, accept: str) -> int:
    from buffer_pubsub import Node, fast_lane

    # Import the conversion stack before matching: a first import inside the callback (torch
    # takes about a second) would delay every queued frame and skew the latency figures.
    from tensor_conversions import numpy as tcn

    stats = _new_stats()
    torch_view = _torch_frame_check(args) if accept == "warp" else None
    if accept == "warp" and torch_view is None:  # torch is an extra: Warp views the frame then
        from tensor_conversions import warp as tcw

        stats["viewer"] = "warp"

    def frame_is_right(msg: Any) -> bool:
        if torch_view is not None:
            return torch_view(msg)
        if accept == "warp":
            # zero copy; .numpy() reads it in place on the cpu device (a GPU frame is copied)
            view = tcw.from_input_tensor_msg(msg, clone=False).numpy()
        else:
            view = tcn.from_input_tensor_msg(msg, clone=False)
        frame = int(view[0, 0]) // 1000
        return view.shape == (args.height, args.width) and bool(
            np.array_equal(view, _expected(frame, args.height, args.width)))

    def check(msg: Any, info: Any) -> None:
        record_frame(stats, msg, info, frame_is_right)

    with Node(f"demo_{accept}_subscriber", domain_id=args.domain) as node:
        # (a queue deeper than the same-host lane's keeps a subscription off it)
        depth = min(args.frames, fast_lane.MAX_DEPTH)
        sub = node.create_subscription(TENSOR, args.topic, check, depth=depth,
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
    from warp_buffer import init_warp

    init_warp()  # before any Warp call: nothing of Warp's on the protocol (stdout) or stderr
    try:
        if args.role == "publisher":
            code = _publisher(args)
        else:
            code = _subscriber(args, args.role)
    except KeyboardInterrupt:  # (run by hand: the demo's own children ignore SIGINT)
        code = 130
    sys.exit(code)


# --------------------------------------------------------------------------- parent
def _spawn(role: str, args: argparse.Namespace) -> subprocess.Popen:
    argv = [sys.executable, "-c", _CHILD, role, "--frames", str(args.frames),
            "--height", str(args.height), "--width", str(args.width), "--rate", str(args.rate),
            "--device", args.device, "--domain", str(args.domain), "--topic", args.topic,
            "--timeout", str(args.timeout)]
    return subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            preexec_fn=_die_with_parent)


def _die_with_parent() -> None:
    """In a child, before exec: SIGTERM when the demo's process dies, whatever kills it
    (SIGKILL, SIGHUP: its own handlers reap the children only for SIGTERM and Ctrl-C); and no
    Ctrl-C of its own (a terminal sends it to the whole group, and a child interrupted while
    it imports prints a traceback): the demo ends its children itself."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # (kept across exec: Python leaves it)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):  # not Linux: the parent's handlers still reap them
        pass


class _Child:
    """A demo child whose stdout is read on a thread; ``result`` is its RESULT line, parsed."""

    def __init__(self, role: str, args: argparse.Namespace) -> None:
        self.proc = _spawn(role, args)
        self.result: dict[str, Any] | None = None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("RESULT "):
                self.result = json.loads(line[len("RESULT "):])

    def done(self) -> bool:
        return self.proc.poll() is not None

    def tell_done(self) -> None:
        try:
            assert self.proc.stdin is not None
            self.proc.stdin.write("done\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            pass

    def finish(self, timeout: float) -> dict[str, Any] | None:
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(timeout=5)
        return self.result


def _percentiles(values: list[float]) -> str:
    if not values:
        return "n/a"
    p50, p90, p99 = np.percentile(np.asarray(values), [50, 90, 99])
    return f"p50 {p50:.2f} ms  p90 {p90:.2f} ms  p99 {p99:.2f} ms"


def _check_setup(args: argparse.Namespace) -> str | None:
    """Resolve ``--device`` (default: Warp's preferred one) and try it, and the transport's
    configuration, at once: the typed error's message, or None. A bad device or configuration
    must fail here in a second, not in a child after a timeout."""
    from rosidl_buffer import RosidlBufferError
    from rosidl_buffer.registry import create_backend_instance

    try:
        create_backend_instance("warp")
        import warp_buffer

        if args.device is None:
            args.device = str(warp_buffer.init_warp().get_preferred_device().alias)
        warp_buffer.allocate_buffer(1, device=args.device)
        # The transport's configuration too (files, router endpoint, timeouts, the domain from
        # ROS_DOMAIN_ID): its typed error here, not a traceback in each child.
        from buffer_pubsub.config import connect_timeout_s, make_config, resolve_domain_id

        make_config()
        connect_timeout_s()
        resolve_domain_id(args.domain)
    except RosidlBufferError as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


class _Termination:
    """The demo's SIGTERM and Ctrl-C handler: either ends the demo by an exception through the
    ``finally`` that reaps the children (SystemExit(143) for SIGTERM, KeyboardInterrupt for
    Ctrl-C); but while a child is being spawned it only notes the signal (an exception inside
    ``Popen``, or before the child is recorded, would orphan it), and :meth:`deliver` raises it
    once every spawned child is in hand."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.deferred = True

    def __call__(self, signum: int, frame: Any) -> None:
        self.signum = signum
        if not self.deferred:
            _end_by(signum)

    def deliver(self) -> None:
        self.deferred = False
        if self.signum is not None:
            _end_by(self.signum)


def _end_by(signum: int) -> None:
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise SystemExit(128 + signum)


def run(args: argparse.Namespace) -> int:
    """Run the demo; 0 only if both subscribers got every frame by the expected path, intact."""
    error = _check_setup(args)
    if error is not None:
        print(f"warp-buffer demo: FAILED: {error}", file=sys.stderr)
        return 1
    if args.domain is None:  # ROS_DOMAIN_ID when set (checked above), else one of our own
        from buffer_pubsub.config import resolve_domain_id

        args.domain = (resolve_domain_id(None) if os.environ.get("ROS_DOMAIN_ID", "").strip()
                       else 150 + os.getpid() % 80)
    if args.topic is None:  # (a shared domain then carries another demo's frames on another topic)
        args.topic = f"{TOPIC}_{os.getpid()}"
    print(f"warp-buffer demo: {args.frames} frames of {args.height}x{args.width} float32 on "
          f"Warp device {args.device!r}, domain {args.domain}, topic {args.topic}")
    children: dict[str, _Child] = {}
    termination = _Termination()
    previous = {signum: signal.signal(signum, termination)
                for signum in (signal.SIGTERM, signal.SIGINT)}
    try:
        for role in ("warp", "cpu", "publisher"):
            if termination.signum is None:
                children[role] = _Child(role, args)
        termination.deliver()
        publisher = children["publisher"]
        deadline = time.monotonic() + args.timeout + 30
        # Until both subscribers are done; a publisher that fails ends the demo at once.
        while not (children["warp"].done() and children["cpu"].done()):
            if publisher.done() or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        publisher.tell_done()
        published = publisher.finish(30)
        failed_early = not (published and published.get("ok"))
        subs = {role: children[role].finish(1 if failed_early else 30) for role in ("warp", "cpu")}
    finally:
        termination.deferred = True  # a second signal must not cut the reaping short
        for child in children.values():
            if child.proc.poll() is None:
                child.proc.kill()
            child.proc.wait()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    termination.deliver()
    ok = bool(published and published.get("ok"))
    if ok:
        print(f"publisher: published {published['published']} frames "
              f"({published['backend']} storage)")
    else:
        reason = (published or {}).get("error") or "no result"
        print(f"publisher: FAILED: {reason}")
    expected_path = {"warp": "warp", "cpu": "cpu"}
    from warp_buffer.pool import ipc_disabled

    if ipc_disabled():  # the documented fallback: the warp subscriber gets CPU bytes
        print("warp subscriber: IPC is disabled here (WARP_BUFFER_DISABLE_IPC): "
              "CPU bytes expected")
        expected_path["warp"] = "cpu"
    for role, stats in subs.items():
        if stats is None or "failed" in stats:
            print(f"{role} subscriber: FAILED ({(stats or {}).get('failed', 'no result')})")
            ok = False
            continue
        path_ok = stats["backends"] == [expected_path[role]]
        good = (path_ok and stats["received"] == args.frames and stats["bad"] == 0
                and stats["lost"] == 0 and stats["transport_errors"] == 0)
        ok = ok and good
        if stats.get("viewer") == "warp":
            print(f"{role} subscriber: torch is not installed (pip install "
                  "'warp-buffer[torch]'): frames viewed through Warp instead")
        print(f"{role} subscriber: path {'+'.join(stats['backends']) or '-'} "
              f"(route {'+'.join(stats['routes']) or '-'}), received {stats['received']}/"
              f"{args.frames}, bad {stats['bad']}, lost {stats['lost']}  "
              f"{'OK' if good else 'FAILED'}")
        print(f"    latency (publish to callback entry): {_percentiles(stats['latency_ms'])}")
        print(f"    check of every element (apart): {_percentiles(stats['check_ms'])}")
        for error in stats["errors"][:3]:
            print(f"    error: {error}")
    print("demo: " + ("all checks passed" if ok else "FAILED"))
    return 0 if ok else 1


if __name__ == "__main__":
    demo_parser = argparse.ArgumentParser(prog="warp-buffer demo")
    add_arguments(demo_parser)
    sys.exit(run(demo_parser.parse_args()))
