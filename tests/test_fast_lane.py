"""The fast lane with real processes: order, no loss, doorbell wake-ups, nothing left after a
crash, the switch, and a typed error naming the remedy when the native core is missing."""

from __future__ import annotations

import contextlib
import os
import pathlib
import queue
import signal
import subprocess
import sys
import threading
import time
import uuid

import pytest

from buffer_pubsub import fast_lane
from tests._reliability_helpers import wait_until
from tests.conftest import lane_files

CHILD = pathlib.Path(__file__).with_name("_lane_child.py")
ROOT = CHILD.parent.parent


class Peer:
    """A lane child process whose stdout lines the test reads with a timeout."""

    def __init__(self, *args: str, env: dict[str, str] | None = None) -> None:
        self.process = subprocess.Popen(
            [sys.executable, str(CHILD), *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            text=True, cwd=ROOT, env={**os.environ, **(env or {})})
        self._lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self._lines.put(line.strip())
        self._lines.put(None)

    def line(self, timeout: float = 10.0) -> str:
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"no output from {self.process.args[2:]} in {timeout} s") from None
        if line is None:
            raise AssertionError(f"{self.process.args[2:]} exited ({self.process.wait()})")
        return line

    def send(self, text: str) -> None:
        self.process.stdin.write(text + "\n")
        self.process.stdin.flush()

    def finish(self, timeout: float = 10.0) -> int:
        with contextlib.suppress(OSError):
            self.process.stdin.close()
        return self.process.wait(timeout)

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        self._reader.join(timeout=5)
        for stream in (self.process.stdin, self.process.stdout):
            with contextlib.suppress(OSError):
                stream.close()


@contextlib.contextmanager
def peers():
    """Every Peer made inside is reaped, whatever happens."""
    started: list[Peer] = []

    def start(*args: str, **kwargs) -> Peer:
        peer = Peer(*args, **kwargs)
        started.append(peer)
        return peer

    try:
        yield start
    finally:
        for peer in started:
            peer.kill()


def reader_and_writer(start, name: str, count: int, interval_s: str = "0",
                      depth: str = "16") -> tuple[Peer, Peer]:
    """A reader process, ready, then a writer process that writes ``count`` messages."""
    reader = start("reader", name, depth)
    assert reader.line() == "ready"
    return reader, start("writer", name, str(count), interval_s)


def route() -> str:
    return fast_lane.service_name(f"0/test_{uuid.uuid4().hex[:8]}/T/H", os.urandom(16))


def test_order_and_no_loss_between_processes() -> None:
    name = route()
    with peers() as start:
        # ~1 kHz, within the reader's pace
        reader, writer = reader_and_writer(start, name, 200, "0.001", depth="64")
        got = [reader.line() for _ in range(200)]
        assert got == [f"msg m{i}" for i in range(200)]
        assert writer.line() == "done"
        writer.send("stop")
        assert writer.finish() == 0
        assert reader.finish() == 0


def test_idle_reader_sleeps_and_wakes_by_event() -> None:
    """A reader blocked in ``wait(None)`` uses no CPU while idle (a busy-poll would burn ~1 s
    of it) and wakes at once for a message: no timeout can be what delivers it."""
    name = route()
    with peers() as start:
        reader, writer = reader_and_writer(start, name, 0)
        assert writer.line() == "done"
        writer.send("cpu?")
        cpu_before = float(reader.line().split()[1])
        time.sleep(1.0)
        sent = time.monotonic()
        writer.send("cpu?")
        cpu_after = float(reader.line().split()[1])
        assert time.monotonic() - sent < 0.5
        assert cpu_after - cpu_before < 0.1, f"idle reader used {cpu_after - cpu_before:.3f} s"
        writer.send("stop")
        assert writer.finish() == 0 and reader.finish() == 0


def _bound(name: str) -> bool:
    """Is the abstract socket of lane ``name``'s reader bound (by any process)?"""
    wanted = "@" + fast_lane.address(name)[1:].decode()
    with open("/proc/net/unix", encoding="ascii", errors="replace") as table:
        return any(line.split()[-1] == wanted for line in table if line.count(" ") >= 7)


def _maps_files(pid: int) -> set[str]:
    """The named files process ``pid`` maps shared from /dev/shm or /tmp (named memory a crash
    could leave). Private mappings are not that: a checkout under /tmp maps its libraries."""
    found = set()
    with open(f"/proc/{pid}/maps", encoding="ascii", errors="replace") as maps:
        for line in maps:
            fields = line.split(maxsplit=5)
            path = fields[5].strip() if len(fields) == 6 else ""
            if "s" in fields[1] and path.startswith(("/dev/shm/", "/tmp/")):
                found.add(path)
    return found


def test_sigkilled_writer_is_cleaned_and_reader_goes_on() -> None:
    """The reader lets a SIGKILLed writer's ring go (its connection hung up) and serves the
    next writer; nothing of the dead writer remains in either process or in /dev/shm."""
    name = route()
    with peers() as start:
        reader, writer = reader_and_writer(start, name, 3)
        assert [reader.line() for _ in range(3)] == ["msg m0", "msg m1", "msg m2"]
        assert len(lane_files(reader.process.pid)) == 1  # the writer's ring
        assert not _maps_files(reader.process.pid) and not _maps_files(writer.process.pid)
        writer.kill()  # SIGKILL: the kernel closes its end, the reader drops the ring
        assert wait_until(lambda: not lane_files(reader.process.pid))
        second = start("writer", name, "1", "0")  # the reader serves a new writer
        assert reader.line() == "msg m0"
        assert len(lane_files(reader.process.pid)) == 1
        second.send("stop")
        assert second.finish() == 0 and reader.finish() == 0
    assert not _bound(name)


def test_sigkilled_reader_and_writer_leave_nothing() -> None:
    name = route()
    with peers() as start:
        reader, writer = reader_and_writer(start, name, 1)
        assert reader.line() == "msg m0"
        assert _bound(name)
        assert not _maps_files(reader.process.pid) and not _maps_files(writer.process.pid)
        reader.process.send_signal(signal.SIGKILL)
        writer.process.send_signal(signal.SIGTERM)  # Python's default: dies without cleanup
        reader.kill()
        writer.kill()
    # Nothing to clean up: the kernel took the rings, doorbells and the socket name.
    assert not _bound(name)


def test_mappings_do_not_grow_with_messages_or_readers_coming_and_going() -> None:
    before = lane_files()
    name = route()
    reader = fast_lane.LaneReader(name, depth=4)
    writer = fast_lane.LaneWriter(name)
    for i in range(2000):
        assert writer.write(b"x" * (i % 600))
        assert reader.take() == b"x" * (i % 600)
    steady = lane_files()
    assert len(steady - before) == 2  # the writer's ring, and the reader's mapping of it
    writer.close()
    reader.close()
    assert lane_files() == before
    with peers() as start:  # reader processes joining and leaving a writer in this process
        for _ in range(3):
            name = route()
            peer = start("reader", name, "16")
            assert peer.line() == "ready"
            lane = fast_lane.LaneWriter(name)
            lane.write(b"hello")
            assert peer.line() == "msg hello"
            lane.write(b"stop")
            assert peer.finish() == 0
            assert not lane.write(b"to nobody")  # the reader closed its end
            lane.close()
            assert lane_files() == before


def test_writer_without_reader_is_unavailable_and_oversize_is_refused() -> None:
    with pytest.raises(fast_lane.LaneUnavailableError, match="no lane reader"):
        fast_lane.LaneWriter(route())
    name = route()
    reader = fast_lane.LaneReader(name)
    writer = fast_lane.LaneWriter(name, max_payload=64)
    try:
        assert writer.fits(64) and not writer.fits(65)
        with pytest.raises(fast_lane.LaneError, match="exceeds"):
            writer.write(b"x" * 65)
        assert writer.write(bytearray(b"y" * 64)) and reader.take() == b"y" * 64
        assert writer.write(b"head", memoryview(b"-body-"), bytearray(b"tail"))
        assert reader.take() == b"head-body-tail"
        with pytest.raises(fast_lane.LaneError, match="exceeds"):
            writer.write(b"x" * 60, b"y" * 5)
        with pytest.raises(fast_lane.LaneUnavailableError, match="cannot create"):
            fast_lane.LaneReader(name)  # one reader per route
    finally:
        writer.close()
        reader.close()
    with pytest.raises(fast_lane.LaneError, match="closed"):
        writer.write(b"late")


def test_waker_notify_attach_and_close_from_other_threads() -> None:
    waker = fast_lane.LaneWaker()
    name = route()
    reader = fast_lane.LaneReader(name)
    writer = fast_lane.LaneWriter(name)
    got: list[bytes] = []
    try:
        threading.Timer(0.05, waker.notify).start()
        started = time.monotonic()
        waker.wait(5.0)
        assert time.monotonic() - started < 1.0  # woken by notify, not the timeout
        writer.write(b"early")  # written before the attachment: delivered when it applies
        threading.Timer(0.05, waker.attach, (reader, got.append)).start()
        waker.wait(5.0)
        assert got == [b"early"]
        threading.Timer(0.05, writer.write, (b"late",)).start()
        waker.wait(5.0)
        assert got == [b"early", b"late"]
        waker.detach(reader)
        waker.wait(0.0)
        writer.write(b"after detach")
        waker.wait(0.1)
        assert got == [b"early", b"late"]
        waker.attach(reader, got.append)
        waker.wait(0.0)  # the message written while detached arrives on re-attachment
        assert got == [b"early", b"late", b"after detach"]
        waker.detach(reader, close=True)
        waker.wait(0.0)
        assert reader.listener is None and reader.take() is None  # closed by the waker
        assert not writer.write(b"to a closed reader")
        threading.Timer(0.05, waker.close).start()
        waker.wait(5.0)  # close while waiting: the waiting thread releases the eventfd
        waker.wait(5.0)  # closed: returns at once
        assert time.monotonic() - started < 4.0
    finally:
        waker.close()
        writer.close()
        reader.close()


def test_busy_poll_delivers_without_blocking() -> None:
    waker = fast_lane.LaneWaker(busy_poll_s=0.2)
    name = route()
    reader, writer = fast_lane.LaneReader(name), fast_lane.LaneWriter(name)
    got: list[bytes] = []
    try:
        waker.attach(reader, got.append)
        waker.wait(0.0)
        threading.Timer(0.02, writer.write, (b"spun",)).start()
        waker.wait(1.0)
        assert got == [b"spun"]
    finally:
        waker.close()
        writer.close()
        reader.close()


@pytest.mark.usefixtures("sigint_raises")
@pytest.mark.parametrize("attached", [False, True], ids=["no-reader", "reader"])
def test_ctrl_c_interrupts_a_wait(attached: bool) -> None:
    """A KeyboardInterrupt ends a wait at once, with or without a reader attached; the waker
    still works after."""
    waker = fast_lane.LaneWaker()
    reader = fast_lane.LaneReader(route())
    timer = threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT))
    try:
        if attached:
            waker.attach(reader, lambda _: None)
            waker.wait(0.0)
        started = time.monotonic()
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            waker.wait(5.0)
            time.sleep(1.0)  # a signal handled after the wait would still raise here
        assert time.monotonic() - started < 1.0
        threading.Timer(0.05, waker.notify).start()
        started = time.monotonic()
        waker.wait(5.0)  # the next notify wakes the next wait
        assert time.monotonic() - started < 1.0
        waker.wait(-0.5)  # a deadline already past returns at once, in either mode
    finally:
        timer.cancel()
        waker.close()
        reader.close()


def test_service_name_is_stable_and_hashed_when_too_long() -> None:
    gid = bytes(range(16))
    short = fast_lane.service_name("0/t/T/H", gid)
    assert short == "warp_buffer/0/t/T/H/_buf/" + gid.hex()
    long = fast_lane.service_name("0/" + "t" * 300 + "/T/H", gid)
    assert long == fast_lane.service_name("0/" + "t" * 300 + "/T/H", gid)
    assert long.startswith("warp_buffer/sha256/") and len(long) < 100
    assert fast_lane.service_name("0/é/T/H", gid).startswith("warp_buffer/sha256/")


def test_switch_off() -> None:
    assert not fast_lane.enabled(False) and fast_lane.enabled(True)
    code = ("from buffer_pubsub import fast_lane as f; s = f.status(); "
            "assert not s.available and 'turned off' in s.reason, s; "
            "assert f.status(True).available")
    for off in ("0", "false", "OFF"):
        env = {**os.environ, "WARP_BUFFER_FAST_LANE": off}
        subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, check=True, timeout=30)


def test_a_missing_native_core_is_a_typed_error_naming_the_remedy() -> None:
    """Without its native extension the lane does not import: one typed error (also an
    ImportError) that names the extension and says how to build it."""
    code = ("import sys\n"
            "sys.modules['buffer_pubsub._ring'] = None  # as if it were never built\n"
            "from rosidl_buffer.errors import NativeExtensionMissingError\n"
            "try:\n"
            "    import buffer_pubsub\n"
            "except NativeExtensionMissingError as error:\n"
            "    assert isinstance(error, ImportError)\n"
            "    print(error)\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                            text=True, timeout=60, check=True)
    assert "buffer_pubsub._ring" in result.stdout and "pip install" in result.stdout, result


def test_an_off_lane_gives_its_reason_logged_once(monkeypatch, caplog) -> None:
    monkeypatch.setenv(fast_lane.ENV_SWITCH, "0")
    monkeypatch.setattr(fast_lane, "_logged", False)
    with caplog.at_level("INFO", logger="buffer_pubsub.fast_lane"):
        first, second = fast_lane.status(), fast_lane.status()
    assert not first.available and "turned off" in first.reason and second == first
    assert [r.getMessage() for r in caplog.records].count(
        f"fast lane off, Zenoh carries same-host messages: {first.reason}") == 1


def test_info_says_whether_the_lane_runs() -> None:
    import json

    command = [sys.executable, "-m", "warp_buffer_cli.main", "info", "--json"]
    off = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60, check=True,
                         env={**os.environ, "WARP_BUFFER_FAST_LANE": "0"})
    lane = json.loads(off.stdout)["fast_lane"]
    assert lane["available"] is False and "turned off" in lane["reason"]
    on = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60, check=True)
    lane = json.loads(on.stdout)["fast_lane"]
    assert lane["available"] is True and lane["resource_prefix"] == fast_lane.resource_prefix()


def test_exit_without_closing_leaves_nothing() -> None:
    """A process that exits with its lane objects open, a daemon thread blocked in the waker,
    leaves nothing behind (its socket name gone; it named no memory)."""
    name = route()
    code = (
        "import threading, time\n"
        "from buffer_pubsub import fast_lane as f\n"
        f"name = {name!r}\n"
        "reader, waker = f.LaneReader(name), f.LaneWaker()\n"
        "writer = f.LaneWriter(name)\n"
        "got = []\n"
        "waker.attach(reader, got.append)\n"
        "threading.Thread(target=lambda: [waker.wait(None) for _ in range(100)],"
        " daemon=True).start()\n"
        "writer.write(b'x')\n"
        "deadline = time.monotonic() + 5\n"
        "while not got and time.monotonic() < deadline: time.sleep(0.01)\n"
        "assert got == [b'x'], got\n"
        "maps = open('/proc/self/maps').read()\n"
        "assert '/dev/shm/' not in maps and 'memfd:warp_buffer_lane' in maps\n")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=30)
    assert not _bound(name)


def test_frozen_reader_never_blocks_the_writer_and_keeps_the_last_depth() -> None:
    """Keep-last: a SIGSTOPped reader's queue drops its oldest messages; write() never waits
    for it (a keep-last publisher must not stall behind a frozen subscriber)."""
    name = route()
    with peers() as start:
        reader = start("reader", name, "8")
        assert reader.line() == "ready"
        writer = fast_lane.LaneWriter(name)
        try:
            reader.process.send_signal(signal.SIGSTOP)
            started = time.monotonic()
            for i in range(100):
                writer.write(f"m{i}".encode())
            assert time.monotonic() - started < 2.0
            reader.process.send_signal(signal.SIGCONT)
            writer.write(b"stop")
            assert reader.finish() == 0
            lines = []
            while (line := reader._lines.get(timeout=5)) is not None:
                lines.append(line)
        finally:
            writer.close()
    assert 1 <= len(lines) <= 8 and lines[-1] == "msg m99", lines


def test_a_forked_child_leaves_its_parents_lane_alone() -> None:
    """A child forked from a process with lane ends, which then uses the lane and closes what it
    inherited, must not close the parent's ends (the ring says "closed" to the other side) nor
    write into the parent's ring."""
    name = route()
    reader = fast_lane.LaneReader(name)
    writer = fast_lane.LaneWriter(name)
    try:
        pid = os.fork()
        if pid == 0:  # the child: a lane of its own, then it closes everything
            code = 1
            try:
                other = route()
                own_reader = fast_lane.LaneReader(other)
                own = fast_lane.LaneWriter(other)
                assert own.write(b"mine") and own_reader.take() == b"mine"
                try:
                    writer.write(b"from the child")
                except fast_lane.LaneError:
                    pass
                else:
                    raise AssertionError("the child wrote into its parent's ring")
                for end in (own, own_reader, writer, reader):
                    end.close()
                code = 0
            finally:
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        assert writer.write(b"after the child") and reader.take() == b"after the child"
    finally:
        writer.close()
        reader.close()


@pytest.mark.parametrize("attached", [False, True], ids=["no-reader", "reader"])
def test_waker_wakes_for_every_notify_and_idles_after_them(attached: bool) -> None:
    """With or without a reader attached, and while readers come and go, each notify wakes the
    sleeping waiter at once, and no stale wake-up is left to make the next idle wait return
    early (a busy loop)."""
    waker = fast_lane.LaneWaker()
    reader = fast_lane.LaneReader(route())
    acked = threading.Event()
    stop = threading.Event()

    def waiter() -> None:
        while not stop.is_set():
            waker.wait(3.0)  # a lost wake-up costs this whole timeout
            acked.set()

    thread = threading.Thread(target=waiter)
    try:
        if attached:
            waker.attach(reader, lambda _: None)
        thread.start()
        worst = 0.0
        for i in range(60):
            if i % 10 == 5:  # switch modes between notifies
                waker.detach(reader) if attached else waker.attach(reader, lambda _: None)
                attached = not attached
                time.sleep(0.01)
            time.sleep(0.003)  # let the waiter fall asleep again
            acked.clear()
            started = time.monotonic()
            waker.notify()
            assert acked.wait(5.0)
            worst = max(worst, time.monotonic() - started)
        assert worst < 1.0, f"a notify took {worst:.2f} s to wake the waiter"
    finally:
        stop.set()
        waker.notify()
        thread.join(5)
    try:
        # a count left on the eventfd by a notify whose flag was already consumed: the poll
        # reports it once, the waker reads it, and the next idle wait sleeps its full timeout
        waker.attach(reader, lambda _: None)
        waker.wait(0.0)
        os.eventfd_write(waker.fd, 1)
        waker.wait(0.3)
        idle = time.monotonic()
        waker.wait(0.3)
        assert time.monotonic() - idle >= 0.25
    finally:
        waker.close()
        reader.close()


def test_close_wakes_a_wait_with_a_reader() -> None:
    """With a reader attached, a close from another thread wakes the wait, and the waiting
    thread releases the waker."""
    waker = fast_lane.LaneWaker()
    reader = fast_lane.LaneReader(route())
    try:
        waker.attach(reader, lambda _: None)
        waker.wait(0.0)
        threading.Timer(0.05, waker.close).start()
        started = time.monotonic()
        waker.wait(5.0)
        waker.wait(5.0)  # closed: returns at once
        assert time.monotonic() - started < 1.0
    finally:
        waker.close()
        reader.close()


def test_lane_ends_out_of_file_descriptors_are_unavailable_and_leak_none() -> None:
    """A waker, reader or writer that cannot get its descriptors is unavailable (the transport
    then uses Zenoh) and leaves none open."""
    code = (
        "import os, resource\n"
        "from buffer_pubsub import fast_lane as f\n"
        "name = 'warp_buffer/fd/' + os.urandom(4).hex()\n"
        "reader = f.LaneReader(name)\n"
        "spare = []\n"
        "try:\n"
        "    while True: spare.append(os.open('/dev/null', os.O_RDONLY))\n"
        "except OSError: pass\n"
        "def count():  # one descriptor lent to the listing, then taken back\n"
        "    os.close(spare.pop())\n"
        "    n = len(os.listdir('/proc/self/fd'))\n"
        "    spare.append(os.open('/dev/null', os.O_RDONLY))\n"
        "    return n\n"
        "before = count()\n"
        "for make in (f.LaneWaker, lambda: f.LaneWriter(name), lambda: f.LaneReader(name + 'x')):\n"
        "    try: make()\n"
        "    except f.LaneUnavailableError as error: print('UNAVAILABLE', error)\n"
        "    else: print('MADE')\n"
        "    assert count() == before\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                            text=True, timeout=60, check=True,
                            preexec_fn=lambda: __import__("resource").setrlimit(
                                __import__("resource").RLIMIT_NOFILE, (128, 128)))
    lines = result.stdout.splitlines()
    assert len(lines) == 3 and all(line.startswith("UNAVAILABLE") for line in lines), result


def test_a_node_out_of_file_descriptors_gets_a_typed_error_that_says_so() -> None:
    code = (
        "import resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_NOFILE, (200, 200))\n"
        "from buffer_pubsub import Node\n"
        "from rosidl_buffer import RosidlBufferError\n"
        "nodes = []\n"
        "try:\n"
        "    for i in range(1000):\n"
        "        node = Node(f'fds_{i}', domain_id=int(sys.argv[1]))\n"
        "        nodes.append(node)\n"
        "        node.create_subscription('tensor_msgs/msg/ExperimentalTensor', '/fds', lambda m: None,\n"
        "                                 acceptable_buffer_backends='warp')\n"
        "    print('NO LIMIT')\n"
        "except RosidlBufferError as error:\n"
        "    print('TYPED', type(error).__name__, error)\n"
        "finally:\n"
        "    for node in nodes:\n"
        "        node.close()\n")
    domain = 150 + os.getpid() % 80
    result = subprocess.run([sys.executable, "-c", code, str(domain)], capture_output=True,
                            text=True, timeout=120, cwd=pathlib.Path(__file__).parent.parent)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.startswith("TYPED"), (result.stdout, result.stderr[-2000:])
    assert "file descriptors" in result.stdout


def test_a_ring_is_an_owner_only_sealed_memfd_and_names_only_numbers() -> None:
    from buffer_pubsub import _ring

    ring = _ring.RingWriter(4)
    fd = ring.take_memfd()
    try:
        assert os.fstat(fd).st_mode & 0o077 == 0
        assert os.readlink(f"/proc/self/fd/{fd}").startswith("/memfd:warp_buffer_lane")
    finally:
        os.close(fd)
        ring.close()
    address = fast_lane.address("warp_buffer/some/route")
    assert address.startswith(f"\0warp_buffer.lane.{os.getuid()}.".encode())
    assert address[1:].decode().replace(".", "").replace("_", "").isalnum()


def test_an_unknown_lane_switch_value_warns_once_and_leaves_the_lane_on(monkeypatch, caplog):
    monkeypatch.setenv(fast_lane.ENV_SWITCH, "maybe")
    monkeypatch.setattr(fast_lane, "_warned_values", {})
    with caplog.at_level("WARNING", logger="buffer_pubsub.fast_lane"):
        assert fast_lane.enabled() and fast_lane.enabled()
    assert caplog.text.count("neither on") == 1
    monkeypatch.setenv(fast_lane.ENV_SWITCH, "Off")
    assert not fast_lane.enabled()


@pytest.mark.parametrize("lane", [True, False], ids=["lane-on", "lane-off"])
def test_every_node_waits_on_one_kind_of_waker_and_closes_its_own(domain, lane) -> None:
    """One waker: a node's executor waits on a LaneWaker whether the lane runs or not (there is
    no second, queue-based waker), and closing the node releases that waker's eventfd."""
    from buffer_pubsub import Node
    with Node("one_waker", domain_id=domain, fast_lane=lane) as node:
        waker = node.scheduler.waker
        assert type(waker) is fast_lane.LaneWaker
        assert waker.fd >= 0
        assert (node.lane is waker) == fast_lane.enabled(lane)
    assert waker.fd == -1


def test_a_users_own_waker_carries_no_lane_and_stays_open(domain) -> None:
    """``Node(waker=...)`` with something that only waits and notifies: the node uses it, runs
    no lane on it, and leaves it to its owner when it closes."""
    from buffer_pubsub import Node

    class Waker:
        def __init__(self) -> None:
            self.event, self.closed = threading.Event(), False

        def wait(self, timeout: float | None) -> None:
            self.event.wait(timeout)
            self.event.clear()

        def notify(self) -> None:
            self.event.set()

        def close(self) -> None:
            self.closed = True

    own = Waker()
    with Node("own_waker", domain_id=domain, waker=own) as node:
        assert node.scheduler.waker is own and node.lane is None
    assert not own.closed
