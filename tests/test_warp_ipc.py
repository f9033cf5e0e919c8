"""warp_buffer.ipc: exports in /dev/shm, imports with zero copies, holds, recycling, staleness,
foreign and hostile records, permissions, orphan sweep; with real second processes."""

from __future__ import annotations

import dataclasses
import gc
import os
import signal
import stat

import numpy as np
import pytest
import warp as wp

import warp_buffer
from rosidl_buffer import Buffer
from tests._warp_helpers import Child, checksum, expected_pattern, fill_pattern, mapping_of
from warp_buffer import (
    DescriptorError,
    ExportBoundsError,
    ForeignExportError,
    StaleBufferError,
    WriteHandleError,
    allocate_buffer,
    from_input_buffer,
    from_output_buffer,
    ipc,
)

pytestmark = [pytest.mark.multiprocess, pytest.mark.usefixtures("warp_pool_drained")]



def _published(nbytes: int = 8192, seed: int = 7):
    buffer = allocate_buffer(nbytes, "cpu")
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, seed)
    return buffer, ipc.export_buffer(buffer)


def test_record_names_a_0600_file_under_the_user_prefix():
    buffer, record = _published()
    assert record.kind is ipc.ExportKind.HOST_SHM
    assert record.path.startswith(ipc.shm_prefix()) and record.owner_pid == os.getpid()
    assert ipc.shm_prefix() == f"/dev/shm/warp_buffer.{os.getuid()}."
    mine = ipc.list_exports(os.getpid())
    assert record.path in [f.path for f in mine]
    for f in mine:  # block files and the session lock file
        st = os.lstat(f.path)
        assert stat.S_ISREG(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o600
        assert st.st_uid == os.getuid()
    assert 0 < record.size <= record.capacity and record.uid != 0


def test_import_in_process_maps_the_same_file_copy_on_write():
    buffer, record = _published(8192, seed=3)
    imported = ipc.import_export(record)
    assert imported.is_imported and imported.device == "cpu"
    assert mapping_of(imported.array.ptr) == record.path  # zero copies: the export's own pages
    np.testing.assert_array_equal(imported.to_cpu().view(), expected_pattern(8192, 3))
    with pytest.raises(WriteHandleError):  # imports are read-only through the API
        from_output_buffer(Buffer(imported))
    # A stray write by a reader changes only its private copy of that page.
    imported.array.numpy()[:16] = 0
    np.testing.assert_array_equal(buffer.to_numpy(), expected_pattern(8192, 3))


def test_a_held_block_is_never_recycled_and_is_reused_once_released():
    buffer, record = _published(5000)
    block = buffer.get_impl()._block
    imported = ipc.import_export(record)  # holds LOCK_SH and acknowledges
    del buffer
    gc.collect()
    other = allocate_buffer(5000, "cpu")
    assert other.get_impl()._block is not block
    np.testing.assert_array_equal(imported.to_cpu().view(), expected_pattern(5000, 7))
    del imported, other
    gc.collect()
    again = allocate_buffer(5000, "cpu")
    assert again.get_impl()._block is block
    with pytest.raises(StaleBufferError):  # the old record now names a recycled block
        ipc.import_export(record)


def test_missing_export_is_stale():
    buffer, record = _published()
    with pytest.raises(StaleBufferError):
        ipc.import_export(dataclasses.replace(record, block_id=record.block_id + 1000))
    with pytest.raises(StaleBufferError):
        ipc.import_export(dataclasses.replace(record, session=record.session ^ 1))
    del buffer
    gc.collect()
    warp_buffer.trim_pools(0.0, inflight_grace=0.0)
    assert not os.path.exists(record.path)
    with pytest.raises(StaleBufferError):
        ipc.import_export(record)


def test_truncated_export_is_stale_and_oversize_records_are_bounds_errors():
    buffer, record = _published(4096)
    with pytest.raises(ExportBoundsError):
        ipc.import_export(dataclasses.replace(record, size=record.capacity + 1))
    with pytest.raises(ExportBoundsError):
        ipc.import_export(dataclasses.replace(record, offset=record.capacity - 10, size=20))
    with pytest.raises(ExportBoundsError):
        ipc.import_export(dataclasses.replace(record, capacity=1 << 30, size=1 << 29))
    with pytest.raises(ExportBoundsError):
        ipc.import_export(dataclasses.replace(record, capacity=12345))
    os.truncate(record.path, 4096 + 100)  # a damaged file must not SIGBUS the importer
    with pytest.raises(StaleBufferError):
        ipc.import_export(record)


def test_malformed_records_raise_descriptor_errors():
    buffer, record = _published()
    bad = [dict(version=2), dict(owner_pid=0), dict(block_id=0), dict(uid=0), dict(session=0),
           dict(ack_slot=100), dict(host_id=""), dict(device="x" * 40),
           dict(kind=ipc.ExportKind.CUDA_IPC)]
    for change in bad:
        with pytest.raises(DescriptorError):
            ipc.import_export(dataclasses.replace(record, **change))
    with pytest.raises(DescriptorError):
        ipc.ExportRecord.from_dict({"kind": 9})


def test_foreign_exports_raise(tmp_path):
    buffer, record = _published()
    with pytest.raises(ForeignExportError):
        ipc.import_export(dataclasses.replace(record, host_id="another-host"))
    with pytest.raises(ForeignExportError):
        ipc.import_export(dataclasses.replace(record, user_id=record.user_id + 1))
    os.chmod(record.path, 0o644)
    try:
        with pytest.raises(ForeignExportError):
            ipc.import_export(record)
    finally:
        os.chmod(record.path, 0o600)
    if os.getuid() == 0:  # as root, make the file another user's
        os.chown(record.path, 12345, -1)
        try:
            with pytest.raises(ForeignExportError):
                ipc.import_export(record)
        finally:
            os.chown(record.path, 0, -1)
    # A symbolic link planted at an export's name is never followed.
    fake = dataclasses.replace(record, block_id=record.block_id + 999)
    target = tmp_path / "elsewhere"
    target.write_bytes(b"\0" * 8192)
    os.symlink(target, fake.path)
    try:
        with pytest.raises(ForeignExportError):
            ipc.import_export(fake)
    finally:
        os.unlink(fake.path)


def test_second_process_sees_kernel_bytes_holds_the_block_and_is_sigkilled_without_leaking():
    nbytes = 1 << 20
    buffer, record = _published(nbytes, seed=42)
    block = buffer.get_impl()._block
    with Child("import", {"record": record.to_dict()}) as child:
        result = child.result()
        assert result["backend"] == "warp" and result["size"] == nbytes
        assert result["crc"] == checksum(expected_pattern(nbytes, 42))
        assert result["mapping"] == record.path  # zero payload copies: the same shm pages
        # The publisher drops its buffer and tries to recycle: the held block is refused.
        del buffer
        gc.collect()
        for _ in range(3):
            other = allocate_buffer(nbytes, "cpu")
            assert other.get_impl()._block is not block
            with from_output_buffer(other) as out:
                out.array.zero_()
        warp_buffer.trim_pools(0.0, inflight_grace=0.0)
        assert os.path.exists(record.path)  # nor freed while held
        with open(record.path, "rb") as f:
            f.seek(4096)
            assert checksum(np.frombuffer(f.read(nbytes), np.uint8)) == result["crc"]
        child.process.send_signal(signal.SIGKILL)
        child.process.wait(timeout=30)
    # The kernel dropped the dead reader's lock: the block is reclaimed and nothing leaks.
    reused = allocate_buffer(nbytes, "cpu")
    assert reused.get_impl()._block is block
    del reused, other, out
    gc.collect()
    warp_buffer.trim_pools(0.0, inflight_grace=0.0)
    # Only this process's exports: a concurrent test run may own live ones of its own.
    assert not [f for f in ipc.list_exports() if f.block_id is not None and f.owner_pid == os.getpid()]


def test_sigkilled_publisher_leaves_files_that_the_sweep_removes():
    with Child("publish", {"nbytes": 10000, "seed": 9}) as child:
        result = child.result()
        record = ipc.ExportRecord.from_dict(result["record"])
        imported = ipc.import_export(record)  # a reader of the dying publisher
        assert checksum(imported.to_cpu().view()) == result["crc"]
        assert not ipc.sweep_orphans()  # the owner is alive: nothing to sweep
        child.process.send_signal(signal.SIGKILL)
        child.process.wait(timeout=30)
    assert ipc.list_exports(child.process.pid)
    removed = ipc.sweep_orphans()
    assert record.path in removed
    assert not ipc.list_exports(child.process.pid)
    # The reader keeps its mapping: the bytes stay valid after the owner died and was swept.
    assert checksum(imported.to_cpu().view()) == result["crc"]
    with from_input_buffer(Buffer(imported)) as view:
        np.testing.assert_array_equal(view.array.numpy()[:8], expected_pattern(8, 9))


def test_clean_shutdown_removes_every_file():
    with Child("publish", {"nbytes": 4096, "seed": 1}) as child:
        record = ipc.ExportRecord.from_dict(child.result()["record"])
        assert os.path.exists(record.path)
        assert child.finish() == 0
    assert not ipc.list_exports(child.process.pid)


# --------------------------------------------------------------------------- CUDA paths
@pytest.mark.cuda
def test_cuda_ipc_and_staging_exports_reach_another_process():  # pragma: no cover - needs a GPU
    device = wp.get_cuda_devices()[0]
    buffer = allocate_buffer(1 << 16, device.alias)
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, 8)
    expected = checksum(expected_pattern(1 << 16, 8))
    kinds = [ipc.ExportKind.CUDA_STAGING]
    if device.is_ipc_supported:
        kinds.append(ipc.ExportKind.CUDA_IPC)
    for kind in kinds:
        record = ipc.export_buffer(buffer, kind)
        assert record.kind is kind
        with Child("import", {"record": record.to_dict()}) as child:
            result = child.result()
            assert result["crc"] == expected
            assert result["device"] == ("cpu" if kind is ipc.ExportKind.CUDA_STAGING
                                        else device.alias)
            child.finish()
