"""The IPC core, side by side in one run: descriptor build and import cost, fds with 10,000
messages in flight and 10,000 views held, /dev/shm entries after SIGTERM and SIGKILL, and the
cpu device's ``to_cpu()`` / ``clone()`` against ``np.empty`` + ``np.copyto``.

    python -m benchmarks.ipc_core [--quick] [--sizes 4K,64M]

Goals (issue 11): build <= 10 us and import <= 10 us (the transport's descriptor stages were 92
and 142 us before the arena design); publisher and subscriber fds O(1) (a few, not 10,000);
nothing in /dev/shm after any death; ``to_cpu``/``clone`` >= 0.95x ``np.empty`` + ``np.copyto``
from 4 KiB to 256 MiB, fresh and reused destinations.

Build = ``create_descriptor_with_endpoint`` + the descriptor's bytes; import = decode +
``from_descriptor_with_endpoint`` + ``release()``, in another process that has attached to the
publisher's session (the steady state). Each is measured twice, interleaved: with the fixed
layout (``warp_buffer.descriptor.pack``/``unpack``, one struct call) and with the generic CDR codec
(``serialize_message`` / ``deserialize_message`` of the descriptor alone). Medians.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from benchmarks.copy_bandwidth import _median_seconds as _median

BUILD_GOAL_US = 10.0
IMPORT_GOAL_US = 10.0
BEFORE_US = {"build": 92.0, "import": 142.0}
COPY_GOAL = 0.95
FLOOD = 10_000
SIZES = "4K,64K,1M,16M,64M,256M"
QUICK_SIZES = "4K,1M,64M"
_CHILD = [sys.executable, "-m", "benchmarks.ipc_core", "--child"]


def _parse_size(text: str) -> int:
    text = text.strip().upper().removesuffix("B").removesuffix("I")
    scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1:], 1)
    return int(float(text[:-1] if scale > 1 else text) * scale)


def _fmt(nbytes: int) -> str:
    for unit, scale in (("M", 1 << 20), ("K", 1 << 10)):
        if nbytes >= scale:
            return f"{nbytes // scale}{unit}"
    return str(nbytes)


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _quiet_warp() -> None:
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING


def _infos(publisher_pid: int | None = None) -> tuple[Any, Any, Any]:
    """The backend, a subscription's info (this process) and the publisher's (``publisher_pid``,
    default this process: the child is told its parent's, whose memory its descriptors name)."""
    from rosidl_buffer import EndpointInfo, EndpointType, local_host_id
    from warp_buffer_backend import WarpBufferBackend

    backend = WarpBufferBackend()

    def info(kind: Any, gid: int, pid: int = os.getpid()) -> Any:
        supported = {"warp": backend.get_backend_metadata()} if kind is EndpointType.SUBSCRIPTION \
            else {}
        return EndpointInfo(gid=gid.to_bytes(16, "little"), node_name="bench", node_namespace="/",
                            topic_name="/bench", topic_type="sensor_msgs/msg/Image",
                            endpoint_type=kind, host_id=local_host_id(), process_id=pid,
                            user_id=os.getuid(), supported_backends=supported)

    return (backend, info(EndpointType.SUBSCRIPTION, 1),
            info(EndpointType.PUBLISHER, 2, publisher_pid or os.getpid()))


# --------------------------------------------------------------------------- child roles
def _child(role: str, path: str, count: int) -> None:
    """Roles run in a child: ``import`` (time imports), ``hold`` (keep them all), ``wait``."""
    _quiet_warp()
    from rosidl_buffer.messages import deserialize_message
    from warp_buffer import descriptor

    out: dict[str, Any] = {"fds_before": _fds()}
    # The descriptors are all there: "go" (the parent published them) or the publisher's pid.
    line = sys.stdin.readline().strip()
    backend, _sub, pub = _infos(publisher_pid=int(line) if line.isdigit() else os.getppid())
    raw = open(path, "rb").read()
    size = descriptor.LAYOUT.size + 4
    frames = [raw[i:i + size] for i in range(0, len(raw), size)]
    kind = descriptor.DESCRIPTOR_TYPE
    if role == "import":
        backend.from_descriptor_with_endpoint(deserialize_message(frames[0], kind), pub).release()
        fixed, generic = [], []
        for index, frame in enumerate(frames[1:]):
            if index % 2:
                start = time.perf_counter()
                impl = backend.from_descriptor_with_endpoint(deserialize_message(frame, kind), pub)
                impl.release()
                generic.append(time.perf_counter() - start)
            else:
                start = time.perf_counter()
                impl = backend.from_descriptor_with_endpoint(descriptor.unpack(frame[4:]), pub)
                impl.release()
                fixed.append(time.perf_counter() - start)
        out["import_us"] = statistics.median(fixed) * 1e6
        out["import_cdr_us"] = statistics.median(generic) * 1e6
    else:
        held = [backend.from_descriptor_with_endpoint(deserialize_message(f, kind), pub)
                for f in frames]
        out.update(held=len(held), fds=_fds())
    print("RESULT " + json.dumps(out), flush=True)
    sys.stdin.readline()


def _spawn(role: str, path: str, count: int) -> subprocess.Popen:
    return subprocess.Popen(_CHILD + [role, path, str(count)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _result(proc: subprocess.Popen) -> dict[str, Any]:
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"benchmark child {proc.args} exited ({proc.wait()}) without a result")


def _finish(proc: subprocess.Popen, sig: int | None = None) -> None:
    try:
        if sig is not None:
            proc.send_signal(sig)
        elif proc.stdin is not None:
            proc.stdin.write("\n")
            proc.stdin.flush()
    except OSError:
        pass
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


# --------------------------------------------------------------------------- measurements
def _publish(backend: Any, sub: Any, count: int, path: str, timed: bool) -> dict[str, Any]:
    """Publish ``count`` 4 KiB buffers for ``sub`` into ``path`` (descriptor CDR each)."""
    from rosidl_buffer.messages import CDR_HEADER, serialize_message
    from warp_buffer import allocate_buffer, descriptor

    fixed: list[float] = []
    generic: list[float] = []
    keep = []
    with open(path, "wb") as out:
        for index in range(count):
            impl = allocate_buffer(4096, "cpu").get_impl()
            if index % 2:
                start = time.perf_counter()
                data = serialize_message(backend.create_descriptor_with_endpoint(impl, sub))
                generic.append(time.perf_counter() - start)
            else:
                start = time.perf_counter()
                raw = descriptor.pack(backend.create_descriptor_with_endpoint(impl, sub))
                fixed.append(time.perf_counter() - start)
                data = CDR_HEADER + raw
            out.write(data)
            if timed:
                keep.append(impl)  # the import run reads them all: keep them published
    if not timed or not generic:
        return {"keep": keep}
    return {"build_us": statistics.median(fixed) * 1e6,
            "build_cdr_us": statistics.median(generic) * 1e6, "keep": keep}


def _with_child(role: str, count: int, publish: Callable[[Any, Any, str], Any],
                ) -> tuple[Any, dict[str, Any]]:
    """Start child ``role``, publish for it (``publish(backend, sub, path)``), let it read, and
    return what ``publish`` returned with the child's result."""
    backend, sub, _pub = _infos()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "d")
        child = _spawn(role, path, count)
        try:
            sub = type(sub)(**{**sub.__dict__, "process_id": child.pid})
            published = publish(backend, sub, path)
            assert child.stdin is not None
            child.stdin.write("go\n")
            child.stdin.flush()
            result = _result(child)
        finally:
            _finish(child)
        backend.on_endpoint_gone(sub)
    return published, result


def descriptor_costs(count: int) -> dict[str, float]:
    built, result = _with_child(
        "import", count, lambda backend, sub, path: _publish(backend, sub, count, path, True))
    return {"build_us": built["build_us"], "build_cdr_us": built["build_cdr_us"],
            "import_us": result["import_us"], "import_cdr_us": result["import_cdr_us"]}


def resources_in_flight(count: int) -> dict[str, int]:
    """Publisher fds with ``count`` messages in flight to a subscriber that has not read any;
    then the subscriber's fds once it holds them all."""
    def publish(backend: Any, sub: Any, path: str) -> tuple[int, int]:
        gc.collect()
        before = _fds()
        _publish(backend, sub, count, path, timed=False)  # each buffer dropped at once
        return before, _fds()

    (before, in_flight), held = _with_child("hold", count, publish)
    return {"pub_fds_before": before, "pub_fds_in_flight": in_flight,
            "sub_fds_before": held["fds_before"], "sub_fds_holding": held["fds"],
            "sub_held": held["held"]}


def _entries() -> set[str]:
    return {n for n in os.listdir("/dev/shm") if n.startswith("warp_buffer")}


def dev_shm_after_deaths() -> dict[str, int]:
    """Entries in /dev/shm named for the processes after a publisher and a subscriber are
    SIGTERMed / SIGKILLed while the subscriber holds the publisher's frames."""
    code = ("import sys, os; from benchmarks.ipc_core import _deaths_publisher; "
            "_deaths_publisher()")
    out: dict[str, int] = {}
    for name, sig in (("SIGTERM", signal.SIGTERM), ("SIGKILL", signal.SIGKILL)):
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "d")
            sub = _spawn("hold", path, 16)
            pub = subprocess.Popen([sys.executable, "-c", code, path, str(sub.pid)],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                   cwd=os.path.dirname(os.path.dirname(
                                       os.path.abspath(__file__))))
            try:
                _result(pub)
                assert sub.stdin is not None
                sub.stdin.write(f"{pub.pid}\n")  # whose memory the descriptors name
                sub.stdin.flush()
                _result(sub)
                pids = (pub.pid, sub.pid)
                _finish(pub, sig)
                _finish(sub, sig)
            finally:
                _finish(pub, signal.SIGKILL)
                _finish(sub, signal.SIGKILL)
            out[name] = len([n for n in _entries() if any(f".{p}" in n for p in pids)])
    return out


def _deaths_publisher() -> None:
    _quiet_warp()
    backend, sub, _pub = _infos()
    sub = type(sub)(**{**sub.__dict__, "process_id": int(sys.argv[2])})
    keep = _publish(backend, sub, 16, sys.argv[1], timed=True)
    print("RESULT " + json.dumps({"published": len(keep["keep"])}), flush=True)
    sys.stdin.readline()


def copies(sizes: Sequence[int], quick: bool) -> list[dict[str, Any]]:
    """``to_cpu`` and ``clone`` of a cpu buffer as ratios to the plain NumPy copy ``np.empty`` +
    ``np.copyto`` (interleaved, one run; each destination comes from the same allocator as the
    baseline's, fresh or reused pages as it decides, so both see the same pages). ``clone_export``
    (no goal, for information) is a clone that is then exported once: a cpu clone is private
    memory and moves into the arena on its first export (one more copy, once per buffer)."""
    from warp_buffer import allocate_buffer, from_output_buffer, to_buffer, trim_pools
    from warp_buffer.ipc import export_buffer

    rows = []
    for nbytes in sizes:
        repeat = max(5, min(2000 if not quick else 300, (256 << 20) // nbytes * 3))
        buffer = allocate_buffer(nbytes, "cpu")
        with from_output_buffer(buffer) as out:
            to_buffer(np.arange(nbytes, dtype=np.uint64).astype(np.uint8), out)
        impl = buffer.get_impl()
        src = impl.host

        def numpy_copy() -> None:
            np.copyto(np.empty(nbytes, np.uint8), src)

        def clone_export() -> None:
            export_buffer(impl.clone())

        base = _median(numpy_copy, repeat)
        to_cpu = _median(impl.to_cpu, repeat)
        base_again = _median(numpy_copy, repeat)
        clone = _median(impl.clone, repeat)
        base_last = _median(numpy_copy, repeat)
        exported = _median(clone_export, max(3, repeat // 4))
        assert np.array_equal(impl.to_cpu().view(), src)
        assert np.array_equal(impl.clone().to_cpu().view(), src)
        rows.append({"nbytes": nbytes, "to_cpu": base / to_cpu,
                     "clone": min(base_again, base_last) / clone,
                     "clone_export": base_last / exported})
        del buffer, impl, src
        gc.collect()
        trim_pools(0.0)
    return rows


# --------------------------------------------------------------------------- report
def measure(quick: bool, sizes: Sequence[int], flood: int = FLOOD) -> dict[str, Any]:
    _quiet_warp()
    count = 500 if quick else 3000
    return {"descriptor": descriptor_costs(count), "in_flight": resources_in_flight(flood),
            "dev_shm": dev_shm_after_deaths(), "copies": copies(sizes, quick)}


def format_report(report: dict[str, Any]) -> str:
    d, f, s = report["descriptor"], report["in_flight"], report["dev_shm"]
    lines = [
        "IPC core (benchmarks.ipc_core; p50, this machine, one run)",
        f"  descriptor build  {d['build_us']:7.1f} us  goal <= {BUILD_GOAL_US:.0f}  "
        f"({d['build_us'] / BUILD_GOAL_US:.2f}x of the goal; was {BEFORE_US['build']:.0f}); "
        f"with the generic CDR codec {d['build_cdr_us']:.1f} us",
        f"  descriptor import {d['import_us']:7.1f} us  goal <= {IMPORT_GOAL_US:.0f}  "
        f"({d['import_us'] / IMPORT_GOAL_US:.2f}x of the goal; was {BEFORE_US['import']:.0f}); "
        f"with the generic CDR codec {d['import_cdr_us']:.1f} us",
        f"  publisher fds, {f['sub_held']:,} messages in flight: {f['pub_fds_before']} -> "
        f"{f['pub_fds_in_flight']} (+{f['pub_fds_in_flight'] - f['pub_fds_before']})",
        f"  subscriber fds, {f['sub_held']:,} views held: {f['sub_fds_before']} -> "
        f"{f['sub_fds_holding']} (+{f['sub_fds_holding'] - f['sub_fds_before']})",
        f"  /dev/shm entries of the processes after SIGTERM: {s['SIGTERM']}, after SIGKILL: "
        f"{s['SIGKILL']} (goal 0)",
        f"  host copies, ratio to np.empty + np.copyto (goal >= {COPY_GOAL}):",
        "      size   to_cpu   clone   (clone + first export: info, no goal)",
    ]
    for row in report["copies"]:
        lines.append(f"    {_fmt(row['nbytes']):>6}   {row['to_cpu']:6.2f}  {row['clone']:6.2f}"
                     f"   {row['clone_export']:6.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        _child(argv[1], argv[2], int(argv[3]))
        return 0
    parser = argparse.ArgumentParser(prog="python -m benchmarks.ipc_core", description=__doc__)
    parser.add_argument("--quick", action="store_true", help=f"sizes {QUICK_SIZES}, fewer runs")
    parser.add_argument("--sizes", default=None, help=f"copy sizes (default {SIZES})")
    parser.add_argument("--flood", type=int, default=FLOOD,
                        help="messages in flight / views held (default %(default)s)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON too")
    args = parser.parse_args(argv)
    text = args.sizes or (QUICK_SIZES if args.quick else SIZES)
    report = measure(args.quick, [_parse_size(x) for x in text.split(",") if x.strip()],
                     args.flood)
    print(format_report(report))
    if args.json:
        print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
