"""One owner per block (issue 25): the lease state machine, readers' tokens instead of reference
counts, holds that end with their token, and finalizers that take no lock.

In one process: a block's lease goes WRITABLE -> WRITING -> WRITTEN / READ / PUBLISHED and back to
WRITABLE only through ``reclaim``, which refuses while any reader's token lives (a NumPy view, a
``wp.array``, a read handle, a view of one) or a peer may still read the block; an import's
``release()`` drops the import's own token, and views keep theirs; a hold or a write handle
collected inside someone's critical section ends at once, without waiting for a lock.
"""

from __future__ import annotations

import ast
import gc
import pathlib
import threading

import numpy as np
import pytest
import warp as wp

from rosidl_buffer import Buffer, CpuBufferImpl
from warp_buffer import allocate_buffer, from_input_buffer, from_output_buffer, ipc, lease
from warp_buffer.errors import WriteHandleError
from warp_buffer.loan import loan_buffer

pytestmark = pytest.mark.usefixtures("warp_pool_drained")

ROOT = pathlib.Path(__file__).resolve().parent.parent
LIBRARY = ("rosidl_buffer", "warp_buffer", "warp_buffer_backend", "tensor_conversions",
           "buffer_pubsub", "warp_buffer_cli")


def _published_loan(nbytes: int = 4096):
    buffer = loan_buffer(nbytes, "cpu")
    impl = buffer.get_impl()
    impl.host[:] = 7
    buffer.seal()
    impl.end_publish()
    return buffer, impl


# ------------------------------------------------------------------------------ no refcounts
def test_no_reference_count_is_read_anywhere_in_the_library():
    """Reuse is decided by tokens: ``sys.getrefcount`` appears nowhere in the packages."""
    found = []
    for package in LIBRARY:
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Attribute) and node.attr == "getrefcount":
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
                elif isinstance(node, ast.Name) and node.id == "getrefcount":
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert found == []


# ------------------------------------------------------------------------------ transitions
def test_the_lease_moves_through_its_states_one_transition_at_a_time():
    buffer = allocate_buffer(4096, "cpu")
    state = buffer.get_impl().lease
    assert state.state == lease.WRITABLE
    handle = from_output_buffer(buffer)
    assert state.state == lease.WRITING
    with pytest.raises(WriteHandleError, match="one write handle"):
        from_output_buffer(buffer)
    handle.release()
    assert state.state == lease.WRITTEN
    from_input_buffer(buffer).release()
    assert state.state == lease.READ and buffer.get_impl().is_read
    buffer.seal()
    assert state.state == lease.PUBLISHED and buffer.get_impl().is_published
    buffer.seal()  # once per publish: a second seal changes nothing
    assert state.state == lease.PUBLISHED
    with pytest.raises(WriteHandleError, match="published"):
        from_output_buffer(buffer)


def test_an_export_is_the_published_lease_s_transition_and_seals_a_buffer_nobody_sealed():
    buffer = allocate_buffer(4096, "cpu")
    with from_output_buffer(buffer) as out:
        out.host_array()[:] = 3
    state = buffer.get_impl().lease
    descriptor = ipc.export_buffer(buffer)
    assert state.state == lease.PUBLISHED
    assert descriptor.generation == buffer.get_impl().block.generation != 0
    again = ipc.export_buffer(buffer)  # the same export: the same generation
    assert again.generation == descriptor.generation


# ------------------------------------------------------------------------------ tokens
@pytest.mark.parametrize("reader", ["reader_host", "read_handle_host", "read_handle_array",
                                    "read_handle_view", "impl_array", "torch_of_host"])
def test_every_reader_of_a_loan_holds_a_token_until_it_is_gone(reader):
    buffer, impl = _published_loan()
    if reader == "reader_host":
        kept = impl.reader_host()[:8]  # a view of the view: the token is in the base chain
    elif reader == "read_handle_host":
        kept = from_input_buffer(buffer).host_array()
    elif reader == "read_handle_array":
        kept = from_input_buffer(buffer).array
    elif reader == "read_handle_view":
        kept = from_input_buffer(buffer).view(wp.float32)
    elif reader == "impl_array":
        kept = impl.array.numpy()
    else:
        import torch

        kept = torch.from_numpy(impl.reader_host())
    gc.collect()
    assert not impl.reclaim(), f"{reader} read the block without a token"
    assert impl.is_protected and impl.is_published  # nothing changed
    del kept
    gc.collect()
    assert impl.reclaim() and not impl.is_published and not impl.is_protected


def test_a_loan_s_own_cached_view_is_not_a_reader():
    buffer, impl = _published_loan()
    owner = impl.owner_view()  # what a loan's cached writable views are built over
    assert impl.reclaim()  # the owner's view keeps the block leased, not its contents
    owner[:4] = 9  # re-armed: writable through it again
    assert int(impl.host[0]) == 9
    del owner


def test_a_token_keeps_the_block_from_the_pool_after_its_owner_is_gone():
    buffer, impl = _published_loan()
    block = impl.block
    view = impl.reader_host()
    del buffer, impl
    gc.collect()
    other = loan_buffer(4096, "cpu")
    assert other.get_impl().block is not block  # the reader still reads it
    np.testing.assert_array_equal(view, np.full(4096, 7, np.uint8))
    del view, other
    gc.collect()
    assert loan_buffer(4096, "cpu").get_impl().block is block  # the token gone: back


def test_cpu_storage_tracks_its_views_by_tokens_from_its_first_reclaim():
    impl = CpuBufferImpl(np.zeros(64, np.uint8))
    early = impl.writable_view()  # handed out before the pool asked: not tracked...
    assert impl.reclaim()  # ...so the storage moves into memory of its own
    early[:] = 5
    assert not impl.view().any()  # the early view writes its own copy, not the pooled storage
    kept = impl.writable_view()[10:20]
    assert not impl.reclaim()
    del kept
    assert impl.reclaim()
    readonly = CpuBufferImpl(b"received")
    assert not readonly.reclaim()  # borrowed read-only bytes are never rewritten


# ------------------------------------------------------------------------------ imports
def test_release_drops_the_import_s_own_token_and_views_keep_theirs():
    buffer = allocate_buffer(4096, "cpu")
    with from_output_buffer(buffer) as out:
        out.host_array()[:] = 4
    block = buffer.get_impl().block
    imported = ipc.import_buffer(ipc.export_buffer(buffer))
    handle = from_input_buffer(Buffer(imported))
    view = handle.host_array()
    handle.release()
    with Buffer(imported):  # the message's own token goes here
        pass
    assert imported.is_released
    assert not block.try_reclaim(), "a view of the import lost its hold at release()"
    np.testing.assert_array_equal(view, np.full(4096, 4, np.uint8))
    del view, handle
    gc.collect()
    assert block.try_reclaim()  # the last token gone: the publisher may reuse the block


def test_a_hold_ends_at_once_inside_the_arena_s_critical_section():
    """A hold collected while another thread imports from its session (a collection inside an
    import) unlocks at once: its end is one native call under the GIL that takes no lock and
    defers nothing (the publisher saw the block held until the next import of this process)."""
    buffer = allocate_buffer(4096, "cpu")
    block = buffer.get_impl().block
    other = ipc.export_buffer(allocate_buffer(4096, "cpu"))
    stop = threading.Event()

    def importing() -> None:
        while not stop.is_set():
            ipc.import_buffer(other).release()

    thread = threading.Thread(target=importing)
    thread.start()
    try:
        for _ in range(50):
            imported = ipc.import_buffer(ipc.export_buffer(buffer))
            del imported
            assert block.try_reclaim(), "the hold's end waited for the session"
    finally:
        stop.set()
        thread.join(10)


def test_a_write_handle_collected_while_another_thread_holds_the_lease_does_not_wait():
    buffer = allocate_buffer(4096, "cpu")
    handle = from_output_buffer(buffer)
    held, release = threading.Event(), threading.Event()

    def hold_the_lock() -> None:
        with buffer.get_impl().lease._lock:
            held.set()
            release.wait(10)

    holder = threading.Thread(target=hold_the_lock)
    holder.start()
    assert held.wait(5)
    finished = threading.Event()

    def collect() -> None:
        nonlocal handle
        del handle  # the finalizer ends the write
        gc.collect()
        finished.set()

    collector = threading.Thread(target=collect)
    collector.start()
    try:
        assert finished.wait(2), "a write handle's finalizer waited for the lease's lock"
    finally:
        release.set()
        holder.join(10)
        collector.join(10)
    buffer.seal()  # the collected write counts as ended: sealing finds it closed
    assert buffer.get_impl().is_published
