"""Loaned messages: fill a publisher's reused warp storage in place, publish on exit.

    from tensor_conversions import torch as tc
    with tc.loan_tensor_msg(pub, (480, 640, 3), torch.uint8) as msg:
        out = tc.from_output_tensor_msg(msg)   # the same tensor object every loan of this block
        out.copy_(frame)
    # published here; the storage comes back to the next loan once nobody can read it

    with tc.loan_image_msg(pub, 720, 1280, "rgb8") as msg:   # sensor_msgs/Image, pooled too
        tc.from_output_image_msg(msg).copy_(frame)

A loan spec (:class:`TensorLoanSpec`, :class:`ImageLoanSpec`, :class:`PointCloudLoanSpec`) is the
factory ``Publisher.loan`` calls when its pool has no free message: the message its
``allocate_*_msg`` arguments describe, over a :class:`warp_buffer.loan.LoanedBufferImpl`, with a
:class:`LoanState` in the message's state (``_native``, :class:`.storage.NativeState`). Specs
with equal arguments share one pool (``loan_key``: the message type and the arguments). The state
caches the writable views (one per framework) built straight over the block's memory,
without a write handle: they are the owner's views (they keep the block leased to the loan, not a
reader's token), so the second loan of the same block reuses them and steady state allocates
nothing.

The loan ends at publish. On Warp's ``cpu`` device the block's pages are read-only from publish
to the next loan of that block, so writing through a view kept past publish faults (SIGSEGV)
instead of changing what zero-copy subscribers read; on CUDA nothing can stop it: do not write
a loan's views after the ``with`` block. On CUDA, fill on the framework's current stream when
you call ``from_output_*_msg`` (torch's current stream for torch views): publish records the
write's completion there, and readers wait for it.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from typing import Any

import numpy as np

from .dlpack import TensorView, warp_dtype
from .errors import (InvalidTensorMetadataError, StorageNotWritableError, UnsupportedBackendError,
                     UnsupportedValueError)
from .metadata import TensorLayout, write_metadata
from .storage import NativeState, resolve_warp_device

__all__ = ["ImageLoanSpec", "LoanState", "PointCloudLoanSpec", "TensorLoanSpec",
           "loan_image_msg", "loan_pointcloud_msg", "loan_tensor_msg"]

_PUBLISHED: int | None = None  # warp_buffer.lease.PUBLISHED (imported with the first loan)


class LoanState:
    """A loaned message's loan (in its :class:`.storage.NativeState`): its spec, the storage
    impl and its lease, the buffer the current loan handed out, and the cached writable views
    (per framework and layout)."""

    __slots__ = ("spec", "impl", "lease", "buffer", "view", "natives")

    def __init__(self, spec: _LoanSpec, data: Any) -> None:
        self.spec = spec
        self.impl = impl = data.get_impl()
        self.lease = impl.lease
        # Weakly: the Buffer a loan hands out is its holders' token (buffer_pubsub.loan)
        self.buffer = weakref.ref(data)
        self.view = TensorView(impl.owner_view(), spec.layout, writable=True)
        self.natives: dict[Any, Any] = {}

    @property
    def layout(self) -> TensorLayout:
        return self.spec.layout

    def holds(self, msg: Any) -> bool:
        """``msg`` still stores the loan's storage (its views can be built over that memory)."""
        data = msg.data
        return data is self.buffer() or data.get_impl() is self.impl

    def view_for(self, layout: TensorLayout) -> TensorView:
        """A writable view of ``layout`` (checked to fit the loan's bytes) over the loan's own
        memory: the cached one for the spec's layout, else a new one (a reshape in the loan).
        Refused once published: the loan ended."""
        self._check_open()
        if layout == self.spec.layout:
            return self.view
        return TensorView(self.impl.owner_view(), layout, writable=True)

    def _check_open(self) -> None:
        if self.lease.state == _PUBLISHED:
            raise StorageNotWritableError(
                "this loaned message was published: its loan ended, so it is no longer "
                "writable (take the next loan from the publisher)")

    def native(self, adapter: Any) -> Any:
        """The cached writable native view of the spec's layout for ``adapter``'s framework
        (built on first use). Refused once published: the loan ended."""
        if self.lease.state == _PUBLISHED:
            self._check_open()
        found = self.natives.get(adapter.name)
        if found is None:
            adapter.check_dtype(self.spec.layout.dtype)
            found = self.natives[adapter.name] = adapter.from_view(self.view)
        view = self.view
        if view.device != "cpu":  # CUDA: publish records completion on the framework's stream
            stream = adapter.stream(view.device)
            if stream is not None:
                self.impl.write_on(stream)
        return found


def loan_state(msg: Any) -> LoanState | None:
    """The loan of ``msg`` if it is a loaned message still holding its loan's storage
    (whatever layout its metadata says now: views of it are built over the loan's memory)."""
    state = getattr(msg, "_native", None)
    if type(state) is NativeState:
        loan = state.loan
        if loan is not None and loan.holds(msg):
            return loan
    return None


def loaned_native(adapter: Any, msg: Any) -> Any:
    """The cached writable view of a loaned message whose metadata and buffer are as the loan
    made them (the common case: a few compares, no layout to rebuild), else None.
    (:meth:`LoanState.native` inline: this runs once per loan.)"""
    state = getattr(msg, "_native", None)
    if type(state) is not NativeState:
        return None
    loan = state.loan
    if loan is None or msg.data is not loan.buffer() or not loan.spec.untouched(msg):
        return None
    if loan.lease.state == _PUBLISHED:
        loan._check_open()
    found = loan.natives.get(adapter.name)
    if found is None or loan.view.device != "cpu":
        return loan.native(adapter)
    return found


class _LoanSpec:
    """What every loan spec shares: the layout of its cached views, the Warp device, the pool
    key, the factory call and the re-loan (see the module docstring)."""

    __slots__ = ("layout", "device", "loan_key", "nbytes")

    def _storage_device(self, backend: str, device: Any) -> str:
        if backend != "warp":
            raise UnsupportedBackendError(
                f"loans reuse warp storage (backend='warp'), not {backend!r}: a CPU message is "
                "reused through the publisher's pool only with a plain factory")
        return resolve_warp_device(device)

    def new_msg(self, data: Any) -> Any:
        """A new message of the spec over ``data`` (metadata written)."""
        raise NotImplementedError

    def untouched(self, msg: Any) -> bool:
        """``msg`` still holds the spec's metadata (a few compares per loan)."""
        raise NotImplementedError

    def write(self, msg: Any) -> None:
        """Write the spec's metadata into ``msg``."""
        raise NotImplementedError

    def __call__(self) -> Any:
        global _PUBLISHED
        from warp_buffer.lease import PUBLISHED
        from warp_buffer.loan import loan_buffer

        _PUBLISHED = PUBLISHED
        data = loan_buffer(max(1, self.nbytes), self.device)
        msg = self.new_msg(data)
        object.__setattr__(msg, "_native", NativeState(LoanState(self, data)))
        return msg

    def reloan(self, msg: Any) -> None:
        """The pool hands ``msg`` out again: back to the spec's metadata (a loan may have
        changed it), over the Buffer this loan hands out."""
        state = getattr(msg, "_native", None)
        loan = state.loan if type(state) is NativeState else None
        if loan is not None:
            loan.buffer = weakref.ref(msg.data)
            if not self.untouched(msg):
                self.write(msg)


class TensorLoanSpec(_LoanSpec):
    """The factory ``Publisher.loan`` takes for loaned ExperimentalTensor messages (the
    arguments of ``allocate_tensor_msg``); specs with equal values share one pool."""

    __slots__ = ("fields",)

    def __init__(self, adapter: Any, shape: Sequence[int] | int, dtype: Any,
                 backend: str = "warp", device: Any = None) -> None:
        device = self._storage_device(backend, device)
        dt = adapter.to_dtype(dtype)
        adapter.check_dtype(dt)
        warp_dtype(dt)
        self.layout = layout = TensorLayout.contiguous(dt, shape)
        dims = layout.shape
        self.nbytes = layout.required_nbytes
        self.device = device
        # plain values: hashed in C at every loan (a dataclass's hash is a Python call)
        self.loan_key = ("tensor_msgs/msg/ExperimentalTensor", dt.code, dt.bits, dt.lanes, dims,
                         device)
        # The metadata values new_msg writes: while the message holds them, its layout is the
        # spec's and no per-loan validation is needed.
        self.fields = (dt.code, dt.bits, dt.lanes, 0, list(dims), [])

    def new_msg(self, data: Any) -> Any:
        from ._api import new_msg

        return new_msg(self.layout, "warp", self.device, data=data)

    def untouched(self, msg: Any) -> bool:
        code, bits, lanes, offset, shape, strides = self.fields
        dims, steps = msg.shape, msg.strides
        return (type(dims) is np.ndarray and type(steps) is np.ndarray
                and msg.dtype_code == code and msg.dtype_bits == bits
                and msg.dtype_lanes == lanes and msg.byte_offset == offset
                and dims.tolist() == shape and steps.tolist() == strides)

    def write(self, msg: Any) -> None:
        write_metadata(msg, self.layout)


class ImageLoanSpec(_LoanSpec):
    """The factory ``Publisher.loan`` takes for loaned ``sensor_msgs/msg/Image`` messages (the
    arguments of ``allocate_image_msg``); specs with equal values share one pool. Its cached
    view is the image's HWC view (the row padding ``step`` is the row stride)."""

    __slots__ = ("fields",)

    def __init__(self, adapter: Any, height: int, width: int, encoding: str,
                 backend: str = "warp", device: Any = None, step: int | None = None) -> None:
        from .image import IMAGE_MSG_TYPE, image_spec

        device = self._storage_device(backend, device)
        height, width, step, layout = image_spec(adapter, height, width, encoding, step)
        warp_dtype(layout.dtype)
        self.layout, self.device = layout, device
        self.nbytes = step * height  # (the last row's padding too: what the image says)
        self.fields = (height, width, encoding, step)
        self.loan_key = (IMAGE_MSG_TYPE, self.fields, device)

    def new_msg(self, data: Any) -> Any:
        from .image import new_image_msg

        return new_image_msg(*self.fields, data)

    def untouched(self, msg: Any) -> bool:
        from .image import NATIVE_BIGENDIAN

        height, width, encoding, step = self.fields
        return (msg.height == height and msg.width == width and msg.step == step
                and msg.encoding == encoding and msg.is_bigendian == NATIVE_BIGENDIAN)

    def write(self, msg: Any) -> None:
        from .image import NATIVE_BIGENDIAN

        msg.height, msg.width, msg.encoding, msg.step = self.fields
        msg.is_bigendian = NATIVE_BIGENDIAN


class PointCloudLoanSpec(_LoanSpec):
    """The factory ``Publisher.loan`` takes for loaned ``sensor_msgs/msg/PointCloud2`` messages
    (the arguments of ``allocate_pointcloud_msg``: fields of one dtype, packed); specs with
    equal values share one pool. Its cached view is the ``(height * width, len(fields))``
    tensor of the points."""

    __slots__ = ("fields",)

    def __init__(self, adapter: Any, width: int, fields: Sequence[str], dtype: Any,
                 height: int = 1, backend: str = "warp", device: Any = None) -> None:
        from .pointcloud import POINTCLOUD_MSG_TYPE, cloud_spec

        device = self._storage_device(backend, device)
        names, dt, height, width, layout = cloud_spec(adapter, width, fields, dtype, height)
        warp_dtype(dt)
        self.layout, self.device = layout, device
        self.nbytes = layout.required_nbytes
        self.fields = (names, dt, height, width)
        self.loan_key = (POINTCLOUD_MSG_TYPE, names, dt.name, height, width, device)

    def new_msg(self, data: Any) -> Any:
        from .pointcloud import new_cloud_msg

        return new_cloud_msg(*self.fields, data)

    def untouched(self, msg: Any) -> bool:
        from .pointcloud import cloud_matches

        return cloud_matches(msg, *self.fields)

    def write(self, msg: Any) -> None:
        from .pointcloud import write_cloud_metadata

        write_cloud_metadata(msg, *self.fields)


_SPECS: dict[tuple[Any, ...], _LoanSpec] = {}


def _loan(publisher: Any, kind: type[_LoanSpec], adapter: Any, *args: Any,
          max_loans: int | None = None) -> Any:
    """``publisher.loan(spec, max_loans=max_loans)`` for a spec of ``kind`` with ``args``
    (specs memoised by value, so a loan per frame builds no spec). ``max_loans``: the most
    pooled messages of the spec (:meth:`buffer_pubsub.Publisher.loan`; default 16): a
    subscriber that keeps frames, and its queue, hold pooled messages."""
    key = (kind, adapter.name, *args)
    try:
        spec = _SPECS.get(key)
    except TypeError:  # an unhashable argument (a dtype, a device): no memo
        spec = None
        key = None  # type: ignore[assignment]
    if spec is None:
        spec = kind(adapter, *args)
        if key is not None:
            if len(_SPECS) >= 256:
                _SPECS.clear()
            _SPECS[key] = spec
    return _loan_from(publisher, spec, max_loans)


def _loan_from(publisher: Any, spec: _LoanSpec, max_loans: int | None) -> Any:
    """``publisher.loan(spec)``; anything but a publisher is :class:`UnsupportedValueError`."""
    try:
        loan = publisher.loan
    except AttributeError:
        raise UnsupportedValueError(f"a loan comes from a buffer_pubsub Publisher, not "
                                    f"{type(publisher).__name__}") from None
    return loan(spec, max_loans=max_loans)


def loan_tensor_msg(adapter: Any, publisher: Any, shape: Sequence[int] | int, dtype: Any,
                    backend: str = "warp", device: Any = None, *,
                    max_loans: int | None = None) -> Any:
    """``publisher.loan(spec)`` for a tensor of ``shape``/``dtype`` (:func:`_loan` inline: the
    memo lookup of a loan per frame)."""
    if shape.__class__ is not tuple and not isinstance(shape, (int, np.integer)):
        try:
            shape = tuple(shape)
        except TypeError:
            raise InvalidTensorMetadataError(
                f"shape must be a sequence of ints, got {shape!r}") from None
    try:
        spec = _SPECS.get((TensorLoanSpec, adapter.name, shape, dtype, backend, device))
    except TypeError:  # an unhashable argument: no memo
        spec = None
    if spec is None:
        return _loan(publisher, TensorLoanSpec, adapter, shape, dtype, backend, device,
                     max_loans=max_loans)
    return _loan_from(publisher, spec, max_loans)


def loan_image_msg(adapter: Any, publisher: Any, height: int, width: int, encoding: str,
                   backend: str = "warp", device: Any = None, step: int | None = None, *,
                   max_loans: int | None = None) -> Any:
    """``publisher.loan(spec)`` for an Image (the arguments of ``allocate_image_msg``)."""
    return _loan(publisher, ImageLoanSpec, adapter, height, width, encoding, backend, device,
                 step, max_loans=max_loans)


def loan_pointcloud_msg(adapter: Any, publisher: Any, width: int, fields: Sequence[str],
                        dtype: Any, height: int = 1, backend: str = "warp",
                        device: Any = None, *, max_loans: int | None = None) -> Any:
    """``publisher.loan(spec)`` for a PointCloud2 (the arguments of
    ``allocate_pointcloud_msg``)."""
    if isinstance(fields, str) or not isinstance(fields, Sequence):
        raise InvalidTensorMetadataError(
            f"fields must be a sequence of field names, got {fields!r}")
    return _loan(publisher, PointCloudLoanSpec, adapter, width, tuple(fields), dtype, height,
                 backend, device, max_loans=max_loans)
