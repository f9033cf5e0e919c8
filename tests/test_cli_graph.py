"""The introspection commands (``warp-buffer topic ...``, ``warp-buffer node ...``) run in their
own processes against a graph of real processes: a publisher of ours, a warp subscription of
ours, and an rmw_zenoh subscription (the independent model of tests/upstream_model)."""

from __future__ import annotations

import re
import subprocess
import time
import sys

import pytest

from tests._pubsub_helpers import ROOT, child_env
from tests.test_ros2_interop import Procs, wait_ready

pytestmark = pytest.mark.multiprocess

RATE = 20.0
#: What else the rmw_zenoh node declares, as rclcpp nodes do: services, clients, the feedback
#: topics of an action server and of an action client, a private topic
GRAPH_TOKENS = ("SS:/ros2_viewer/get_parameters=rcl_interfaces/srv/GetParameters",
                "SC:/talker/describe_parameters=rcl_interfaces/srv/DescribeParameters",
                "MP:/fib/_action/feedback=example_interfaces/action/Fibonacci_FeedbackMessage",
                "MS:/arm/_action/feedback="
                "control_msgs/action/FollowJointTrajectory_FeedbackMessage",
                "MP:/ns/_private/data=std_msgs/msg/String")


@pytest.fixture(scope="module")
def graph():
    """One graph for the module: talker, viewer (ours) and an rmw_zenoh CPU-only subscription."""
    import os
    import uuid

    domain = 7000 + os.getpid() % 900
    topic = f"/cli_graph/image_{uuid.uuid4().hex[:8]}"
    procs = Procs()
    try:
        viewer = procs.start("tests._graph_talker", "viewer", "--domain", str(domain),
                             "--topic", topic)
        model = procs.model("sub", domain, topic, "sensor_msgs/msg/Image", "--node-name",
                            "ros2_viewer", *(f"--graph-token={token}" for token in GRAPH_TOKENS))
        talker = procs.start("tests._graph_talker", "talker", "--domain", str(domain),
                             "--topic", topic, "--rate", str(RATE))
        for proc in (viewer, model, talker):
            wait_ready(proc)
        _wait_for_routes(domain)  # the lane's files exist before the first test looks
        yield domain, topic
    finally:
        procs.close()


def _wait_for_routes(domain: int, timeout: float = 20.0) -> None:
    """Until the talker has settled both subscriptions' routes (its lane to the viewer open)."""
    import time

    from buffer_pubsub import Node
    from warp_buffer_cli._graph import routes_by_publisher

    with Node("_cli_graph_probe", domain_id=domain, fast_lane=False) as node:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            routes = [r for rs in routes_by_publisher(node).values() for r in rs]
            if len(routes) == 2 and any(r["via"] == "same-host lane" for r in routes):
                return
            time.sleep(0.1)


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", *args], cwd=ROOT,
                          env=child_env(), capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def test_topic_list_shows_the_topic_its_type_and_the_backends(graph):
    domain, topic = graph
    typed = cli("topic", "list", "-t", "--domain", str(domain))
    assert typed.returncode == 0 and f"{topic} [sensor_msgs/msg/Image]" in typed.stdout.split("\n")
    assert typed.stderr == ""
    listed = cli("topic", "list", "-v", "--domain", str(domain))
    assert listed.stderr == ""  # -v is the command's, not the top-level --verbose (logs)
    verbose = listed.stdout
    published, subscribed = verbose.split("Subscribed topics:")
    # (the tests' children also load the test-only "fake" backend)
    assert re.search(rf" \* {topic} \[sensor_msgs/msg/Image\] 1 publisher "
                     r"\(backends: cpu, (fake, )?warp\)", published), published
    assert f" * {topic} [sensor_msgs/msg/Image] 2 subscribers (backends: cpu, warp)" in subscribed


def test_topic_info_shows_every_endpoint_and_the_routes(graph):
    domain, topic = graph
    short = cli("topic", "info", topic, "--domain", str(domain)).stdout
    assert short.splitlines() == ["Type: sensor_msgs/msg/Image", "Publisher count: 1",
                                  "Subscription count: 2"]
    done = cli("topic", "info", "-v", topic, "--domain", str(domain))
    out = done.stdout
    assert done.stderr == ""
    assert "Node name: talker" in out and "Node name: ros2_viewer" in out
    assert "Node namespace: /robot" in out
    assert out.count("Buffer backends: cpu\n") == 1  # the rmw_zenoh CPU-only subscription
    assert "Implementation: another ROS 2 node (rmw_zenoh)" in out
    assert "History (Depth): KEEP_LAST (10)" in out
    routes = [line for line in out.splitlines() if line.startswith("  -> ")]
    assert len(routes) == 2, out
    warp = next(line for line in routes if line.startswith("  -> /robot/viewer"))
    # ours, on this host and user: warp descriptors over the same-host lane (or Zenoh)
    assert re.search(r": descriptor \((same-host lane|own stream \(_buf/<gid>\))\): served by warp",
                     warp), warp
    model = next(line for line in routes if line.startswith("  -> /ros2_viewer"))
    assert ": cpu (shared CPU stream (_buf_cpu)): it accepts only CPU" in model


def test_topic_echo_prints_fields_and_summarises_buffers(graph):
    domain, topic = graph
    out = cli("topic", "echo", topic, "--once", "--domain", str(domain)).stdout
    assert out.endswith("---\n")
    assert "encoding: mono8" in out and "height: 2" in out and "width: 4" in out
    assert re.search(r"frame_id: talker/\d+", out)
    assert "data:\n  backend: cpu\n  size: 8\n  first_bytes:\n  - " in out
    field = cli("topic", "echo", topic, "--once", "--field", "header.frame_id",
                "--domain", str(domain)).stdout
    assert re.fullmatch(r"talker/\d+\n---\n", field)
    csv = cli("topic", "echo", topic, "--once", "--csv", "--field", "data",
              "--domain", str(domain)).stdout.strip()
    assert csv.split(",")[:2] == ["cpu", "8"]
    count = cli("topic", "echo", topic, "--count", "3", "--field", "header.frame_id",
                "--domain", str(domain)).stdout
    indices = [int(x) for x in re.findall(r"talker/(\d+)", count)]
    assert len(indices) == 3 and indices == sorted(indices)
    # ros2 topic echo's positional type: subscribed at once; short names as ROS 2 takes them
    typed = cli("topic", "echo", topic, "sensor_msgs/Image", "--once", "--field", "encoding",
                "--domain", str(domain))
    assert typed.returncode == 0 and typed.stdout == "mono8\n---\n", typed.stderr
    unknown = cli("topic", "echo", topic, "no_such_msgs/msg/Nope", "--once",
                  "--domain", str(domain))
    assert unknown.returncode == 1 and "no_such_msgs/msg/Nope" in unknown.stderr
    assert len(unknown.stderr.strip().splitlines()) == 1


def test_topic_hz_is_within_ten_percent_of_the_published_rate(graph):
    domain, topic = graph
    out = cli("topic", "hz", topic, "--count", "3", "--domain", str(domain)).stdout
    rates = [float(x) for x in re.findall(r"average rate: ([\d.]+)", out)]
    assert len(rates) == 3 and abs(rates[-1] - RATE) <= 0.1 * RATE, out
    assert re.search(r"\tmin: [\d.]+s max: [\d.]+s std dev: [\d.]+s window: \d+", out)


def test_topic_bw_reports_bytes_per_second_and_sizes(graph):
    domain, topic = graph
    out = cli("topic", "bw", topic, "--count", "2", "--domain", str(domain)).stdout
    assert re.search(r"[\d.]+ (B|KB)/s from \d+ messages\n\tMessage size mean: [\d.]+ B "
                     r"min: [\d.]+ B max: [\d.]+ B", out), out


def test_node_list_and_info(graph):
    domain, topic = graph
    names = cli("node", "list", "--domain", str(domain)).stdout.split()
    assert {"/talker", "/robot/viewer", "/ros2_viewer"} <= set(names)
    assert not [n for n in names if n.rsplit("/", 1)[-1].startswith("_")]  # the CLI's own
    out = cli("node", "info", "/talker", "--domain", str(domain)).stdout
    assert out.startswith("/talker\n  Subscribers:\n  Publishers:\n"
                          f"    {topic}: sensor_msgs/msg/Image\n")


def test_node_info_shows_services_and_actions_and_hides_hidden_names(graph):
    """As ``ros2 node info``: the services and clients its tokens declare, its actions found by
    their feedback topics (rcl_action), and no hidden name (a part starting with '_') unless
    --include-hidden. The headings were printed empty for every rclcpp node."""
    domain, topic = graph
    out = cli("node", "info", "/ros2_viewer", "--domain", str(domain)).stdout
    assert out == ("/ros2_viewer\n"
                   "  Subscribers:\n"
                   f"    {topic}: sensor_msgs/msg/Image\n"
                   "  Publishers:\n"
                   "  Service Servers:\n"
                   "    /ros2_viewer/get_parameters: rcl_interfaces/srv/GetParameters\n"
                   "  Service Clients:\n"
                   "    /talker/describe_parameters: rcl_interfaces/srv/DescribeParameters\n"
                   "  Action Servers:\n"
                   "    /fib: example_interfaces/action/Fibonacci\n"
                   "  Action Clients:\n"
                   "    /arm: control_msgs/action/FollowJointTrajectory\n"), out
    everything = cli("node", "info", "/ros2_viewer", "--include-hidden", "--domain",
                     str(domain)).stdout
    published = everything.split("  Publishers:\n")[1].split("  Service Servers:")[0]
    assert published == ("    /fib/_action/feedback: "
                         "example_interfaces/action/Fibonacci_FeedbackMessage\n"
                         "    /ns/_private/data: std_msgs/msg/String\n"), everything


def test_topic_list_hides_hidden_topics_as_ros2_does(graph):
    domain, topic = graph
    hidden = {"/fib/_action/feedback", "/arm/_action/feedback", "/ns/_private/data"}
    listed = set(cli("topic", "list", "--domain", str(domain)).stdout.split())
    assert topic in listed and not hidden & listed, listed
    verbose = cli("topic", "list", "-v", "--domain", str(domain)).stdout
    assert "_action" not in verbose and "_private" not in verbose, verbose
    assert hidden <= set(cli("topic", "list", "--include-hidden", "--domain",
                             str(domain)).stdout.split())


def test_the_graph_api_answers_for_other_nodes_services(graph):
    """rclpy's names: the services and clients other nodes declare (this transport has none of
    its own)."""
    from buffer_pubsub import Node

    domain, topic = graph
    with Node("_cli_graph_services", domain_id=domain, fast_lane=False) as node:
        def discovered() -> bool:  # every token below (they arrive in any order)
            return (len(node.get_service_names_and_types()) == 2
                    and len(node.get_subscriber_names_and_types_by_node("ros2_viewer")) == 2
                    and len(node.get_publisher_names_and_types_by_node("ros2_viewer")) == 2)

        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not discovered():
            time.sleep(0.05)
        assert node.get_service_names_and_types() == [
            ("/ros2_viewer/get_parameters", ["rcl_interfaces/srv/GetParameters"]),
            ("/talker/describe_parameters", ["rcl_interfaces/srv/DescribeParameters"])]
        assert node.get_service_names_and_types_by_node("ros2_viewer", "/") == [
            ("/ros2_viewer/get_parameters", ["rcl_interfaces/srv/GetParameters"])]
        assert node.get_client_names_and_types_by_node("ros2_viewer") == [
            ("/talker/describe_parameters", ["rcl_interfaces/srv/DescribeParameters"])]
        assert node.get_service_names_and_types_by_node("talker") == []
        # (rclpy's topic names-and-types of one node, which node info prints)
        assert node.get_subscriber_names_and_types_by_node("ros2_viewer") == [
            ("/arm/_action/feedback",
             ["control_msgs/action/FollowJointTrajectory_FeedbackMessage"]),
            (topic, ["sensor_msgs/msg/Image"])]
        assert node.get_publisher_names_and_types_by_node("ros2_viewer", "/") == [
            ("/fib/_action/feedback", ["example_interfaces/action/Fibonacci_FeedbackMessage"]),
            ("/ns/_private/data", ["std_msgs/msg/String"])]
        names = {name for name, _ in node.get_topic_names_and_types()}
        assert "/ros2_viewer/get_parameters" not in names  # a service is not a topic


def test_topic_type_and_find_answer_as_ros2s(graph):
    domain, topic = graph
    typed = cli("topic", "type", topic, "--domain", str(domain))
    assert (typed.returncode, typed.stdout, typed.stderr) == (0, "sensor_msgs/msg/Image\n", "")
    found = cli("topic", "find", "sensor_msgs/Image", "--domain", str(domain))
    assert found.returncode == 0 and topic in found.stdout.split("\n")
    # a type not installed here is matched by its name (it may be a ROS 2 peer's own)
    none = cli("topic", "find", "my_robot_msgs/Custom", "-c", "--domain", str(domain),
               "--spin-time", "0.3")
    assert (none.returncode, none.stdout) == (0, "0\n")


@pytest.mark.parametrize("argv, message", [
    (("topic", "type", "/no/such/topic"), "is not in the graph"),
    (("topic", "find", "std_msgs/msg/Nope/x"), "not a message type name"),
    (("topic", "info", "/no/such/topic"), "is not in the graph"),
    (("node", "info", "/nobody"), "is not in the graph"),
    (("topic", "hz", "/x", "--window", "0"), "--window"),
])
def test_bad_input_is_one_line_and_a_non_zero_exit(graph, argv, message):
    domain, _ = graph
    done = cli(*argv, "--domain", str(domain), "--spin-time", "0.3")
    assert done.returncode == 1 and done.stdout == ""
    assert len(done.stderr.strip().splitlines()) == 1 and message in done.stderr, done.stderr


@pytest.mark.parametrize("command", ["echo", "hz", "bw", "info"])
@pytest.mark.parametrize("name", ["bad name", "/a//b", "/1x"])
def test_a_topic_name_ros_2_refuses_is_a_usage_error_not_a_wait(command, name):
    """An invalid topic name exits 2 at once, naming the rule (echo, hz and bw waited for it
    forever, since nobody can publish it; info called it unknown)."""
    done = cli("topic", command, name, "--domain", "7999", timeout=30)
    assert done.returncode == 2 and done.stdout == "", (done.returncode, done.stderr)
    assert "invalid topic name" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.parametrize("command", ["echo", "hz"])
def test_echo_and_hz_wait_for_a_topic_that_is_not_published_yet(command):
    """As ``ros2 topic echo / hz``: a monitor started before its publisher warns once on stderr
    and waits (it failed at once with UnknownTopicError, so it could not watch a bag played
    after it started), then reports the topic once it appears."""
    import os
    import time
    import uuid

    import numpy as np

    from buffer_pubsub import Node

    domain = 7900 + os.getpid() % 90
    topic = f"/cli_graph/late_{uuid.uuid4().hex[:8]}"
    argv = ["--once"] if command == "echo" else ["--count", "1", "--window", "2"]
    monitor = subprocess.Popen(
        [sys.executable, "-m", "warp_buffer_cli.main", "topic", command, topic, *argv,
         "--domain", str(domain), "--spin-time", "0.2"],
        cwd=ROOT, env=child_env(), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        warning = monitor.stderr.readline()
        assert "does not appear to be published yet" in warning and topic in warning
        assert monitor.poll() is None  # still waiting
        with Node("late_talker", domain_id=domain) as node:
            pub = node.create_publisher("std_msgs/msg/UInt8MultiArray", topic)
            msg_type = pub.msg_type
            deadline = time.monotonic() + 30
            while monitor.poll() is None and time.monotonic() < deadline:
                msg = msg_type(data=np.arange(4, dtype=np.uint8))
                pub.publish(msg)
                time.sleep(0.05)
        out, err = monitor.communicate(timeout=30)
    finally:
        if monitor.poll() is None:
            monitor.kill()
            monitor.communicate()
    assert monitor.returncode == 0, err
    assert ("data:" in out) if command == "echo" else ("average rate" in out), out


def test_a_buffer_preview_honours_a_shorter_truncate_length():
    import numpy as np

    from rosidl_buffer import Buffer
    from warp_buffer_cli.topic._fields import BUFFER_PREVIEW, to_plain

    buffer = Buffer(np.arange(40, dtype=np.uint8))
    assert to_plain(buffer, 4)["first_bytes"] == [0, 1, 2, 3]
    assert to_plain(buffer, 0)["first_bytes"] == list(range(BUFFER_PREVIEW))
    assert to_plain(buffer, 128) == {"backend": "cpu", "size": 40,
                                     "first_bytes": list(range(BUFFER_PREVIEW))}


def test_echo_of_a_latched_topic_shows_what_was_published_before_it_started(domain, topic):
    """As ``ros2 topic echo``: when every publisher of the topic is transient-local (an
    rmw_zenoh node latching /tf_static, a map), echo subscribes transient-local and prints the
    message published before it started (a volatile echo waited for a next one forever)."""
    procs = Procs()
    try:
        pub = procs.model("pub", domain, topic, "std_msgs/msg/String", "--durability",
                          "transient_local", "--depth", "1", "--count", "1", "--hold")
        wait_ready(pub)
        time.sleep(0.3)  # published, and kept
        done = cli("topic", "echo", topic, "--once", "--field", "data", "--domain", str(domain),
                   timeout=30)
    finally:
        procs.close()
    assert done.returncode == 0 and done.stdout.endswith("---\n"), (done.stdout, done.stderr)


def test_nodes_that_share_a_name_are_listed_each_with_ros2s_warning(domain):
    from buffer_pubsub import Node

    with Node("twin", domain_id=domain) as first, Node("twin", domain_id=domain) as second:
        deadline = time.monotonic() + 10
        while (min(node.get_node_names_and_namespaces().count(("twin", "/"))
                   for node in (first, second)) < 2 and time.monotonic() < deadline):
            time.sleep(0.05)
        assert first.get_node_names_and_namespaces().count(("twin", "/")) == 2  # as rclpy
        assert second.get_node_names_and_namespaces().count(("twin", "/")) == 2
        listed = cli("node", "list", "--domain", str(domain))
    assert listed.returncode == 0 and listed.stdout.split().count("/twin") == 2, listed
    assert "share an exact name" in listed.stderr
