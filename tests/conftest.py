"""Suite-wide set-up: a project-local Warp kernel cache shared by every test and child process,
and a guard that fails the run if a test leaves shared memory or child processes behind."""

from __future__ import annotations

import itertools
import os
import pathlib
import re
import uuid

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
# Before anything imports warp: children inherit the variable, so kernels compile once per machine.
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))


def _cuda_available() -> bool:
    try:
        from warp_buffer import init_warp  # quiet: no Warp banner in the test report

        wp = init_warp()
        return wp.get_cuda_device_count() > 0
    except Exception:
        return False


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze what collection imported (torch, Warp, Zenoh, NumPy, our packages: ~250,000
    objects): the leak guards below call ``gc.collect()`` after every test, which otherwise walks
    all of them (~100 ms a call, minutes over the suite). Objects the tests create stay
    collectable, unless they end up in a garbage cycle with a frozen object (none in practice:
    the guards would then report a leak, never hide one)."""
    import gc

    while gc.collect():  # finalizers may free more: freeze only what is really alive
        pass
    gc.freeze()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if _cuda_available():
        return
    skip_cuda = pytest.mark.skip(reason="no CUDA device on this machine")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip_cuda)


# --------------------------------------------------------------------------- isolation
# Domain ids of this run: a block of its own per process, so concurrent runs (another checkout's
# suite, a demo) do not share a ROS domain with ours; topics are unique names as well.
_domains = itertools.count(1000 + os.getpid() % 4000 * 50)


@pytest.fixture
def domain() -> int:
    """A ROS domain id used by this test alone."""
    return next(_domains)


@pytest.fixture
def topic(request: pytest.FixtureRequest) -> str:
    """A topic name used by this test alone (its module in the name, for reading logs)."""
    return f"/{request.module.__name__.rsplit('.', 1)[-1]}/t_{uuid.uuid4().hex[:10]}"


@pytest.fixture
def sigint_raises():
    """SIGINT raises KeyboardInterrupt in this process during the test, as under a terminal. A
    suite started from a background job (nohup, &, some CI runners) inherits an ignored SIGINT,
    and Python then installs no handler of its own: a test that sends itself SIGINT needs it."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


# --------------------------------------------------------------------------- leak guard
SHM_DIR = pathlib.Path("/dev/shm")
# Long-lived helpers the standard library starts once per session on purpose.
_ALLOWED_CHILDREN = ("resource_tracker", "forkserver", "semaphore_tracker")
# Names the library used to give shared memory (/dev/shm/warp_buffer.<uid>.<pid>-...). The arena
# design names nothing, so any such file of this process is a regression. Files of other
# processes (a concurrent run, another checkout of the library) are theirs: never counted.
_OWNER = re.compile(r"^warp_buffer\.\d+\.(\d+)[-.]")


def _our_shm_files() -> set[str]:
    """Files in /dev/shm named by this library for this very process."""
    me = str(os.getpid())
    try:
        names = [p.name for p in SHM_DIR.iterdir() if p.name.startswith("warp_buffer")]
    except OSError:
        return set()
    return {n for n in names if (m := _OWNER.match(n)) is not None and m.group(1) == me}


def _is_leak(name: str) -> bool:
    return True  # _our_shm_files only reports this process's own


def _child_processes() -> dict[int, str]:
    """Live (non-zombie) processes whose parent is this test process, with their command line."""
    me = str(os.getpid())
    children = {}
    for entry in pathlib.Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        state, ppid = fields[0], fields[1]
        if ppid == me and state != "Z" and not any(a in cmdline for a in _ALLOWED_CHILDREN):
            children[int(entry.name)] = cmdline.strip()
    return children


def _release_idle_pool_blocks() -> None:
    """Give back the Warp pool's idle blocks now: the pool keeps them for a while on purpose
    (steady-state publishing allocates nothing), which is not a leak."""
    import gc
    import sys

    warp_buffer = sys.modules.get("warp_buffer")
    if warp_buffer is not None:
        gc.collect()
        warp_buffer.trim_pools(0.0)


@pytest.fixture(autouse=True)
def no_leaks(request: pytest.FixtureRequest):
    """Fail a test that leaves a shared-memory export or a child process behind, then clean up
    so that one leak does not fail every later test."""
    import signal
    import time

    shm_before = _our_shm_files()
    children_before = set(_child_processes())
    yield
    _release_idle_pool_blocks()
    deadline = time.monotonic() + 3.0
    while True:  # exports and children may take a moment to go after a clean shutdown
        leaked_shm = {name for name in _our_shm_files() - shm_before if _is_leak(name)}
        leaked_children = {p: c for p, c in _child_processes().items() if p not in children_before}
        if (not leaked_shm and not leaked_children) or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    for pid in leaked_children:
        try:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
    for name in leaked_shm:
        try:
            (SHM_DIR / name).unlink()
        except OSError:
            pass
    problems = []
    if leaked_shm:
        problems.append(f"shared memory left in /dev/shm: {sorted(leaked_shm)}")
    if leaked_children:
        problems.append(f"child processes left running: {leaked_children}")
    if problems:
        pytest.fail(f"{request.node.nodeid} leaked: " + "; ".join(problems), pytrace=False)


_session_shm_before: set[str] = set()


def pytest_sessionstart(session: pytest.Session) -> None:
    _session_shm_before.update(_our_shm_files())


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Catch leaks of module- and session-scoped fixtures, which the per-test guard cannot see."""
    leaked = {name for name in _our_shm_files() - _session_shm_before if _is_leak(name)}
    children = _child_processes()
    if leaked or children:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.write_line(
                f"LEAK after the session: shm={sorted(leaked)} children={children}", red=True
            )


@pytest.fixture
def warp_pool_drained():
    """Fail a test that leaves a warp buffer alive: after it, every pooled block must go back.

    Modules that allocate warp buffers use it for every test (``pytest.mark.usefixtures``), which
    also keeps the /dev/shm leak guard exact."""
    import gc
    import time

    import warp_buffer

    yield
    deadline = time.monotonic() + 3.0
    while True:  # a block leaves the pool once its buffer is collected (may take a GC pass)
        gc.collect()
        warp_buffer.trim_pools(0.0)
        stats = list(warp_buffer.pool_stats().values())
        if all(s["leased"] == 0 and s["free_blocks"] == 0 for s in stats):
            return
        if time.monotonic() > deadline:
            pytest.fail(f"warp buffers still alive after the test: {stats}")
        time.sleep(0.02)


# --------------------------------------------------------------------------- iceoryx2 leak guard
# The fast lane's iceoryx2 files carry a prefix naming its domain (buffer_pubsub._iox2); this run
# gets a domain of its own, inherited by the processes its tests start, so the guard judges only
# files this run created, never those of other iceoryx2 programs or concurrent test runs.
_OWN_LANE_DOMAIN = "WARP_BUFFER_FAST_LANE_DOMAIN" not in os.environ
os.environ.setdefault("WARP_BUFFER_FAST_LANE_DOMAIN", f"t{os.getpid()}")
IOX2_ROOT = pathlib.Path("/tmp/iceoryx2")


def lane_files() -> set[str]:
    """Our run's iceoryx2 files in /dev/shm and under iceoryx2's root, but the 16-byte
    ``global_mgmt`` segment iceoryx2 keeps per domain on purpose (removed at session end)."""
    from buffer_pubsub._iox2 import resource_prefix

    prefix = resource_prefix()
    found = {p.name for p in _listdir(SHM_DIR) if p.name.startswith(prefix)}
    for root, _dirs, files in os.walk(IOX2_ROOT):
        found.update(os.path.join(root, f) for f in files if f.startswith(prefix))
    return {name for name in found if not name.endswith(".global_mgmt")}


def _listdir(path: pathlib.Path) -> list[pathlib.Path]:
    try:
        return list(path.iterdir())
    except OSError:
        return []


def _remove_lane_files(names: set[str]) -> None:
    from buffer_pubsub._iox2 import cleanup_dead_nodes

    cleanup_dead_nodes()
    for name in names:
        try:
            (SHM_DIR / name if "/" not in name else pathlib.Path(name)).unlink()
        except OSError:
            pass


@pytest.fixture(autouse=True)
def no_lane_leaks(request: pytest.FixtureRequest):
    """Fail a test after which iceoryx2 files of this run remain that were not there before."""
    import time

    import sys

    before = lane_files()
    yield
    iox2 = sys.modules.get("buffer_pubsub._iox2")
    if iox2 is not None:  # this process's own node lives as long as the process, like the pool
        iox2.close_node()
    deadline = time.monotonic() + 3.0
    while True:  # a reaped child's node may take a moment to go
        leaked = lane_files() - before
        if not leaked or time.monotonic() > deadline:
            break
        # What the next lane process would do: iceoryx2's dead-node clean-up (a SIGKILLed
        # child leaves its node's files to it). Files of live nodes stay and fail the test.
        from buffer_pubsub._iox2 import cleanup_dead_nodes

        cleanup_dead_nodes()
        time.sleep(0.05)
    if leaked:
        _remove_lane_files(leaked)
        pytest.fail(f"{request.node.nodeid} leaked iceoryx2 files: {sorted(leaked)}", pytrace=False)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config: pytest.Config) -> None:
    """Remove the ``global_mgmt`` segment of this run's lane domain (nothing else uses it)."""
    if not _OWN_LANE_DOMAIN:
        return
    from buffer_pubsub._iox2 import resource_prefix

    prefix = resource_prefix()
    for path in _listdir(SHM_DIR):
        if path.name.startswith(prefix) and path.name.endswith(".global_mgmt"):
            path.unlink(missing_ok=True)
