"""rclpy's names on a Node, for code ported from rclpy: ``get_name``, ``get_logger``,
``destroy_publisher`` / ``destroy_subscription`` / ``destroy_node``, and ``node.spin()`` on a
node that runs its own callbacks (the port of ``rclpy.spin(node)``): a user trial met an
AttributeError or an ExecutorModeError for each."""

from __future__ import annotations

import threading
import time

import pytest

from buffer_pubsub import ExecutorModeError, Node, NodeClosedError
from rosidl_buffer.messages import get_message_type

STRING = "std_msgs/msg/String"


def test_names_and_logger_follow_rclpy(domain):
    with Node("talker", namespace="/robot1/arm", domain_id=domain) as node:
        assert node.get_name() == "talker"
        assert node.get_namespace() == "/robot1/arm"
        assert node.get_fully_qualified_name() == "/robot1/arm/talker"
        assert node.get_logger().name == "robot1.arm.talker"
    with Node("plain", domain_id=domain) as node:
        assert node.get_namespace() == "/"
        assert node.get_fully_qualified_name() == "/plain"
        assert node.get_logger().name == "plain"


def test_destroy_endpoints_through_their_node(domain, topic):
    with Node("owner", domain_id=domain) as node, Node("other", domain_id=domain) as other:
        publisher = node.create_publisher(STRING, topic)
        subscription = node.create_subscription(STRING, topic, lambda m: None)
        assert not other.destroy_publisher(publisher)  # not that node's: left alone
        assert node.destroy_publisher(publisher)
        with pytest.raises(NodeClosedError):
            publisher.publish(get_message_type(STRING)(data="x"))
        assert not node.destroy_publisher(publisher)  # once
        assert node.destroy_subscription(subscription)
        assert not node.destroy_subscription(subscription)
        probe = other.create_publisher(STRING, topic)
        assert probe.get_subscription_count() == 0
    node = Node("closing", domain_id=domain)
    node.destroy_node()
    assert node.closed


def test_spin_on_a_node_with_its_own_thread_waits_while_callbacks_run(domain, topic):
    with Node("own_thread", domain_id=domain) as node:
        ticks: list[str] = []
        node.create_timer(0.02, lambda: ticks.append(threading.current_thread().name))
        start = time.monotonic()
        node.spin(timeout=0.5)
        assert time.monotonic() - start >= 0.45
        assert ticks and threading.current_thread().name not in ticks  # the node's thread ran them
        with pytest.raises(ExecutorModeError, match="spin_once"):
            node.spin_once(0)  # one callback on this thread cannot be promised: refused
        closer = threading.Timer(0.3, node.close)
        closer.start()
        start = time.monotonic()
        node.spin()  # no limit: returns once another thread closed the node
        assert time.monotonic() - start < 5
        closer.join()
    with pytest.raises(NodeClosedError):
        node.spin(0)


def test_spin_inside_a_callback_of_the_node_is_refused(domain):
    with Node("self_spinning", domain_id=domain) as node:
        outcome: list[str] = []

        def tick() -> None:
            timer.cancel()
            try:
                node.spin(timeout=5)
                outcome.append("returned")
            except ExecutorModeError:
                outcome.append("refused")

        timer = node.create_timer(0.01, tick)
        deadline = time.monotonic() + 10
        while not outcome and time.monotonic() < deadline:
            time.sleep(0.01)
        assert outcome == ["refused"]
