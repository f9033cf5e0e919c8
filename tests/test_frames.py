"""Python frames per warp message (issue 25 point 5), counted with ``sys.setprofile`` on the real
path between two processes: ``benchmarks.lane_stages`` loans a warp tensor, publishes it over the
same-host lane, and its subscriber (a child) takes a NumPy view of it; the publisher counts from
the loan to the end of ``publish()``, the subscriber from the frame's arrival in the subscription
to the readable view (:class:`benchmarks.frames.FrameCounter`).

Before the lease and its tokens a message cost 229 frames (134 + 95); the native core and a
leaner Python path brought it to 71 (38 + 33), held here with a margin. An in-process publish
(to a subscription of the same process) runs 11.
"""

from __future__ import annotations

import sys

import pytest

from benchmarks.frames import FrameCounter

TENSOR = "tensor_msgs/msg/ExperimentalTensor"

#: Frames of one message, publisher and subscriber together, measured before issue 25.
BEFORE = 229
#: What one message may cost now (71 measured), publisher and subscriber together.
BOUND = 80
#: What an in-process publish may cost (11 measured).
INTRA_BOUND = 14


def test_the_counter_counts_python_calls_and_nothing_of_its_own():
    def leaf() -> int:
        return 1

    def branch() -> int:
        return leaf() + leaf()

    counter = FrameCounter()
    with counter:
        branch()
        len("c calls are not frames")
    assert counter.count == 3
    assert sys.getprofile() is None


def test_a_warp_message_costs_at_most_the_bound():
    from benchmarks import lane_stages

    try:
        records = lane_stages.publisher(count=12, nbytes=4096, route="lane", frames=6)
    except RuntimeError as exc:
        if "cannot run the lane" in str(exc):
            pytest.skip(f"no same-host lane here: {exc}")
        raise
    counts = lane_stages.frame_counts(records)
    assert counts is not None, "no message was counted"
    publisher, subscriber = counts
    assert publisher > 0 and subscriber > 0
    assert publisher + subscriber <= BOUND, (
        f"a warp message runs {publisher} + {subscriber} Python frames (publisher + subscriber), "
        f"more than {BOUND} ({BEFORE} before the lease): see `python -m benchmarks.lane_stages "
        "--frame-detail` for where they go")


def test_an_in_process_publish_costs_at_most_the_bound(domain, topic):
    import numpy as np
    import tensor_conversions.numpy as tc

    from buffer_pubsub import Node

    with Node("frames_intra", domain_id=domain, executor="manual") as node:
        node.create_subscription(TENSOR, topic, lambda msg: None, depth=4,
                                 acceptable_buffer_backends="cpu")
        pub = node.create_publisher(TENSOR, topic, depth=4)
        msg = tc.allocate_tensor_msg((4096,), np.uint8, backend="cpu")
        pub.publish(msg)  # the first compiles the type's validator and copier
        counter = FrameCounter(exclude={__file__})
        with counter:
            pub.publish(msg)
        assert 0 < counter.count <= INTRA_BOUND, counter.by_function
        assert node.spin_once(0) + node.spin_once(0) == 2  # both were delivered
