"""Nothing of ours on stdout: every package and command leaves stdout to the application.

Each check runs a fresh interpreter (Warp prints its banner once per process, at its first
initialisation) and compares stdout with the application's own lines exactly. The demo's run is
checked the same way in ``tests/test_pubsub_demo.py``.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import textwrap

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.multiprocess

# A program that uses every package the way an application does and prints one line itself.
LIBRARY_USER = textwrap.dedent("""
    import numpy as np
    import warp_buffer
    from warp_buffer import allocate_buffer, from_output_buffer, from_input_buffer
    from tensor_conversions import numpy as tcn, torch as tct, warp as tcw
    from buffer_pubsub import Node

    buf = allocate_buffer(64)
    with from_output_buffer(buf) as out:
        out.array.fill_(7)          # a Warp kernel of ours: Warp logs its module load
    with from_input_buffer(buf) as inp:
        assert int(inp.array.numpy()[0]) == 7
    msg = tcn.allocate_tensor_msg((4, 4), np.uint8, backend="warp")
    tcn.from_output_tensor_msg(msg)[:] = 3
    import tensor_conversions
    tensor_conversions.release_output(msg)
    assert int(tct.from_input_tensor_msg(msg)[0, 0]) == 3
    tcw.to_tensor_msg(tcw.from_input_tensor_msg(msg))
    with Node("quiet_check", domain_id=%(domain)d) as node:
        pub = node.create_publisher("tensor_msgs/msg/ExperimentalTensor", "/quiet_check")
        pub.publish(msg)
    print("application line")
""")


def _run(argv: list[str], env: dict[str, str] | None = None,
         timeout: float = 120) -> subprocess.CompletedProcess[str]:
    full_env = dict(os.environ)
    full_env.pop("WARP_BUFFER_VERBOSE", None)  # quiet unless the test asks
    full_env.update(env or {})
    return subprocess.run(argv, cwd=ROOT, env=full_env, capture_output=True, text=True,
                          timeout=timeout)


def _no_warp_noise(text: str) -> None:
    assert "Warp 1." not in text and "initialized" not in text, text
    assert "CUDA driver" not in text, text
    assert "Module " not in text, text  # Warp's "Module ... load on device ... took ..."


# Importing only the Warp adapter, then using Warp directly, must be just as quiet.
WARP_ADAPTER_USER = textwrap.dedent("""
    from tensor_conversions import warp as tcw
    import warp as wp
    tcw.to_tensor_msg(wp.zeros(3))
    print("application line")
""")


@pytest.mark.parametrize("program", ["library", "warp_adapter"])
def test_library_use_prints_only_the_applications_line(program: str) -> None:
    code = (LIBRARY_USER % {"domain": 200 + os.getpid() % 30} if program == "library"
            else WARP_ADAPTER_USER)
    done = _run([sys.executable, "-c", code])
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout == "application line\n"
    _no_warp_noise(done.stderr)


def test_verbose_hands_warp_its_own_output_back() -> None:
    """The silence is ours, not an accident of this machine: asked for, Warp speaks."""
    done = _run([sys.executable, "-c", "import warp_buffer"], env={"WARP_BUFFER_VERBOSE": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Warp 1." in done.stderr and "Warp 1." not in done.stdout  # stdout is the app's


def test_verbose_info_json_stays_json() -> None:
    import json

    done = _run([sys.executable, "-m", "warp_buffer_cli.main", "--verbose", "info", "--json"])
    assert done.returncode == 0, done.stderr[-3000:]
    json.loads(done.stdout)


def test_info_prints_only_its_report() -> None:
    done = _run([sys.executable, "-m", "warp_buffer_cli.main", "info"])
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    assert lines[0] == "Buffer backends:" and "Warp devices:" in lines
    assert all(line == "Buffer backends:" or line == "Warp devices:" or line.startswith("  ")
               or line.startswith("Same-host fast lane: ")
               for line in lines), done.stdout
    _no_warp_noise(done.stdout + done.stderr)


def test_captured_native_output_is_logged_or_handed_back(
        caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]) -> None:
    import logging

    from warp_buffer import startup

    caplog.set_level(logging.INFO, logger="warp_buffer")
    startup._replay("Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU "
                    "execution will not be available.\nsomething else went wrong\n")
    assert any("CUDA driver" in r.getMessage() and r.levelno == logging.INFO
               for r in caplog.records)
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == "something else went wrong\n"


def test_warp_messages_go_to_logging(caplog: pytest.LogCaptureFixture,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    import logging

    import warp as wp

    from warp_buffer import startup  # importing warp_buffer installed the logger

    if startup.verbose_requested():
        pytest.skip("WARP_BUFFER_VERBOSE is set: Warp keeps its own logger by request")
    assert isinstance(wp.get_logger(), startup._LoggingWarpLogger)
    caplog.set_level(logging.INFO, logger="warp")
    wp.get_logger().info("a Warp info message")
    assert capsys.readouterr().out == ""
    assert any(r.getMessage() == "a Warp info message" for r in caplog.records)
