"""``Buffer``: the storage of a ``uint8[]`` message field, in CPU memory or a backend's domain.

Mirrors ``rosidl::Buffer<T>``: a pimpl over a :class:`BufferImplBase`. ``Buffer()`` and
``Buffer(array_like)`` are CPU buffers that behave like a growable 1-D array; ``Buffer(impl)`` is
the only way to hold another backend. Operations that need host memory raise
:class:`CpuBackendRequiredError` naming the current backend when the storage is elsewhere.
"""

from __future__ import annotations

import operator
from collections.abc import Iterable, Iterator
from typing import Any, Generic, TypeVar

import numpy as np
import numpy.typing as npt

from .buffer_impl import CPU_BACKEND, BufferImplBase, CpuBufferImpl, exact_array
from .errors import CpuBackendRequiredError, InvalidBufferDataError

__all__ = ["Buffer", "impl_of", "set_impl", "set_origin"]

T = TypeVar("T", bound=np.generic)
_new_buffer = object.__new__


def _values(value: Any, dtype: np.dtype, ndim: int | None) -> np.ndarray:
    """``value`` as ``ndim``-D (0: one value, 1: a sequence, None: any) ``dtype`` data for a
    mutator, checked before the buffer changes: floats for an integer buffer and values out of
    its range raise :class:`InvalidBufferDataError` (as ``Buffer(data)`` does), rather than being
    stored truncated or wrapped."""
    try:
        array = exact_array(value, dtype, same_kind=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise _cannot_store(value, dtype, exc) from None
    if ndim is not None and array.ndim != ndim:
        raise InvalidBufferDataError(
            f"expected {'one value' if ndim == 0 else 'a 1-D sequence'} for a {dtype} buffer, "
            f"got shape {array.shape}")
    return array


def _cannot_store(data: Any, dtype: npt.DTypeLike, exc: Exception) -> InvalidBufferDataError:
    kind = f"{type(data).__name__} {data.dtype}" if isinstance(data, np.ndarray) \
        else type(data).__name__
    return InvalidBufferDataError(f"cannot store {kind} data in a {np.dtype(dtype)} buffer: {exc}")


_PYBUF_WRITABLE = 0x0001  # (inspect.BufferFlags.WRITABLE, 3.12+)


class Buffer(Generic[T]):
    """A contiguous 1-D array of ``dtype`` elements (default uint8) held by a backend impl.

    Works on every backend: ``len``, :meth:`size`, :meth:`empty`, :meth:`get_backend_type`,
    :meth:`get_impl`, :meth:`to_numpy`, ``==`` and ``copy.copy`` (a deep clone in the same
    backend). Everything else (indexing, slicing, iteration, :meth:`resize`, :meth:`append`,
    :meth:`numpy`, the buffer protocol) requires CPU storage.
    """

    # ``_origin``: set on a reader's share only (see :data:`set_origin`), else unset.
    __slots__ = ("_impl", "_origin", "__weakref__")

    def __init__(
        self,
        data: BufferImplBase | npt.ArrayLike | bytes = (),
        dtype: npt.DTypeLike | None = None,
    ) -> None:
        if data is None:
            raise InvalidBufferDataError(
                "Buffer(None) is not allowed: pass a BufferImplBase, an array-like, or nothing"
            )
        if isinstance(data, BufferImplBase):
            if dtype is not None and np.dtype(dtype) != data.dtype:
                raise InvalidBufferDataError(f"impl stores {data.dtype}, not {np.dtype(dtype)}")
            self._impl: BufferImplBase = data
        elif isinstance(data, str):
            raise InvalidBufferDataError(
                "Buffer takes bytes or array-like data, not a str: encode it first")
        else:
            try:
                self._impl = CpuBufferImpl(data, np.uint8 if dtype is None else dtype)
            except (TypeError, ValueError, OverflowError) as exc:
                # float values for a uint8 buffer (never cast silently), 300 for a uint8, ...
                raise _cannot_store(data, np.uint8 if dtype is None else dtype, exc) from None

    @classmethod
    def _of(cls, impl: BufferImplBase) -> Buffer[Any]:
        """A Buffer over ``impl`` without the checks of ``__init__`` (decoders call it once per
        field per message; the caller guarantees ``impl`` is a BufferImplBase)."""
        buffer = cls.__new__(cls)
        buffer._impl = impl
        return buffer

    # -- every backend -------------------------------------------------------------------------
    def get_impl(self) -> BufferImplBase:
        """The backend storage behind this buffer (a :class:`BufferImplBase`)."""
        return self._impl

    def get_backend_type(self) -> str:
        """Name of the backend holding the data (``"cpu"``, ``"warp"``)."""
        return self._impl.get_backend_type()

    def is_cpu(self) -> bool:
        """True when the data lives in host memory (a :class:`CpuBufferImpl`), so the CPU-only
        operations work."""
        return isinstance(self._impl, CpuBufferImpl)

    @property
    def dtype(self) -> np.dtype:
        """NumPy dtype of one element (uint8 unless given)."""
        return self._impl.dtype

    @property
    def nbytes(self) -> int:
        """Size of the contents in bytes (elements times the item size)."""
        return self._impl.nbytes

    def size(self) -> int:
        """Number of elements (bytes only for a uint8 buffer); any backend."""
        return self._impl.size()

    def empty(self) -> bool:
        """True when the buffer holds no elements; any backend."""
        return self._impl.size() == 0

    def __len__(self) -> int:
        return self._impl.size()

    def __bool__(self) -> bool:
        return self._impl.size() != 0

    def to_numpy(self) -> np.ndarray:
        """A CPU array of the contents: a copy (``to_cpu`` of the backend, or of CPU storage)."""
        if isinstance(self._impl, CpuBufferImpl):
            return self._impl.view().copy()
        return self._impl.to_cpu().view()

    def to_cpu(self) -> Buffer[T]:
        """A CPU buffer with the same contents (a copy, whatever the backend)."""
        return Buffer(self._impl.to_cpu())

    def tobytes(self) -> bytes:
        """The contents as ``bytes`` (a copy; any backend, copied to the host first)."""
        return self.host_view().tobytes()

    def host_view(self) -> np.ndarray:
        """Contents in host memory, to read: a view for CPU storage (no copy), a ``to_cpu``
        copy otherwise (any backend). What the CDR codec writes for a buffer sent as CPU bytes,
        and what comparisons read."""
        if isinstance(self._impl, CpuBufferImpl):
            return self._impl.view()
        return self._impl.to_cpu().view()

    def __eq__(self, other: object) -> bool:
        if isinstance(other, Buffer):
            if other is self:
                return True
            if self.size() != other.size():
                return False
            return bool(np.array_equal(self.host_view(), other.host_view()))
        if isinstance(other, (list, tuple, np.ndarray, bytes, bytearray, memoryview)):
            theirs = np.frombuffer(other, np.uint8) if isinstance(
                other, (bytes, bytearray, memoryview)) else np.asarray(other)
            return theirs.ndim == 1 and bool(np.array_equal(self.host_view(), theirs))
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]  # mutable, like list

    def __copy__(self) -> Buffer[T]:
        return Buffer(self._impl.clone())

    def __deepcopy__(self, memo: dict[int, Any]) -> Buffer[T]:
        return Buffer(self._impl.clone())

    def copy(self) -> Buffer[T]:
        """Deep clone in the same backend (``rosidl::Buffer``'s copy constructor)."""
        return Buffer(self._impl.clone())

    def share(self) -> Buffer[T]:
        """Another ``Buffer`` over the same storage (no copy): a holder of the same bytes whose
        lifetime is its own. A publisher's loan pool hands out one per loan: a ``Buffer`` is the
        token of whoever keeps it (see ``buffer_pubsub.loan``)."""
        buffer = _new_buffer(Buffer)
        buffer._impl = self._impl
        return buffer

    # -- lifetime ------------------------------------------------------------------------------
    def seal(self) -> None:
        """End write access (see :meth:`BufferImplBase.seal`); the transport calls it on publish."""
        self._impl.seal()

    def release(self) -> None:
        """End this buffer's access to its storage now, as dropping an iceoryx2 sample does:
        later access to the bytes through it raises :class:`BufferReleasedError` (warp_buffer's
        ``HandleReleasedError``); its size and backend still answer. Idempotent.

        What it held goes back: a received zero-copy buffer's hold on the publisher's memory,
        an in-process subscription's share of its publisher's buffer (:data:`set_origin`).
        Storage other holders share (views taken before, another ``Buffer`` over it, the
        publisher's own) stays theirs and readable."""
        impl = self._impl
        impl.release()
        self._origin = None  # (a reader's share: the publisher's buffer no longer held by us)
        self._impl = impl.as_released()

    def __enter__(self) -> Buffer[T]:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.release()

    def __repr__(self) -> str:
        backend = self.get_backend_type()
        if isinstance(self._impl, CpuBufferImpl):
            return f"Buffer({np.array2string(self._impl.view(), threshold=8)}, dtype={self.dtype})"
        return f"Buffer(<{backend}>, size={self.size()}, dtype={self.dtype})"

    # -- CPU only ------------------------------------------------------------------------------
    def _cpu(self, operation: str) -> CpuBufferImpl:
        impl = self._impl
        if not isinstance(impl, CpuBufferImpl):
            raise CpuBackendRequiredError(operation, impl.get_backend_type())
        return impl

    def numpy(self, *, writable: bool = True) -> np.ndarray:
        """A NumPy view of CPU storage (invalidated by a later resize).

        ``writable=True`` (default): a writable view. It is zero-copy, except for storage
        borrowed read-only from received bytes: that is copied once first (copy-on-write), and
        the view is of the copy. ``writable=False``: always zero-copy, ``flags.writeable`` is
        False (what a subscriber that only reads should use).
        """
        impl = self._cpu("numpy")
        if writable:
            return impl.writable_view()
        view = impl.view().view()  # a new array object, so the flag does not leak to others
        view.flags.writeable = False
        return view

    data = numpy

    def __array__(self, dtype: npt.DTypeLike | None = None, copy: bool | None = None) -> np.ndarray:
        view = self._cpu("__array__").view()
        if dtype is not None and np.dtype(dtype) != view.dtype:
            if copy is False:  # NumPy 2's protocol: refuse rather than hand back a copy
                raise ValueError(f"a {view.dtype} buffer cannot be viewed as {np.dtype(dtype)} "
                                 "without a copy (copy=False)")
            return view.astype(dtype)
        return view.copy() if copy else view

    def memoryview(self) -> memoryview:
        """A writable memoryview (received bytes are copied first, as any write copies them).
        On Python 3.12+ ``memoryview(buffer)`` is the buffer protocol: zero-copy, read-only over
        received bytes."""
        return memoryview(self._cpu("memoryview").writable_view())

    # The buffer protocol from Python 3.12 on (3.11 ignores the method).
    def __buffer__(self, flags: int) -> memoryview:
        view = self._cpu("buffer protocol").view()
        if flags & _PYBUF_WRITABLE and not view.flags.writeable:
            # Received bytes are borrowed: refused as a read-only object refuses a writable
            # request, so NumPy (asarray, frombuffer) asks again read-only and copies
            # nothing. buffer[...] and .memoryview() write, copying first.
            raise BufferError("this buffer holds received bytes, read-only through the "
                              "buffer protocol: buffer.memoryview() is a writable copy")
        return memoryview(view)

    def __bytes__(self) -> bytes:
        return self._cpu("bytes").view().tobytes()

    def __getitem__(self, index: int | slice) -> Any:
        view = self._cpu("__getitem__").view()
        return view[index]

    def __setitem__(self, index: int | slice, value: Any) -> None:
        impl = self._cpu("__setitem__")
        impl.writable_view()[index] = _values(value, impl.dtype, None)

    def __iter__(self) -> Iterator[Any]:
        return iter(self._cpu("__iter__").view().tolist())

    def __contains__(self, value: object) -> bool:
        return bool(np.any(self._cpu("__contains__").view() == value))

    def capacity(self) -> int:
        """Elements the storage holds before growing reallocates, like ``vector::capacity``
        (CPU only)."""
        return self._cpu("capacity").capacity()

    def reserve(self, capacity: int) -> None:
        """Grow the CPU storage to hold at least ``capacity`` elements without reallocating,
        like ``vector::reserve``; the size is unchanged (CPU only)."""
        self._cpu("reserve").reserve(capacity)

    def resize(self, size: int, value: int | float = 0) -> None:
        """Set the number of elements, like ``vector::resize``: new ones are ``value``, extra ones
        are dropped (CPU only)."""
        impl = self._cpu("resize")
        impl.resize(size, _values(value, impl.dtype, 0))

    def clear(self) -> None:
        """Remove every element (size 0, capacity kept; CPU only)."""
        self._cpu("clear").resize(0)

    def append(self, value: int | float) -> None:
        """Add one element at the end (CPU only; ``push_back`` is the same method)."""
        impl = self._cpu("append")
        impl.resize(impl.size() + 1, _values(value, impl.dtype, 0))

    push_back = append

    def extend(self, values: Iterable[Any] | np.ndarray | bytes) -> None:
        """Add ``values`` at the end: a sequence, an array, bytes or another ``Buffer`` (CPU only;
        checked before the buffer grows)."""
        impl = self._cpu("extend")
        if isinstance(values, (bytes, bytearray, memoryview)):
            values = np.frombuffer(values, dtype=np.uint8)
        elif isinstance(values, Buffer):
            values = values.host_view()
        elif not hasattr(values, "__len__"):
            values = list(values)
        array = _values(values, impl.dtype, 1)  # checked before the buffer grows
        n = impl.size()
        impl.resize(n + array.shape[0])
        impl.writable_view()[n:] = array

    def insert(self, index: int, value: int | float) -> None:
        """Insert ``value`` before ``index``, as ``list.insert`` does (out-of-range indices clamp;
        CPU only)."""
        impl = self._cpu("insert")
        n = impl.size()
        if index < 0:
            index = max(0, n + index)
        index = min(index, n)
        item = _values(value, impl.dtype, 0)  # checked before the buffer grows
        impl.resize(n + 1)
        view = impl.writable_view()
        view[index + 1:] = view[index:n].copy()
        view[index] = item

    def pop(self, index: int = -1) -> Any:
        """Remove and return the element at ``index`` (the last by default), as ``list.pop``
        does; :class:`IndexError` if empty or out of range (CPU only)."""
        impl = self._cpu("pop")
        n = impl.size()
        if n == 0:
            raise IndexError("pop from empty Buffer")
        if index < 0:
            index += n
        if not 0 <= index < n:
            raise IndexError("pop index out of range")
        view = impl.writable_view()
        value = view[index].item()
        view[index:n - 1] = view[index + 1:n].copy()
        impl.resize(n - 1)
        return value

    def erase(self, start: int, stop: int | None = None) -> None:
        """Remove ``[start, stop)`` (or the one element at ``start``), like ``vector::erase``."""
        impl = self._cpu("erase")
        n = impl.size()
        stop = start + 1 if stop is None else stop
        if not 0 <= start <= stop <= n:
            raise IndexError(f"erase range [{start}, {stop}) outside [0, {n})")
        view = impl.writable_view()
        view[start:n - (stop - start)] = view[stop:n].copy()
        impl.resize(n - (stop - start))

    def swap(self, other: Buffer[T]) -> None:
        """Exchange storage with another buffer (any backends), like ``vector::swap``."""
        self._impl, other._impl = other._impl, self._impl

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickling sends CPU bytes; a backend buffer is not picklable by reference.
        return (Buffer, (self.to_numpy(),))


# The storage slot of a Buffer, as C-level callables (no Python frame, unlike get_impl(), which is
# a method): for the message codec (rosidl_buffer.messages), which reads a buffer's impl once per
# buffer field of every message it serializes and sets one per field it deserializes.
#: ``impl_of(buffer)``: what ``buffer.get_impl()`` returns.
impl_of = operator.attrgetter("_impl")
#: ``set_impl(buffer, impl)``: the storage of ``buffer`` becomes ``impl``, unchecked (``impl``
#: must be a BufferImplBase): for a Buffer made with ``Buffer.__new__(Buffer)``, without the
#: checks of ``__init__``.
set_impl = Buffer._impl.__set__  # type: ignore[attr-defined]
#: ``set_origin(share, buffer)``: makes ``share`` (a Buffer over ``buffer``'s storage, see
#: ``set_impl``) a *reader's share*: a token of one more reader (an in-process subscription's
#: message) that holds ``buffer`` until it is released or collected, so a publisher's loan
#: pool, which watches ``buffer``, sees the storage held. Unlike :meth:`Buffer.share` (a loan's
#: token, independent of the Buffer it came from). The transport's snapshot copier makes them.
set_origin = Buffer._origin.__set__  # type: ignore[attr-defined]
