"""tensor_conversions: ROS 2 messages <-> torch, NumPy, Warp, JAX, CuPy and ONNX Runtime.

One small framework-neutral core lets DLPack carry dtype, shape, strides, device and ownership:
:class:`TensorView` (:mod:`.dlpack`) lays a NumPy or Warp array over a message's bytes and
forwards ``__dlpack__``; layouts are validated once per distinct metadata (:mod:`.metadata`);
storage and handles live in :mod:`.storage`. One module per framework offers the same four
operations on ``tensor_msgs/msg/ExperimentalTensor``: ``allocate_tensor_msg``,
``from_output_tensor_msg``, ``from_input_tensor_msg`` and ``to_tensor_msg``; torch, NumPy and Warp
also the same four for ``sensor_msgs/msg/Image`` (:mod:`.image`) and
``from_input_pointcloud_msg`` for ``sensor_msgs/msg/PointCloud2`` (:mod:`.pointcloud`):

    from tensor_conversions import torch as tc
    msg = tc.allocate_tensor_msg((480, 640, 3), torch.uint8, backend="warp", device="cuda:0")
    out = tc.from_output_tensor_msg(msg)   # fill in place, on torch's current stream
    out[:] = frame
    del out                                # or tensor_conversions.release_output(msg)

A publisher's loans (:mod:`.loan`) reuse the storage and the views frame after frame::

    with tc.loan_tensor_msg(pub, (480, 640, 3), torch.uint8) as msg:
        tc.from_output_tensor_msg(msg).copy_(frame)   # published on exit

Framework modules are imported on demand (``import tensor_conversions.jax``), so the core needs
none of them; JAX, CuPy and ONNX Runtime are optional extras.
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
    StorageNotWritableError,
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
    "StorageNotWritableError",
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
