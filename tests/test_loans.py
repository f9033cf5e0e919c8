"""Loaned messages (issue 13 point 1): ``Publisher.loan`` and ``tensor_conversions.*.loan_tensor_msg``.

Generic pool rules on CPU messages (holds by reference, the ``reclaim`` hook), then warp loans:
cached views, steady state without allocation, intra-process holds, an exception in the block,
the read-only pages after publish (a write through a stale view faults, in a child process),
and a subscriber in another process.
"""

from __future__ import annotations

import gc
import mmap
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
import torch

from tests._pubsub_helpers import ROOT, TENSOR, Child, child_env, pattern

from buffer_pubsub import InvalidEndpointError, Node  # noqa: E402
from rosidl_buffer import Buffer, BufferImplBase, CpuBufferImpl, registry  # noqa: E402
from rosidl_buffer.messages import get_message_type  # noqa: E402
from tensor_conversions import numpy as tn  # noqa: E402
from tensor_conversions import torch as tc  # noqa: E402
from tensor_conversions import warp as tw  # noqa: E402
from tensor_conversions.errors import UnsupportedBackendError  # noqa: E402
from warp_buffer import pool_stats  # noqa: E402
from warp_buffer import loan as warp_loan  # noqa: E402
from warp_buffer.loan import LoanedBufferImpl, loan_buffer  # noqa: E402

N = 1024




@pytest.fixture(scope="module")
def backends():
    loaded, _errors = registry.load_backends()
    assert "warp" in loaded
    return loaded


def _cpu_factory():
    tensor = get_message_type(TENSOR)
    return tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=np.array([N]),
                  data=Buffer(np.zeros(N, np.uint8)))


def _wait(predicate, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.002)
    return True


# --------------------------------------------------------------------------- the reclaim hook
def test_cpu_reclaim_is_false_while_a_view_of_the_storage_lives():
    impl = CpuBufferImpl(np.zeros(16, np.uint8))
    assert impl.reclaim()
    view = impl.view()[4:]
    assert not impl.reclaim()
    del view
    assert impl.reclaim()
    borrowed = CpuBufferImpl(b"received bytes")  # read-only received bytes: never rewritten
    assert not borrowed.reclaim()


def test_a_backend_without_reclaim_is_never_reused():
    class Opaque(BufferImplBase):
        def get_backend_type(self): return "opaque"
        def size(self): return 1
        def to_cpu(self): return CpuBufferImpl(np.zeros(1, np.uint8))
        def clone(self): return Opaque()

    assert Opaque().reclaim() is False


def test_warp_reclaim_rearms_a_published_buffer_and_unprotects_it():
    buffer = loan_buffer(5000, "cpu")
    impl = buffer.get_impl()
    assert isinstance(impl, LoanedBufferImpl)
    impl.host[:] = 7
    buffer.seal()
    assert impl.is_published and not impl.is_protected  # until every route has sent it
    impl.end_publish()
    assert impl.is_protected
    assert int(impl.host[0]) == 7  # still readable
    assert impl.reclaim()
    assert not impl.is_published and not impl.is_protected
    impl.host[:] = 9  # writable again (a fault would kill the test process)
    assert int(impl.host[-1]) == 9


def test_a_loan_protects_its_own_window_onto_the_pages_it_uses():
    buffer = loan_buffer(9000, "cpu")  # a 16 KiB block whose bytes cover 3 pages
    impl = buffer.get_impl()
    block = impl.block
    assert block.shared and impl.data_ptr != block.data_ptr  # a mapping of its own
    assert impl._pages.nbytes == 3 * mmap.PAGESIZE < block.capacity
    impl.host[:] = 4
    buffer.seal()
    impl.end_publish()
    assert impl.is_protected
    assert int(block.host[8999]) == 4  # the same bytes, seen through the arena's mapping
    block.host[block.capacity - 1] = 1  # which is never protected (a fault kills the test)
    del buffer, impl
    gc.collect()
    block.host[:] = 6  # back in the pool: writable everywhere, the window unmapped


def test_without_a_window_the_block_is_protected_in_place(monkeypatch):
    def no_mapping(*args, **kwargs):
        raise OSError(12, "no mapping left")

    monkeypatch.setattr(warp_loan.memory, "map_fd", no_mapping)
    buffer = loan_buffer(5000, "cpu")
    impl = buffer.get_impl()
    block = impl.block
    assert impl.data_ptr == block.data_ptr and impl._pages.nbytes == 2 * mmap.PAGESIZE
    buffer.seal()
    impl.end_publish()
    assert impl.is_protected
    assert impl.reclaim() and not impl.is_protected
    buffer.seal()
    impl.end_publish()
    del buffer, impl
    gc.collect()
    block.host[:] = 3  # returned to the pool writable though the last loan left it protected


def test_no_window_and_no_protection_when_turned_off(monkeypatch):
    monkeypatch.setenv("WARP_BUFFER_LOAN_PROTECT", "0")
    buffer = loan_buffer(5000, "cpu")
    impl = buffer.get_impl()
    assert impl.data_ptr == impl.block.data_ptr and impl._pages is None
    buffer.seal()
    impl.end_publish()
    assert impl.is_published and not impl.is_protected


# --------------------------------------------------------------------------- generic pool (CPU)
def test_cpu_loans_reuse_the_message_unless_someone_holds_it(domain, topic, backends):
    with Node("loan_cpu", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        with pub.loan(_cpu_factory) as msg:
            msg.data.numpy()[:] = 1
        first = id(msg)
        del msg
        with pub.loan(_cpu_factory) as msg:  # nobody held it: the same message again
            assert id(msg) == first
        kept_view = msg.data.numpy()  # a NumPy view of the storage is a hold
        del msg
        with pub.loan(_cpu_factory) as msg:
            assert id(msg) != first
        second = msg
        del msg
        kept_buffer = second.data  # the Buffer alone is a hold too
        del second
        with pub.loan(_cpu_factory) as msg:
            pass
        assert pub.loan_stats()["created"] == 3
        del msg, kept_view, kept_buffer
        with pub.loan(_cpu_factory) as msg:
            pass
        del msg
        stats = pub.loan_stats()
        assert stats["created"] == 3 and stats["reused"] == 2


def test_past_max_loans_a_loan_is_a_fresh_unpooled_message(domain, topic, backends):
    with Node("loan_max", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        held = []
        for _ in range(4):
            with pub.loan(_cpu_factory, max_loans=2) as msg:
                held.append(msg.data)  # the loan's Buffer is a hold (the message object is not:
                # it goes back to the pool at publish, as rclcpp's loaned messages do)
        assert pub.loan_stats() == {"created": 2, "reused": 0, "unpooled": 2, "pooled": 2}


@pytest.mark.parametrize("helper", ["tensor", "image", "pointcloud"])
def test_the_tensor_loan_helpers_take_max_loans(domain, topic, backends, helper):
    """A subscriber keeping frames holds pooled messages: the helpers bound the pool as
    ``pub.loan(..., max_loans=)`` does."""
    msg_type = {"tensor": TENSOR, "image": "sensor_msgs/msg/Image",
                "pointcloud": "sensor_msgs/msg/PointCloud2"}[helper]
    loan = {"tensor": lambda: tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu",
                                                 max_loans=2),
            "image": lambda: tc.loan_image_msg(pub, 4, 4, "mono8", device="cpu", max_loans=2),
            "pointcloud": lambda: tc.loan_pointcloud_msg(pub, 4, ("x", "y", "z"),
                                                         torch.float32, device="cpu",
                                                         max_loans=2)}[helper]
    with Node("loan_helper_max", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(msg_type, topic)
        held = []
        for _ in range(4):
            with loan() as msg:
                held.append(msg.data)  # a kept frame holds its block
        stats = pub.loan_stats()
        assert (stats["created"], stats["unpooled"]) == (2, 2), stats


# --------------------------------------------------------------------------- warp loans
def _intra(node, topic, on_msg):
    return node.create_subscription(TENSOR, topic, on_msg, depth=100,
                                    acceptable_buffer_backends="warp")


def test_loan_views_are_cached_and_steady_state_allocates_nothing(domain, topic, backends):
    received = []
    with Node("loan_steady", domain_id=domain, backends=backends) as node:
        _intra(node, topic, lambda m: received.append(
            float(tc.from_input_tensor_msg(m, clone=False)[-1])))
        pub = node.create_publisher(TENSOR, topic)
        assert pub.wait_for_subscriptions(1)
        views: dict[int, torch.Tensor] = {}
        before = None
        for i in range(40):
            if i == 4:
                before = (pool_stats()["cpu"]["created"], pub.loan_stats()["created"])
            with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
                out = tc.from_output_tensor_msg(msg)
                assert tc.from_output_tensor_msg(msg) is out  # one view per framework
                views.setdefault(out.data_ptr(), out)
                assert views[out.data_ptr()] is out  # the second loan of a block reuses it
                out.fill_(i)
            del out
            assert _wait(lambda: len(received) == i + 1)
        after = (pool_stats()["cpu"]["created"], pub.loan_stats()["created"])
        assert received == [float(i) for i in range(40)]
    assert after == before, "a loan allocated in steady state"
    assert len(views) <= 2  # the pointers are stable: the same blocks go round
    assert pub.loan_stats()["reused"] >= 36


def test_numpy_and_warp_views_of_a_loan(domain, topic, backends):
    import warp as wp

    with Node("loan_np", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        with tn.loan_tensor_msg(pub, (4, 8), np.int32, device="cpu") as msg:
            array = tn.from_output_tensor_msg(msg)
            warp_view = tw.from_output_tensor_msg(msg)
            assert array.shape == (4, 8) and array.flags.writeable
            assert warp_view.ptr == array.ctypes.data  # zero-copy, same bytes
            array[:] = np.arange(32, dtype=np.int32).reshape(4, 8)
            assert np.array_equal(warp_view.numpy(), array)
        assert warp_view.dtype == wp.int32 and warp_view.shape == (4, 8)
        with pytest.raises(UnsupportedBackendError):
            tn.loan_tensor_msg(pub, (4,), np.float32, backend="cpu")


def test_intra_process_reader_holding_the_message_is_never_rewritten(domain, topic, backends):
    held = []
    with Node("loan_hold", domain_id=domain, backends=backends) as node:
        _intra(node, topic, held.append)
        pub = node.create_publisher(TENSOR, topic)
        assert pub.wait_for_subscriptions(1)
        pointers = []
        for i in range(6):  # the subscriber keeps every message: each loan needs a new block
            with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
                out = tc.from_output_tensor_msg(msg)
                out.fill_(float(i))
                pointers.append(out.data_ptr())
            del out, msg
            assert _wait(lambda: len(held) == i + 1)
        assert len(set(pointers)) == 6
        for i, msg in enumerate(held):  # what readers hold was never overwritten
            assert torch.all(tc.from_input_tensor_msg(msg, clone=False) == float(i))
        del msg
        created = pool_stats()["cpu"]["created"]
        held.clear()  # release: the blocks go round again
        for i in range(6):
            with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
                out = tc.from_output_tensor_msg(msg)
                out.fill_(100.0 + i)
                assert out.data_ptr() in pointers
            del out, msg
            assert _wait(lambda: len(held) == 1)
            assert float(tc.from_input_tensor_msg(held.pop(), clone=False)[0]) == 100.0 + i
        assert pool_stats()["cpu"]["created"] == created


@pytest.mark.parametrize("ending", ["an exception", "publish() inside the block"])
def test_a_block_that_fails_publishes_nothing_and_returns_the_loan(domain, topic, backends,
                                                                   ending):
    """An exception in the block; or rclcpp's habit, ``publish(loaned)``, inside the block
    that publishes when it ends (it sent the message twice): a typed error, nothing sent."""
    from buffer_pubsub.errors import LoanError

    received = []
    with Node("loan_exc", domain_id=domain, backends=backends) as node:
        _intra(node, topic, lambda m: received.append(
            float(tc.from_input_tensor_msg(m, clone=False)[0])))
        pub = node.create_publisher(TENSOR, topic)
        assert pub.wait_for_subscriptions(1)
        error, match = ((ValueError, "camera") if ending == "an exception" else
                        (LoanError, "publishes it when the block ends"))
        with pytest.raises(error, match=match):
            with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
                out = tc.from_output_tensor_msg(msg)
                out.fill_(1.0)
                first = out.data_ptr()
                if ending == "an exception":
                    raise ValueError("camera unplugged")
                pub.publish(msg)
        del msg, out
        time.sleep(0.2)
        assert received == [] and pub._last_stamp == 0  # nothing published
        with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
            out = tc.from_output_tensor_msg(msg)
            assert out.data_ptr() == first  # the loan came back to the pool, writable
            out.fill_(2.0)
        assert _wait(lambda: received == [2.0])
        assert pub.loan_stats()["created"] == 1 and not pub._loans.in_blocks


_STALE_CHILD = textwrap.dedent("""
    import sys, torch
    from buffer_pubsub import Node
    from rosidl_buffer import registry
    from tensor_conversions import torch as tc
    backends, _ = registry.load_backends()
    with Node("stale", domain_id=int(sys.argv[1]), backends=backends) as node:
        pub = node.create_publisher("tensor_msgs/msg/ExperimentalTensor", sys.argv[2])
        with tc.loan_tensor_msg(pub, (1024,), torch.float32, device="cpu") as msg:
            out = tc.from_output_tensor_msg(msg)
            out.fill_(1.0)
        print("PUBLISHED", float(out[5]), flush=True)  # reading a stale view is fine
        out[5] = 2.0  # writing through it after publish must not happen
        print("WROTE", flush=True)
""")


class _RecordingImpl(CpuBufferImpl):
    """CPU storage that records when the transport seals it and ends its publish."""

    def __init__(self, events: list[str]) -> None:
        super().__init__(np.zeros(16, np.uint8))
        self.events = events

    def seal(self) -> None:
        self.events.append("seal")

    def end_publish(self) -> None:
        self.events.append("end_publish")


def test_publish_ends_the_write_before_the_sends_and_fences_after_them(domain, topic, backends):
    events: list[str] = []
    msg = get_message_type(TENSOR)(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=[16],
                                   data=Buffer(_RecordingImpl(events)))
    with Node("loan_order", domain_id=domain, backends=backends, executor="manual") as node:
        sub = node.create_subscription(TENSOR, topic, lambda m: None)
        pub = node.create_publisher(TENSOR, topic)
        deliver = sub.deliver_intra

        def recorded(*args):
            events.append("send")
            return deliver(*args)

        sub.deliver_intra = recorded
        pub.publish(msg)
        assert events == ["seal", "send", "end_publish"]
        events.clear()
        pub.destroy()
        with pytest.raises(Exception, match="closed"):
            pub.publish(msg)  # a publish that fails after the seal still ends it
        assert events == ["seal", "end_publish"]


class _RecordingWaker:
    """A waker (see buffer_pubsub._waker) that records its notifications."""

    def __init__(self, events: list[str]) -> None:
        self.events = events
        self._event = threading.Event()

    def wait(self, timeout):
        self._event.wait(timeout)
        self._event.clear()

    def notify(self) -> None:
        self.events.append("notify")
        self._event.set()


def _recorded(domain: int, backends, name: str):
    """What the two wake-up tests record into: its events, a message whose storage records its
    seal and fence, the node (manual executor) whose waker records its notifications."""
    events: list[str] = []
    msg = get_message_type(TENSOR)(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=[16],
                                   data=Buffer(_RecordingImpl(events)))
    node = Node(name, domain_id=domain, backends=backends, executor="manual",
                waker=_RecordingWaker(events))
    return events, msg, node


def test_publish_wakes_the_in_process_executor_last_and_once(domain, topic, backends):
    # Woken before the fence, the executor thread would wait for the GIL the publish holds.
    events, msg, node = _recorded(domain, backends, "wake_order")
    received = []
    with node:
        for _ in range(2):  # two subscriptions of one executor: one wake-up
            node.create_subscription(TENSOR, topic, received.append)
        pub = node.create_publisher(TENSOR, topic)
        events.clear()
        pub.publish(msg)
        assert events == ["seal", "end_publish", "notify"]
        assert node.spin_once(0) == 2 and len(received) == 2


def test_a_publish_failing_after_its_in_process_delivery_still_wakes_the_executor(
        domain, topic, backends, monkeypatch):
    import buffer_pubsub.publisher as publisher_module
    from buffer_pubsub.errors import TransportError

    events, msg, node = _recorded(domain, backends, "wake_on_failure")
    received = []
    with node:
        node.create_subscription(TENSOR, topic, received.append)
        pub = node.create_publisher(TENSOR, topic)

        def failing(msg, backends, nbytes, stamp, routing, wakers, intra=None):
            pub._publish_intra(msg, backends, stamp, wakers)  # delivered in process, then
            raise TransportError("a remote route failed")  # a Zenoh put fails

        monkeypatch.setattr(pub, "_publish_remote", failing)
        pub._remote = publisher_module._Routing((), True, False)  # as if a peer were matched
        events.clear()
        with pytest.raises(TransportError):
            pub.publish(msg)
        assert events == ["seal", "end_publish", "notify"]
        assert node.spin_once(0) == 1 and len(received) == 1


def test_writing_through_a_view_kept_past_publish_faults(domain, topic):
    proc = subprocess.run([sys.executable, "-c", _STALE_CHILD, str(domain), topic], cwd=ROOT,
                          env=child_env(), capture_output=True, text=True, timeout=60)
    assert "PUBLISHED 1.0" in proc.stdout, proc.stderr
    assert "WROTE" not in proc.stdout
    assert proc.returncode == -signal.SIGSEGV, (proc.returncode, proc.stderr[-2000:])


def test_a_re_loaned_block_is_writable_through_its_cached_view(domain, topic, backends):
    with Node("loan_relo", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
            out = tc.from_output_tensor_msg(msg)
            out.fill_(1.0)
        impl = msg.data.get_impl()
        assert impl.is_protected  # read-only from publish to the next loan of the block
        del msg
        with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
            assert not impl.is_protected and msg.data.get_impl() is impl
            again = tc.from_output_tensor_msg(msg)
            assert again is out
            again.fill_(3.0)
        assert impl.is_protected and float(out[0]) == 3.0


def test_a_loaned_warp_message_reaches_another_process_zero_copy_and_blocks_go_round(
        domain, topic, backends):
    count = 30
    sub = Child("sub", domain=domain, topic=topic, accept="warp", expect=count)
    try:
        with Node("loan_inter", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            sub.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            pointers = set()
            for index in range(count):
                with tn.loan_tensor_msg(pub, (N,), np.uint8, device="cpu") as msg:
                    out = tn.from_output_tensor_msg(msg)
                    out[:] = pattern(0, index, N)
                    pointers.add(out.ctypes.data)
                del out, msg
                time.sleep(0.02)  # the subscriber checks and drops each frame meanwhile
            result = sub.stop()
            stats = pub.loan_stats()
    finally:
        sub.close()
    records = result["records"]
    assert [r["index"] for r in records] == list(range(count))
    assert all(r["ok"] for r in records), "wrong bytes"
    # imported from the publisher's block (over Zenoh or the same-host fast lane), not CPU bytes
    assert {r["backend"] for r in records} == {"warp"}
    assert len({r["route"] for r in records}) == 1 and records[0]["route"] in ("buffer", "lane")
    assert stats["reused"] >= count - stats["created"] and stats["created"] <= 4, stats
    assert len(pointers) == stats["created"]



def test_the_loans_benchmark_reports_every_figure():
    proc = subprocess.run([sys.executable, "-m", "benchmarks.loans", "--quick"], cwd=ROOT,
                          env=child_env(), capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    text = proc.stdout
    for framework in ("torch", "numpy", "warp"):
        assert f"\n{framework} " in text
    assert "from_input_tensor_msg(clone=False)" in text
    assert "end to end in process" in text and "end to end to another process" in text
    assert "stages (median us): loan+view" in text
    assert "nan" not in text  # every series received its messages


def test_loan_misuse_raises_typed_errors(domain, topic, backends):
    from buffer_pubsub import LoanError, NodeClosedError

    with Node("loan_err", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        loan = pub.loan(_cpu_factory)
        with loan:
            with pytest.raises(LoanError, match="entered once"):
                loan.__enter__()
        with pytest.raises(LoanError, match="not a message"):
            with pub.loan(lambda: np.zeros(4)):
                pass
        with pytest.raises(LoanError, match="factory"):
            pub.loan(5)
        entered = []
        image = get_message_type("sensor_msgs/msg/Image")
        with pytest.raises(InvalidEndpointError, match="cannot loan a sensor_msgs/msg/Image"):
            with pub.loan(image):  # refused when taken, before the block runs
                entered.append(True)
        assert not entered
        assert isinstance(LoanError("x"), RuntimeError)
        pub.destroy()
        with pytest.raises(NodeClosedError):
            pub.loan(_cpu_factory)


@pytest.mark.cuda
def test_cuda_loans_deliver_and_reuse_the_block_in_process(domain, topic, backends):
    import warp as wp

    received = []
    with Node("loan_cuda", domain_id=domain, backends=backends) as node:
        _intra(node, topic, lambda m: received.append(
            tc.from_input_tensor_msg(m, clone=True).cpu()))
        pub = node.create_publisher(TENSOR, topic)
        assert pub.wait_for_subscriptions(1)
        pointers = set()
        for i in range(6):
            with wp.ScopedStream(wp.get_stream("cuda:0")):
                with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cuda:0") as msg:
                    out = tc.from_output_tensor_msg(msg)
                    assert out.device.type == "cuda"
                    out.fill_(float(i))
                    pointers.add(out.data_ptr())
            del msg, out
            assert _wait(lambda: len(received) == i + 1)
        assert [float(t[0]) for t in received] == [float(i) for i in range(6)]
        assert all(bool(torch.all(t == t[0])) for t in received)
        assert len(pointers) <= 2 and pub.loan_stats()["reused"] >= 4


def test_a_re_loan_starts_from_the_specs_layout(domain, topic, backends):
    """A loan may reshape or retype its message; the next loan of the block starts as the spec
    made it (it came back float16 [2048] after one loan set those)."""
    with Node("reloan_meta", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
            msg.dtype_bits, msg.dtype_code, msg.shape = 16, 2, [2 * N]
            first = id(msg)
        del msg  # a reference of ours would be a hold
        with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
            assert id(msg) == first  # the pooled one
            view = tc.from_output_tensor_msg(msg)
            assert tuple(view.shape) == (N,) and view.dtype == torch.float32
            del view
        assert pub.loan_stats()["created"] == 1


@pytest.mark.parametrize("how", ["reshape", "to_tensor_msg"])
def test_reshaping_inside_loans_keeps_reusing_the_block(domain, topic, backends, how):
    got = []
    with Node("reloan_shape", domain_id=domain, backends=backends) as node:
        _intra(node, topic, lambda m: got.append(tn.from_input_tensor_msg(m).copy()))
        pub = node.create_publisher(TENSOR, topic)
        for index in range(12):
            with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
                if how == "reshape":
                    msg.shape = [N // 4, 4]
                    out = tc.from_output_tensor_msg(msg)
                    assert tuple(out.shape) == (N // 4, 4)
                    out.fill_(float(index))
                    del out
                else:
                    tc.to_tensor_msg(msg, torch.full((N // 4, 4), float(index)))
            assert _wait(lambda: len(got) == index + 1)
            del msg
        stats = pub.loan_stats()
    assert stats["created"] <= 2 and stats["unpooled"] == 0, stats  # reused, not pinned
    assert [float(g.reshape(-1)[0]) for g in got] == [float(i) for i in range(12)]
    assert all(g.shape == (N // 4, 4) for g in got)


def test_a_subscriber_gets_no_writable_view_of_a_published_loan(domain, topic, backends):
    from tensor_conversions.errors import TensorConversionError

    errors = []

    def on_msg(msg):
        try:
            tc.from_output_tensor_msg(msg)  # the publisher's cached view, once: now refused
        except TensorConversionError as exc:
            errors.append(exc)

    with Node("loan_subwrite", domain_id=domain, backends=backends) as node:
        _intra(node, topic, on_msg)
        pub = node.create_publisher(TENSOR, topic)
        with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
            tc.from_output_tensor_msg(msg).fill_(1.0)
        del msg
        assert _wait(lambda: errors)
    assert "published" in str(errors[0])
    assert isinstance(errors[0], RuntimeError)  # StorageNotWritableError: typed and a builtin


def test_max_loans_bounds_its_own_factory_key_only(domain, topic, backends):
    with Node("loan_max", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        held = [pub.loan(_cpu_factory, max_loans=1) for _ in range(3)]
        for loan in held:
            loan.__enter__()
        assert pub.loan_stats()["unpooled"] == 2  # one pooled under max_loans=1

        def other():
            return _cpu_factory()

        others = [pub.loan(other) for _ in range(3)]  # the default (16) for this key
        for loan in others:
            loan.__enter__()
        assert pub.loan_stats()["unpooled"] == 2 and pub.loan_stats()["pooled"] == 4
        for loan in held + others:
            loan.__exit__(RuntimeError, RuntimeError("abandon"), None)


def test_max_loans_holds_when_loans_are_taken_from_several_threads(domain, topic, backends):
    """Loans taken at once, each factory call slow: the pool is checked again when a new
    message joins it (8 pooled under max_loans=2 before)."""
    import threading

    threads = 6
    barrier = threading.Barrier(threads)

    def slow_factory():
        msg = _cpu_factory()
        time.sleep(0.05)  # every thread finds the pool not yet full
        return msg

    slow_factory.loan_key = "slow"
    with Node("loan_max_threads", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)

        def worker():
            barrier.wait()
            with pub.loan(slow_factory, max_loans=2):
                pass

        workers = [threading.Thread(target=worker) for _ in range(threads)]
        for thread in workers:
            thread.start()
        for thread in workers:
            thread.join(10)
        stats = pub.loan_stats()
        assert stats["pooled"] == 2 and stats["created"] == 2, stats
        assert stats["unpooled"] == threads - 2, stats


def test_a_message_without_buffers_is_not_pooled(domain, topic, backends):
    """In-process readers hold snapshots that share its arrays, which nothing counts: pooling
    it let a later loan write into what a reader held ([2, 2] where [0, 0] was published)."""
    numbers = "std_msgs/msg/Float64MultiArray"
    held = []
    with Node("loan_nobuf", domain_id=domain, backends=backends, executor="manual") as node:
        node.create_subscription(numbers, topic, held.append, depth=10)
        pub = node.create_publisher(numbers, topic)
        cls = pub.msg_type

        def factory():
            return cls(data=np.zeros(2))

        for i in range(3):
            with pub.loan(factory) as msg:
                msg.data[:] = i
            while node.spin_once(0.2):
                pass
        assert [m.data.tolist() for m in held] == [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]
        assert pub.loan_stats()["pooled"] == 0 and pub.loan_stats()["unpooled"] == 3


def test_a_factory_whose_storage_cannot_be_re_armed_is_not_pooled(domain, topic, backends):
    """A plain warp buffer has no reclaim: pooling its messages would only pin 16 of them."""
    import warp_buffer

    def warp_factory():
        tensor = get_message_type(TENSOR)
        return tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=np.array([N]),
                      data=warp_buffer.allocate_buffer(N, "cpu"))

    with Node("loan_plain_warp", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        for _ in range(5):
            with pub.loan(warp_factory):
                pass
        stats = pub.loan_stats()
    assert stats["pooled"] == 0 and stats["unpooled"] == 5, stats


def test_loan_and_allocate_shapes_take_numpy_ints_and_refuse_fractions(domain, topic, backends):
    from tensor_conversions.errors import InvalidTensorMetadataError

    with Node("loan_shapes", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        with tc.loan_tensor_msg(pub, np.int64(8), torch.float32, device="cpu") as msg:
            assert list(msg.shape) == [8]
        del msg
    with pytest.raises(InvalidTensorMetadataError, match="ints"):
        tc.allocate_tensor_msg((2.5, 4), torch.float32)  # was truncated to (2, 4)
    assert list(tc.allocate_tensor_msg((2.0, 4), torch.float32).shape) == [2, 4]


@pytest.mark.parametrize("keep", ["warp_buffer_view", "impl_array"])
def test_an_in_process_reader_keeping_a_warp_array_of_the_block_is_a_hold(
        domain, topic, backends, keep):
    """A warp_buffer handle's view, or impl.array, holds neither the message nor its Buffer:
    the block is still not re-loaned while it is kept (every kept one read the last frame)."""
    import warp as wp
    import warp_buffer

    held = []

    def on_msg(msg):
        if keep == "warp_buffer_view":
            held.append(warp_buffer.from_input_buffer(msg.data).view(wp.float32))
        else:
            held.append(msg.data.get_impl().array)

    with Node("loan_wp_hold", domain_id=domain, backends=backends) as node:
        _intra(node, topic, on_msg)
        pub = node.create_publisher(TENSOR, topic)
        for index in range(6):
            with tc.loan_tensor_msg(pub, (N,), torch.float32, device="cpu") as msg:
                tc.from_output_tensor_msg(msg).fill_(float(index))
            del msg
            assert _wait(lambda: len(held) == index + 1)
        values = [float(np.frombuffer(h.numpy()[:4].tobytes(), np.float32)[0]) for h in held]
        held.clear()
    assert values == [float(i) for i in range(6)]


# --------------------------------------------------------------------------- pool keys (issue 24)
def test_a_factory_written_inside_the_frame_loop_is_one_pool(domain, topic, backends):
    """``pub.loan(lambda: ...)`` written in the frame loop made a new pool per frame (a new
    function object each time) and pooled a new message in each, never freed: 300 frames grew
    RSS by 1.2 GB. A factory is keyed by its call site (code and captured values)."""
    with Node("loan_lambda", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        for frame in range(60):
            with pub.loan(lambda: _cpu_factory()) as msg:
                msg.data.numpy()[:] = frame
            del msg
        stats = pub.loan_stats()
        assert stats["created"] <= 2 and stats["pooled"] <= 2, stats
        assert stats["reused"] >= 58 and stats["unpooled"] == 0, stats
        assert pub._loans.pools() == 1


def test_pools_are_bounded_whatever_the_factory_keys(domain, topic, backends):
    """Keys that differ every frame (a factory capturing the frame number) still bound the
    pools, and with them the pooled messages (max_loans alone bounded one key's)."""
    from buffer_pubsub import loan

    MAX_POOLS = getattr(loan, "MAX_POOLS", 16)  # noqa: N806 - (the module's bound)
    with Node("loan_keys", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        for frame in range(3 * MAX_POOLS):
            with pub.loan(lambda frame=frame: _cpu_factory()):
                pass
        stats = pub.loan_stats()
        assert stats["pooled"] <= MAX_POOLS < 3 * MAX_POOLS == stats["created"] + stats[
            "unpooled"]
        assert pub._loans.pools() <= MAX_POOLS


def test_what_a_factory_makes_decides_its_pool():
    import functools

    from buffer_pubsub.loan import loan_key

    def make(height, width, encoding="rgb8"):
        return (height, width, encoding)

    loop = [(lambda: make(720, 1280)) for _ in range(3)]
    assert len({loan_key(f) for f in loop}) == 1  # one call site, the same values
    sizes = [(lambda h=h: make(h, 1280)) for h in (480, 720)]
    assert loan_key(sizes[0]) != loan_key(sizes[1])  # other values: another pool

    def closure(h):
        return lambda: make(h, 1280)

    assert loan_key(closure(480)) == loan_key(closure(480)) != loan_key(closure(720))
    assert loan_key(functools.partial(make, 1, 2)) == loan_key(functools.partial(make, 1, 2))
    assert loan_key(functools.partial(make, 1, 2)) != loan_key(functools.partial(make, 1, 3))
    array = np.zeros(3)  # unhashable captured values are compared by identity
    same, other = [(lambda a=a: a) for a in (array, array)], (lambda a=np.zeros(3): a)
    assert loan_key(same[0]) == loan_key(same[1]) != loan_key(other)

    class Spec:
        loan_key = ("mine", 1)

        def __call__(self):
            return None

    assert loan_key(Spec()) == ("mine", 1)


# --------------------------------------------------------------------------- image and cloud loans
@pytest.mark.parametrize("framework", ["torch", "numpy"])
def test_image_loans_are_pooled_and_reused_with_no_allocation(domain, topic, backends,
                                                              framework):
    """An Image loaned with allocate_image_msg's arguments is pooled like a tensor: the same
    blocks and cached views go round (``unpooled`` was every loan)."""
    module = tc if framework == "torch" else tn
    got = []
    with Node("loan_image", domain_id=domain, backends=backends) as node:
        node.create_subscription("sensor_msgs/msg/Image", topic, lambda m: got.append(
            (m.height, m.width, m.encoding, m.step,
             int(tn.from_input_image_msg(m, clone=False)[-1, -1, -1]))),
            depth=100, acceptable_buffer_backends="warp")
        pub = node.create_publisher("sensor_msgs/msg/Image", topic)
        assert pub.wait_for_subscriptions(1)
        outputs = set()
        before = None
        for frame in range(30):
            if frame == 4:
                before = pool_stats()["cpu"]["created"]
            with module.loan_image_msg(pub, 48, 64, "rgb8", device="cpu", step=200) as msg:
                out = module.from_output_image_msg(msg)
                assert tuple(out.shape) == (48, 64, 3)
                out[...] = frame
                outputs.add(id(out))
            del out, msg
            assert _wait(lambda: len(got) == frame + 1)
        stats = pub.loan_stats()
        after = pool_stats()["cpu"]["created"]
    assert stats["unpooled"] == 0 and stats["reused"] >= 27 and stats["created"] <= 3, stats
    assert after == before, "an image loan allocated in steady state"
    assert len(outputs) <= stats["created"]  # each block's view is built once
    assert got == [(48, 64, "rgb8", 200, frame) for frame in range(30)]


def test_point_cloud_loans_are_pooled_and_their_points_written_in_place(domain, topic,
                                                                       backends):
    got = []
    with Node("loan_cloud", domain_id=domain, backends=backends) as node:
        node.create_subscription("sensor_msgs/msg/PointCloud2", topic, lambda m: got.append(
            tn.from_input_pointcloud_msg(m, ("x", "y", "z")).copy()), depth=100,
            acceptable_buffer_backends="warp")
        pub = node.create_publisher("sensor_msgs/msg/PointCloud2", topic)
        assert pub.wait_for_subscriptions(1)
        for frame in range(12):
            with tc.loan_pointcloud_msg(pub, 100, ("x", "y", "z", "intensity"), torch.float32,
                                        device="cpu") as msg:
                points = tc.from_output_pointcloud_msg(msg)
                assert tuple(points.shape) == (100, 4)
                points.fill_(float(frame))
            del points, msg
            assert _wait(lambda: len(got) == frame + 1)
        stats = pub.loan_stats()
    assert stats["unpooled"] == 0 and stats["reused"] >= 9, stats
    assert [float(g[0, 0]) for g in got] == [float(f) for f in range(12)]
    assert all(g.shape == (100, 3) for g in got)


def test_allocate_pointcloud_msg_makes_packed_fields_of_one_dtype():
    msg = tn.allocate_pointcloud_msg(5, ("x", "y", "z"), np.float32, height=2)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (2, 5, 12, 60)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]
    tn.from_output_pointcloud_msg(msg)[:] = np.arange(30, dtype=np.float32).reshape(10, 3)
    np.testing.assert_array_equal(tn.from_input_pointcloud_msg(msg, ("y",)),
                                  np.arange(1, 30, 3, dtype=np.float32).reshape(10, 1))
    from tensor_conversions.errors import InvalidTensorMetadataError, UnsupportedDTypeError

    with pytest.raises(InvalidTensorMetadataError):
        tn.allocate_pointcloud_msg(5, ("x", "x"), np.float32)
    with pytest.raises(UnsupportedDTypeError):
        tn.allocate_pointcloud_msg(5, ("x",), np.int64)
    with pytest.raises(InvalidTensorMetadataError):
        tn.from_output_pointcloud_msg(msg, ("x", "z"))  # not adjacent: no one strided view
