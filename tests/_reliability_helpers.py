"""Child programs and parent-side helpers for the reliability tests (faults, hostile input, soak).

Run a child as ``python -m tests._reliability_helpers <role> ...`` from the repository root.
Same stdout protocol as :mod:`tests._pubsub_helpers` (``READY``, then ``RESULT <json>`` after
``stop`` on stdin), plus progress lines:

- ``hold``: a warp subscription that keeps every message it receives (so its process holds the
  imported blocks) and prints ``HELD <n>`` each time it holds ``--hold`` more; killed by the test.
- ``soak``: subscriptions that join and leave in turns of ``--turn`` seconds until ``stop``;
  reports messages received, bad payloads, typed errors and its own resource samples.
- ``export``: allocates and exports ``--count`` warp buffers, prints ``READY`` and waits to be
  killed.
- ``outrun``: a warp publisher that publishes ``--count`` frames as fast as it can once matched,
  then prints ``RESULT`` (publish failures, its fds before and after) and waits.

``hold`` takes ``--delay`` (a slow subscriber) and on a stdin line prints ``RESULT`` with how many
held frames are still intact.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import resource
import subprocess
import sys
import threading
import time
from typing import Any

import zenoh

from tests import _pubsub_helpers as pubsub
from tests._pubsub_helpers import TENSOR, check_frame, child_env

MODULE = "tests._reliability_helpers"
SHM_DIR = "/dev/shm"


# --------------------------------------------------------------------------- resource probes
def resources() -> dict[str, int]:
    """This process's open fds, shared mappings (arenas, /dev/shm), /dev/shm files named for
    this process, and RSS in KiB."""
    with open("/proc/self/maps") as maps:
        # (the lane's rings are per route, not per message: not counted)
        mappings = sum(1 for line in maps if (f" {SHM_DIR}/" in line and "/warp_lane_" not in line)
                       or "/memfd:warp_buffer" in line)
    with open("/proc/self/status") as status:
        rss = next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))
    mine = [n for n in os.listdir(SHM_DIR) if n.startswith("warp_buffer") and f".{os.getpid()}" in n]
    return {"fds": len(os.listdir("/proc/self/fd")), "maps": mappings,
            "shm_files": len(mine), "rss_kib": rss}


# --------------------------------------------------------------------------- child programs
def _emit(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def run_hold(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node

    held: list[Any] = []
    with Node(f"holder_{os.getpid()}", domain_id=args.domain) as node:
        def on_msg(msg) -> None:
            if check_frame(msg)["ok"] and msg.data.get_backend_type() == "warp":
                held.append(msg)
                if len(held) % args.hold == 0:
                    _emit(f"HELD {len(held)}")
            if args.delay:
                time.sleep(args.delay)  # a slow subscriber

        sub = node.create_subscription(TENSOR, args.topic, on_msg, depth=args.depth,
                                       acceptable_buffer_backends="warp")
        _emit("READY")
        sys.stdin.readline()  # held until the parent kills us (or says stop)
        intact = sum(check_frame(msg)["ok"] for msg in held)  # still the bytes received
        _emit("RESULT " + json.dumps({"held": len(held), "intact": intact,
                                      "errors": sub.counters.errors, **resources()}))
    return 0


def run_outrun(args: argparse.Namespace) -> int:
    """A warp publisher that runs ``--count`` messages ahead as fast as it can, once a
    subscription is matched; reports publish failures and its fds before and after."""
    from buffer_pubsub import Node

    import warp_buffer

    with Node(f"outrun_{os.getpid()}", domain_id=args.domain) as node:
        pub = node.create_publisher(TENSOR, args.topic, depth=args.depth)
        _emit("READY")
        pub.wait_for_subscriptions(1, timeout=30)
        # The first message sets the route up (the lane's ring connects, or Zenoh's
        # channel is declared): fds are counted from there, against the messages in flight.
        pub.publish(pubsub.make_frame(0, 0, 2048, "warp"))
        before = resources()
        failures = []
        for index in range(1, args.count):
            try:
                pub.publish(pubsub.make_frame(0, index, 2048, "warp"))
            except Exception as exc:  # noqa: BLE001 - counted and reported, never expected
                failures.append(f"{index}: {type(exc).__name__}: {exc}")
        _emit("RESULT " + json.dumps({"published": args.count, "failures": failures[:5],
                                      "failed": len(failures), "before": before,
                                      "after": resources(),
                                      "pool": warp_buffer.pool_stats()["cpu"]}))
        sys.stdin.readline()
    return 0


def run_soak(args: argparse.Namespace) -> int:
    """Subscriptions join and leave; every received frame is verified then dropped."""
    from buffer_pubsub import Node

    stats = {"received": 0, "bad": 0, "errors": 0, "dropped": 0, "turns": 0,
             "backends": {}, "samples": []}
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()

    def on_msg(msg) -> None:
        record = check_frame(msg)
        stats["received"] += 1
        stats["bad"] += not record["ok"]
        stats["backends"][record["backend"]] = stats["backends"].get(record["backend"], 0) + 1
        if stats["received"] % args.progress == 0:
            _emit(f"GOT {stats['received']}")  # the publisher's flow-control window

    with Node(f"soak_{os.getpid()}", domain_id=args.domain) as node:
        _emit("READY")
        while not stop.is_set():
            sub = node.create_subscription(TENSOR, args.topic, on_msg, depth=args.depth,
                                           acceptable_buffer_backends="warp")
            stop.wait(args.turn)
            time.sleep(0.05)  # let the executor drain what is queued
            sub.destroy()
            stats["errors"] += sub.counters.errors
            stats["dropped"] += sub.counters.dropped
            stats["turns"] += 1
            time.sleep(args.gap)  # the whole gap, also after the stop line (the last sample)
            # Sampled at the end of the gap: a departed subscription's Zenoh and lane resources
            # close on other threads shortly after destroy(); a leak never closes.
            stats["samples"].append(resources())
    _emit("RESULT " + json.dumps(stats))
    return 0


def run_export(args: argparse.Namespace) -> int:
    from warp_buffer import allocate_buffer, ipc

    buffers = [allocate_buffer(4096) for _ in range(args.count)]
    for buffer in buffers:
        ipc.export_buffer(buffer)
    _emit("READY")
    sys.stdin.readline()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=MODULE)
    parser.add_argument("role", choices=["hold", "soak", "export", "outrun"])
    parser.add_argument("--domain", type=int, default=0)
    parser.add_argument("--topic", default="/reliability")
    parser.add_argument("--depth", type=int, default=100)
    parser.add_argument("--hold", type=int, default=8, help="hold: report every N held")
    parser.add_argument("--delay", type=float, default=0.0, help="hold: seconds per callback")
    parser.add_argument("--count", type=int, default=2, help="export/outrun: buffers")
    parser.add_argument("--turn", type=float, default=2.0, help="soak: seconds subscribed")
    parser.add_argument("--gap", type=float, default=0.3, help="soak: seconds unsubscribed")
    parser.add_argument("--progress", type=int, default=250, help="soak: GOT line every N")
    args = parser.parse_args(argv)
    roles = {"hold": run_hold, "soak": run_soak, "export": run_export, "outrun": run_outrun}
    return roles[args.role](args)


# --------------------------------------------------------------------------- parent side
class Child(pubsub.Child):
    """A child running a role of this module (or of ``module``), with extra environment."""

    def __init__(self, role: str, *, module: str = MODULE, env: dict[str, str] | None = None,
                 nofile: int | None = None, **options: Any) -> None:
        argv = [sys.executable, "-m", module, role]
        for key, value in options.items():
            argv += [f"--{key.replace('_', '-')}", str(value)]
        environment = child_env()
        environment.update(env or {})

        def limit() -> None:  # in the child, before exec: ``ulimit -n nofile``
            if nofile is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        self.proc = subprocess.Popen(argv, cwd=pubsub.ROOT, env=environment,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     preexec_fn=limit)
        self._lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def expect(self, prefix: str, timeout: float = 30.0) -> str:
        return self._expect(prefix, timeout)

    def result(self, timeout: float = 30.0) -> dict[str, Any]:
        """The RESULT of a child that ends by itself."""
        line = self._expect("RESULT ", timeout)
        self.proc.wait(timeout=timeout)
        return json.loads(line[len("RESULT "):])

    def progress(self) -> int:
        """The latest ``GOT <n>`` count the child printed (0 if none yet); never blocks."""
        latest = getattr(self, "_progress", 0)
        while True:
            try:
                line = self._lines.get_nowait()
            except queue.Empty:
                break
            if line is None:
                raise RuntimeError(f"child exited ({self.proc.wait()})")
            if line.startswith("GOT "):
                latest = int(line[4:])
        self._progress = latest
        return latest

    def kill(self) -> None:
        """SIGKILL and reap (no clean shutdown: the kernel drops its locks and mappings)."""
        self.proc.kill()
        self.proc.wait(timeout=10)


def publisher_child(**options: Any) -> Child:
    """A warp publisher child of :mod:`tests._pubsub_helpers` (self-checking frames)."""
    return Child("pub", module=pubsub.__name__, backend="warp", **options)


class ForgedPublisher:
    """A hand-made publisher: its own Zenoh session and liveliness token (a real, discovered
    buffer-aware publisher of this host and user), putting arbitrary payloads straight on a
    subscription's ``_buf/<gid>`` channel, so hostile descriptors reach the real receive path."""

    def __init__(self, domain: int, topic: str) -> None:
        from buffer_pubsub import make_config, wire
        from rosidl_buffer import local_host_id
        from rosidl_buffer.messages import get_type_hash

        self._wire = wire
        self.session = zenoh.open(make_config())
        self.token = wire.EndpointToken(
            domain_id=domain, zid=str(self.session.zid()), node_id=0, entity_id=1,
            kind=wire.PUBLISHER_KIND, namespace="", node_name="forger", topic=topic,
            type_name=TENSOR, type_hash=get_type_hash(TENSOR), qos=wire.QoSProfile.of(10),
            backends={"cpu": ""},
            locality=wire.Locality(local_host_id(), os.getpid(), os.getuid()))
        self._liveliness = self.session.liveliness().declare_token(self.token.key())
        self._sequence = 0

    def send(self, subscription: Any, payload: bytes | bytearray) -> None:
        self._sequence += 1
        attachment = self._wire.Attachment(self._sequence, time.time_ns(), self.token.gid)
        self.session.put(self._wire.buffer_channel_key(subscription.base_key, subscription.gid),
                         bytes(payload), attachment=attachment.encode())

    def close(self) -> None:
        try:
            self._liveliness.undeclare()
        finally:
            self.session.close()


def release_pool_memory(timeout: float = 5.0) -> dict[str, Any]:
    """Give every free pool block of this process back (its arena pages are punched out);
    returns the pool stats, in which a test expects no leased block left."""
    import gc

    import warp_buffer

    deadline = time.monotonic() + timeout
    while True:
        gc.collect()
        warp_buffer.trim_pools(0.0)
        stats = warp_buffer.pool_stats()
        idle = all(s["leased"] == 0 and s["free_blocks"] == 0 for s in stats.values())
        if idle or time.monotonic() > deadline:
            return stats
        time.sleep(0.02)


def wait_until(predicate, timeout: float = 10.0, interval: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(interval)
    return True


if __name__ == "__main__":
    sys.exit(main())
