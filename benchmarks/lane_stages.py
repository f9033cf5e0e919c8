"""Where a message's time goes on the transport's real path, stage by stage, between two processes.

``python -m benchmarks.lane_stages [--count N] [--nbytes N] [--route lane|cpu]``: a publisher
(this process) and a subscriber (a child), both real ``buffer_pubsub`` nodes on one host (a
loopback Zenoh port and a domain of their own), one message in flight.

- ``--route lane`` (default): a loaned warp tensor (``loan_tensor_msg``), whose descriptor the
  publisher writes to the subscriber's fast lane (a ring, an eventfd doorbell); the subscriber's
  node runs ``executor="manual"`` and spins in its main thread, woken by the doorbell, and the
  callback takes ``from_input_tensor_msg(msg, clone=False)``.
- ``--route cpu``: a prepared CPU tensor message (stamped in place, as the bench's
  ``cpu_fallback`` path) over Zenoh to a CPU subscriber on the node's default executor thread.

Stage boundaries are stamped with ``perf_counter_ns`` (one clock for every process of a host)
by thin wrappers the benchmark puts, in its own processes only, around the functions the
transport calls: ``LaneWriter.write`` (publisher), ``Subscription._on_lane`` /
``Subscription._on_sample`` (where a frame or a Zenoh sample enters the subscription) and
``buffer_pubsub.subscription.deserialize_message`` (the CDR read, descriptor import included);
the user callback stamps its entry and the moment the view is usable. Each wrapper costs ~1 us.
For the lane, a bare 602-byte frame on a lane reader of the child's own, attached to the same
waker, is interleaved with the messages: what the lane alone costs in the same run.

``--warm`` runs it all again warm (the publisher spins, the subscriber's waker busy-polls:
nobody sleeps) and prints each stage's two medians side by side: what a stage costs after an
idle wake-up (caches and branch predictors cold, a core woken from idle) against its own work.

After the timed messages, ``--frames N`` more (default 10) are sent with the Python frames they
run counted (:class:`benchmarks.frames.FrameCounter`, ``sys.setprofile``): on the publisher from
the loan to the end of ``publish()``, on the subscriber from the frame's arrival in the
subscription to the usable view; the benchmark's own wrappers are not counted. Then
``--syscalls N`` more (default 20 when ``strace`` is installed) with the system calls of each
side's message thread counted (:mod:`benchmarks.native_syscalls`; the control pipe's left out).
The first line prints the medians and the counts; the calls by name go to stderr.
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
STAMP = struct.Struct("<qq")  # (message index, t0) in the first 16 bytes of the tensor
BARE_BYTES = 602  # a bare frame: the size of a descriptor message, nothing imported
# COUNTED: a message whose Python frames were counted; TRACED: one whose system calls were (slow,
# not timed); SYSCALLS: the system calls of the traced ones; BARE_IDLE: a bare frame written
# after the publisher ran as long as it did before a message's write (see publisher)
BARE, FULL, COUNTED, SYSCALLS, TRACED, BARE_IDLE = 0, 1, 2, 3, 4, 5
# Stamps of one message, in order (publisher ones first, then the subscriber's).
PUB_STAMPS = ("t0", "loaned", "write_in", "write_out", "published")
SUB_STAMPS = ("entered", "deser_in", "deser_out", "callback", "viewed")
STAGES = {
    "lane": (
        ("publisher: loan + output view + stamp", "t0", "loaned"),
        ("publisher: publish up to the lane write (descriptor + CDR)", "loaned", "write_in"),
        ("publisher: lane write + notify", "write_in", "write_out"),
        ("subscriber: write returned -> frame enters the subscription (wake-up)", "write_out",
         "entered"),
        ("subscriber: frame checks (attachment, publisher)", "entered", "deser_in"),
        ("subscriber: deserialize + descriptor import", "deser_in", "deser_out"),
        ("subscriber: queue -> user callback", "deser_out", "callback"),
        ("subscriber: from_input_tensor_msg (NumPy view)", "callback", "viewed"),
        ("subscriber total (write returned -> view)", "write_out", "viewed"),
        ("one-way total (loan -> readable view)", "t0", "viewed"),
    ),
    "cpu": (
        ("publisher: publish() (validate, CDR, Zenoh put)", "loaned", "published"),
        ("wire: publish returned -> sample enters the subscription", "published", "entered"),
        ("subscriber: sample enters -> deserialize (checks, queue, hand-off)", "entered",
         "deser_in"),
        ("subscriber: deserialize", "deser_in", "deser_out"),
        ("subscriber: deserialized -> user callback", "deser_out", "callback"),
        ("subscriber: from_input_tensor_msg (NumPy view)", "callback", "viewed"),
        ("subscriber total (sample enters -> view)", "entered", "viewed"),
        ("one-way total (publish -> readable view)", "loaned", "viewed"),
    ),
}


def _settings(run: str, port: int, domain: int) -> Any:
    from benchmarks.paths import PathSettings

    return PathSettings(name="lane_stages", run_id=run, max_nbytes=0, port=port,
                        domain_id=domain)


def _node(role: str, run: str, port: int, domain: int, **options: Any) -> Any:
    import buffer_pubsub
    from benchmarks.paths.zenoh_common import our_node_config

    settings = _settings(run, port, domain)
    return buffer_pubsub.Node(f"lane_stages_{role}_{run[:8]}", domain_id=domain,
                              config=our_node_config(settings, role == "sub"),
                              **options)


def _topic(run: str) -> str:
    return f"/lane_stages_{run[:12]}"


def _bare_route(run: str) -> str:
    from buffer_pubsub import fast_lane

    return fast_lane.service_name(f"lane_stages/{run}", bytes.fromhex(run[:32]))


def subscriber(run: str, port: int, domain: int, route: str, busy_poll_s: float,
               ctrl: Connection) -> None:
    """Subscribe (stamping the stages), send every message's stamps back on ``ctrl``."""
    import tensor_conversions.numpy as tc
    from rosidl_buffer.messages import get_message_type

    import buffer_pubsub.subscription as subscription
    from buffer_pubsub import fast_lane

    from benchmarks.frames import FrameCounter

    stamps: dict[str, int] = {}
    clock = time.perf_counter_ns
    deserialize = subscription.deserialize_message
    counter = FrameCounter(exclude={__file__})
    # counting: frames are counted per message; inside: a lane frame is being delivered, the
    # record of its callback waits in pending until the delivery returned (and counting stopped)
    state: dict[str, Any] = {"counting": False, "inside": False, "pending": None}

    def stamped_deserialize(*args: Any, **kwargs: Any) -> Any:
        stamps["deser_in"] = clock()
        try:
            return deserialize(*args, **kwargs)
        finally:
            stamps["deser_out"] = clock()

    def entry(original: Any) -> Any:
        def stamped(self: Any, *args: Any) -> Any:
            stamps.setdefault("entered", clock())
            if not state["counting"]:
                return original(self, *args)
            state["inside"] = True
            counter.start()
            try:
                return original(self, *args)
            finally:
                frames = counter.stop()
                state["inside"] = False
                pending, state["pending"] = state["pending"], None
                if pending is not None:
                    pending[3]["frames"] = frames
                    pending[3]["detail"] = counter.by_function
                    ctrl.send(pending)
        return stamped

    subscription.deserialize_message = stamped_deserialize
    subscription.Subscription._on_lane = entry(subscription.Subscription._on_lane)
    subscription.Subscription._on_sample = entry(subscription.Subscription._on_sample)

    def on_message(msg: Any) -> None:
        stamps["callback"] = clock()
        view = tc.from_input_tensor_msg(msg, clone=False)
        index, t0 = STAMP.unpack_from(view)  # the payload is readable here
        stamps["viewed"] = clock()
        del view
        record = dict(stamps)
        stamps.clear()
        if state["inside"]:
            state["pending"] = (FULL, index, t0, record)  # sent once the delivery returned
        else:
            ctrl.send((FULL, index, t0, record))

    def on_bare(data: bytes) -> None:
        now = clock()
        index, t0 = STAMP.unpack_from(data)
        ctrl.send((BARE, index, t0, {"viewed": now}))

    lane = route == "lane"
    options: dict[str, Any] = {"executor": "manual" if lane else "thread"}
    if busy_poll_s > 0:
        options["waker"] = waker = fast_lane.LaneWaker(busy_poll_s=busy_poll_s)
    with _node("sub", run, port, domain, **options) as node:
        node.create_subscription(get_message_type(TENSOR_TYPE), _topic(run), on_message,
                                 depth=16, acceptable_buffer_backends="warp" if lane else "cpu")
        bare = None
        if lane:
            if node.lane is None:
                ctrl.send(("unavailable", fast_lane.status().reason))
                return
            bare = fast_lane.LaneReader(_bare_route(run), depth=16)
            node.lane.attach(bare, on_bare)  # the same waker as the subscription's lane
        ctrl.send(("ready", os.getpid()))
        try:
            while True:
                if ctrl.poll():
                    command = ctrl.recv()
                    if command not in ("count", "uncount"):
                        break
                    state["counting"] = command == "count"
                    ctrl.send(("counting" if command == "count" else "uncounting", 0, 0, {}))
                if lane:
                    node.spin_once(0.05)
                else:
                    time.sleep(0.05)
        finally:
            if bare is not None:
                node.lane.detach(bare, close=True)
                node.spin_once(0.0)  # the waker applies the detach (and closes the reader)
    if busy_poll_s > 0:
        waker.close()  # a waker given to the node stays ours to close


def publisher(count: int, nbytes: int, route: str, busy_poll_s: float = 0.0,
              spin: bool = False, frames: int = 0, syscalls: int = 0
              ) -> list[tuple[int, dict[str, Any]]]:
    """Publish ``count`` messages one at a time; every message's stamps, by kind. ``spin``:
    wait for each message's stamps by polling (this process never sleeps, so its stages run
    warm). ``frames``: that many more messages follow with their Python frames counted (kind
    ``COUNTED``: ``pub_frames`` and ``frames``, the subscriber's, in the record). ``syscalls``:
    then that many more with the system calls of both sides' message threads counted (one
    record of kind ``SYSCALLS``: per side, calls by name, and the messages)."""
    import numpy as np
    import tensor_conversions.numpy as tc
    from rosidl_buffer.messages import get_message_type

    from benchmarks.frames import FrameCounter
    from benchmarks.processes import free_tcp_port
    from buffer_pubsub import fast_lane

    run = os.urandom(16).hex()
    port = free_tcp_port()
    domain = 100 + int(run[:4], 16) % 100
    parent, child = _pipe()
    child_fd = child.fileno()
    process = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.lane_stages", "--role", "sub", "--run", run,
         "--port", str(port), "--domain", str(domain), "--route", route,
         "--busy-poll", str(busy_poll_s),
         "--fd", str(child.fileno())],
        pass_fds=(child.fileno(),), cwd=os.path.dirname(os.path.dirname(__file__)))
    child.close()
    clock = time.perf_counter_ns
    stamps: dict[str, int] = {}
    write = fast_lane.LaneWriter.write

    def stamped_write(self: Any, *parts: Any) -> bool:
        stamps["write_in"] = clock()
        try:
            return write(self, *parts)
        finally:
            stamps["write_out"] = clock()

    records: list[tuple[int, dict[str, int]]] = []
    try:
        ready, detail = parent.recv()
        if ready != "ready":
            raise RuntimeError(f"the subscriber cannot run the lane: {detail}")
        with _node("pub", run, port, domain) as node:
            publisher = node.create_publisher(get_message_type(TENSOR_TYPE), _topic(run), depth=16)
            if not publisher.wait_for_subscriptions(1, timeout=20.0):
                raise RuntimeError("the subscriber was not matched within 20 s")
            fast_lane.LaneWriter.write = stamped_write  # type: ignore[method-assign]
            bare = fast_lane.LaneWriter(_bare_route(run)) if route == "lane" else None
            frame = bytearray(BARE_BYTES)
            prepared = tc.allocate_tensor_msg((nbytes,), np.uint8) if route == "cpu" else None
            head = tc.from_output_tensor_msg(prepared) if prepared is not None else None
            counter = FrameCounter(exclude={__file__})
            traces: list[Any] = []
            for index in range(count + frames + syscalls):
                counting = count <= index < count + frames
                if index == count and frames:  # the subscriber counts from now on
                    parent.send("count")
                    if parent.recv()[0] != "counting":
                        raise RuntimeError("the subscriber did not start counting frames")
                if index == count + frames and syscalls:
                    if frames:
                        parent.send("uncount")
                        if parent.recv()[0] != "uncounting":
                            raise RuntimeError("the subscriber did not stop counting frames")
                    traces = _trace_both(process.pid, parent.fileno(), child_fd)
                if counting:
                    counter.start()
                stamps.clear()
                t0 = clock()
                if prepared is not None:
                    STAMP.pack_into(head, 0, index, t0)
                    stamps["loaned"] = clock()
                    publisher.publish(prepared)
                else:
                    with tc.loan_tensor_msg(publisher, (nbytes,), np.uint8,
                                            backend="warp") as msg:
                        array = tc.from_output_tensor_msg(msg)
                        STAMP.pack_into(array, 0, index, t0)
                        del array
                        stamps["loaned"] = clock()
                stamps["published"] = clock()
                mine: dict[str, Any] = dict(stamps)
                if counting:
                    mine["pub_frames"] = counter.stop()
                    mine["pub_detail"] = counter.by_function
                mine["t0"] = t0
                while spin and not parent.poll(0):
                    pass
                kind, got, _, theirs = parent.recv()
                if kind != FULL or got != index:
                    raise RuntimeError(f"expected message {index}, got {kind, got}")
                kind = COUNTED if counting else FULL if index < count else TRACED
                records.append((kind, {**mine, **theirs}))
                if bare is not None and index < count:  # the lane alone, interleaved
                    now = clock()
                    STAMP.pack_into(frame, 0, index, now)
                    write(bare, frame)
                    while spin and not parent.poll(0):
                        pass
                    _, _, sent, theirs = parent.recv()
                    records.append((BARE, {"t0": sent, **theirs}))
                    # Again, after running (spinning) as long as this message's loan and
                    # publish ran before its write: the subscriber idled as long, so its
                    # wake-up is the same, with none of our per-message work after it.
                    until = clock() + (mine["write_out"] - t0)
                    while clock() < until:
                        pass
                    now = clock()
                    STAMP.pack_into(frame, 0, index, now)
                    write(bare, frame)
                    written = clock()  # the write's own cost, the floor of "lane write + notify"
                    _, _, sent, theirs = parent.recv()
                    records.append((BARE_IDLE, {"t0": sent, "write_in": now,
                                                "write_out": written, **theirs}))
            if traces:  # ours first: stopping the other's runs on this thread
                mine_calls = traces[0].stop()
                theirs_calls = traces[1].stop()
                records.append((SYSCALLS, {"publisher": dict(mine_calls),
                                           "subscriber": dict(theirs_calls),
                                           "messages": syscalls}))
            if bare is not None:
                bare.close()
        parent.send("stop")
        process.wait(timeout=20)
    finally:
        fast_lane.LaneWriter.write = write  # type: ignore[method-assign]
        if process.poll() is None:
            process.kill()
            process.wait()
    return records


def _trace_both(child_pid: int, *plumbing: int) -> list[Any]:
    """System-call traces of this process's main thread and the subscriber's (each side's
    message thread), the control pipe's calls left out; started (attached) on return."""
    from benchmarks.native_syscalls import SyscallTrace

    traces = [SyscallTrace(os.getpid(), set(plumbing)), SyscallTrace(child_pid, set(plumbing))]
    traces[1].start()
    traces[0].start()  # ours last: starting the other's runs on this thread
    return traces


def _pipe() -> tuple[Connection, Connection]:
    import multiprocessing

    return multiprocessing.Pipe(duplex=True)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def _span(record: dict[str, int], start: str, end: str) -> float | None:
    if start not in record or end not in record:
        return None
    return (record[end] - record[start]) / 1000


def stage_figures(records: list[tuple[int, dict[str, int]]], route: str
                  ) -> list[tuple[str, float, float]]:
    """``(stage, p50 us, p99 us)`` rows from the stamps."""
    full = [r for kind, r in records if kind == FULL]
    rows = []
    for name, start, end in STAGES[route]:
        values = [v for r in full if (v := _span(r, start, end)) is not None]
        if values:
            rows.append((name, _percentile(values, 0.5), _percentile(values, 0.99)))
    for kind, name in ((BARE, "interleaved"),
                       (BARE_IDLE, "after a message's lead time (the idle wake-up)")):
        bare = [(r["viewed"] - r["t0"]) / 1000 for k, r in records if k == kind]
        if bare:
            rows.append((f"lane alone, {BARE_BYTES} B frame, {name} (write -> callback)",
                         _percentile(bare, 0.5), _percentile(bare, 0.99)))
    idle_writes = [(r["write_out"] - r["write_in"]) / 1000 for k, r in records
                   if k == BARE_IDLE and "write_out" in r]
    if idle_writes:  # the same call as the publisher's lane write, with no message around it
        rows.append((f"lane alone, {BARE_BYTES} B frame, after a message's lead time: "
                     "write + notify", _percentile(idle_writes, 0.5),
                     _percentile(idle_writes, 0.99)))
    return rows


def frame_counts(records: list[tuple[int, dict[str, Any]]]) -> tuple[int, int] | None:
    """The median Python frames per message ``(publisher, subscriber)`` of the counted
    messages, or None when none was counted."""
    counted = [r for kind, r in records if kind == COUNTED and "frames" in r]
    if not counted:
        return None
    return (int(_percentile([r["pub_frames"] for r in counted], 0.5)),
            int(_percentile([r["frames"] for r in counted], 0.5)))


def frame_detail(records: list[tuple[int, dict[str, Any]]]) -> str:
    """Where the frames of the last counted message went, per side and function."""
    counted = [r for kind, r in records if kind == COUNTED and "frames" in r]
    if not counted:
        return ""
    lines = []
    for side, key in (("publisher", "pub_detail"), ("subscriber", "detail")):
        lines.append(f"{side}:")
        detail = counted[-1][key]
        for name, n in sorted(detail.items(), key=lambda item: (-item[1], item[0])):
            lines.append(f"  {n:4d}  {name}")
    return "\n".join(lines)


def syscall_counts(records: list[tuple[int, dict[str, Any]]]) -> tuple[str, str]:
    """System calls per message of each side's message thread: ``publisher N, subscriber M``
    and the same by name, or two empty strings when they were not counted."""
    traced = [r for kind, r in records if kind == SYSCALLS]
    if not traced:
        return "", ""
    record = traced[-1]
    messages = record["messages"]
    totals, named = [], []
    for side in ("publisher", "subscriber"):
        calls = record[side]
        totals.append(f"{side} {sum(calls.values()) / messages:.1f}")
        named.append(f"{side}: " + ", ".join(
            f"{name} {n / messages:.1f}" for name, n in sorted(calls.items(),
                                                                key=lambda i: -i[1])))
    return ", ".join(totals), "; ".join(named)


def table(rows: list[tuple[str, float, float]]) -> str:
    """The rows as a text table."""
    width = max(len(r[0]) for r in rows)
    lines = [f"{'stage':<{width}}  {'p50 us':>8}  {'p99 us':>8}"]
    lines += [f"{name:<{width}}  {p50:8.1f}  {p99:8.1f}" for name, p50, p99 in rows]
    return "\n".join(lines)


#: ``--warm``: the subscriber's waker spins this long before it blocks (the publisher spins too).
WARM_BUSY_POLL_S = 0.05


def _records_per_message(route: str) -> int:
    """Timed records per message: the lane's adds its two bare frames."""
    return 3 if route == "lane" else 1


def _after_warm_up(records: list[tuple[int, dict[str, Any]]], args: argparse.Namespace
                   ) -> list[tuple[int, dict[str, Any]]]:
    """The timed records past the first ones (first imports map files, warm caches)."""
    timed = [r for r in records if r[0] in (BARE, BARE_IDLE, FULL)]
    return timed[_records_per_message(args.route) * min(20, args.count // 10):]


def side_by_side(idle: list[tuple[str, float, float]], hot: list[tuple[str, float, float]]
                 ) -> str:
    """The p50 of each stage after an idle wake-up (the default run) beside the same stage warm
    (nobody sleeps), and their ratio."""
    warm = {name: p50 for name, p50, _ in hot}
    width = max(len(r[0]) for r in idle)
    lines = [f"{'stage':<{width}}  {'idle p50':>9}  {'warm p50':>9}  {'ratio':>6}"]
    for name, p50, _ in idle:
        other = warm.get(name)
        ratio = (f"{p50 / other:5.1f}x" if other is not None and other > 0.5 and p50 > 0
                 else "     -")
        shown = f"{other:9.1f}" if other is not None else f"{'-':>9}"
        lines.append(f"{name:<{width}}  {p50:9.1f}  {shown}  {ratio}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the publisher (default) or the subscriber role."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.lane_stages",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=300)
    parser.add_argument("--nbytes", type=int, default=4096)
    parser.add_argument("--route", choices=("lane", "cpu"), default="lane")
    parser.add_argument("--busy-poll", type=float, default=0.0, metavar="S",
                        help="the subscriber's lane waker spins S seconds before it blocks "
                             "(a core at 100%% meanwhile): the stages without the idle wake-up")
    parser.add_argument("--spin", action="store_true",
                        help="the publisher polls for each message's stamps instead of "
                             "sleeping (with --busy-poll: every stage warm, no wake-up)")
    parser.add_argument("--frames", type=int, default=10, metavar="N",
                        help="count the Python frames of N more messages after the timed ones "
                             "(0: none)")
    parser.add_argument("--syscalls", type=int, default=-1, metavar="N",
                        help="count the system calls of N more messages (strace on each side's "
                             "message thread; default 20 when strace is installed, 0: none)")
    parser.add_argument("--warm", action="store_true",
                        help="also run every stage warm (--spin, --busy-poll 0.05: no idle "
                             "wake-up on either side) and print both medians side by side: what "
                             "each stage costs after an idle wake-up against its own work")
    parser.add_argument("--frame-detail", action="store_true",
                        help="print where the counted frames go, per function (to stderr)")
    parser.add_argument("--role", choices=("pub", "sub"), default="pub")
    parser.add_argument("--run")
    parser.add_argument("--port", type=int)
    parser.add_argument("--domain", type=int)
    parser.add_argument("--fd", type=int)
    args = parser.parse_args(argv)
    if args.role == "sub":
        subscriber(args.run, args.port, args.domain, args.route, args.busy_poll,
                   Connection(args.fd))
        return 0
    syscalls = args.syscalls
    if syscalls < 0:
        from benchmarks.native_syscalls import available

        syscalls = 20 if available() else 0
    records = publisher(args.count, args.nbytes, args.route, args.busy_poll, args.spin,
                        max(0, args.frames), syscalls)
    warm = _after_warm_up(records, args)
    per = _records_per_message(args.route)
    what = ("loaned warp tensor over the fast lane" if args.route == "lane"
            else "prepared CPU tensor over Zenoh")
    frames = frame_counts(records)
    counted = "" if frames is None else (
        f"; Python frames per message: publisher {frames[0]}, subscriber {frames[1]}, "
        f"total {sum(frames)}")
    calls, by_name = syscall_counts(records)
    if calls:
        counted += f"; system calls per message: {calls}"
    print(f"{what}, {args.nbytes} B, {len(warm) // per} messages (one in flight){counted}:")
    rows = stage_figures(warm, args.route)
    if args.warm:
        hot = publisher(args.count, args.nbytes, args.route, WARM_BUSY_POLL_S, True)
        print(side_by_side(rows, stage_figures(_after_warm_up(hot, args), args.route)))
    else:
        print(table(rows))
    if by_name:
        print(f"system calls per message, by name: {by_name}", file=sys.stderr)
    if args.frame_detail:
        print(frame_detail(records), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
