"""Python frames per warp message (issue 25 point 5), counted with ``sys.setprofile`` on the real
path between two processes: ``benchmarks.lane_stages`` loans a warp tensor, publishes it over the
same-host lane, and its subscriber (a child) takes a NumPy view of it; the publisher counts from
the loan to the end of ``publish()``, the subscriber from the frame's arrival in the subscription
to the readable view (:class:`benchmarks.frames.FrameCounter`).

Before the lease and its tokens a message cost 229 frames (134 + 95); the bound is half of that.
"""

from __future__ import annotations

import sys

import pytest

from benchmarks.frames import FrameCounter

#: Frames of one message, publisher and subscriber together, measured before issue 25.
BEFORE = 229


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


def test_a_warp_message_costs_at_most_half_the_frames_it_did():
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
    assert publisher + subscriber <= BEFORE // 2, (
        f"a warp message runs {publisher} + {subscriber} Python frames (publisher + subscriber), "
        f"more than half the {BEFORE} it took before: see `python -m benchmarks.lane_stages "
        "--frame-detail` for where they go")
