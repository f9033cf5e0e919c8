"""warp_buffer's native core (warp_buffer._core): the descriptor's fixed layout, with the generic
CDR codec as the reference, and its checks of what the wire can carry."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rosidl_buffer.messages import serialize_message
from warp_buffer import _core, descriptor
from warp_buffer.errors import (
    DescriptorError,
    ExportBoundsError,
    RecycledBufferError,
    StaleBufferError,
)

WIDTHS = (1, 1, 2, 4) + (8,) * 23
values = st.tuples(*(st.integers(0, (1 << (8 * w)) - 1) for w in WIDTHS))


@settings(max_examples=300, deadline=None)
@given(values)
def test_pack_is_the_cdr_codecs_bytes_and_unpack_inverts_it(fields: tuple[int, ...]) -> None:
    message = descriptor.make(fields)
    cdr = bytes(serialize_message(message))[4:]  # after the encapsulation header: offset 0
    packed = _core.pack(fields)
    assert packed == cdr == descriptor.pack(message)
    assert _core.unpack(packed) == fields
    assert descriptor.values_of(descriptor.unpack(packed)) == fields
    out = bytearray(8 + len(packed))
    _core.pack_into(out, 8, fields)
    assert bytes(out[8:]) == packed and _core.unpack(out, 8) == fields


@pytest.mark.parametrize("index, value", [(0, 256), (1, -1), (2, 1 << 16), (3, 1 << 32),
                                          (4, 1 << 64), (8, "7"), (26, 1.5)])
def test_a_field_the_wire_cannot_carry_is_refused_by_name(index: int, value: object) -> None:
    fields = [0] * 27
    fields[index] = value
    with pytest.raises(DescriptorError, match=descriptor.FIELDS[index]):
        _core.pack(fields)
    message = descriptor.make(tuple(fields))
    with pytest.raises(DescriptorError, match=descriptor.FIELDS[index]):
        descriptor.values_of(message)


def test_wrong_sizes_and_counts_are_typed_errors() -> None:
    with pytest.raises(DescriptorError, match="27 fields"):
        _core.pack((0,) * 26)
    with pytest.raises(DescriptorError, match="192 bytes, not 191"):
        _core.unpack(bytes(191))
    with pytest.raises(DescriptorError, match="at offset 8"):
        _core.unpack(bytes(199), 8)
    with pytest.raises(DescriptorError, match="no room"):
        _core.pack_into(bytearray(191), 0, (0,) * 27)
    with pytest.raises(DescriptorError):
        descriptor.unpack(b"short")


# --------------------------------------------------------------------------- imports
DATA_BYTES = 1 << 20
GENS_OFFSET = 4096 + 1024 * 64
DATA_OFFSET = -(-(GENS_OFFSET + DATA_BYTES // 4096 * 8) // 4096) * 4096


class _Arena:
    """A publisher's arena laid out as warp_buffer.arena does, made by hand: the test writes
    its generations, the Session under test imports from it (a hostile publisher's memory)."""

    def __init__(self) -> None:
        import mmap
        import os

        self.fd = os.memfd_create("native_test", os.MFD_CLOEXEC)
        os.ftruncate(self.fd, DATA_OFFSET + DATA_BYTES)
        self.map = mmap.mmap(self.fd, DATA_OFFSET + DATA_BYTES)
        self.base = _address(self.map)
        self.pid, self.tag = os.getpid(), 0x5EED
        reader_fd = os.open(f"/proc/self/fd/{self.fd}", os.O_RDWR | os.O_CLOEXEC)
        self.session = _core.Session(self.pid, self.tag, reader_fd, self.base, DATA_OFFSET,
                                     self.base + DATA_OFFSET, DATA_BYTES, DATA_OFFSET, False)

    def export(self, offset: int, capacity: int, generation: int) -> None:
        import struct

        struct.pack_into("<Q", self.map, GENS_OFFSET + (offset - DATA_OFFSET) // 4096 * 8,
                         generation)

    def close(self) -> None:
        import os

        del self.session
        self.map.close()
        os.close(self.fd)


def _address(buffer) -> int:
    import ctypes

    return ctypes.addressof(ctypes.c_char.from_buffer(buffer))


def _values(arena: _Arena, **fields: int) -> tuple[int, ...]:
    base = dict(version=descriptor.VERSION, kind=descriptor.KIND_HOST, peer_slot=3,
                owner_pid=arena.pid, session=arena.tag, offset=DATA_OFFSET + 8192,
                capacity=8192, size=100, generation=(7 << 6) | 13, sequence=1, device_uuid=0)
    base.update(fields)
    return tuple(base[name] for name in descriptor.FIELDS[:11]) + (0,) * 16


def test_an_import_holds_views_read_only_and_ends_with_its_last_reference() -> None:
    import io

    import numpy as np

    arena = _Arena()
    try:
        arena.export(DATA_OFFSET + 8192, 8192, (7 << 6) | 13)
        arena.map[DATA_OFFSET + 8192:DATA_OFFSET + 8197] = b"hello"
        hold = arena.session.import_block(_values(arena))
        assert arena.session.held == 1 and arena.session.ack(3) == 1
        view = np.frombuffer(hold, np.uint8)
        assert bytes(view[:5]) == b"hello" and not view.flags.writeable and len(hold) == 100
        assert bytes(np.from_dlpack(hold)[:5]) == b"hello"
        assert memoryview(hold).readonly
        with pytest.raises((BufferError, TypeError)):
            io.BytesIO(b"xxxx").readinto(hold)  # a writable view is refused
        del hold
        assert arena.session.held == 1  # the view holds it
        del view
        assert arena.session.held == 0
        again = arena.session.import_block(_values(arena, sequence=5))
        again.release()
        assert arena.session.held == 0 and not again.live and arena.session.ack(3) == 5
    finally:
        arena.close()


@pytest.mark.parametrize("fields, error, words", [
    ({"version": 1}, DescriptorError, "version"),
    ({"kind": 9}, DescriptorError, "kind"),
    ({"owner_pid": 0}, DescriptorError, "names no export"),
    ({"session": 0}, DescriptorError, "names no export"),
    ({"generation": 0}, DescriptorError, "names no export"),
    ({"owner_pid": 1}, DescriptorError, "imported through"),
    ({"peer_slot": 2000}, DescriptorError, "peer slot"),
    ({"capacity": 12288}, ExportBoundsError, "block size"),
    ({"capacity": 1 << 40}, ExportBoundsError, "block size"),
    ({"offset": DATA_OFFSET + 4096}, ExportBoundsError, "start of"),
    ({"offset": 4096}, ExportBoundsError, "start of"),
    ({"offset": DATA_OFFSET + DATA_BYTES}, ExportBoundsError, "start of"),
    ({"size": 0}, ExportBoundsError, "size"),
    ({"size": 8193}, ExportBoundsError, "size"),
    ({"generation": (6 << 6) | 13}, RecycledBufferError, "recycled"),  # the block moved on
    ({"generation": (8 << 6) | 13}, StaleBufferError, "no export of generation"),  # never was
    ({"capacity": 4096, "size": 10}, ExportBoundsError, "not that of block"),
])
def test_hostile_descriptors_are_typed_errors_that_hold_nothing(fields, error, words) -> None:

    arena = _Arena()
    try:
        arena.export(DATA_OFFSET + 8192, 8192, (7 << 6) | 13)
        with pytest.raises(error, match=words):
            arena.session.import_block(_values(arena, **fields))
        assert arena.session.held == 0
    finally:
        arena.close()


@settings(max_examples=400, deadline=None)
@given(st.tuples(*(st.integers(0, (1 << (8 * w)) - 1) for w in WIDTHS[:11])),
       st.integers(0, (1 << 64) - 1))
def test_random_descriptors_and_generations_never_crash_the_import(fields, generation) -> None:
    _random_import(fields, generation)


@pytest.mark.slow
@settings(max_examples=20_000, deadline=None)
@given(st.tuples(*(st.integers(0, (1 << (8 * w)) - 1) for w in WIDTHS[:11])),
       st.integers(0, (1 << 64) - 1))
def test_random_descriptors_and_generations_long(fields, generation) -> None:
    _random_import(fields, generation)


def _random_import(fields: tuple[int, ...], generation: int) -> None:
    """Any field values against any generation word: a typed error or a hold inside the block."""
    from warp_buffer.errors import WarpBufferError

    arena = _Arena()
    try:
        offset = fields[5]
        if DATA_OFFSET <= offset < DATA_OFFSET + DATA_BYTES:
            arena.export(offset - (offset - DATA_OFFSET) % 4096, 4096, generation)
        values = (*fields[:3], arena.pid if fields[3] % 2 else fields[3],
                  arena.tag if fields[4] % 2 else fields[4], *fields[5:]) + (0,) * 16
        try:
            hold = arena.session.import_block(values)
        except WarpBufferError:
            assert arena.session.held == 0
            return
        start = hold.address - (arena.base + DATA_OFFSET)
        assert 0 <= start and start + len(hold) <= DATA_BYTES
        hold.release()
        assert arena.session.held == 0
    finally:
        arena.close()


# ------------------------------------------------------------ misuse from Python (the audit's)
def test_a_released_hold_gives_no_new_view_and_a_huge_stream_is_a_typed_error() -> None:
    import numpy as np

    arena = _Arena()
    try:
        arena.export(DATA_OFFSET + 8192, 8192, (7 << 6) | 13)
        hold = arena.session.import_block(_values(arena))
        with pytest.raises(BufferError, match="no stream"):
            hold.__dlpack__(stream=2**70)  # (was: a capsule returned with an error pending)
        with pytest.raises(BufferError, match="no stream"):
            hold.__dlpack__(stream=0)
        assert hold.live and arena.session.held == 1
        hold.__dlpack__(stream=-1)  # the one stream a cpu consumer passes
        hold.release()
        with pytest.raises(BufferError, match="released"):
            np.frombuffer(hold, np.uint8)  # its lock is gone: the bytes may be reused
        with pytest.raises(BufferError, match="released"):
            memoryview(hold)
    finally:
        arena.close()


def test_a_session_over_no_mapping_is_refused() -> None:
    arena = _Arena()
    try:
        with pytest.raises(ValueError, match="session of"):
            _core.Session(arena.pid, arena.tag, -1, 0, DATA_OFFSET, arena.base + DATA_OFFSET,
                          DATA_BYTES, DATA_OFFSET, False)
    finally:
        arena.close()


class _Device:
    is_cpu = True


@pytest.mark.parametrize("name", ["pool", "block", "writer", "event", "fence", "write_stream"])
def test_a_lease_field_may_be_set_but_not_deleted(name: str) -> None:
    lease = _core.Lease(None, None, _Device())
    with pytest.raises(AttributeError, match="cannot be deleted"):
        delattr(lease, name)
    setattr(lease, name, None)
    assert getattr(lease, name) is None
    lease.seal()
    lease.end_publish()  # (read a deleted field as NULL before: SIGSEGV)
    assert lease.state == _core.PUBLISHED


def test_an_export_of_a_block_whose_offset_is_not_in_its_arena_is_refused() -> None:
    from warp_buffer.arena import Arena

    arena = Arena(1 << 20)  # (unmapped when collected)

    class Block(_core.Exports):
        capacity = 4096

    for offset in (0, arena.data_offset + 4096 * 100_000, arena.data_offset + 1):
        block = Block()
        block.arena = arena
        block.offset = offset
        with pytest.raises(ValueError, match="no block"):
            _core.Lease(None, block, _Device()).export(None)
        assert block.generation == 0


def test_an_export_survives_python_code_that_replaces_the_lease_block() -> None:
    import gc

    from warp_buffer.arena import Arena

    arena = Arena(1 << 20)  # (unmapped when collected)
    leases: list = []

    class Block(_core.Exports):
        @property
        def capacity(self) -> int:
            leases[0].block = None  # the last reference to this block, during the export
            gc.collect()
            return 4096

    block = Block()
    block.arena, block.offset = arena, arena.data_offset
    leases.append(_core.Lease(None, block, _Device()))
    del block
    generation, slot, sequence = leases[0].export(None)  # (freed the block under it before)
    assert generation != 0 and sequence == 0 and leases[0].block is None
    assert arena.core.generation(arena.data_offset) == generation
