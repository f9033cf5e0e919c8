"""The transport's lane pieces: route decision, frame, descriptor budget."""

from __future__ import annotations

import dataclasses
import os
import time

import pytest

from buffer_pubsub import _lane_routes, wire
from rosidl_buffer import local_host_id

HERE = wire.Locality(local_host_id(), os.getpid(), os.getuid())


def token(locality: wire.Locality | None) -> wire.EndpointToken:
    return wire.EndpointToken(
        domain_id=0, zid="0" * 32, node_id=1, entity_id=2, kind=wire.SUBSCRIPTION_KIND,
        namespace="", node_name="n", topic="/t", type_name="std_msgs/msg/String",
        type_hash="RIHS01_00", qos=wire.QoSProfile.of(10), locality=locality,
        backends={"warp": ""})


def test_serves_only_same_host_user_other_process_keep_last_served_individual() -> None:
    other = dataclasses.replace(HERE, process_id=HERE.process_id + 1)
    assert _lane_routes.serves(HERE, token(other), individual=True, served=True)
    refused = [
        (token(HERE), {}),  # this process: intra-process route
        (token(dataclasses.replace(other, host_id="elsewhere")), {}),
        (token(dataclasses.replace(other, user_id=HERE.user_id + 1)), {}),
        (token(None), {}),  # not ours (no locality): it has no lane
        (token(other), {"individual": False}),
        (token(other), {"served": False}),
        (token(other), {"keep_all": True}),
    ]
    for peer, change in refused:
        flags = {"individual": True, "served": True, **change}
        assert not _lane_routes.serves(HERE, peer, **flags), (peer.locality, change)


def test_split_frame_round_trip_and_malformed() -> None:
    attachment = wire.Attachment(7, 123, bytes(range(16)))
    head, payload = wire.split_frame(attachment.encode() + b"cdr")
    assert head == attachment and bytes(payload) == b"cdr"
    with pytest.raises(wire.WireFormatError):
        wire.split_frame(b"short")


def test_open_writer_without_reader_is_none_and_with_one_delivers() -> None:
    gid = os.urandom(16)
    assert _lane_routes.open_writer("0/routes/T/H", gid) is None
    reader = _lane_routes.open_reader("0/routes/T/H", gid, depth=4)
    writer = _lane_routes.open_writer("0/routes/T/H", gid)
    try:
        attachment = wire.Attachment(1, 2, gid).encode()
        assert writer.write(attachment, b"payload")
        head, payload = wire.split_frame(reader.take())
        assert head.sequence_number == 1 and bytes(payload) == b"payload"
    finally:
        writer.close()
        reader.close()


def test_no_lane_end_opens_when_file_descriptors_run_short(monkeypatch) -> None:
    """The lane is an optimization: short of descriptors, its ends are not opened (Zenoh
    carries those routes) and the descriptors left go to what needs them (imports)."""
    assert _lane_routes.fd_headroom() is None or _lane_routes.fd_headroom() > 0
    monkeypatch.setattr(_lane_routes, "fd_headroom",
                        lambda: _lane_routes.LANE_FDS + _lane_routes.FD_RESERVE - 1)
    gid = os.urandom(16)
    assert _lane_routes.open_reader(f"routes_test/{gid.hex()}", gid, depth=4) is None
    assert _lane_routes.open_writer(f"routes_test/{gid.hex()}", gid) is None


def _ready_child(script: str, domain: int, topic: str):
    """``python -c script domain topic`` once it printed READY (the caller reaps it)."""
    import subprocess
    import sys

    from tests._pubsub_helpers import ROOT, child_env

    child = subprocess.Popen([sys.executable, "-c", script, str(domain), topic], cwd=ROOT,
                             env=child_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)
    try:
        assert child.stdout.readline().startswith("READY")
    except BaseException:
        child.kill()
        child.wait()
        raise
    return child


_IDLE_SUBSCRIPTIONS_CHILD = r"""
import json, os, resource, sys
resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))
from buffer_pubsub import Node
domain, topic = int(sys.argv[1]), sys.argv[2]
tensor = "tensor_msgs/msg/ExperimentalTensor"
got = []
with Node("idle_subscriptions", domain_id=domain) as node:
    # each holds a lane reader: together they must leave room for the imports
    idle = [node.create_subscription(tensor, f"{topic}/idle{i}", lambda m: None, depth=4,
                                     acceptable_buffer_backends="warp") for i in range(40)]
    live = node.create_subscription(tensor, topic, lambda m: got.append(m.data.get_backend_type()),
                                    depth=10, acceptable_buffer_backends="warp")
    print("READY", len(os.listdir("/proc/self/fd")), flush=True)
    sys.stdin.readline()
    print("RESULT", json.dumps({"got": got, "errors": live.counters.errors}), flush=True)
"""


def test_idle_warp_subscriptions_under_a_low_fd_limit_leave_room_for_imports(domain, topic):
    """41 warp subscriptions in a process limited to 256 descriptors: the live one still gets
    every zero-copy frame (lane readers of idle ones took every descriptor, and each import
    then failed with EMFILE)."""
    import json

    import numpy as np

    import tensor_conversions.numpy as tc
    from buffer_pubsub import Node
    child = _ready_child(_IDLE_SUBSCRIPTIONS_CHILD, domain, topic)
    try:
        with Node("idle_subscriptions_pub", domain_id=domain) as node:
            pub = node.create_publisher("tensor_msgs/msg/ExperimentalTensor", topic, depth=10)
            assert pub.wait_for_subscriptions(1, timeout=15)
            time.sleep(0.3)  # the subscription's own discovery of this publisher
            for i in range(5):
                msg = tc.allocate_tensor_msg((5000,), np.uint8, backend="warp")
                tc.from_output_tensor_msg(msg)[:] = i
                pub.publish(msg)
                time.sleep(0.05)
            time.sleep(1.0)
            child.stdin.write("done\n")
            child.stdin.flush()
            line = child.stdout.readline()
        result = json.loads(line.split(" ", 1)[1])
        assert result == {"got": ["warp"] * 5, "errors": 0}, result
    finally:
        if child.poll() is None:
            child.kill()
        child.wait(timeout=20)


_SLOW_WARP_SUBSCRIBER = r"""
import json, sys, time
import numpy as np
from buffer_pubsub import Node
import tensor_conversions.numpy as tc
domain, topic = int(sys.argv[1]), sys.argv[2]
bad = []
with Node("routes_slow_sub", domain_id=domain) as node:
    def callback(msg):
        values = tc.from_input_tensor_msg(msg)
        if not (values == values[0]).all():
            bad.append(int(values[0]))
        time.sleep(0.01)  # frames wait, not imported yet, in the lane's queue
    sub = node.create_subscription("tensor_msgs/msg/ExperimentalTensor", topic, callback,
                                   depth=200, acceptable_buffer_backends="warp")
    print("READY", flush=True)
    sys.stdin.readline()
    deadline = time.monotonic() + 10
    while sub.counters.received + sub.counters.errors < 80 and time.monotonic() < deadline:
        time.sleep(0.05)
    c = sub.counters
    print("RESULT", json.dumps({"received": c.received, "errors": c.errors, "bad": bad}),
          flush=True)
"""


def test_destroying_a_publisher_keeps_its_queued_frames_readable(domain, topic):
    """Destroying a publisher told the backend that each of its subscriptions was gone: blocks
    of frames still waiting in a live subscriber's lane queue were recycled, and the subscriber
    lost them (StaleBufferError), those of a sibling publisher too."""
    import json

    import numpy as np

    import tensor_conversions.numpy as tc
    from buffer_pubsub import Node
    child = _ready_child(_SLOW_WARP_SUBSCRIBER, domain, topic)
    try:
        with Node("routes_destroy_pub", domain_id=domain) as node:
            tensor = "tensor_msgs/msg/ExperimentalTensor"
            sibling = node.create_publisher(tensor, topic, depth=200)  # lives on, idle
            value = 0
            for _ in range(2):
                pub = node.create_publisher(tensor, topic, depth=200)
                assert pub.wait_for_subscriptions(1, timeout=15)
                for _ in range(40):
                    msg = tc.allocate_tensor_msg((1024,), np.uint32, backend="warp")
                    tc.from_output_tensor_msg(msg)[:] = value
                    pub.publish(msg)
                    value += 1
                    del msg
                    time.sleep(0.001)
                pub.destroy()  # while most of its frames still wait in the subscriber's queue
            child.stdin.write("go\n")
            child.stdin.flush()
            line = child.stdout.readline()
            sibling.destroy()
        result = json.loads(line.split(" ", 1)[1])
        assert result == {"received": 80, "errors": 0, "bad": []}, result
    finally:
        if child.poll() is None:
            child.kill()
        child.wait(timeout=20)
