"""The ``warp-buffer`` command: ``info`` reports backends, metadata, devices and IPC support."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from warp_buffer_cli.main import main


def test_info_json_lists_every_backend_with_metadata_and_the_cpu_device() -> None:
    completed = subprocess.run(
        [sys.executable, "-m", "warp_buffer_cli.main", "info", "--json"],
        capture_output=True, text=True, timeout=120, check=True)
    report = json.loads(completed.stdout)
    backends = {entry["name"]: entry for entry in report["backends"]}
    assert list(backends)[0] == "cpu" and backends["cpu"]["status"] == "built in"
    assert backends["warp"]["status"] == "loaded"
    assert "ipc=" in backends["warp"]["metadata"]
    devices = {device["name"]: device for device in report["warp_devices"]}
    assert devices["cpu"]["ipc"] == "shared memory (mmap)"


def test_info_table_names_the_backends(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "Buffer backends:" in out and "warp" in out and "Warp devices:" in out


def test_unknown_subcommand_is_a_usage_error() -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["frobnicate"])
    assert exit_info.value.code == 2


def test_help_lists_every_command_and_the_verbose_flag(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for command in ("info", "demo", "bench", "router", "bag"):
        assert command in out
    assert "--verbose" in out


def test_verbose_flag_reaches_child_processes(monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    import os

    # setenv records the original state, so the "1" that main() sets is undone after the test
    # (delenv of an absent variable records nothing, and later tests' children would be verbose).
    monkeypatch.setenv("WARP_BUFFER_VERBOSE", "")
    assert main(["--verbose", "info"]) == 0
    assert os.environ.get("WARP_BUFFER_VERBOSE") == "1"  # inherited by demo / bench children


def test_a_reader_that_leaves_early_gets_no_traceback() -> None:
    """``warp-buffer info | head -0``: a BrokenPipeError traceback (rc 1) before."""
    import os
    import subprocess
    import sys

    read, write = os.pipe()
    os.close(read)  # the reader is gone before anything is written
    try:
        done = subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", "info"],
                              stdout=write, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write)
    assert done.returncode == 141 and "Traceback" not in done.stderr, done.stderr[-2000:]


def _cli(*argv: str, **streams) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", *argv],
                          stderr=subprocess.PIPE, text=True, timeout=120, **streams)


def test_a_stdout_that_cannot_be_written_is_one_line_not_a_traceback() -> None:
    """``warp-buffer info > /dev/full`` ended in an OSError traceback; with descriptor 1 closed
    (``>&-``) a command died on ``None.flush()``."""
    with open("/dev/full", "w") as full:
        done = _cli("info", stdout=full)
    assert done.returncode == 1, done.stderr
    assert done.stderr.strip() == ("warp-buffer info: cannot write to stdout: No space left on "
                                   "device"), done.stderr
    closed = _cli("info", "--json", stdout=subprocess.DEVNULL,
                  preexec_fn=lambda: os.close(1))
    assert closed.returncode == 0 and "Traceback" not in closed.stderr, closed.stderr


@pytest.mark.parametrize("command", [("bag", "info"), ("bag", "play"), ("bag", "reindex"),
                                     ("bag", "record"), ("topic", "echo"), ("node", "info")])
def test_help_shows_no_docstring_markup(command: tuple[str, ...]) -> None:
    """The leaves' --help printed their docstrings' :class:`~.errors.X` and ``literals``."""
    done = subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", *command, "--help"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "`" not in done.stdout and ":class:" not in done.stdout and ":mod:" not in done.stdout
