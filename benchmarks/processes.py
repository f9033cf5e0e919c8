"""Runner side of one path: start its child processes, collect the result, reap, clean up."""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import subprocess
import sys
import time
from typing import Any

from benchmarks.paths import PathSettings, load_path
from benchmarks.shm import remove_leftovers, shm_entries


def free_tcp_port() -> int:
    """A loopback TCP port nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _spawn(role: str, spec: dict, fds: tuple[int, ...] = ()) -> subprocess.Popen[str]:
    command = [sys.executable, "-m", "benchmarks.child", "--role", role, "--spec", json.dumps(spec)]
    if fds:
        command += ["--ctrl-fd", str(fds[0]), "--ack-fd", str(fds[1])]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=None, text=True,
                            pass_fds=fds, cwd=_project_root())


def _project_root() -> str:
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _reap(process: subprocess.Popen[str], timeout_s: float) -> str:
    """Wait for ``process`` up to ``timeout_s`` (then kill it); its stdout."""
    try:
        out, _ = process.communicate(timeout=timeout_s)
        return out or ""
    except subprocess.TimeoutExpired:
        process.kill()
        out, _ = process.communicate()
        return out or ""


def _last_json(text: str) -> dict[str, Any]:
    for line in reversed(text.strip().splitlines()):
        try:
            value = json.loads(line)
        except ValueError:
            continue
        if isinstance(value, dict):
            return value
    return {}


def _shm_prefixes(module: Any, settings: PathSettings) -> tuple[str, ...]:
    """The /dev/shm name prefixes only this run of a path creates (a path may declare some)."""
    declare = getattr(module, "shm_prefixes", None)
    return tuple(declare(settings)) if declare is not None else ()


def run_path(settings: PathSettings, plan: dict, timeout_s: float) -> dict[str, Any]:
    """Measure one path in child processes; always reaps them and removes their shared memory."""
    module = load_path(settings.name)
    topology = module.TOPOLOGY
    spec = {"settings": dataclasses.asdict(settings), "plan": plan, "topology": topology}
    before = shm_entries()
    processes: list[subprocess.Popen[str]] = []
    outputs: list[dict[str, Any]] = []
    start = time.monotonic()
    try:
        if topology == "pair":
            ctrl_r, ctrl_w = os.pipe()
            ack_r, ack_w = os.pipe()
            try:
                processes.append(_spawn("recv", spec, (ctrl_r, ack_w)))
                processes.append(_spawn("send", spec, (ctrl_w, ack_r)))
            finally:
                for fd in (ctrl_r, ctrl_w, ack_r, ack_w):  # the children hold their own copies
                    os.close(fd)
        else:
            processes.append(_spawn("both", spec))
        for process in reversed(processes):  # the sender finishes first, then the receiver
            left = max(timeout_s - (time.monotonic() - start), 1.0)
            outputs.append(_last_json(_reap(process, left)))
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
            process.wait()
        reported = [path for output in outputs for path in output.get("shm_files", [])]
        removed = remove_leftovers(before, reported, [p.pid for p in processes],
                                   _shm_prefixes(module, settings))
    result = outputs[0] if outputs else {}
    if not result:
        result = {"error": f"child exited with {processes[-1].returncode} and no result"
                  if processes else "no child started"}
    if time.monotonic() - start >= timeout_s and "latency" not in result:
        result.setdefault("error", f"timed out after {timeout_s:.0f} s")
    result["wall_s"] = time.monotonic() - start
    result["shm_removed"] = removed
    return result
