"""buffer_pubsub: ROS 2-style publish/subscribe over Eclipse Zenoh with rosidl::Buffer backends.

The RMW role of the rosidl::Buffer guides: each ``uint8[]`` field travels by the backend each
subscription accepts (negotiated through discovery), falling back to CPU bytes. On the wire it is
ROS 2's rmw_zenoh 0.10.5 / 0.12.0 (see :mod:`buffer_pubsub.wire`): ROS 2 nodes and ours see and
talk to each other. ``Node`` exposes the graph as rclpy does (:mod:`buffer_pubsub.graph`).

Quick start::

    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type

    Tensor = get_message_type("tensor_msgs/msg/ExperimentalTensor")
    with Node("talker") as node:
        pub = node.create_publisher(Tensor, "/frames", depth=10)
        pub.wait_for_subscriptions(1, timeout=5)
        pub.publish(Tensor(data=b"..."))

    with Node("listener") as node:
        node.create_subscription(Tensor, "/frames", print, acceptable_buffer_backends="any")

Connectivity (no router by default; a config file or a router endpoint for multi-host use) is
described in :mod:`buffer_pubsub.config`. QoS (:mod:`buffer_pubsub.qos`, as rclpy's profiles):
keep-last ``depth`` (congestion control DROP) or ``history="keep_all"`` (BLOCK), reliable or
best-effort, volatile or transient-local (latched).
Loaned messages (``with pub.loan(factory) as msg:``, filled in place, published on exit, storage
reused once no reader holds it) are described in :mod:`buffer_pubsub.loan`.
Callbacks run on the node's executor thread, or on your own thread with
``Node(..., executor="manual")`` and ``node.spin()`` / ``node.spin_once(timeout)``, one at a time;
to run them in parallel, add nodes to a ``MultiThreadedExecutor`` (:mod:`buffer_pubsub.executors`)
and choose callback groups (:mod:`buffer_pubsub.callback_groups`), as in rclpy. Timers
(``node.create_timer(period, callback)``, :mod:`buffer_pubsub.timer`) run on the same executor.

buffer_pubsub knows backends only through :class:`rosidl_buffer.BufferBackend` and
:mod:`rosidl_buffer.registry`; it imports no backend.
"""

from .config import DEFAULT_CONFIG, make_config
from .errors import (
    ExecutorModeError,
    ForkedAfterZenohError,
    InvalidTimeoutError,
    InvalidEndpointError,
    InvalidNameError,
    LoanError,
    NodeClosedError,
    PayloadTooLargeError,
    PubSubError,
    TransportConfigError,
    TransportError,
    WireFormatError,
    WrongMessageTypeError,
)
from ._waker import Waker
from .fast_lane import LaneWaker as ThreadWaker  # every executor's waker (there is one kind)
from .graph import EndpointKind, NodeInfo, TopicEndpointInfo
from .loan import Loan
from .node import Node
from .publisher import Publisher, RouteInfo
from .qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
    qos_profile_system_default,
)
from .subscription import MessageInfo, Subscription, SubscriptionCounters
from .timer import Timer, TimerCounters

__all__ = [
    "DEFAULT_CONFIG",
    "DurabilityPolicy",
    "HistoryPolicy",
    "QoSProfile",
    "ReliabilityPolicy",
    "qos_profile_sensor_data",
    "qos_profile_system_default",
    "EndpointKind",
    "NodeInfo",
    "RouteInfo",
    "TopicEndpointInfo",
    "ExecutorModeError",
    "ForkedAfterZenohError",
    "InvalidTimeoutError",
    "InvalidEndpointError",
    "InvalidNameError",
    "Loan",
    "LoanError",
    "PayloadTooLargeError",
    "ThreadWaker",
    "TransportError",
    "WrongMessageTypeError",
    "Waker",
    "MessageInfo",
    "Node",
    "NodeClosedError",
    "PubSubError",
    "Publisher",
    "Subscription",
    "SubscriptionCounters",
    "Timer",
    "TimerCounters",
    "TransportConfigError",
    "WireFormatError",
    "make_config",
]
