"""Two real "hosts" on one machine: Linux namespaces joined through ``warp-buffer router``.

Host A and host B each run in their own network, UTS, IPC and mount namespaces with a private
``/dev/shm``, host name and machine id (``tests/_two_hosts_helpers.py``); the only link between
them is a Zenoh router on a Unix socket. Each host runs a publisher and a subscriber that accepts
``warp`` on one topic: a subscriber must get its own host's frames by ``warp`` (zero-copy through
its host's /dev/shm) and the other host's frames as correct CPU bytes, each frame exactly once.
No test-only host or user override is involved. Skips, with the kernel's reason, where namespaces
cannot be made (unprivileged user, a container without CAP_SYS_ADMIN).
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import uuid
from collections.abc import Iterator

import pytest

from tests._two_hosts_helpers import SETUP_ERROR

ROOT = pathlib.Path(__file__).resolve().parent.parent
UNSHARE = ["unshare", "--net", "--uts", "--ipc", "--mount", "--propagation", "private", "--fork"]
COUNT = 8
TIMEOUT_S = 40.0

pytestmark = pytest.mark.multiprocess


def _namespaces_refused() -> str | None:
    """Why namespaces cannot be made here (None when they can)."""
    if shutil.which("unshare") is None or shutil.which("mount") is None:
        return "unshare(1) / mount(8) not installed"
    probe = subprocess.run([*UNSHARE, "mount", "-t", "tmpfs", "tmpfs", "/dev/shm"],
                           capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        return f"the kernel refused namespaces: {probe.stderr.strip() or probe.returncode}"
    return None


@pytest.fixture(scope="module")
def workdir() -> Iterator[pathlib.Path]:
    reason = _namespaces_refused()
    if reason is not None:
        pytest.skip(reason)
    path = pathlib.Path(tempfile.mkdtemp(prefix="wb2h_", dir="/tmp"))  # short: a socket lives here
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def _popen(argv: list[str]) -> subprocess.Popen[str]:
    # Own session: the test can kill a host with everything it started (killpg).
    return subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)


def _stop(process: subprocess.Popen[str], signum: int = signal.SIGKILL) -> None:
    if process.poll() is None:
        try:
            os.killpg(process.pid, signum)
        except ProcessLookupError:
            pass
    try:
        process.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()


@pytest.fixture(scope="module")
def exchange(workdir: pathlib.Path) -> dict[str, dict]:
    """Run both hosts once; every role's result, by role."""
    socket_path = workdir / "router.sock"
    router = _popen([sys.executable, "-m", "warp_buffer_cli.main", "router", "--listen",
                     f"unixsock-stream/{socket_path}"])
    hosts: list[subprocess.Popen[str]] = []
    marker = f"two_hosts_marker_{os.getpid()}_{uuid.uuid4().hex[:8]}"
    marker_path = pathlib.Path("/dev/shm") / marker
    marker_path.write_bytes(b"")
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        assert line.startswith("warp-buffer router"), line + router.stderr.read()
        domain = 100 + os.getpid() % 100
        for name, roles in (("host-a", "pub_a,sub_a"), ("host-b", "pub_b,sub_b")):
            hosts.append(_popen([
                *UNSHARE, sys.executable, "-m", "tests._two_hosts_helpers", "host", name,
                "--dir", str(workdir), "--router", f"unixsock-stream/{socket_path}",
                "--machine-id", uuid.uuid4().hex, "--roles", roles, "--domain", str(domain),
                "--count", str(COUNT), "--timeout", str(TIMEOUT_S)]))
        errors = []
        for host in hosts:
            try:
                _, err = host.communicate(timeout=TIMEOUT_S + 30)
            except subprocess.TimeoutExpired:
                _stop(host)
                err = "timed out"
            if host.returncode != 0:
                errors.append(f"host exited {host.returncode}: {err[-2000:]}")
        setup_errors = sorted(workdir.glob(f"*.{SETUP_ERROR}"))
        if setup_errors:
            pytest.skip("namespace set-up refused: " + setup_errors[0].read_text())
        assert not errors, errors
        found = {role: json.loads((workdir / f"{role}.json").read_text())
                 for role in ("pub_a", "pub_b", "sub_a", "sub_b")}
        found["marker"] = {"name": marker, "host_shm": os.listdir("/dev/shm")}
        return found
    finally:
        marker_path.unlink(missing_ok=True)
        for host in hosts:
            _stop(host)
        _stop(router, signal.SIGTERM)


def _by_publisher(result: dict) -> dict[int, list[dict]]:
    found: dict[int, list[dict]] = {}
    for record in result["records"]:
        found.setdefault(record["pub"], []).append(record)
    return found


def test_each_namespace_looks_like_another_host(exchange: dict[str, dict]) -> None:
    a = {exchange[r]["host_id"] for r in ("pub_a", "sub_a")}
    b = {exchange[r]["host_id"] for r in ("pub_b", "sub_b")}
    assert len(a) == 1 and len(b) == 1 and a != b
    assert exchange["sub_a"]["hostname"] == "host-a" and exchange["sub_b"]["hostname"] == "host-b"
    # Each host's /dev/shm is its own: the marker this test left in ours is in neither; and the
    # zero-copy arenas are anonymous memfds, so nothing of ours is named in any of them.
    shm_a, shm_b = set(exchange["pub_a"]["shm"]), set(exchange["pub_b"]["shm"])
    marker = exchange["marker"]["name"]
    assert marker in exchange["marker"]["host_shm"] and marker not in shm_a | shm_b
    assert not {n for n in shm_a | shm_b if n.startswith("warp_buffer")}


def test_same_host_subscriber_gets_warp_other_host_gets_cpu_bytes(
        exchange: dict[str, dict]) -> None:
    for sub, own_pub, other_pub in (("sub_a", 1, 2), ("sub_b", 2, 1)):
        assert exchange[sub]["matched"], sub
        frames = _by_publisher(exchange[sub])
        own, other = frames.get(own_pub, []), frames.get(other_pub, [])
        assert sorted(r["index"] for r in own) == list(range(COUNT)), (sub, own)
        assert sorted(r["index"] for r in other) == list(range(COUNT)), (sub, other)
        assert {r["backend"] for r in own} == {"warp"}, sub
        assert {r["backend"] for r in other} == {"cpu"}, sub
        assert all(r["ok"] for r in own + other), sub


def test_publisher_on_the_other_host_reaches_both(exchange: dict[str, dict]) -> None:
    assert exchange["pub_b"]["matched"] and exchange["pub_b"]["ready"]
    for sub in ("sub_a", "sub_b"):
        assert len(_by_publisher(exchange[sub]).get(2, [])) == COUNT
