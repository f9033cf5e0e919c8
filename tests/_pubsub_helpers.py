"""Child-process programs and parent-side helpers for the buffer_pubsub topology tests.

Run a child as ``python -m tests._pubsub_helpers {sub,pub,relay} ...`` from the repository root.
Protocol on stdout: ``READY`` once its endpoints exist, then (after the parent writes ``stop`` to
its stdin, or on its own timeout) one line ``RESULT <json>``.

Frames are self-checking ExperimentalTensor messages: the first 8 bytes hold (publisher id, frame
index) and every other byte follows a pattern derived from them, optionally XORed by a relay, so
a receiver verifies content without knowing what was sent.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import queue
import signal
import subprocess
import sys
import threading
import time
import zlib
from typing import Any

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
FAKE_BACKEND_PATH = ROOT / "tests" / "fake_backend"
TENSOR = "tensor_msgs/msg/ExperimentalTensor"
HEADER = 8


# --------------------------------------------------------------------------- backends
def use_fake_backend() -> None:
    """Make the test-only ``fake`` backend discoverable in this process."""
    if str(FAKE_BACKEND_PATH) not in sys.path:
        sys.path.insert(0, str(FAKE_BACKEND_PATH))
    from rosidl_buffer import registry

    registry.refresh()


def warp_available() -> bool:
    try:
        from rosidl_buffer.registry import create_backend_instance

        create_backend_instance("warp")
        import warp_buffer  # noqa: F401

        return hasattr(warp_buffer, "allocate_buffer")
    except Exception:
        return False


def pick_backend() -> str:
    """The accelerated backend the topology tests use: ``warp`` once it exists, else ``fake``."""
    return "warp" if warp_available() else "fake"


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    paths = [str(ROOT), str(FAKE_BACKEND_PATH), env.get("PYTHONPATH", "")]
    env["PYTHONPATH"] = os.pathsep.join(p for p in paths if p)
    return env


# --------------------------------------------------------------------------- frames
def pattern(pub_id: int, index: int, n: int) -> np.ndarray:
    k = np.arange(n, dtype=np.uint32)
    data = ((k * 7 + index * 13 + pub_id * 101) % 251).astype(np.uint8)
    data[:HEADER] = np.frombuffer(np.array([pub_id, index], dtype="<u4").tobytes(), np.uint8)
    return data


def make_buffer(data: np.ndarray, backend: str, stale: bool = False):
    """A Buffer holding ``data`` in ``backend`` ("cpu", "fake" or "warp")."""
    from rosidl_buffer import Buffer

    if backend == "cpu":
        return Buffer(data.copy())
    if backend == "fake":
        from fake_buffer_backend import FakeBufferImpl

        return Buffer(FakeBufferImpl(data.copy(), stale=stale))
    if backend == "warp":
        import warp as wp
        from warp_buffer import allocate_buffer, from_output_buffer

        buffer = allocate_buffer(int(data.shape[0]))
        handle = from_output_buffer(buffer)
        wp.copy(handle.array, wp.array(data, dtype=wp.uint8, device=handle.array.device))
        _close_handle(handle)
        return buffer
    raise ValueError(f"unknown backend {backend!r}")


def _close_handle(handle: Any) -> None:
    for name in ("close", "release"):
        if hasattr(handle, name):
            getattr(handle, name)()
            return


def make_frame(pub_id: int, index: int, n: int, backend: str, stale: bool = False):
    from rosidl_buffer.messages import get_message_type

    tensor = get_message_type(TENSOR)
    data = pattern(pub_id, index, n)
    return tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=np.array([n]),
                  data=make_buffer(data, backend, stale))


def frame_bytes(msg) -> np.ndarray:
    return msg.data.to_numpy()


def check_frame(msg, xor: int = 0) -> dict[str, Any]:
    """Verify a received frame; returns its record (ids, backend, checksum, ok)."""
    data = frame_bytes(msg)
    if xor:
        data = data ^ np.uint8(xor)
    pub_id, index = (int(v) for v in np.frombuffer(data[:HEADER].tobytes(), "<u4"))
    expected = pattern(pub_id, index, int(data.shape[0]))
    return {
        "pub": pub_id, "index": index, "backend": msg.data.get_backend_type(),
        "crc": zlib.crc32(data.tobytes()), "ok": bool(np.array_equal(data, expected)),
        "size": int(data.shape[0]),
    }


# --------------------------------------------------------------------------- child programs
def _stdin_stop(timeout: float) -> threading.Event:
    stop = threading.Event()

    def watch() -> None:
        sys.stdin.readline()
        stop.set()

    threading.Thread(target=watch, daemon=True).start()
    timer = threading.Timer(timeout, stop.set)
    timer.daemon = True
    timer.start()
    return stop


def _emit(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _stall_first_import(release_file: str) -> dict[str, str]:
    """Make this process's first warp import wait, after its frame was taken off its route,
    until ``release_file`` exists (printing ``TAKEN`` first): a reader descheduled between
    taking a descriptor and importing it. Returns where the outcome of that import is noted."""
    from warp_buffer_backend.backend import WarpBufferBackend

    original = WarpBufferBackend.from_descriptor_with_endpoint
    outcome: dict[str, str] = {}

    def stalled(self, descriptor, endpoint_info):
        if outcome:
            return original(self, descriptor, endpoint_info)
        outcome["import"] = "waiting"
        _emit("TAKEN")
        while not os.path.exists(release_file):
            time.sleep(0.01)
        try:
            impl = original(self, descriptor, endpoint_info)
        except Exception as exc:
            outcome["import"] = type(exc).__name__
            raise
        outcome["import"] = "imported"
        return impl

    WarpBufferBackend.from_descriptor_with_endpoint = stalled
    return outcome


def run_sub(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node

    records: list[dict[str, Any]] = []
    stalled = _stall_first_import(args.stall_first_import) if args.stall_first_import else {}
    with Node(f"sub_{os.getpid()}", domain_id=args.domain) as node:
        def on_msg(msg, info) -> None:
            record = check_frame(msg, args.xor)
            record["route"] = info.route
            record["latency_us"] = (info.received_timestamp_ns - info.source_timestamp_ns) / 1e3
            records.append(record)

        sub = node.create_subscription(TENSOR, args.topic, on_msg, depth=args.depth,
                                       acceptable_buffer_backends=args.accept, with_info=True,
                                       max_rate=args.max_rate or None, history=args.history)
        sub.wait_for_publishers(args.publishers, timeout=args.timeout)
        _emit("READY")
        _stdin_stop(args.timeout).wait()
        deadline = time.monotonic() + 10
        while len(records) < args.expect and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)  # a duplicate would land in this window
        counters = vars(sub.counters).copy()
    _emit("RESULT " + json.dumps({"records": records, "counters": counters, **stalled}))
    return 0


def run_pub(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node

    with Node(f"pub_{os.getpid()}", domain_id=args.domain) as node:
        pub = node.create_publisher(TENSOR, args.topic, depth=args.depth)
        matched = pub.wait_for_subscriptions(args.subscriptions, timeout=args.timeout)
        _emit("READY")
        for index in range(args.count):
            pub.publish(make_frame(args.pub_id, index, args.size, args.backend,
                                   stale=index == args.stale_index))
            time.sleep(args.interval)
        stop = _stdin_stop(args.timeout)
        stop.wait()
    _emit("RESULT " + json.dumps({"matched": matched, "published": args.count}))
    return 0


def run_relay(args: argparse.Namespace) -> int:
    """Receive frames, XOR every byte with a Warp kernel into a new buffer, republish."""
    from buffer_pubsub import Node
    from tests._pubsub_kernels import xor_buffer

    seen: list[str] = []
    xor_buffer(make_buffer(pattern(0, 0, 64), "cpu"), args.xor)  # compile before READY
    with Node(f"relay_{os.getpid()}", domain_id=args.domain) as node:
        pub = node.create_publisher(TENSOR, args.out_topic, depth=args.depth)

        def on_msg(msg) -> None:
            seen.append(msg.data.get_backend_type())
            msg.data = xor_buffer(msg.data, args.xor)
            pub.publish(msg)

        sub = node.create_subscription(TENSOR, args.topic, on_msg, depth=args.depth,
                                       acceptable_buffer_backends=args.accept)
        sub.wait_for_publishers(1, timeout=args.timeout)
        pub.wait_for_subscriptions(1, timeout=args.timeout)
        _emit("READY")
        _stdin_stop(args.timeout).wait()
        counters = vars(sub.counters).copy()
    _emit("RESULT " + json.dumps({"backends": seen, "counters": counters}))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tests._pubsub_helpers")
    parser.add_argument("role", choices=["sub", "pub", "relay"])
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--out-topic", default="")
    parser.add_argument("--accept", default="cpu")
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--depth", type=int, default=100)
    parser.add_argument("--history", default="keep_last", choices=["keep_last", "keep_all"])
    parser.add_argument("--count", type=int, default=10)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--pub-id", type=int, default=0)
    parser.add_argument("--publishers", type=int, default=1)
    parser.add_argument("--subscriptions", type=int, default=1)
    parser.add_argument("--interval", type=float, default=0.005)
    parser.add_argument("--xor", type=int, default=0)
    parser.add_argument("--expect", type=int, default=0, help="sub: wait for this many on stop")
    parser.add_argument("--stale-index", type=int, default=-1, help="pub: frame sent stale")
    parser.add_argument("--timeout", type=float, default=30.0)
    parser.add_argument("--max-rate", type=float, default=0.0, help="sub: its max_rate (Hz)")
    parser.add_argument("--stall-first-import", default="",
                        help="sub: the first warp import waits for this file (prints TAKEN)")
    args = parser.parse_args(argv)
    use_fake_backend()
    return {"sub": run_sub, "pub": run_pub, "relay": run_relay}[args.role](args)


# --------------------------------------------------------------------------- parent side
class Child:
    """A helper child process; always reaped (``close`` kills it if it is still running)."""

    def __init__(self, role: str, module: str = "tests._pubsub_helpers", stderr: Any = None,
                 **options: Any) -> None:
        argv = [sys.executable, "-m", module, role]
        for key, value in options.items():
            argv += [f"--{key.replace('_', '-')}", str(value)]
        self._start(role, argv, child_env(), stderr)

    def _start(self, name: str, argv: list[str], env: dict[str, str], stderr: Any) -> None:
        self.name = name
        self.proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=stderr, text=True)
        self._lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line.rstrip("\n"))
        self._lines.put(None)

    def wait_ready(self, timeout: float = 30.0) -> None:
        self._expect("READY", timeout)

    def _expect(self, prefix: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self._lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise TimeoutError(f"child {self.name} did not print {prefix}") from None
            if line is None:
                raise RuntimeError(f"child {self.name} exited ({self.proc.wait()}) "
                                   f"before {prefix}")
            if line.startswith(prefix):
                return line

    def stop(self, timeout: float = 20.0) -> dict[str, Any]:
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write("stop\n")
            self.proc.stdin.flush()
        except BrokenPipeError:
            pass
        line = self._expect("RESULT ", timeout)
        self.proc.wait(timeout=timeout)
        return json.loads(line[len("RESULT "):])

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            try:  # a SIGSTOPped child dies of SIGKILL too, but let it run its exit
                os.kill(self.proc.pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        self.proc.wait(timeout=10)
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


if __name__ == "__main__":
    sys.exit(main())
