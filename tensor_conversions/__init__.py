"""tensor_conversions: ``tensor_msgs/msg/ExperimentalTensor`` <-> torch, NumPy and Warp.

The core here is framework-neutral: DLPack dtypes (:mod:`.dtypes`), metadata validation
(:mod:`.metadata`), storage backends (:mod:`.storage`) and :class:`TensorView`, a zero-copy
DLPack producer over a message's bytes (:mod:`.dlpack`). One module per framework offers the same
four operations: ``allocate_tensor_msg``, ``from_output_tensor_msg``, ``from_input_tensor_msg``
and ``to_tensor_msg``:

    from tensor_conversions import torch as tc
    msg = tc.allocate_tensor_msg((480, 640, 3), torch.uint8, backend="warp", device="cuda:0")
    out = tc.from_output_tensor_msg(msg)   # fill in place
    out[:] = frame
    del out                                # or tensor_conversions.release_output(msg)

Framework modules are imported on demand (``import tensor_conversions.torch``), so the core
needs none of them.
"""

from .dlpack import TensorView, input_view, output_view
from .dtypes import (
    SUPPORTED_DTYPES,
    DLDataTypeCode,
    DType,
    dtype_from_metadata,
    dtype_from_name,
    dtype_from_numpy,
)
from .errors import (
    InvalidTensorMetadataError,
    TensorConversionError,
    TensorSizeError,
    UnsupportedBackendError,
    UnsupportedDTypeError,
    UnsupportedEncodingError,
    UnsupportedValueError,
    WrongMessageTypeError,
)
from .metadata import (
    TENSOR_MSG_TYPE,
    TensorLayout,
    contiguous_strides,
    layout_of,
    tensor_msg_type,
    write_metadata,
)
from .storage import release_output

__all__ = [
    "SUPPORTED_DTYPES",
    "TENSOR_MSG_TYPE",
    "DLDataTypeCode",
    "DType",
    "InvalidTensorMetadataError",
    "TensorConversionError",
    "TensorLayout",
    "TensorSizeError",
    "TensorView",
    "UnsupportedBackendError",
    "UnsupportedDTypeError",
    "UnsupportedEncodingError",
    "UnsupportedValueError",
    "WrongMessageTypeError",
    "contiguous_strides",
    "dtype_from_metadata",
    "dtype_from_name",
    "dtype_from_numpy",
    "input_view",
    "layout_of",
    "output_view",
    "release_output",
    "tensor_msg_type",
    "write_metadata",
]
