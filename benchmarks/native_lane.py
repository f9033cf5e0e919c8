"""The same-host descriptor hand-off, by mechanism, side by side in one run (issue 26, decision 3).

``python -m benchmarks.native_lane [--count N] [--rounds R]``: one sending process
(this one) and one receiving child; one 602-byte frame in flight (a descriptor message), its
send time stamped in its first 8 bytes; latency = the receiver's clock when its Python code holds
the frame minus the stamp. The mechanisms take turns in every round (``R`` rounds of ``N``
frames each), so the machine's drifting load falls on all of them alike:

- ``ring``: the native lane ring (``buffer_pubsub._ring``: a sealed memfd, an eventfd doorbell),
  the receiver blocked in ``Waker.wait`` (GIL released in ``ppoll``);
- ``ring_busy``: the same, the waker spinning (``busy_poll_s``) before it blocks;
- ``lane``: ``buffer_pubsub.fast_lane`` as the transport uses it (``LaneWriter`` /
  ``LaneWaker``, the ring with its Python layer);
- ``iceoryx2_listener``: iceoryx2 publish-subscribe carrying the frame, woken by an iceoryx2
  event (``Listener.timed_wait``);
- ``iceoryx2_busy``: the same, the receiver busy-polling ``receive()``;
- ``eventfd`` and ``pipe``: the floor, a bare blocking wake-up between two processes (eventfd:
  8 bytes, no frame; pipe: the frame through the kernel).

Busy-polling variants hold a core at 100% while they wait; their CPU use is printed.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import statistics
import subprocess
import sys
import time
import uuid
from typing import Any

FRAME_BYTES = 602
DEPTH = 16
MECHANISMS = ("ring", "ring_busy", "lane", "iceoryx2_listener", "iceoryx2_busy", "eventfd",
              "pipe")
BUSY_S = 1.0
_CHILD = [sys.executable, "-m", "benchmarks.native_lane", "--child"]


def _stamp(frame: bytearray) -> None:
    frame[:8] = time.perf_counter_ns().to_bytes(8, "little")


def _latency_ns(head: bytes | memoryview) -> int:
    return time.perf_counter_ns() - int.from_bytes(head[:8], "little")


def _iox2(run: str) -> tuple[Any, Any]:
    import iceoryx2 as iox2

    iox2.set_log_level_from_env_or(iox2.LogLevel.Error)
    config = iox2.config.global_config()
    config.global_cfg.prefix = iox2.FileName.new(f"iox2nl_{run[:12]}_")
    return iox2, config


def _iox2_services(node: Any, iox2: Any, run: str) -> tuple[Any, Any]:
    name = iox2.ServiceName.new(f"native_lane/{run}")
    pubsub = (node.service_builder(name).publish_subscribe(iox2.Slice[ctypes.c_uint8])
              .subscriber_max_buffer_size(DEPTH).history_size(0).open_or_create())
    return pubsub, node.service_builder(name).event().open_or_create()


def _lane_route(run: str) -> str:
    from buffer_pubsub import fast_lane

    return fast_lane.service_name(f"native_lane/{run}", bytes.fromhex(run[:32]))


# ------------------------------------------------------------------------------ receiver
class Receiver:
    """The child: one receive loop per mechanism; latencies per mechanism at the end."""

    def __init__(self, run: str, fds: dict[str, int]) -> None:
        from buffer_pubsub import _ring, fast_lane

        self.fds = fds
        self.latencies: dict[str, list[int]] = {m: [] for m in MECHANISMS}
        self.cpu: dict[str, list[float]] = {m: [] for m in MECHANISMS}
        self._current: list[int] = []
        self.rings = {}
        for name in ("ring", "ring_busy"):
            reader = _ring.RingReader(fds[f"{name}_memfd"], fds[f"{name}_bell"], DEPTH,
                                      _ring.DEFAULT_SLOT)
            waker = _ring.Waker(None, BUSY_S if name == "ring_busy" else 0.0)
            waker.watch([(reader, self._on_frame, name)], [])
            self.rings[name] = (reader, waker)
        self.lane_reader = fast_lane.LaneReader(_lane_route(run), depth=DEPTH)
        self.lane_waker = fast_lane.LaneWaker()
        self.lane_waker.attach(self.lane_reader, self._on_frame)
        self.lane_waker.wait(0)
        self.iox2, config = _iox2(run)
        self.node = (self.iox2.NodeBuilder.new().config(config)
                     .create(self.iox2.ServiceType.Ipc))
        pubsub, event = _iox2_services(self.node, self.iox2, run)
        self.subscriber = pubsub.subscriber_builder().buffer_size(DEPTH).create()
        self.listener = event.listener_builder().create()
        self.wait = self.iox2.Duration.from_secs_f64(1.0)

    def _on_frame(self, frame: bytes) -> None:
        self._current.append(_latency_ns(frame))

    def _iox2_take(self) -> bool:
        sample = self.subscriber.receive()
        if sample is None:
            return False
        try:
            frame = ctypes.string_at(sample.payload_ptr, sample.header.number_of_elements)
        finally:
            sample.delete()
        self._current.append(_latency_ns(frame))
        return True

    def run(self, mechanism: str, count: int, ack: int) -> None:
        self._current = got = self.latencies[mechanism]
        target = len(got) + count
        cpu = time.process_time()
        wall = time.perf_counter()
        while len(got) < target:
            before = len(got)
            if mechanism in ("ring", "ring_busy"):
                self.rings[mechanism][1].wait(1.0)
            elif mechanism == "lane":
                self.lane_waker.wait(1.0)
            elif mechanism == "iceoryx2_listener":
                if not self._iox2_take():
                    self.listener.timed_wait(self.wait)
                    while self._iox2_take():
                        pass
            elif mechanism == "iceoryx2_busy":
                while not self._iox2_take():
                    pass
            elif mechanism == "eventfd":
                os.eventfd_read(self.fds["efd"])
                got.append(_latency_ns(os.read(self.fds["stamp_r"], 8)))
            else:
                got.append(_latency_ns(os.read(self.fds["pipe_r"], FRAME_BYTES)))
            if len(got) > before:
                os.write(ack, b"k")
        self.cpu[mechanism].append((time.process_time() - cpu) / (time.perf_counter() - wall))

    def close(self) -> None:
        self.lane_waker.close()
        self.lane_reader.close()
        self.listener.delete()
        self.subscriber.delete()
        self.node = None


def child(run: str, fds_json: str) -> None:
    fds = json.loads(fds_json)
    receiver = Receiver(run, fds)
    print("ready", flush=True)
    for line in sys.stdin:
        mechanism, _, count = line.strip().partition(" ")
        if mechanism == "done":
            break
        receiver.run(mechanism, int(count), fds["ack_w"])
    receiver.close()
    print("RESULT " + json.dumps({"latencies": receiver.latencies, "cpu": receiver.cpu}),
          flush=True)


# ------------------------------------------------------------------------------ sender
class Sender:
    def __init__(self, run: str) -> None:
        from buffer_pubsub import _ring

        self.run_id = run
        self.rings = {name: _ring.RingWriter(DEPTH) for name in ("ring", "ring_busy")}
        self.efd = os.eventfd(0, os.EFD_CLOEXEC)
        self.stamp_r, self.stamp_w = os.pipe()
        self.pipe_r, self.pipe_w = os.pipe()
        self.ack_r, self.ack_w = os.pipe()
        self.frame = bytearray(FRAME_BYTES)
        self.lane: Any = None
        self.publisher: Any = None
        self.notifier: Any = None
        self.node: Any = None

    def child_fds(self) -> dict[str, int]:
        fds = {"efd": self.efd, "stamp_r": self.stamp_r, "pipe_r": self.pipe_r,
               "ack_w": self.ack_w}
        for name, ring in self.rings.items():
            fds[f"{name}_memfd"] = ring.take_memfd()
            fds[f"{name}_bell"] = ring.doorbell
        return fds

    def connect(self) -> None:
        """The child made the lane reader and iceoryx2 services: open our ends."""
        from buffer_pubsub import fast_lane

        self.lane = fast_lane.LaneWriter(_lane_route(self.run_id))
        iox2, config = _iox2(self.run_id)
        self.node = iox2.NodeBuilder.new().config(config).create(iox2.ServiceType.Ipc)
        pubsub, event = _iox2_services(self.node, iox2, self.run_id)
        self.publisher = (pubsub.publisher_builder().initial_max_slice_len(FRAME_BYTES)
                          .max_loaned_samples(2).create())
        self.notifier = event.notifier_builder().create()

    def send(self, mechanism: str) -> None:
        frame = self.frame
        if mechanism in ("ring", "ring_busy"):
            _stamp(frame)
            self.rings[mechanism].write(frame)
        elif mechanism == "lane":
            _stamp(frame)
            self.lane.write(frame)
        elif mechanism.startswith("iceoryx2"):
            _stamp(frame)
            sample = self.publisher.loan_slice_uninit(FRAME_BYTES)
            ctypes.memmove(sample.payload_ptr, bytes(frame), FRAME_BYTES)
            sample.assume_init().send()
            if mechanism == "iceoryx2_listener":
                self.notifier.notify()
        elif mechanism == "eventfd":
            os.write(self.stamp_w, time.perf_counter_ns().to_bytes(8, "little"))
            os.eventfd_write(self.efd, 1)
        else:
            _stamp(frame)
            os.write(self.pipe_w, frame)
        os.read(self.ack_r, 1)

    def close(self) -> None:
        for ring in self.rings.values():
            ring.close()
        if self.lane is not None:
            self.lane.close()
        for port in (self.notifier, self.publisher):
            if port is not None:
                port.delete()
        self.node = None
        for fd in (self.efd, self.stamp_r, self.stamp_w, self.pipe_r, self.pipe_w, self.ack_r,
                   self.ack_w):
            os.close(fd)


def _remove_iceoryx2_files(run: str) -> None:
    """What iceoryx2 left of this run (a child that died leaves its node's files): its prefix
    names this run alone."""
    prefix = f"iox2nl_{run[:12]}_"
    for root in ("/dev/shm", "/tmp/iceoryx2"):
        for path, _dirs, files in os.walk(root):
            for name in files:
                if name.startswith(prefix):
                    try:
                        os.unlink(os.path.join(path, name))
                    except OSError:
                        pass


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def measure(count: int, rounds: int, mechanisms: tuple[str, ...] = MECHANISMS) -> dict[str, Any]:
    """Run every mechanism ``rounds`` times ``count`` frames; p50/p99 (us) and CPU per mechanism."""
    run = uuid.uuid4().hex
    sender = Sender(run)
    fds = sender.child_fds()
    proc = subprocess.Popen(_CHILD + [run, json.dumps(fds)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, pass_fds=list(fds.values()),
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    for name in ("ring_memfd", "ring_busy_memfd"):
        os.close(fds[name])
    try:
        assert proc.stdin is not None and proc.stdout is not None
        if proc.stdout.readline().strip() != "ready":
            raise RuntimeError("the receiving child did not start")
        sender.connect()
        warm = max(5, count // 10)
        for r in range(rounds + 1):  # round 0 warms every mechanism up, untimed
            order = mechanisms[r % len(mechanisms):] + mechanisms[:r % len(mechanisms)]
            for mechanism in order:
                n = warm if r == 0 else count
                proc.stdin.write(f"{mechanism} {n}\n")
                proc.stdin.flush()
                for _ in range(n):
                    sender.send(mechanism)
        proc.stdin.write("done 0\n")
        proc.stdin.flush()
        result = None
        for line in proc.stdout:
            if line.startswith("RESULT "):
                result = json.loads(line[7:])
        if proc.wait(30) != 0 or result is None:
            raise RuntimeError("the receiving child failed")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sender.close()
        _remove_iceoryx2_files(run)
    out: dict[str, Any] = {}
    for mechanism in mechanisms:
        values = [v / 1000 for v in result["latencies"][mechanism]]
        warm = max(5, count // 10)
        values = values[warm:]
        out[mechanism] = {"p50_us": _percentile(values, 0.5), "p99_us": _percentile(values, 0.99),
                          "n": len(values),
                          "cpu_per_wall": statistics.median(result["cpu"][mechanism][1:])}
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=300, help="frames per mechanism per round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(*args.child)
        return
    results = measure(args.count, args.rounds)
    floor = results["eventfd"]["p50_us"]
    iox = results["iceoryx2_listener"]["p50_us"]
    print(f"one-way, {FRAME_BYTES} B frame, one in flight, {args.rounds} rounds x {args.count}")
    print(f"{'mechanism':20} {'p50 us':>8} {'p99 us':>8} {'/eventfd':>9} {'/iox2 lst':>9} "
          f"{'CPU/wall':>9}")
    for mechanism, figures in results.items():
        print(f"{mechanism:20} {figures['p50_us']:8.1f} {figures['p99_us']:8.1f} "
              f"{figures['p50_us'] / floor:9.2f} {figures['p50_us'] / iox:9.2f} "
              f"{figures['cpu_per_wall']:9.2f}")


if __name__ == "__main__":
    main()
