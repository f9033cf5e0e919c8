"""Where a full zero-copy message's time goes when the fast lane carries it, stage by stage.

``python -m benchmarks.lane_stages [--count N] [--nbytes N]``: a publisher (this process) and a
subscriber (a child) on one host. Per message, one in flight: allocate a warp tensor message,
take its output view and stamp it, build the descriptor CDR for the subscriber (the warp
backend's ``create_descriptor_with_endpoint`` through ``serialize_message``, today's export as a
stand-in for the IPC core being reworked), write it to the lane; the subscriber wakes on the
lane's event, deserializes (the descriptor import), and takes the input NumPy view. Each side
reads ``perf_counter_ns`` (one clock for every process) at each stage boundary; the table shows
per-stage medians and p99 and the one-way total. The raw lane figure (descriptor only) is the
``lane`` path of ``warp-buffer bench``.
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

TENSOR_TYPE = "tensor_msgs/msg/ExperimentalTensor"
HEADER = struct.Struct("<4qq")  # t0 start, t1 allocated, t2 stamped+released, t3 serialized, kind
FULL, BARE, STOP = 0, 1, 2
BARE_BYTES = 602  # a bare frame: the size of a descriptor message, nothing imported
STAGES_PUB = ("allocate_tensor_msg", "output view + stamp + release_output",
              "descriptor + CDR (serialize_message with route)", "lane write + notify")
STAGES_SUB = ("lane: write returned -> callback on the waiting thread",
              "deserialize + descriptor import", "from_input_tensor_msg (NumPy view)")


def _info(role: str, gid: bytes, pid: int, backends: dict[str, str]) -> Any:
    from rosidl_buffer import EndpointInfo, EndpointType, local_host_id

    kind = EndpointType.PUBLISHER if role == "pub" else EndpointType.SUBSCRIPTION
    return EndpointInfo(gid=gid, node_name=f"lane_stages_{role}", node_namespace="/",
                        topic_name="/lane_stages", topic_type=TENSOR_TYPE, endpoint_type=kind,
                        host_id=local_host_id(), process_id=pid, user_id=os.getuid(),
                        supported_backends=backends)


def _route(run: str) -> str:
    from buffer_pubsub import fast_lane

    return fast_lane.service_name(f"lane_stages/{run}", bytes.fromhex(run))


def subscriber(run: str, publisher_pid: int, ctrl: Connection) -> None:
    """Wake on the lane, import, view; send the stage stamps back on ``ctrl``."""
    import tensor_conversions.numpy as tc
    from rosidl_buffer import registry
    from rosidl_buffer.messages import deserialize_message, get_message_type

    from buffer_pubsub import fast_lane

    backend = registry.create_backend_instance("warp")
    msg_type = get_message_type(TENSOR_TYPE)
    publisher = _info("pub", bytes(16), publisher_pid, {})
    reader = fast_lane.LaneReader(_route(run), depth=16)
    waker = fast_lane.LaneWaker()
    stop = False

    def on_message(data: bytes) -> None:
        nonlocal stop
        t4 = time.perf_counter_ns()
        header = HEADER.unpack_from(data)
        if header[4] == STOP:
            stop = True
            return
        if header[4] == BARE:
            ctrl.send((*header[:4], t4, t4, t4, BARE))
            return
        msg = deserialize_message(memoryview(data)[HEADER.size:], msg_type,
                                  backends={"warp": backend}, endpoint_info=publisher)
        t5 = time.perf_counter_ns()
        view = tc.from_input_tensor_msg(msg, clone=False)
        int(view[0])  # the payload is readable here
        t6 = time.perf_counter_ns()
        del view, msg
        ctrl.send((*header[:4], t4, t5, t6, FULL))

    waker.attach(reader, on_message)
    waker.wait(0.0)
    ctrl.send(("ready", backend.get_backend_metadata()))
    while not stop:
        waker.wait(1.0)
    waker.close()
    reader.close()


def publisher(count: int, nbytes: int) -> list[tuple[int, ...]]:
    """Publish ``count`` messages one at a time; every message's stamps."""
    import numpy as np
    import tensor_conversions
    import tensor_conversions.numpy as tc
    from rosidl_buffer import registry
    from rosidl_buffer.messages import serialize_message

    from buffer_pubsub import fast_lane

    run = os.urandom(16).hex()
    parent, child = _pipe()
    process = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.lane_stages", "--role", "sub", "--run", run,
         "--publisher-pid", str(os.getpid()), "--fd", str(child.fileno())],
        pass_fds=(child.fileno(),), cwd=os.path.dirname(os.path.dirname(__file__)))
    child.close()
    records = []
    try:
        ready, metadata = parent.recv()
        backend = registry.create_backend_instance("warp")
        peer = _info("sub", bytes.fromhex(run), process.pid, {"warp": metadata})
        accepted, _ = backend.on_discovering_endpoint(peer, [], peer.supported_backends)
        if not accepted:
            raise RuntimeError(f"the warp backend refuses the subscriber: {metadata!r}")

        def route(buffer: Any) -> tuple[str, Any] | None:
            descriptor = backend.create_descriptor_with_endpoint(buffer.get_impl(), peer)
            return None if descriptor is None else ("warp", descriptor)

        writer = fast_lane.LaneWriter(_route(run))
        frame = bytearray(fast_lane.MAX_PAYLOAD)
        bare = bytearray(BARE_BYTES)
        for _ in range(count):
            t0 = time.perf_counter_ns()
            msg = tc.allocate_tensor_msg((nbytes,), np.uint8, backend="warp")
            t1 = time.perf_counter_ns()
            array = tc.from_output_tensor_msg(msg)
            array[:8] = 1
            del array
            tensor_conversions.release_output(msg)
            t2 = time.perf_counter_ns()
            cdr = serialize_message(msg, route=route)
            t3 = time.perf_counter_ns()
            end = HEADER.size + len(cdr)
            HEADER.pack_into(frame, 0, t0, t1, t2, t3, FULL)
            frame[HEADER.size:end] = cdr
            writer.write(memoryview(frame)[:end])
            records.append(parent.recv())
            del msg
            # The same transport with nothing around it, interleaved: what the lane alone costs.
            now = time.perf_counter_ns()
            HEADER.pack_into(bare, 0, now, now, now, now, BARE)
            writer.write(bare)
            records.append(parent.recv())
        writer.write(HEADER.pack(0, 0, 0, 0, STOP))
        writer.close()
        process.wait(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        _trim_warp_pool()
    return records


def _trim_warp_pool() -> None:
    """Give the pool's blocks back now rather than leave them to the exit path."""
    import gc

    import warp_buffer

    gc.collect()
    warp_buffer.trim_pools(0.0)


def _pipe() -> tuple[Connection, Connection]:
    import multiprocessing

    return multiprocessing.Pipe(duplex=True)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def table(records: list[tuple[int, ...]]) -> str:
    """Per-stage p50 / p99 (us) from the stamps ``(t0, t1, t2, t3, t4, t5, t6, kind)``."""
    full = [r for r in records if r[7] == FULL]
    bare = [r for r in records if r[7] == BARE]
    names = [*STAGES_PUB[:3], "lane: write + notify -> callback (one-way transport)",
             *STAGES_SUB[1:]]
    rows = []
    for index, name in enumerate(names):
        values = [(r[index + 1] - r[index]) / 1000 for r in full]
        rows.append((name, _percentile(values, 0.5), _percentile(values, 0.99)))
    total = [(r[6] - r[0]) / 1000 for r in full]
    rows.append(("one-way total (allocate -> readable view)", _percentile(total, 0.5),
                 _percentile(total, 0.99)))
    alone = [(r[4] - r[0]) / 1000 for r in bare]
    rows.append((f"lane alone, {BARE_BYTES} B frame, interleaved (write -> callback)",
                 _percentile(alone, 0.5), _percentile(alone, 0.99)))
    width = max(len(r[0]) for r in rows)
    lines = [f"{'stage':<{width}}  {'p50 us':>8}  {'p99 us':>8}"]
    lines += [f"{name:<{width}}  {p50:8.1f}  {p99:8.1f}" for name, p50, p99 in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the publisher (default) or the subscriber role."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.lane_stages",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=200)
    parser.add_argument("--nbytes", type=int, default=4096)
    parser.add_argument("--role", choices=("pub", "sub"), default="pub")
    parser.add_argument("--run")
    parser.add_argument("--publisher-pid", type=int)
    parser.add_argument("--fd", type=int)
    args = parser.parse_args(argv)
    if args.role == "sub":
        subscriber(args.run, args.publisher_pid, Connection(args.fd))
        return 0
    records = publisher(args.count, args.nbytes)
    warm = records[2 * min(10, args.count // 10):]  # first imports map files and warm caches
    print(f"fast lane, full message, {args.nbytes} B tensor, {len(warm) // 2} messages "
          f"(one in flight) and as many bare frames interleaved:")
    print(table(warm))
    return 0


if __name__ == "__main__":
    sys.exit(main())
