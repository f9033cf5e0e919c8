"""Zero-copy torch views of received messages are read-only (issue 24 point 6).

A subscriber in another process maps the publisher's warp storage read-only. NumPy views say so
(``writeable=False``) and refuse writes; a torch view had no such flag, and writing into it
killed the process with SIGSEGV. ``from_input_*_msg(msg, clone=False)`` now returns tensors on
which torch itself refuses every write (RuntimeError), while reads and computations work; the
default ``clone=True`` returns a writable copy. The subscriber runs in a child process: before
the fix it died of SIGSEGV.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import torch

from buffer_pubsub import Node
from tensor_conversions import torch as tc
from tests._pubsub_helpers import ROOT, child_env

pytestmark = pytest.mark.multiprocess

TENSOR = "tensor_msgs/msg/ExperimentalTensor"
IMAGE = "sensor_msgs/msg/Image"

_SUBSCRIBER = textwrap.dedent(r"""
    import json, sys, time
    import torch
    from buffer_pubsub import Node
    from tensor_conversions import torch as tc

    domain, topic = int(sys.argv[1]), sys.argv[2]
    results = {}

    def attempt(name, write):
        try:
            write()
            results[name] = "wrote"
        except RuntimeError as exc:
            results[name] = "refused"

    def check(kind, view, copy):
        results[kind + "_backend"] = backend
        results[kind + "_sum"] = int(view.to(torch.int64).sum())   # reads work
        results[kind + "_conv"] = float(torch.nn.functional.conv2d(
            view.reshape(1, 1, *view.shape[:2]).float() if view.dim() == 2 else
            view.permute(2, 0, 1)[None].float(), torch.ones(1, view.shape[-1] if view.dim() == 3
            else 1, 1, 1)).sum())
        attempt(kind + "_fill", lambda: view.fill_(7))
        attempt(kind + "_setitem", lambda: view[0].__setitem__(0, 7))
        attempt(kind + "_out", lambda: torch.add(view, 1, out=view))
        copy.fill_(7)  # clone=True: a private, writable copy
        results[kind + "_copy"] = int(copy.flatten()[0])
        results[kind + "_after"] = int(view.to(torch.int64).sum())  # unchanged

    def on_tensor(msg):
        global backend
        backend = msg.data.get_backend_type()
        if "tensor_fill" not in results:
            check("tensor", tc.from_input_tensor_msg(msg, clone=False),
                  tc.from_input_tensor_msg(msg))

    def on_image(msg):
        global backend
        backend = msg.data.get_backend_type()
        if "image_fill" not in results:
            check("image", tc.from_input_image_msg(msg, clone=False), tc.from_input_image_msg(msg))

    with Node("readonly_sub", domain_id=domain) as node:
        node.create_subscription("tensor_msgs/msg/ExperimentalTensor", topic, on_tensor,
                                 acceptable_buffer_backends="warp")
        node.create_subscription("sensor_msgs/msg/Image", topic + "_image", on_image,
                                 acceptable_buffer_backends="warp")
        print("READY", flush=True)
        deadline = time.monotonic() + 60
        while len(results) < 16 and time.monotonic() < deadline:
            time.sleep(0.01)
    print("RESULT " + json.dumps(results), flush=True)
""")


def test_writing_into_a_received_zero_copy_view_raises_instead_of_crashing(domain, topic):
    proc = subprocess.Popen([sys.executable, "-c", _SUBSCRIBER, str(domain), topic], cwd=ROOT,
                            env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("READY"), proc.stderr.read() if proc.stderr else ""
        with Node("readonly_pub", domain_id=domain) as node:
            tensors = node.create_publisher(TENSOR, topic)
            images = node.create_publisher(IMAGE, f"{topic}_image")
            assert tensors.wait_for_subscriptions(1, timeout=30)
            assert images.wait_for_subscriptions(1, timeout=30)
            tensor = tc.allocate_tensor_msg((4, 6), torch.uint8, backend="warp", device="cpu")
            tc.from_output_tensor_msg(tensor).copy_(torch.arange(24, dtype=torch.uint8).view(4, 6))
            image = tc.allocate_image_msg(4, 6, "rgb8", backend="warp", device="cpu")
            tc.from_output_image_msg(image).fill_(1)
            deadline = time.monotonic() + 60
            while proc.poll() is None and time.monotonic() < deadline:
                tensors.publish(tensor)
                images.publish(image)
                time.sleep(0.05)
                if proc.poll() is not None:
                    break
            out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, (proc.returncode, err[-3000:])
    result = json.loads(out.split("RESULT ", 1)[1])
    assert result["tensor_backend"] == result["image_backend"] == "warp"  # zero-copy imports
    for kind, total in (("tensor", int(np.arange(24).sum())), ("image", 4 * 6 * 3)):
        assert result[f"{kind}_sum"] == total
        assert result[f"{kind}_conv"] == float(total)
        assert result[f"{kind}_fill"] == result[f"{kind}_setitem"] == "refused"
        assert result[f"{kind}_out"] == "refused"
        assert result[f"{kind}_copy"] == 7 and result[f"{kind}_after"] == total


def test_a_zero_copy_view_of_a_cpu_message_is_read_only_too():
    """Received CPU bytes (immutable) and the caller's own message alike: clone=False is the
    read-only contract, whatever the storage; the writable views are the output ones."""
    msg = tc.to_tensor_msg(torch.arange(6, dtype=torch.float32))
    view = tc.from_input_tensor_msg(msg, clone=False)
    assert float(view.sum()) == 15.0
    with pytest.raises(RuntimeError):
        view.add_(1)
    out = tc.from_output_tensor_msg(msg)
    out.add_(1)  # the output view stays writable
    assert float(view.sum()) == 21.0


_INTRA = textwrap.dedent(r"""
    import sys
    import torch
    from buffer_pubsub import Node
    from rosidl_buffer import registry
    from tensor_conversions import torch as tc

    domain, topic = int(sys.argv[1]), sys.argv[2]
    loaded, _ = registry.load_backends()

    def on_msg(msg):
        view = tc.from_input_tensor_msg(msg, clone=False)
        try:
            view.fill_(3)
            print("WROTE", flush=True)
        except RuntimeError:
            print("REFUSED", float(view.sum()), flush=True)

    with Node("readonly_intra", domain_id=domain, backends=loaded, executor="manual") as node:
        node.create_subscription("tensor_msgs/msg/ExperimentalTensor", topic, on_msg,
                                 acceptable_buffer_backends="warp")
        pub = node.create_publisher("tensor_msgs/msg/ExperimentalTensor", topic)
        with tc.loan_tensor_msg(pub, (8,), torch.float32, device="cpu") as msg:
            tc.from_output_tensor_msg(msg).fill_(1.0)
        assert node.spin_once(10) == 1
""")


def test_a_loaned_warp_view_is_read_only_to_an_intra_process_subscriber(domain, topic):
    """Intra-process subscribers share the publisher's loaned storage, whose pages are
    read-only after publish: the write faulted there as well (in a child, for that reason)."""
    proc = subprocess.run([sys.executable, "-c", _INTRA, str(domain), topic], cwd=ROOT,
                          env=child_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-3000:])
    assert proc.stdout.split() == ["REFUSED", "8.0"]


@pytest.mark.parametrize("framework", ["torch", "numpy"])
def test_a_point_cloud_copy_is_writable_when_a_clone_was_asked(framework):
    """Fields that are not adjacent take one host copy: with clone=True (the default) that copy
    is the caller's and writable; clone=False keeps the read-only contract."""
    from tensor_conversions.testing import MODULES
    from tests.test_tensor_conversions_image import _cloud, _xyzi

    module = MODULES[framework]
    msg = _cloud(_xyzi(4), height=2, row_pad=4)
    copy = module.from_input_pointcloud_msg(msg, ("x", "intensity"))
    copy[0, 0] = 5.0
    assert float(copy[0, 0]) == 5.0
    view = module.from_input_pointcloud_msg(msg, ("x", "intensity"), clone=False)
    with pytest.raises((RuntimeError, ValueError)):  # torch's refusal, NumPy's read-only flag
        view[0, 0] = 5.0


@pytest.mark.cuda
def test_a_cuda_input_view_refuses_writes_too():
    """Warp storage on a GPU: the torch view is on the GPU and refuses writes the same way."""
    value = torch.arange(8, dtype=torch.float32, device="cuda")
    msg = tc.to_tensor_msg(value)
    view = tc.from_input_tensor_msg(msg, clone=False)
    assert view.is_cuda and float(view.sum()) == 28.0
    with pytest.raises(RuntimeError):
        view.add_(1)
    assert torch.equal(tc.from_input_tensor_msg(msg), value)
