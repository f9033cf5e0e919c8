"""``warp-buffer demo`` end to end: three processes, the warp and the CPU path, exit code 0."""

from __future__ import annotations

import argparse
import os

import pytest

from warp_buffer_cli import demo

pytestmark = pytest.mark.multiprocess


def test_demo_passes_on_the_cpu_device(capsys):
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    args = parser.parse_args(["--frames", "12", "--height", "32", "--width", "48",
                              "--rate", "100", "--timeout", "40",
                              "--domain", str(230 + os.getpid() % 20)])
    code = demo.run(args)
    out = capsys.readouterr().out
    assert code == 0, out
    assert "warp subscriber: path warp" in out and "cpu subscriber: path cpu" in out
    assert "received 12/12" in out and "p99" in out


def test_demo_fails_when_a_check_fails(monkeypatch, capsys):
    """The verdict is not hard-coded: a subscriber that sees wrong content makes it fail."""
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    args = parser.parse_args(["--frames", "4", "--height", "8", "--width", "8",
                              "--timeout", "20", "--domain", str(210 + os.getpid() % 20)])
    monkeypatch.setenv("WARP_BUFFER_DEMO_CORRUPT", "1")
    assert demo.run(args) == 1
    assert "FAILED" in capsys.readouterr().out
