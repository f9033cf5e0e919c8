"""Where a message's time goes in buffer_pubsub, stage by stage (printed when a transport target
is missed, or run alone: ``python -m benchmarks.stages [--json]``).

Each stage is timed on its own in this process (median of repeated calls): the publisher's
checks, CDR serialization into the reused buffer, a raw Zenoh put and its delivery between two
loopback sessions, the subscriber's attachment decode and ``to_bytes`` copy, the executor's
thread hand-off (paid until a subscription's callbacks prove short), deserialization and the
NumPy view the user takes. The sum is an estimate; the bench's path figures are the
measurement, and ``benchmarks.lane_stages`` stamps the real path between two processes.
"""

from __future__ import annotations

import argparse
import json
import queue
import statistics
import sys
import threading
import time
from typing import Any, Callable

SIZES = (4 << 10, 16 << 20)


def _median_us(fn: Callable[[], Any], repeat: int) -> float:
    fn()  # warm
    samples = []
    for _ in range(repeat):
        start = time.perf_counter_ns()
        fn()
        samples.append(time.perf_counter_ns() - start)
    return statistics.median(samples) / 1e3


def _handoff_us(repeat: int) -> float:
    """One blocking hand-off to a waiting thread (the executor's wake-up)."""
    tasks: queue.SimpleQueue = queue.SimpleQueue()
    done: queue.SimpleQueue = queue.SimpleQueue()
    samples: list[int] = []

    def worker() -> None:
        while (stamp := tasks.get()) is not None:
            samples.append(time.perf_counter_ns() - stamp)
            done.put(None)

    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    for _ in range(repeat):
        tasks.put(time.perf_counter_ns())
        done.get()
    tasks.put(None)
    thread.join()
    return statistics.median(samples) / 1e3


def _zenoh_one_way_us(nbytes: int, repeat: int) -> float:
    """Raw put -> subscriber callback with ``to_bytes`` between two loopback sessions."""
    import zenoh

    def config(listen: bool, port: int) -> Any:
        endpoint = json.dumps([f"tcp/127.0.0.1:{port}"])
        text = {"mode": "peer", "scouting": {"multicast": {"enabled": False}},
                "transport": {"shared_memory": {"enabled": False}}}
        conf = zenoh.Config.from_json5(json.dumps(text))
        conf.insert_json5("listen/endpoints" if listen else "connect/endpoints", endpoint)
        return conf

    from benchmarks.processes import free_tcp_port

    port = free_tcp_port()
    key = f"warp_buffer_stages/{port}"
    got: queue.SimpleQueue = queue.SimpleQueue()
    with zenoh.open(config(True, port)) as rx, zenoh.open(config(False, port)) as tx:
        sub = rx.declare_subscriber(
            key, lambda s: got.put((time.perf_counter_ns(), s.payload.to_bytes())))
        pub = tx.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.5)
        payload = bytearray(nbytes)
        samples = []
        for _ in range(repeat):
            start = time.perf_counter_ns()
            pub.put(payload)
            arrived, _data = got.get(timeout=10)
            samples.append(arrived - start)
        sub.undeclare()
        pub.undeclare()
    return statistics.median(samples) / 1e3


def measure(repeat: int = 200) -> dict[str, Any]:
    """Stage medians (us) per payload size."""
    import numpy as np
    import zenoh

    import tensor_conversions.numpy as tc
    from buffer_pubsub import wire
    from buffer_pubsub._validation import validate_message
    from buffer_pubsub.publisher import seal_and_list_backends
    from rosidl_buffer.messages import deserialize_message, serialize_message

    result: dict[str, Any] = {"handoff_us": _handoff_us(repeat), "sizes": {}}
    attachment = wire.Attachment(1, time.time_ns(), b"\x01" * 16).encode()
    zbytes = zenoh.ZBytes(attachment)
    for nbytes in SIZES:
        count = repeat if nbytes < (1 << 20) else max(5, repeat // 20)
        msg = tc.allocate_tensor_msg((nbytes,), np.uint8, backend="cpu")
        out = serialize_message(msg)
        data = bytes(out)
        received = deserialize_message(data, type(msg))
        stages = {
            "publish: validate fields": _median_us(lambda: validate_message(msg), count),
            "publish: seal + backends": _median_us(
                lambda: seal_and_list_backends(msg, ("data",)), count),
            "publish: CDR into the reused buffer": _median_us(
                lambda: serialize_message(msg, out=out), count),
            "wire: raw Zenoh put -> callback + to_bytes": _zenoh_one_way_us(nbytes, count),
            "subscriber: attachment decode": _median_us(
                lambda: wire.Attachment.decode(zbytes.to_bytes()), count),
            # Paid until a subscription's callbacks prove short (buffer_pubsub._inline), then
            # they run on the arrival thread: the figure of a subscription that hands off.
            "subscriber: executor hand-off (until callbacks prove short)": result["handoff_us"],
            "subscriber: deserialize": _median_us(
                lambda: deserialize_message(data, type(msg)), count),
            "subscriber: user's NumPy view": _median_us(
                lambda: tc.from_input_tensor_msg(received, clone=False), count),
        }
        stages["sum"] = sum(stages.values())
        result["sizes"][str(nbytes)] = stages
    return result


def format_stages(stages: dict[str, Any]) -> str:
    """The stage table (us per stage, per size)."""
    sizes = list(stages["sizes"])
    names = list(stages["sizes"][sizes[0]])
    width = max(len(n) for n in names)
    from benchmarks.stats import format_size

    lines = ["Where the time goes (each stage alone, median us; the sum estimates one message):",
             "  " + "stage".ljust(width) + "".join(format_size(int(s)).rjust(12) for s in sizes)]
    for name in names:
        cells = "".join(f"{stages['sizes'][s][name]:12,.1f}" for s in sizes)
        lines.append("  " + name.ljust(width) + cells)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.stages [--json]``."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.stages")
    parser.add_argument("--json", action="store_true", help="print JSON instead of the table")
    parser.add_argument("--repeat", type=int, default=200)
    args = parser.parse_args(argv)
    stages = measure(args.repeat)
    print(json.dumps(stages) if args.json else format_stages(stages))
    return 0


if __name__ == "__main__":
    sys.exit(main())
