"""Loaned tensor messages: fill a publisher's reused warp storage in place, publish on exit.

    from tensor_conversions import torch as tc
    with tc.loan_tensor_msg(pub, (480, 640, 3), torch.uint8) as msg:
        out = tc.from_output_tensor_msg(msg)   # the same tensor object every loan of this block
        out.copy_(frame)
    # published here; the storage comes back to the next loan once every reader released it

A :class:`TensorLoanSpec` is the factory ``Publisher.loan`` calls when its pool has no free
message: an ExperimentalTensor over a :class:`warp_buffer.loan.LoanedBufferImpl`, with a
:class:`LoanState` on the message's ``_native`` slot. The state caches the writable views (one
per framework) built straight over the block's memory, without a write handle, so the second loan
of the same block reuses them and steady state allocates nothing. Views hold the impl (never
the message or its ``Buffer``, whose references the pool counts as holds).

The loan ends at publish. On Warp's ``cpu`` device the block's pages are read-only from publish
to the next loan of that block, so writing through a view kept past publish faults (SIGSEGV)
instead of changing what zero-copy subscribers read; on CUDA nothing can stop it: do not write
a loan's views after the ``with`` block. On CUDA, fill on the framework's current stream when
you call ``from_output_tensor_msg`` (torch's current stream for torch views): publish records the
write's completion there, and readers wait for it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .dlpack import TensorView, _host_bytes, warp_dtype
from .errors import StorageNotWritableError, UnsupportedBackendError
from .metadata import TensorLayout, contiguous_strides, normalize_shape, write_metadata

__all__ = ["LoanState", "TensorLoanSpec", "loan_tensor_msg"]


class LoanState:
    """What a loaned message keeps in ``_native``: its layout, the storage impl and the cached
    writable view per framework. Dropped by deepcopy and pickling (a copy is not loaned)."""

    __slots__ = ("layout", "impl", "view", "natives", "fields")

    def __init__(self, layout: TensorLayout, impl: Any) -> None:
        self.layout = layout
        self.impl = impl
        # The metadata values the spec writes (``_api.new_msg``): while the message still holds
        # them, its layout is this one and no per-loan validation is needed (untouched).
        dt = layout.dtype
        self.fields = (dt.code, dt.bits, dt.lanes, layout.byte_offset, list(layout.shape),
                       [] if layout.is_contiguous else list(layout.strides))
        self.view = TensorView(self._storage(), layout, writable=True)
        self.natives: dict[str, Any] = {}

    def _storage(self) -> Any:
        impl = self.impl
        if impl._host is not None:  # host memory: a NumPy carrier that keeps the impl alive
            return _host_bytes(impl._ptr, impl._size, owner=impl)
        return impl.array

    def holds(self, msg: Any) -> bool:
        """``msg`` still stores the loan's buffer (its views can be built over that memory)."""
        return msg.data.get_impl() is self.impl

    def view_for(self, layout: TensorLayout) -> TensorView:
        """A writable view of ``layout`` (checked to fit the loan's bytes) over the loan's own
        memory: the cached one for the spec's layout, else a new one (a reshape in the loan).
        Refused once published: the loan ended."""
        self._check_open()
        if layout == self.layout:
            return self.view
        return TensorView(self._storage(), layout, writable=True)

    def _check_open(self) -> None:
        if self.impl.is_published:
            raise StorageNotWritableError(
                "this loaned message was published: its loan ended, so it is no longer "
                "writable (take the next loan from the publisher)")

    def restore(self, msg: Any) -> None:
        """The next loan starts from the spec: its metadata and this state (a loan may have
        reshaped the message)."""
        if not self.untouched(msg):
            write_metadata(msg, self.layout)
        if getattr(msg, "_native", None) is not self:
            object.__setattr__(msg, "_native", self)

    def untouched(self, msg: Any) -> bool:
        """``msg`` still holds the spec's metadata and storage (so :meth:`matches` holds for its
        layout), judged without building the layout: a few compares per loan."""
        code, bits, lanes, offset, shape, strides = self.fields
        dims, steps = msg.shape, msg.strides
        return (type(dims) is np.ndarray and type(steps) is np.ndarray
                and msg.dtype_code == code and msg.dtype_bits == bits
                and msg.dtype_lanes == lanes and msg.byte_offset == offset
                and dims.tolist() == shape and steps.tolist() == strides
                and msg.data.get_impl() is self.impl)

    def native(self, adapter: Any) -> Any:
        self._check_open()
        view = self.view
        if view.device != "cpu":  # CUDA: publish records completion on the framework's stream
            stream = adapter.stream(view.device)
            if stream is not None:
                self.impl.write_on(stream)
        found = self.natives.get(adapter.name)
        if found is None:
            found = self.natives[adapter.name] = adapter.from_view(self.view)
        return found

    def __deepcopy__(self, memo: dict[int, Any]) -> None:
        return None

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(None), ())


def loaned_native(adapter: Any, msg: Any) -> Any:
    """The cached writable view of a loaned tensor message whose metadata was left as the loan
    made it (the common case: no layout to rebuild and look up), else None."""
    state = getattr(msg, "_native", None)
    if type(state) is LoanState and state.untouched(msg):
        return state.native(adapter)
    return None


def loan_state(msg: Any) -> LoanState | None:
    """The loan state of ``msg`` if it is a loaned message still holding its loan's buffer
    (whatever layout its metadata says now: views of it are built over the loan's memory)."""
    state = getattr(msg, "_native", None)
    if type(state) is LoanState and state.holds(msg):
        return state
    return None


class TensorLoanSpec:
    """The factory ``Publisher.loan`` takes for loaned ExperimentalTensor messages; specs with
    equal values share one pool (``loan_key``). ``reloan(msg)``: the pool hands a pooled message
    out again (its metadata back to the spec's)."""

    __slots__ = ("layout", "device", "loan_key")

    def __init__(self, adapter: Any, shape: Sequence[int] | int, dtype: Any,
                 backend: str = "warp", device: Any = None) -> None:
        if backend != "warp":
            raise UnsupportedBackendError(
                f"loans reuse warp storage (backend='warp'), not {backend!r}: a CPU message is "
                "reused through the publisher's pool only with a plain factory")
        dt = adapter.to_dtype(dtype)
        adapter.check_dtype(dt)
        warp_dtype(dt)
        dims = normalize_shape(shape)
        from .storage import resolve_warp_device

        self.layout = TensorLayout(dt, dims, contiguous_strides(dims), 0)
        self.device = resolve_warp_device(device)
        self.loan_key = ("tensor_conversions.tensor", self.layout, self.device)

    def __call__(self) -> Any:
        from warp_buffer.loan import loan_buffer

        from ._api import new_msg

        layout = self.layout
        data = loan_buffer(max(1, layout.required_nbytes), self.device)
        msg = new_msg(layout, "warp", self.device, data=data)
        object.__setattr__(msg, "_native", LoanState(layout, data.get_impl()))
        return msg

    def reloan(self, msg: Any) -> None:
        state = getattr(msg, "_native", None)
        if type(state) is LoanState:
            state.restore(msg)


_SPECS: dict[tuple[Any, ...], TensorLoanSpec] = {}


def loan_tensor_msg(adapter: Any, publisher: Any, shape: Sequence[int] | int, dtype: Any,
                    backend: str = "warp", device: Any = None) -> Any:
    """``publisher.loan(spec)`` for a tensor of ``shape``/``dtype`` (specs memoised by value)."""
    key = (adapter.name, shape if isinstance(shape, (int, np.integer)) else tuple(shape), dtype,
           backend, device)
    try:
        spec = _SPECS.get(key)
    except TypeError:  # an unhashable dtype or device: no memo
        spec = None
    if spec is None:
        spec = TensorLoanSpec(adapter, shape, dtype, backend, device)
        if len(_SPECS) >= 256:
            _SPECS.clear()
        try:
            _SPECS[key] = spec
        except TypeError:
            pass
    return publisher.loan(spec)
