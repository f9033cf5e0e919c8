"""Errors users meet, typed: project classes that also subclass the matching builtin, with a
message that names what was wrong (issue 13 point 5); and what ``Buffer.numpy()`` promises."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import tensor_conversions as tc
from rosidl_buffer import Buffer
from rosidl_buffer.errors import InvalidBufferDataError, RosidlBufferError, UnknownFieldError
from rosidl_buffer.messages import deserialize_message, get_message_type, serialize_message
from tensor_conversions.testing import MODULES

TENSOR = "tensor_msgs/msg/ExperimentalTensor"


def test_buffer_none_is_a_typed_error():
    with pytest.raises(InvalidBufferDataError, match="None") as info:
        Buffer(None)
    assert isinstance(info.value, TypeError) and isinstance(info.value, RosidlBufferError)


def test_float_array_into_a_uint8_field_names_the_field():
    msg = get_message_type(TENSOR)()
    with pytest.raises(InvalidBufferDataError, match=r"ExperimentalTensor\.data.*float64"):
        msg.data = np.array([1.5, 2.5])
    assert len(msg.data) == 0  # nothing was stored
    with pytest.raises(TypeError, match="data"):
        get_message_type(TENSOR)(data=np.ones(3, np.float32))
    with pytest.raises(InvalidBufferDataError, match="int64"):  # no silent narrowing either
        msg.data = np.array([1, 2], dtype=np.int64)
    msg.data = [1, 2]  # Python ints that fit are fine
    assert msg.data == [1, 2]


def test_misspelt_field_suggests_the_close_match():
    msg = get_message_type(TENSOR)()
    with pytest.raises(UnknownFieldError, match="'strides'") as info:
        msg.strdes = [1]
    assert isinstance(info.value, AttributeError) and info.value.name == "strdes"
    with pytest.raises(TypeError, match="did you mean 'byte_offset'"):
        get_message_type(TENSOR)(byte_ofset=4)
    with pytest.raises(AttributeError, match="no field 'zzz'"):
        msg.zzz = 1


@pytest.mark.parametrize("framework", list(MODULES))
@pytest.mark.parametrize("value", [[1, 2, 3], "abc", 3.5, None])
def test_to_tensor_msg_of_an_unsupported_object(framework, value):
    with pytest.raises(tc.UnsupportedValueError) as info:
        MODULES[framework].to_tensor_msg(value)
    assert isinstance(info.value, TypeError)
    assert type(value).__name__ in str(info.value)


def test_another_frameworks_tensor_is_refused_by_name():
    with pytest.raises(tc.UnsupportedValueError, match="Tensor"):
        MODULES["numpy"].to_tensor_msg(torch.zeros(2))
    with pytest.raises(tc.UnsupportedValueError, match="ndarray"):
        MODULES["torch"].to_tensor_msg(np.zeros(2))


def test_image_given_to_tensor_functions():
    image = MODULES["numpy"].allocate_image_msg(2, 2, "mono8")
    for module in MODULES.values():
        for call in (module.from_input_tensor_msg, module.from_output_tensor_msg,
                     lambda m: module.to_tensor_msg(m, np.zeros(1))):
            with pytest.raises(tc.WrongMessageTypeError, match="Image"):
                call(image)


def test_buffer_numpy_is_zero_copy_or_copies_as_documented():
    storage = np.arange(8, dtype=np.uint8)
    buffer = Buffer(storage)
    assert buffer.numpy().ctypes.data == storage.ctypes.data  # writable storage: zero-copy
    msg = get_message_type(TENSOR)(data=storage)
    received = deserialize_message(bytes(serialize_message(msg)), type(msg))  # borrows them
    before = received.data.get_impl().view().ctypes.data
    view = received.data.numpy(writable=False)
    assert view.ctypes.data == before and not view.flags.writeable  # read-only zero-copy
    with pytest.raises(ValueError):
        view[0] = 1
    writable = received.data.numpy()  # copy-on-write, as the docstring says
    assert writable.flags.writeable and writable.ctypes.data != before
    np.testing.assert_array_equal(writable, storage)


@pytest.mark.parametrize("code, bits, shape, strides, nbytes", [
    (5, 64, [2**63 - 1], [0], 8),  # complex64 broadcast past what NumPy indexes
    (2, 32, [2**63 - 1, 0], [], 0),  # empty, but its other dimension overflows NumPy's size
    (1, 8, [2**40, 2**40], [0, 0], 1),
])
def test_metadata_past_what_the_frameworks_index_is_a_typed_error(code, bits, shape, strides,
                                                                   nbytes):
    """Metadata whose data fits (zero strides) but that no framework can index gave NumPy's and
    Warp's raw ValueError ("array is too big")."""
    tensor = get_message_type("tensor_msgs/msg/ExperimentalTensor")
    msg = tensor(dtype_code=code, dtype_bits=bits, dtype_lanes=1, byte_offset=0,
                 shape=np.array(shape, np.int64), strides=np.array(strides, np.int64),
                 data=np.zeros(nbytes, np.uint8))
    for module in MODULES.values():
        for clone in (False, True):
            with pytest.raises(tc.InvalidTensorMetadataError):
                module.from_input_tensor_msg(msg, clone=clone)


@pytest.mark.parametrize("shape", [(0, 2**62), (0, 2**63), (2**63,), (3, 2**61)])
def test_a_new_message_past_what_a_reader_takes_is_refused_when_made(shape):
    """allocate (and a loan's spec) took shapes its own reader refuses, or raised a raw
    OverflowError building the int64 shape."""
    from tensor_conversions import numpy as tn
    from tensor_conversions import torch as tt

    with pytest.raises(tc.InvalidTensorMetadataError):
        tt.allocate_tensor_msg(shape, torch.float32)
    with pytest.raises(tc.InvalidTensorMetadataError):
        tn.allocate_tensor_msg(shape, np.float64, backend="warp")
    empty = tn.allocate_tensor_msg((0, 2**20), np.float32)  # the largest are still made
    assert tn.from_input_tensor_msg(empty).shape == (0, 2**20)


@pytest.mark.parametrize("make", [lambda: torch.eye(3).to_sparse(),
                                  lambda: torch.eye(3).to_sparse_csr(),
                                  lambda: torch.nested.nested_tensor([torch.zeros(2),
                                                                      torch.zeros(3)])])
def test_a_sparse_or_nested_torch_tensor_is_a_typed_error(make):
    """They gave torch's raw RuntimeErrors ("copy_() between dense and sparse")."""
    import warnings

    from tensor_conversions import torch as tt

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (torch: sparse CSR and nested are beta/prototype)
        value = make()
    with pytest.raises(tc.UnsupportedValueError, match="dense"):
        tt.to_tensor_msg(value)


def test_warp_dimensions_past_int32_are_a_typed_error():
    from tensor_conversions import warp as tw

    tensor = get_message_type("tensor_msgs/msg/ExperimentalTensor")
    msg = tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, byte_offset=0,
                 shape=np.array([2**32 + 2], np.int64), strides=np.array([0], np.int64),
                 data=np.zeros(1, np.uint8))
    with pytest.raises(tc.InvalidTensorMetadataError, match="at most 2147483647"):
        tw.from_input_tensor_msg(msg, clone=False)


def test_a_cpu_tensor_too_large_to_index_is_a_typed_error():
    """NumPy's own ValueError ("Maximum allowed dimension exceeded") came out untyped."""
    import tensor_conversions.numpy as tn

    with pytest.raises(tc.InvalidTensorMetadataError, match="more than any tensor can"):
        tn.allocate_tensor_msg((2**40, 2**30), np.float32, backend="cpu")
