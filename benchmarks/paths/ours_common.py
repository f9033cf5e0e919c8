"""Our paths: ExperimentalTensor messages through buffer_pubsub, by backend and route.

The sender publishes ``tensor_msgs/msg/ExperimentalTensor`` (1-D uint8) built with
``tensor_conversions.numpy``; the receiver takes a zero-copy NumPy view
(``from_input_tensor_msg(msg, clone=False)``) and reads the stamp from it. Both sides count the
bytes copied per message (see :mod:`benchmarks.copies`). The nodes reach each other on a loopback
port of their own (no multicast) in a domain of their own, so other runs never interfere.
"""

from __future__ import annotations

import time
from typing import Any, Callable

from benchmarks import copies
from benchmarks.paths import PathSettings, PathUnavailable
from benchmarks.paths.zenoh_common import our_node_config
from benchmarks.protocol import STAMP_SIZE, stamp_into

TENSOR_TYPE = "tensor_msgs/msg/ExperimentalTensor"
DEPTH = 16  # keep-last depth: more than the rate window


def _imports() -> tuple[Any, Any, Any, Any]:
    """buffer_pubsub, its publisher and subscription modules, tensor_conversions.numpy."""
    try:
        import buffer_pubsub
        import buffer_pubsub.publisher as publisher_module
        import buffer_pubsub.subscription as subscription_module
        import tensor_conversions
        import tensor_conversions.numpy as tc_numpy
    except ImportError as error:
        raise PathUnavailable(f"our stack is not importable: {error}") from error
    for name in ("allocate_tensor_msg", "from_output_tensor_msg", "from_input_tensor_msg"):
        if not hasattr(tc_numpy, name):
            raise PathUnavailable(f"tensor_conversions.numpy has no {name}")
    if not hasattr(tensor_conversions, "release_output"):
        raise PathUnavailable("tensor_conversions has no release_output")
    return buffer_pubsub, publisher_module, subscription_module, tc_numpy


def require_warp_backend(export: bool) -> None:
    """Raise PathUnavailable unless warp storage can be allocated and, with ``export``, the
    'warp' buffer backend (descriptors between processes) loads."""
    try:
        import warp_buffer
        from rosidl_buffer import registry
    except ImportError as error:
        raise PathUnavailable(f"warp_buffer is not importable: {error}") from error
    if not hasattr(warp_buffer, "allocate_buffer"):
        raise PathUnavailable("warp_buffer.allocate_buffer does not exist yet")
    if not export:
        return
    try:
        registry.create_backend_instance("warp")
    except Exception as error:  # noqa: BLE001 - any failure means the backend cannot serve us
        raise PathUnavailable(f"the 'warp' buffer backend cannot load: {error}") from error


def _node(settings: PathSettings, role: str, listen: bool) -> Any:
    buffer_pubsub = _imports()[0]
    return buffer_pubsub.Node(f"bench_{role}_{settings.run_id}",
                              config=our_node_config(settings, listen),
                              domain_id=settings.domain_id)


def _topic(settings: PathSettings) -> str:
    return f"/warp_buffer_bench_{settings.run_id}"


class TensorSender:
    """Publishes one tensor message per send.

    ``backend="warp"``: a loaned warp-backed message per send (``loan_tensor_msg``: the
    publisher's pool reuses a block and its cached view once every reader released it), the
    clock read before the loan. ``backend="cpu"``: one CPU message per
    size and its output view, made untimed in ``prepare`` and reused (serialization copies the
    payload anyway, as the raw Zenoh peer's prepared bytearray), stamped in place.
    """

    def __init__(self, settings: PathSettings, backend: str) -> None:
        _, publisher_module, _, self._tc = _imports()
        if backend == "warp":
            require_warp_backend(export=False)
        self._backend = backend
        self._serialized = copies.ByteCounter()
        copies.wrap_serializer(publisher_module, self._serialized)
        self._node = _node(settings, "pub", listen=False)
        from rosidl_buffer.messages import get_message_type

        self._publisher = self._node.create_publisher(
            get_message_type(TENSOR_TYPE), _topic(settings), depth=DEPTH)
        self._nbytes = 0
        self._reused: Any = None
        self._view: Any = None
        self._published = 0
        self._per_size: dict[str, dict[str, int]] = {}
        self._matched = False

    def prepare(self, nbytes: int) -> None:
        """Remember the size; the CPU path allocates its reusable message now."""
        import numpy as np

        if not self._matched:
            self._matched = bool(self._publisher.wait_for_subscriptions(1, timeout=20.0))
        self._nbytes = nbytes
        self._reused = None
        self._serialized.take()  # counted afresh for this size's first message
        copies.PUBLISHED_POINTERS.clear()
        if self._backend == "cpu":
            self._reused = self._tc.allocate_tensor_msg((nbytes,), np.uint8, backend="cpu")
            self._view = self._tc.from_output_tensor_msg(self._reused)[:STAMP_SIZE]

    def send(self, seq: int) -> None:
        """Stamp a tensor and publish it."""
        import numpy as np

        if self._reused is not None:
            msg = self._reused
            stamp_into(self._view, seq)
            self._publisher.publish(msg)
        else:
            # A loaned message (what a user of the warp path does per frame): the clock starts
            # before the loan; the loan publishes when its block ends.
            t_send = time.perf_counter_ns()
            with self._tc.loan_tensor_msg(self._publisher, (self._nbytes,), np.uint8,
                                          backend=self._backend) as msg:
                array = self._tc.from_output_tensor_msg(msg)
                stamp_into(array[:STAMP_SIZE], seq, t_send)
                copies.PUBLISHED_POINTERS[seq] = int(array.ctypes.data)
                del array
        self._published += 1
        key = str(self._nbytes)
        if key not in self._per_size:  # the first message of a size: what it serialized (later
            # ones skip this, so the receiving thread gets the GIL as soon as publish returns)
            calls, nbytes = self._serialized.take()
            self._per_size[key] = {"serialize_calls_per_message": calls,
                                   "serialized_bytes_per_message": nbytes}

    def report(self) -> dict[str, Any]:
        """Per size: serializer calls and bytes it wrote for one published message."""
        return {"published": self._published, "per_size": self._per_size}

    def close(self) -> None:
        """Close the node (undeclares everything)."""
        self._reused = self._view = None
        self._node.close()


class TensorReceiver:
    """Subscribes with ``acceptable_buffer_backends=accept``; classifies the first delivery of
    every size (where the tensor lives, bytes copied)."""

    polls = False

    def __init__(self, settings: PathSettings, accept: str) -> None:
        _, _, subscription_module, self._tc = _imports()
        if accept == "warp":
            require_warp_backend(export=True)
        self._wire = copies.ByteCounter()
        copies.wrap_deserializer(subscription_module, self._wire)
        self._mappings = copies.ShmMappings()
        self._node = _node(settings, "sub", listen=True)
        from rosidl_buffer.messages import get_message_type

        self._deliver: Callable[[Any], None] | None = None
        self._classify_next = False
        self._nbytes = 0
        self._per_size: dict[str, dict[str, Any]] = {}
        self._received = 0
        self._subscription = self._node.create_subscription(
            get_message_type(TENSOR_TYPE), _topic(settings), self._on_message, depth=DEPTH,
            acceptable_buffer_backends=accept)

    def prepare(self, nbytes: int, deliver: Callable[[Any], None]) -> None:
        """Classify the next delivery (the first of this size)."""
        self._nbytes = nbytes
        self._deliver = deliver
        self._classify_next = True

    def _on_message(self, msg: Any) -> None:
        view = self._tc.from_input_tensor_msg(msg, clone=False)
        if self._deliver is not None:
            self._deliver(memoryview(view[:STAMP_SIZE]))
        self._received += 1
        if self._classify_next:  # after the ack: the check is not timed
            self._classify_next = False
            self._classify(msg, view)

    def _classify(self, msg: Any, view: Any) -> None:
        seq = int.from_bytes(bytes(view[:8]), "little", signed=True)
        wire_payload = self._wire.last  # one message in flight: the wire bytes of this one
        where, materialized = copies.classify_delivery(
            int(view.ctypes.data), int(view.nbytes), seq, wire_payload, self._mappings)
        wire = len(wire_payload) if wire_payload is not None else 0
        self._wire.last = None
        self._per_size.setdefault(str(self._nbytes), {
            "backend": msg.data.get_backend_type(), "tensor_lives_in": where,
            "received_wire_bytes": wire, "materialized_bytes": materialized})

    def report(self) -> dict[str, Any]:
        """Per size: backend delivered, where the tensor lived, bytes copied on this side."""
        return {"received": self._received, "per_size": self._per_size}

    def close(self) -> None:
        """Close the node."""
        self._node.close()


def make_pair(backend: str, accept: str) -> tuple[Callable[..., TensorSender],
                                                   Callable[..., TensorReceiver]]:
    """The two factories of a path publishing ``backend`` tensors to an ``accept`` subscriber."""

    def make_sender(settings: PathSettings, shared: Any) -> TensorSender:
        return TensorSender(settings, backend)

    def make_receiver(settings: PathSettings, shared: Any) -> TensorReceiver:
        return TensorReceiver(settings, accept)

    return make_sender, make_receiver


class StampReader(TensorReceiver):
    """Delivers at callback entry: reads the stamp through a view of the message's buffer,
    cached per buffer (intra-process, the same prepared buffer arrives every time)."""

    def __init__(self, settings: PathSettings, accept: str) -> None:
        super().__init__(settings, accept)
        self._buffer: Any = None
        self._head: Any = None

    def _on_message(self, msg: Any) -> None:
        if msg.data is not self._buffer:
            self._buffer = msg.data
            self._head = memoryview(msg.data.host_view()[:STAMP_SIZE])
        if self._deliver is not None:
            self._deliver(self._head)
        self._received += 1
        if self._classify_next:
            self._classify_next = False
            self._classify(msg, self._tc.from_input_tensor_msg(msg, clone=False))


def make_prepared_pair() -> tuple[Callable[..., TensorSender], Callable[..., TensorReceiver]]:
    """A prepared CPU message to a same-process subscription read at callback entry."""

    def make_sender(settings: PathSettings, shared: Any) -> TensorSender:
        return TensorSender(settings, "cpu")

    def make_receiver(settings: PathSettings, shared: Any) -> TensorReceiver:
        return StampReader(settings, "cpu")

    return make_sender, make_receiver
