"""warp_buffer's native core (warp_buffer._core): the descriptor's fixed layout, with the generic
CDR codec as the reference, and its checks of what the wire can carry."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rosidl_buffer.messages import serialize_message
from warp_buffer import _core, descriptor
from warp_buffer.errors import DescriptorError

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
