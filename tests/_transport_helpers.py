"""Child programs for the transport fault tests (tests/test_pubsub_transport.py).

Run as ``python -m tests._transport_helpers <role> ...`` from the repository root; same stdout
protocol as :mod:`tests._pubsub_helpers` (``READY``, then ``RESULT <json>``).

- ``foreign``: a raw Zenoh peer that is no buffer_pubsub node, publishing frames on our keys the
  way another ROS 2 implementation might: ``base`` (a plain 13-segment publisher token, samples
  whose attachment carries random gids, plus two with no valid attachment), ``seq`` (spoofed
  sequence numbers), ``buffer`` (samples on a subscription's own ``_buf/<gid>`` channel from a
  publisher whose token never comes, then from one whose token comes late), ``restart`` (a
  publisher with a token sends 1..20, its token leaves and comes back, and it numbers again
  from 1, as a restarted rmw_zenoh publisher with the same gid does).
- ``flood``: a keep-last publisher writing 512 KiB frames in a loop inside ``with Node(...)``
  until Ctrl-C (SIGINT); reports how long ``Node.__exit__`` took on stderr.
- ``big``: a CPU subscription that reports size and CRC-32 of each (large) frame.
- ``churn``: creates and destroys a buffer-accepting subscription ``--count`` times.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
import zlib

from tests._pubsub_helpers import TENSOR, _emit, _stdin_stop, make_frame, use_fake_backend


def _wait_for_subscription(session, domain: int, topic: str, timeout: float = 15.0) -> str:
    """Poll the liveliness graph until a subscription on ``topic`` shows up; its key."""
    from buffer_pubsub import wire

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for reply in session.liveliness().get(wire.liveliness_domain_selector(domain),
                                              timeout=1.0):
            try:
                token = wire.parse_token(str(reply.ok.key_expr))
            except Exception:
                continue
            if isinstance(token, wire.EndpointToken) and not token.is_publisher \
                    and token.topic == topic:
                return token.key()
        time.sleep(0.05)
    raise TimeoutError(f"no subscription on {topic}")


def _plain_token(domain: int, zid: str, topic: str, entity_id: int, aware: bool = False):
    """A foreign publisher's token: plain (13 segments), or buffer-aware as rmw_zenoh's
    (advertising cpu)."""
    from buffer_pubsub import wire
    from rosidl_buffer.messages import get_type_hash

    return wire.EndpointToken(
        domain_id=domain, zid=zid, node_id=0, entity_id=entity_id, kind=wire.PUBLISHER_KIND,
        namespace="", node_name="foreign", topic=topic, type_name=TENSOR,
        type_hash=get_type_hash(TENSOR), qos=wire.QoSProfile.of(10),
        backends={"cpu": ""} if aware else None)


def run_foreign(args: argparse.Namespace) -> int:
    import zenoh

    from buffer_pubsub import make_config, wire
    from rosidl_buffer.messages import serialize_message

    session = zenoh.open(make_config())
    try:
        sub_key = _wait_for_subscription(session, args.domain, args.topic)
        base = wire.data_key(args.domain, args.topic, TENSOR)
        zid = str(session.zid())

        def frame(index: int) -> bytes:
            return bytes(serialize_message(make_frame(9, index, 64, "cpu")))

        def attach(sequence: int, gid: bytes) -> bytes:
            return wire.Attachment(sequence, time.time_ns(), gid).encode()

        tokens = []
        if args.mode == "base":
            # A plain publisher token (stock layout); its samples carry gids of its own making.
            tokens.append(session.liveliness().declare_token(
                _plain_token(args.domain, zid, args.topic, 1).key()))
            time.sleep(0.3)
            for index in range(args.count):
                session.put(base, frame(index), attachment=attach(1, os.urandom(16)))
            session.put(base, frame(100))  # no attachment
            session.put(base, frame(101), attachment=b"\x01" * 20)  # malformed attachment
        elif args.mode == "seq":
            gid = os.urandom(16)
            for index, sequence in enumerate([1, 2, 2**62, 2**62 + 1, 3, 5]):
                session.put(base, frame(index), attachment=attach(sequence, gid))
                time.sleep(0.01)
        elif args.mode == "buffer":
            sub_gid = wire.parse_token(sub_key).gid
            channel = wire.buffer_channel_key(base, sub_gid)
            never = os.urandom(16)
            for index in range(2):  # from a publisher whose token never comes
                session.put(channel, frame(index), attachment=attach(index + 1, never))
            late = _plain_token(args.domain, zid, args.topic, 2, aware=True)
            for index in range(3):  # from a publisher whose token comes 0.4 s later
                session.put(channel, frame(10 + index), attachment=attach(index + 1, late.gid))
            time.sleep(0.4)
            tokens.append(session.liveliness().declare_token(late.key()))
        elif args.mode == "restart":
            publisher = _plain_token(args.domain, zid, args.topic, 3)
            token = session.liveliness().declare_token(publisher.key())
            time.sleep(0.3)
            for index in range(20):
                session.put(base, frame(index), attachment=attach(index + 1, publisher.gid))
                time.sleep(0.005)
            token.undeclare()
            time.sleep(0.3)
            tokens.append(session.liveliness().declare_token(publisher.key()))
            time.sleep(0.3)
            for index in range(10):
                session.put(base, frame(100 + index), attachment=attach(index + 1, publisher.gid))
                time.sleep(0.005)
        _emit("READY")
        _stdin_stop(args.timeout).wait()
        for token in tokens:
            token.undeclare()
    finally:
        session.close()
    _emit("RESULT " + json.dumps({"ok": True}))
    return 0


def run_flood(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node

    # Started from a background job (nohup, &, a CI runner) this process inherits an ignored
    # SIGINT, and Python then installs no KeyboardInterrupt handler: restore it, since the test
    # ends this flood with SIGINT.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    started = None
    try:
        with Node(f"flood_{os.getpid()}", domain_id=args.domain) as node:
            pub = node.create_publisher(TENSOR, args.topic, depth=10)
            pub.wait_for_subscriptions(1, timeout=args.timeout)
            frame = make_frame(0, 0, 512 * 1024, "cpu")
            _emit("READY")
            try:
                while True:
                    pub.publish(frame)
                    time.sleep(0.002)
            except KeyboardInterrupt:
                started = time.monotonic()
                raise
    finally:
        if started is not None:
            sys.stderr.write(f"EXIT_S {time.monotonic() - started:.3f}\n")
            sys.stderr.flush()


def run_big(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node

    records = []
    with Node(f"big_{os.getpid()}", domain_id=args.domain) as node:
        def on_msg(msg) -> None:
            data = msg.data.to_numpy()
            records.append({"size": int(data.shape[0]), "crc": zlib.crc32(data)})

        sub = node.create_subscription(TENSOR, args.topic, on_msg, depth=2)
        sub.wait_for_publishers(1, timeout=args.timeout)
        _emit("READY")
        _stdin_stop(args.timeout).wait()
        deadline = time.monotonic() + args.timeout
        while len(records) < args.count and time.monotonic() < deadline:
            time.sleep(0.05)
        counters = vars(sub.counters).copy()
    _emit("RESULT " + json.dumps({"records": records, "counters": counters}))
    return 0


def run_churn(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node

    matched = 0
    with Node(f"churn_{os.getpid()}", domain_id=args.domain) as node:
        _emit("READY")
        for _ in range(args.count):
            sub = node.create_subscription(TENSOR, args.topic, lambda m: None,
                                           acceptable_buffer_backends=args.accept)
            matched += bool(sub.wait_for_publishers(1, timeout=5))
            time.sleep(0.05)  # let the publisher see us before we go
            sub.destroy()
    _emit("RESULT " + json.dumps({"matched": matched}))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tests._transport_helpers")
    parser.add_argument("role", choices=["foreign", "flood", "big", "churn"])
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--mode", default="base")
    parser.add_argument("--accept", default="fake")
    parser.add_argument("--count", type=int, default=5)
    parser.add_argument("--timeout", type=float, default=30.0)
    args = parser.parse_args(argv)
    use_fake_backend()
    roles = {"foreign": run_foreign, "flood": run_flood, "big": run_big, "churn": run_churn}
    return roles[args.role](args)


if __name__ == "__main__":
    sys.exit(main())
