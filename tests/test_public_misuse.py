"""Wrong input to the public API gets the library's typed errors, not an internal
AttributeError or TypeError; and the packages tell type checkers that they are typed."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

import tensor_conversions
import tensor_conversions.numpy as tcn
from rosidl_buffer.errors import (DeserializationError, InvalidMessageDefinitionError,
                                  UnknownMessageTypeError)
from rosidl_buffer.messages import (deserialize_message, get_message_type,
                                    register_message_definitions)
from tensor_conversions.errors import (InvalidTensorMetadataError, UnsupportedDTypeError,
                                       UnsupportedValueError, WrongMessageTypeError)
from warp_buffer import to_buffer
from warp_buffer.errors import UnsupportedSourceError

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGES = ("rosidl_buffer", "warp_buffer", "warp_buffer_backend", "tensor_conversions",
            "buffer_pubsub", "warp_buffer_cli")

CASES = [
    ("get_message_type(None)", lambda: get_message_type(None), UnknownMessageTypeError,
     "not NoneType"),
    ("get_message_type(123)", lambda: get_message_type(123), UnknownMessageTypeError, "not int"),
    ("register_message_definitions(None)", lambda: register_message_definitions(None),
     InvalidMessageDefinitionError, "not NoneType"),
    ("a definition that is not text",
     lambda: register_message_definitions({"trial_pkg/msg/NotText": 5}),
     InvalidMessageDefinitionError, "not int"),
    ("a known name with another definition",
     lambda: register_message_definitions({"sensor_msgs/msg/Image": "int8 x"}),
     InvalidMessageDefinitionError, "sensor_msgs/msg/Image"),
    ("deserialize_message(None)", lambda: deserialize_message(None, "std_msgs/msg/String"),
     DeserializationError, "not NoneType"),
    ("to_buffer(array, None)", lambda: to_buffer(np.zeros(8, np.uint8), None),
     UnsupportedSourceError, "WriteHandle"),
    ("allocate_tensor_msg(dtype=None)", lambda: tcn.allocate_tensor_msg((2,), None),
     UnsupportedDTypeError, "None"),
    ("a point cloud of width -1", lambda: tcn.allocate_pointcloud_msg(-1, ("x",), np.float32),
     InvalidTensorMetadataError, "point cloud sizes"),
    ("loan_tensor_msg(None)", lambda: tcn.loan_tensor_msg(None, (2,), np.float32),
     UnsupportedValueError, "Publisher, not NoneType"),
    ("release_output(None)", lambda: tensor_conversions.release_output(None),
     WrongMessageTypeError, "not NoneType"),
]


@pytest.mark.parametrize(("call", "expected", "words"), [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_wrong_input_gets_a_typed_error(call, expected, words) -> None:
    with pytest.raises(expected, match=words):
        call()


def test_every_package_is_marked_typed() -> None:
    """PEP 561: without py.typed, mypy skipped every package but rosidl_buffer."""
    for package in PACKAGES:
        assert (ROOT / package / "py.typed").is_file(), package
    assert '"py.typed"' in (ROOT / "pyproject.toml").read_text()  # shipped in the wheel



def test_the_distributions_carry_the_license_and_the_whole_suite() -> None:
    """No licence file shipped (Apache-2.0 asks for its text), and the sdist held 78 of the
    tests without their conftest and helpers."""
    assert (ROOT / "LICENSE").read_text().lstrip().startswith("Apache License")
    assert 'license-files = ["LICENSE"]' in (ROOT / "pyproject.toml").read_text()
    manifest = (ROOT / "MANIFEST.in").read_text().splitlines()
    assert {"graft tests", "graft docs", "graft examples"} <= set(manifest)


def test_the_torch_module_names_its_extra_when_torch_is_missing(tmp_path) -> None:
    import subprocess
    import sys

    (tmp_path / "torch.py").write_text("raise ImportError('No module named torch')\n")
    done = subprocess.run([sys.executable, "-c", "import tensor_conversions.torch"],
                          cwd=ROOT, env={"PYTHONPATH": str(tmp_path)}, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 1
    assert "pip install 'warp-buffer[torch]'" in done.stderr, done.stderr[-1500:]


def test_a_machine_without_a_compiler_is_told_what_to_install(tmp_path) -> None:
    """setuptools' generic build error named nothing the user could install."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, CC="/bin/false")
    done = subprocess.run([sys.executable, "setup.py", "build_ext", "-b", str(tmp_path / "lib"),
                           "-t", str(tmp_path / "tmp"), "--force"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert "need a C compiler and Python's headers" in done.stderr, done.stderr[-2000:]
    assert "apt install gcc python3-dev" in done.stderr
