"""QoS profiles as rclpy's (``buffer_pubsub.qos``): a user porting an rclpy camera node wrote
``create_publisher(Image, "/image", qos_profile_sensor_data)`` and ``reliability=...`` and got a
TypeError. The policies reach the wire as rmw_zenoh puts them: the token's QoS segment and the
reliability and congestion control of the Zenoh publishers."""

from __future__ import annotations

import subprocess
import sys

import pytest
import zenoh

from buffer_pubsub import (
    DurabilityPolicy,
    HistoryPolicy,
    InvalidEndpointError,
    Node,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
    wire,
)
from tests._pubsub_helpers import ROOT, child_env

STRING = "std_msgs/msg/String"


def test_profiles_read_rclpy_spellings_and_refuse_the_rest():
    assert qos_profile_sensor_data == QoSProfile(depth=5, reliability="best_effort")
    profile = QoSProfile(depth=3, history=HistoryPolicy.KEEP_ALL,
                         reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    assert (profile.history, profile.reliability, profile.durability) == (
        "keep_all", "best_effort", "transient_local")
    assert QoSProfile(history="KEEP_ALL").history == "keep_all"
    for bad in ({"depth": 0}, {"depth": True}, {"depth": 2.0}, {"reliability": "sometimes"},
                {"history": None}, {"durability": "persistent"}):
        with pytest.raises(InvalidEndpointError):
            QoSProfile(**bad)


def test_keep_all_takes_rclpys_depth_0_as_rmw_zenoh_does(domain, topic):
    """rclpy's keep-all profiles leave depth 0 (rmw's "system default"), which was refused;
    rmw_zenoh's best_available_qos makes it its default depth, 42: the token's depth field is
    then empty, and a transient-local cache keeps 42 samples."""
    profile = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=0)
    assert profile.depth == 42 and profile.history == "keep_all"
    with pytest.raises(InvalidEndpointError, match="or 0 for keep-all"):
        QoSProfile(history="keep_all", depth=-1)
    with Node("qos_keep_all", domain_id=domain) as node:
        pub = node.create_publisher(STRING, topic, depth=0, history="keep_all")
        assert pub._token.qos.to_keyexpr() == "::2,:,:,:,,"  # keep-all (2), depth field empty


def test_a_profile_or_keywords_but_not_both(domain, topic):
    with Node("qos_args", domain_id=domain) as node:
        with pytest.raises(InvalidEndpointError, match="in the QoSProfile"):
            node.create_publisher(STRING, topic, qos_profile_sensor_data, history="keep_all")
        with pytest.raises(InvalidEndpointError, match="not both"):
            node.create_subscription(STRING, topic, lambda m: None, 3,
                                     qos_profile=qos_profile_sensor_data)
        with pytest.raises(InvalidEndpointError, match="reliability"):
            node.create_publisher(STRING, topic, reliability="mostly")
        explicit = node.create_publisher(STRING, topic, 10, reliability="reliable")
        assert explicit._token.qos == wire.QoSProfile.of(10)


_SENSOR_SUBSCRIBER = r"""
import sys
from buffer_pubsub import Node, qos_profile_sensor_data
domain, topic = int(sys.argv[1]), sys.argv[2]
with Node("sensor_viewer", domain_id=domain) as node:
    node.create_subscription("std_msgs/msg/String", topic,
                             lambda m: print(m.data, flush=True),
                             qos_profile=qos_profile_sensor_data)
    print("READY", flush=True)
    sys.stdin.readline()
"""


def test_a_best_effort_publisher_is_best_effort_on_the_wire_and_reaches_a_peer(domain, topic):
    from rosidl_buffer.messages import get_message_type

    peer = subprocess.Popen([sys.executable, "-c", _SENSOR_SUBSCRIBER, str(domain), topic],
                            cwd=ROOT, env=child_env(), stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert peer.stdout.readline().strip() == "READY"
        with Node("camera", domain_id=domain) as node:
            publisher = node.create_publisher(STRING, topic, qos_profile_sensor_data)
            assert publisher._base.reliability == zenoh.Reliability.BEST_EFFORT
            assert publisher._base.congestion_control == zenoh.CongestionControl.DROP
            assert publisher._token.key().split("/")[12].startswith("2::,5:")  # R=2, depth 5
            assert publisher.wait_for_subscriptions(1, timeout=20)
            infos = node.get_subscriptions_info_by_topic(topic)
            assert [i.qos_profile.reliability for i in infos] == [wire.RELIABILITY_BEST_EFFORT]
            message = get_message_type(STRING)
            for index in range(5):
                publisher.publish(message(data=f"m{index}"))
            got = [peer.stdout.readline().strip() for _ in range(5)]
        assert got == [f"m{index}" for index in range(5)]  # loopback loses nothing
        peer.communicate("stop\n", timeout=30)
    finally:
        if peer.poll() is None:
            peer.kill()
        peer.wait()
