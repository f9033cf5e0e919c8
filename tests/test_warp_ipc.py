"""warp_buffer.ipc, the IPC core: one sealed memfd arena per process handed over an abstract
socket, reads in place, OFD read locks as holds, generation-checked recycling, typed failures;
with real second processes (SIGKILL, SIGTERM, clean exit, holds, outrun, shrink attempts, and
``ulimit -n 1024`` on both sides)."""

from __future__ import annotations

import errno
import fcntl
import gc
import os
import json
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import threading
import time

import numpy as np
import pytest
import warp as wp

from rosidl_buffer import Buffer
from tests._warp_helpers import Child, checksum, expected_pattern, fill_pattern
from warp_buffer import (
    DescriptorError,
    ExportError,
    ExportBoundsError,
    HandleReleasedError,
    StaleBufferError,
    WriteHandleError,
    allocate_buffer,
    attach,
    descriptor,
    from_input_buffer,
    from_output_buffer,
    handoff,
    ipc,
)
from warp_buffer.arena import SEALS, current_arena

pytestmark = [pytest.mark.multiprocess, pytest.mark.usefixtures("warp_pool_drained")]


def _published(nbytes: int = 8192, seed: int = 7, peer=None):
    buffer = allocate_buffer(nbytes, "cpu")
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, seed)
    return buffer, ipc.export_buffer(buffer, peer=peer)


def _with(desc, **changes):
    values = dict(zip(descriptor.FIELDS, descriptor.values_of(desc)))
    values.update(changes)
    return descriptor.make(tuple(values[name] for name in descriptor.FIELDS))


def _ours_in_dev_shm(pid: int) -> list[str]:
    return [n for n in os.listdir("/dev/shm") if n.startswith("warp_buffer") and f".{pid}" in n]


def _memfd_fds() -> int:
    count = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            count += os.readlink(f"/proc/self/fd/{fd}").startswith("/memfd:warp_buffer")
        except OSError:
            pass
    return count


# --------------------------------------------------------------------------- in one process
def test_descriptor_names_the_arena_by_numbers_and_its_layout_is_one_struct():
    buffer, desc = _published()
    arena = current_arena()
    assert desc.owner_pid == os.getpid() and desc.session == arena.session
    assert desc.kind == descriptor.KIND_HOST and 0 < desc.size <= desc.capacity
    assert arena.geometry.check_block(desc.offset, desc.capacity) is None
    assert fcntl.fcntl(arena.fd, fcntl.F_GET_SEALS) & SEALS == SEALS
    assert os.readlink(f"/proc/self/fd/{arena.fd}").startswith("/memfd:warp_buffer")
    assert descriptor.unpack(descriptor.pack(desc)) == desc
    assert not _ours_in_dev_shm(os.getpid())  # nothing has a name


def test_import_in_process_reads_the_same_bytes_read_only_and_release_ends_access():
    buffer, desc = _published(8192, seed=3)
    imported = ipc.import_buffer(desc)
    assert imported.is_imported and imported.device == "cpu"
    assert imported.array.ptr == buffer.get_impl().array.ptr  # zero copies: the same pages
    np.testing.assert_array_equal(imported.to_cpu().view(), expected_pattern(8192, 3))
    with pytest.raises(WriteHandleError):  # imports are read-only through the API
        from_output_buffer(Buffer(imported))
    received = Buffer(imported)
    with received:
        assert received.to_numpy()[0] == expected_pattern(8, 3)[0]
    assert imported.is_released
    with pytest.raises(HandleReleasedError):
        from_input_buffer(received)
    with pytest.raises(HandleReleasedError):
        imported.to_cpu()


def test_a_held_block_is_never_recycled_and_is_reused_once_released():
    buffer, desc = _published(5000)
    block = buffer.get_impl().block
    imported = ipc.import_buffer(desc)  # a read lock on the block
    del buffer
    gc.collect()
    other = allocate_buffer(5000, "cpu")
    assert other.get_impl().block is not block
    np.testing.assert_array_equal(imported.to_cpu().view(), expected_pattern(5000, 7))
    imported.release()  # the hold goes now, not at garbage collection
    del other
    gc.collect()
    again = allocate_buffer(5000, "cpu")
    assert again.get_impl().block is block
    with pytest.raises(StaleBufferError):  # the old descriptor names a recycled block
        ipc.import_buffer(desc)


def test_a_descriptor_on_its_way_pins_its_block_until_that_peer_imports_it_or_a_later_one():
    peer = ipc.peer_slot(b"peer-in-flight", os.getpid())
    try:
        first, d1 = _published(3000, peer=peer)
        block = first.get_impl().block
        del first
        gc.collect()
        second = allocate_buffer(3000, "cpu")  # d1 not imported yet: its block is not reused
        assert second.get_impl().block is not block
        d2 = ipc.export_buffer(second)  # not for that peer: no accounting
        d3 = ipc.export_buffer(allocate_buffer(3000, "cpu"), peer=peer)
        ipc.import_buffer(d3).release()  # a later delivery imported: d1 was dropped (keep-last)
        del second, d2
        gc.collect()
        third = allocate_buffer(3000, "cpu")
        assert third.get_impl().block is block
        with pytest.raises(StaleBufferError):
            ipc.import_buffer(d1)
    finally:
        ipc.forget_peer(b"peer-in-flight")


def test_a_forgotten_peer_pins_nothing():
    peer = ipc.peer_slot(b"peer-gone", os.getpid())
    buffer, _desc = _published(3000, peer=peer)
    block = buffer.get_impl().block
    del buffer
    gc.collect()
    assert allocate_buffer(3000, "cpu").get_impl().block is not block
    ipc.forget_peer(b"peer-gone")  # the transport reports the subscription's departure
    gc.collect()
    assert allocate_buffer(3000, "cpu").get_impl().block is block


def test_a_peer_whose_process_died_pins_nothing():
    dead = 4_000_000
    while os.path.exists(f"/proc/{dead}"):
        dead -= 1
    peer = ipc.peer_slot(b"peer-dead", dead)
    try:
        buffer, _desc = _published(3000, peer=peer)
        block = buffer.get_impl().block
        del buffer
        gc.collect()
        time.sleep(0.15)  # liveness is checked at most every 100 ms
        first = allocate_buffer(3000, "cpu")  # finds the block pinned, forgets the dead peer
        again = first if first.get_impl().block is block else allocate_buffer(3000, "cpu")
        assert again.get_impl().block is block
    finally:
        ipc.forget_peer(b"peer-dead")


def test_out_of_bounds_and_malformed_descriptors_raise_typed_errors():
    buffer, desc = _published(4096)
    bounds = [dict(size=desc.capacity + 1), dict(size=0), dict(offset=desc.offset + 100),
              dict(capacity=12345), dict(capacity=1 << 50), dict(offset=1 << 60)]
    for change in bounds:
        with pytest.raises(ExportBoundsError):
            ipc.import_buffer(_with(desc, **change))
    malformed = [dict(version=1), dict(kind=9), dict(owner_pid=0), dict(session=0),
                 dict(generation=0), dict(peer_slot=5000)]
    for change in malformed:
        with pytest.raises(DescriptorError):
            ipc.import_buffer(_with(desc, **change))
    with pytest.raises(DescriptorError):
        ipc.import_buffer(_with(desc, size="big"))
    with pytest.raises(DescriptorError):
        ipc.import_buffer(object())
    with pytest.raises(StaleBufferError):
        ipc.import_buffer(_with(desc, generation=desc.generation + 1))


def test_an_unknown_or_dead_session_is_stale():
    buffer, desc = _published()
    with pytest.raises(StaleBufferError):
        ipc.import_buffer(_with(desc, session=desc.session ^ 1))
    with pytest.raises(StaleBufferError):
        ipc.import_buffer(_with(desc, owner_pid=os.getpid() + 1 if os.getpid() < 4000000 else 2))


# --------------------------------------------------------------------------- other processes
def test_second_process_reads_in_place_holds_the_block_and_is_sigkilled_without_leaking():
    nbytes = 1 << 20
    buffer, desc = _published(nbytes, seed=42)
    block = buffer.get_impl().block
    arena = current_arena()
    with Child("import", {"descriptors": [descriptor.pack(desc).hex()]}) as child:
        result = child.result()
        assert result["backend"] == "warp" and result["size"] == nbytes
        assert result["crc"] == checksum(expected_pattern(nbytes, 42))
        assert result["mapping"].startswith("/memfd:warp_buffer")  # the publisher's pages
        del buffer
        gc.collect()
        for _ in range(3):  # the publisher tries to recycle: the held block is refused
            other = allocate_buffer(nbytes, "cpu")
            assert other.get_impl().block is not block
            with from_output_buffer(other) as out:
                out.array.zero_()
        assert not block.try_reclaim()
        child.process.send_signal(signal.SIGKILL)
        child.process.wait(timeout=30)
    # The kernel dropped the dead reader's lock: the block is reclaimed.
    assert block.try_reclaim() or block.generation == 0
    assert arena.pending_pids() == set()
    del other, out
    gc.collect()


def test_sigterm_of_a_holding_subscriber_frees_its_holds():
    buffer, desc = _published(4096, seed=5)
    block = buffer.get_impl().block
    with Child("import", {"descriptors": [descriptor.pack(desc).hex()]}) as child:
        assert child.result()["crc"] == checksum(expected_pattern(4096, 5))
        assert not block.try_reclaim()
        child.process.send_signal(signal.SIGTERM)
        child.process.wait(timeout=30)
    del buffer
    gc.collect()
    assert block.try_reclaim()


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_a_killed_publisher_leaves_nothing_and_held_frames_stay_readable(sig):
    with Child("publish", {"nbytes": 10000, "seed": 9, "count": 3}) as child:
        result = child.result()
        descs = [descriptor.unpack(bytes.fromhex(h)) for h in result["descriptors"]]
        held = [ipc.import_buffer(d) for d in descs[:2]]  # attaches once, holds two
        pid = child.process.pid
        child.process.send_signal(sig)
        child.process.wait(timeout=30)
    assert not _ours_in_dev_shm(pid)
    for impl, crc in zip(held, result["crcs"]):  # our mapping keeps the memory alive
        assert checksum(impl.to_cpu().view()) == crc
    with from_input_buffer(Buffer(held[0])) as view:
        np.testing.assert_array_equal(view.array.numpy()[:8], expected_pattern(8, 9))
    # The third was queued, never imported: the mapping still has it, intact.
    late = ipc.import_buffer(descs[2])
    assert checksum(late.to_cpu().view()) == result["crcs"][2]
    for impl in [*held, late]:
        impl.release()
    assert attach.forget_idle() >= 1  # nothing held, owner gone: the mapping goes, and with it
    assert not [a for a in attach.attached_sessions() if a.owner_pid == pid]  # the memory


def test_a_publisher_that_exits_cleanly_leaves_every_queued_frame_readable():
    argument = {"nbytes": 6000, "seed": 11, "count": 20, "peer_pid": os.getpid(), "exit": True}
    with Child("publish", argument) as child:
        result = child.result()
        descs = [descriptor.unpack(bytes.fromhex(h)) for h in result["descriptors"]]
        # Nothing imported yet: the exiting publisher lingers until this peer attached.
        first = ipc.import_buffer(descs[0])
        assert child.process.wait(timeout=30) == 0
    rest = [ipc.import_buffer(d) for d in descs[1:]]  # after the publisher exited
    got = [checksum(impl.to_cpu().view()) for impl in [first, *rest]]
    assert got == result["crcs"]
    for impl in [first, *rest]:
        impl.release()
    attach.forget_idle()


def test_another_process_cannot_shrink_the_arena_under_a_reader_or_the_publisher():
    buffer, desc = _published(1 << 16, seed=12)
    reader = ipc.import_buffer(desc)
    with Child("shrink", {"owner_pid": os.getpid(), "session": desc.session}) as child:
        result = child.result()
    outcomes = result["outcomes"]
    for attempt in ("shrink_to_0", "shrink_by_a_page", "grow", "seal_writes"):
        assert outcomes[attempt] == result["eperm"], (attempt, outcomes)
    assert outcomes["size_after"] == result["size"]
    # Reader and publisher read every byte: no SIGBUS, nothing changed.
    np.testing.assert_array_equal(reader.to_cpu().view(), expected_pattern(1 << 16, 12))
    np.testing.assert_array_equal(buffer.to_numpy(), expected_pattern(1 << 16, 12))
    reader.release()


def test_a_peer_cannot_shrink_or_reseal_the_arena():
    buffer, desc = _published(4096, seed=2)
    fd, geometry = handoff.fetch_arena(os.getpid(), desc.session)  # what a peer receives
    try:
        for size in (0, 4096, geometry.file_size + 4096):
            with pytest.raises(OSError) as info:
                os.ftruncate(fd, size)
            assert info.value.errno == errno.EPERM
        with pytest.raises(OSError) as info:
            fcntl.fcntl(fd, fcntl.F_ADD_SEALS, fcntl.F_SEAL_WRITE)
        assert info.value.errno == errno.EPERM
    finally:
        os.close(fd)
    # No SIGBUS here or at any reader: the bytes are all there.
    np.testing.assert_array_equal(buffer.to_numpy(), expected_pattern(4096, 2))
    np.testing.assert_array_equal(ipc.import_buffer(desc).to_cpu().view(),
                                  expected_pattern(4096, 2))


def test_under_ulimit_1024_a_publisher_runs_10000_ahead_and_a_subscriber_holds_10000():
    count, more = 10_000, 2_000
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "descriptors")
        with Child("holdall", {"path": path}, nofile=1024) as sub:
            pub = Child("flood", {"path": path, "count": count, "peer_pid": sub.process.pid,
                                  "nbytes": 4096}, nofile=1024)
            with pub:
                ahead = pub.result(timeout=120)  # published with nobody reading yet
                assert ahead["published"] == count
                assert ahead["pool"]["created"] >= count  # none recycled under the peer
                assert ahead["fds"] - ahead["fds_before"] <= 3  # arena + listener: O(1)
                sub.send("")  # holdall starts reading once its stdin says so
                held = sub.result(timeout=120)
                assert held["held"] == count and held["intact"] == count
                assert held["fds"] - held["fds_before"] <= 2  # one arena fd, whatever is held
                assert held["maps"] <= 3  # the arena mapped once (header + data)
                pub.send(f"more {more}")  # it would recycle now if holds did not stop it
                after = pub.result(timeout=120)
                assert after["published"] == count + more
                assert after["pool"]["created"] >= count + more
                sub.send("check")
                again = sub.result(timeout=120)
                assert again["intact"] == count
                pub.send("exit")
                assert pub.process.wait(timeout=30) == 0
            sub.send("exit")
            assert sub.process.wait(timeout=30) == 0


# --------------------------------------------------------------------------- CUDA paths
@pytest.mark.cuda
def test_cuda_ipc_and_staging_exports_reach_another_process():  # pragma: no cover - needs a GPU
    device = wp.get_cuda_devices()[0]
    buffer = allocate_buffer(1 << 16, device.alias)
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, 8)
    expected = checksum(expected_pattern(1 << 16, 8))
    kinds = [descriptor.KIND_CUDA_STAGING]
    if device.is_ipc_supported:
        kinds.append(buffer.get_impl().block.cuda_kind)  # VMM where supported, else legacy IPC
    for kind in kinds:
        desc = ipc.export_buffer(buffer, kind)
        assert desc.kind == kind
        with Child("import", {"descriptors": [descriptor.pack(desc).hex()]}) as child:
            result = child.result()
            assert result["crc"] == expected
            assert result["device"] == ("cpu" if kind == descriptor.KIND_CUDA_STAGING
                                        else device.alias)
            child.finish()


# --------------------------------------------------------------------------- the benchmark
def test_the_ipc_core_benchmark_measures_every_figure():
    """``python -m benchmarks.ipc_core`` runs end to end (small) and reports what the issue asks,
    with the O(1) and nothing-left figures it measured itself."""
    import json
    import subprocess
    import sys

    from tests._warp_helpers import ROOT

    done = subprocess.run([sys.executable, "-m", "benchmarks.ipc_core", "--quick", "--sizes",
                           "4K", "--flood", "2000", "--json"], cwd=ROOT, capture_output=True,
                          text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-2000:]
    text, raw = done.stdout.rstrip().rsplit("\n", 1)
    report = json.loads(raw)
    for needle in ("descriptor build", "descriptor import", "messages in flight", "views held",
                   "after SIGTERM", "to_cpu"):
        assert needle in text
    assert report["descriptor"]["build_us"] > 0 and report["descriptor"]["import_us"] > 0
    flight = report["in_flight"]
    assert flight["sub_held"] == 2000
    assert flight["pub_fds_in_flight"] - flight["pub_fds_before"] <= 3
    assert flight["sub_fds_holding"] - flight["sub_fds_before"] <= 2
    assert report["dev_shm"] == {"SIGTERM": 0, "SIGKILL": 0}
    assert [row["nbytes"] for row in report["copies"]] == [4096]


def _mapped(address: int) -> bool:
    with open("/proc/self/maps", encoding="ascii") as maps:
        for line in maps:
            start, end = (int(x, 16) for x in line.split()[0].split("-"))
            if start <= address < end:
                return True
    return False


def test_a_view_kept_past_release_reads_its_own_bytes_until_it_is_gone():
    """A NumPy view of an import, kept past release() and past its publisher's death, keeps its
    own mapping: it never reads what a later session maps at that address."""
    with Child("publish", {"nbytes": 4096, "seed": 31, "count": 1}) as first:
        result = first.result()
        impl = ipc.import_buffer(descriptor.unpack(bytes.fromhex(result["descriptors"][0])))
        with from_input_buffer(Buffer(impl)) as handle:
            view = handle.array.numpy()
        impl.release()
        first.process.send_signal(signal.SIGKILL)
        first.process.wait(timeout=30)
    address = view.ctypes.data
    with Child("publish", {"nbytes": 4096, "seed": 32, "count": 1}) as second:
        result = second.result()
        later = ipc.import_buffer(descriptor.unpack(bytes.fromhex(result["descriptors"][0])))
        assert not [a for a in attach.attached_sessions() if a.owner_pid == first.process.pid]
        np.testing.assert_array_equal(view, expected_pattern(4096, 31))  # still its own bytes
        assert later.to_cpu().view()[:8].tobytes() == expected_pattern(8, 32).tobytes()
        later.release()
        second.finish()
    assert _mapped(address)
    del view, handle, impl
    gc.collect()
    assert not _mapped(address)  # the last view gone, the dead session's mapping went with it


def test_a_released_import_refuses_its_cached_array():
    buffer = allocate_buffer(4096, "cpu")
    with from_output_buffer(buffer) as out:
        out.host_array()[:] = 1
    impl = ipc.import_buffer(ipc.export_buffer(buffer))
    assert impl.array.shape == (4096,)  # made and cached before the release
    impl.release()
    with pytest.raises(HandleReleasedError):
        impl.array


def test_peers_that_connect_and_say_nothing_do_not_delay_the_others():
    buffer, desc = _published(4096, seed=41)
    name = handoff.socket_name(os.getuid(), os.getpid(), desc.session)
    idle = []
    try:
        for _ in range(3):  # e.g. subscribers frozen right after connecting
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.connect(name)
            idle.append(sock)
        start = time.monotonic()
        fd, geometry = handoff.fetch_arena(os.getpid(), desc.session)
        took = time.monotonic() - start
        os.close(fd)
    finally:
        for sock in idle:
            sock.close()
    assert took < 1.0, f"the hand-off waited {took:.2f} s behind idle connections"
    assert geometry.data_bytes > 0
    del buffer


_FORKING_PUBLISHER = textwrap.dedent("""
    import json, os, sys, time
    from warp_buffer import allocate_buffer, descriptor, from_output_buffer, ipc
    buffer = allocate_buffer(4096, "cpu")
    with from_output_buffer(buffer) as out:
        out.host_array()[:] = 5
    desc = ipc.export_buffer(buffer)
    worker = os.fork()  # a worker forked without exec (multiprocessing's "fork")
    if worker == 0:
        time.sleep(30)
        os._exit(0)
    print(json.dumps({"desc": descriptor.pack(desc).hex(), "worker": worker}), flush=True)
    time.sleep(60)
""")


def test_a_forked_worker_does_not_keep_its_dead_parents_hand_off_socket():
    proc = subprocess.Popen([sys.executable, "-c", _FORKING_PUBLISHER], stdout=subprocess.PIPE,
                            text=True, cwd=os.path.dirname(os.path.dirname(__file__)))
    worker = None
    try:
        result = json.loads(proc.stdout.readline())
        worker = result["worker"]
        desc = descriptor.unpack(bytes.fromhex(result["desc"]))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        start = time.monotonic()
        with pytest.raises(StaleBufferError, match="is gone"):
            ipc.import_buffer(desc)  # refused at once, not after a 5 s wait on the worker's copy
        assert time.monotonic() - start < 1.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        if worker:
            try:
                os.kill(worker, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_the_arena_is_readable_by_its_owner_only():
    buffer, _desc = _published(4096, seed=43)
    assert os.fstat(current_arena().fd).st_mode & 0o777 == 0o600
    del buffer


def test_a_peer_that_never_imports_pins_at_most_its_window():
    """A frozen keep-last peer can only ever import its latest descriptors (its depth and one
    or two in hand): older ones pin no block, and a late import of one is refused as stale."""
    slot = ipc.peer_slot(os.urandom(16), os.getpid(), window=3)
    published = [_published(4096, seed=50 + i, peer=slot) for i in range(8)]
    reclaimable = [buffer.get_impl().block.try_reclaim() for buffer, _ in published]
    assert reclaimable == [True] * 5 + [False] * 3  # the last 3 may still be imported
    with pytest.raises(StaleBufferError):
        ipc.import_buffer(published[0][1])  # its block was retired: never read as a new frame
    late = ipc.import_buffer(published[-1][1])  # inside the window: still valid
    assert checksum(late.to_cpu().view()) == checksum(expected_pattern(4096, 57))
    late.release()


def test_without_a_window_a_peer_pins_until_it_imports():
    slot = ipc.peer_slot(os.urandom(16), os.getpid())
    published = [_published(4096, seed=60 + i, peer=slot) for i in range(4)]
    assert not any(buffer.get_impl().block.try_reclaim() for buffer, _ in published)
    impl = ipc.import_buffer(published[-1][1])  # a later one imported: the earlier are dropped
    impl.release()
    assert all(buffer.get_impl().block.try_reclaim() for buffer, _ in published)


def _reap(pid: int, timeout: float = 10.0) -> int | None:
    """The exit status of child ``pid``, or None (then killed) if it did not exit in time."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return status
        time.sleep(0.01)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    return None


def test_a_forked_child_releasing_an_inherited_import_keeps_the_parents_hold():
    """The child shares the description the parent's read lock lives on: its release must not
    unlock it, or the publisher recycles a block the parent still reads."""
    buffer, desc = _published(4096, seed=70)
    impl = ipc.import_buffer(desc)
    block = buffer.get_impl().block
    assert not block.try_reclaim()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            impl.release()
        finally:
            os._exit(0)
    assert _reap(pid) == 0
    assert not block.try_reclaim()  # still held by the parent
    impl.release()
    assert block.try_reclaim()


def test_a_forked_child_keeps_its_own_hold_on_an_inherited_import():
    """The child's copy of a view can still be read: when the parent releases, the child's own
    lock keeps the block from being recycled (the parent's unlock ended it for both, and the
    child read a later frame); once the child lets its copy go, the block is free again."""
    buffer, desc = _published(4096, seed=74)
    impl = ipc.import_buffer(desc)
    view = impl.array.numpy()
    block = buffer.get_impl().block
    parent_done, child_done = os.pipe(), os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            os.read(parent_done[0], 1)  # the parent has released its hold
            before = bytes(view[:64])
            os.write(child_done[1], b"r")  # (the parent now checks the block is still held)
            os.read(parent_done[0], 1)
            code = 0 if bytes(view[:64]) == before else 3
            del view
            impl.release()  # the child's own hold ends here
            os.write(child_done[1], b"d")
            os.read(parent_done[0], 1)
        finally:
            os._exit(code)
    try:
        del view
        impl.release()
        os.write(parent_done[1], b"1")
        assert os.read(child_done[0], 1) == b"r"
        assert not block.try_reclaim(), "the child's inherited view lost its hold"
        os.write(parent_done[1], b"2")
        assert os.read(child_done[0], 1) == b"d"
        assert block.try_reclaim(), "the child released its hold, the block stays pinned"
        os.write(parent_done[1], b"3")
    finally:
        status = _reap(pid)
        for fd in (*parent_done, *child_done):
            os.close(fd)
    assert status == 0, f"the child's view changed under it (status {status})"
    del buffer, block


@pytest.mark.parametrize("parent_served", [True, False], ids=["served", "never-served"])
def test_a_forked_child_exports_an_inherited_buffer_from_its_own_arena(parent_served):
    """A child's descriptor of a buffer made before the fork names the child's own session (the
    parent's was refused by every peer), and the child never binds the parent's socket name
    (which blocked the parent's own exports with EADDRINUSE while the child lived)."""
    buffer = allocate_buffer(4096, "cpu")
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, 75)
    parent = current_arena()
    if parent_served:
        ipc.export_buffer(buffer)
    report, done = os.pipe(), os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            desc = ipc.export_buffer(buffer)
            mine = desc.owner_pid == os.getpid() and desc.session != parent.session
            imported = ipc.import_buffer(desc)
            same = (checksum(imported.array.numpy())
                    == checksum(buffer.get_impl().array.numpy()))
            imported.release()
            code = 0 if mine and same else 2
            os.write(report[1], b"x")
            os.read(done[0], 1)  # alive while the parent looks at its socket name
        finally:
            os._exit(code)
    try:
        assert os.read(report[0], 1) == b"x"
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:  # the parent's name is bound by the parent alone, or by nobody
            probe.connect(handoff.socket_name(os.getuid(), os.getpid(), parent.session))
            bound = True
        except (ConnectionRefusedError, FileNotFoundError):
            bound = False
        finally:
            probe.close()
        assert bound == (parent.server is not None)
        if not parent_served:
            ipc.export_buffer(buffer)  # the parent's own first export still binds its name
    finally:
        os.write(done[1], b"x")
        status = _reap(pid)
        for fd in (*report, *done):
            os.close(fd)
    assert status == 0, f"the child described the parent's session (status {status})"
    del buffer


def test_a_fork_while_a_thread_holds_the_servers_lock_does_not_hang_the_child():
    buffer, _desc = _published(4096, seed=71)
    server = current_arena().server
    held, release = threading.Event(), threading.Event()

    def hold() -> None:
        with server._cond:
            held.set()
            release.wait(10)

    thread = threading.Thread(target=hold)
    thread.start()
    try:
        assert held.wait(5)
        pid = os.fork()  # the at-fork handler abandons the parent's server in the child
        if pid == 0:  # pragma: no cover - the child
            os._exit(0)
        assert _reap(pid, 5.0) == 0, "the child hung in the at-fork handler"
    finally:
        release.set()
        thread.join()
    del buffer


def test_a_peer_that_sent_part_of_a_request_delays_nobody():
    buffer, desc = _published(4096, seed=72)
    name = handoff.socket_name(os.getuid(), os.getpid(), desc.session)
    partial = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        partial.connect(name)
        partial.send(b"\\x01")  # one byte of a 24-byte request, then nothing
        time.sleep(0.1)
        start = time.monotonic()
        fd, _geometry = handoff.fetch_arena(os.getpid(), desc.session)
        took = time.monotonic() - start
        os.close(fd)
    finally:
        partial.close()
    assert took < 1.0, f"the hand-off waited {took:.2f} s behind a partial request"
    del buffer


def test_a_hold_released_after_its_arena_is_collected_unlocks_nothing(monkeypatch):
    """A collection of a cycle holding an import and its arena may collect the arena first: the
    hold must then still end on the description it locked (never on a closed fd number, which
    may be another file's by now). The hold keeps its session (its description and mapping)."""
    arena = attach.AttachedArena.local(current_arena())
    buffer, desc = _published(4096, seed=73)
    hold = arena.import_block(descriptor.fields_of(desc))
    fd = arena.fd
    del arena
    gc.collect()
    assert hold.live and hold.session.fd == fd
    os.fstat(fd)  # still this process's open description of the arena
    assert not current_arena().try_retire(desc.offset)  # the publisher's probe meets the hold
    hold.release()
    assert current_arena().try_retire(desc.offset)
    del hold
    with pytest.raises(OSError):  # the last reference took the description with it
        os.fstat(fd)
    del buffer


def test_out_of_file_descriptors_at_connect_is_a_typed_export_error(monkeypatch):
    """A process out of fds cannot make the socket to a publisher's hand-off: ExportError (it
    was a bare OSError, raised before the error handling around the connect)."""
    def no_socket(*args, **kwargs):
        raise OSError(errno.EMFILE, "Too many open files")

    monkeypatch.setattr(handoff.socket, "socket", no_socket)
    with pytest.raises(ExportError, match="no socket"):
        handoff._connect(os.getpid(), 1, "session 1 of this process")


def test_a_session_a_live_process_does_not_serve_is_not_called_its_exit():
    """A descriptor naming a live pid and a session it never served (forged, or ended) was
    refused as "the publisher exited": the refusal now says the process runs."""
    from warp_buffer import handoff

    with pytest.raises(StaleBufferError, match=f"process {os.getpid()} runs but serves no such"):
        handoff.fetch_arena(os.getpid(), 0x5EED_0000_0000_0001)
