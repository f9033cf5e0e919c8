"""Buffer implementations: the abstract pimpl interface and the NumPy-backed CPU storage.

Mirrors ``rosidl::BufferImplBase<T>`` and ``rosidl::CpuBufferImpl<T>``: a backend subclasses
:class:`BufferImplBase` and keeps all of its state (device memory, IPC handles, sync objects) in it.
"""

from __future__ import annotations

import abc
import ctypes
import threading
import weakref
from typing import Any, NoReturn

import numpy as np
import numpy.typing as npt

from .errors import BufferReleasedError

__all__ = ["BufferImplBase", "CpuBufferImpl", "CPU_BACKEND", "array_at", "exact_array"]

CPU_BACKEND = "cpu"
_BYTES = ctypes.c_uint8


def array_at(address: int, nbytes: int, owner: Any = None) -> np.ndarray:
    """A writable 1-D uint8 NumPy array over ``nbytes`` of host memory at ``address`` (no
    copy). ``owner`` stays alive as long as the array and every view of it: their ``base`` is
    the ctypes array this makes, which keeps it (what keeps the memory mapped, or a reader's
    token). ``nbytes`` 0 gives an empty array over no memory."""
    if nbytes <= 0 or not address:
        return np.zeros(0, dtype=np.uint8)
    raw = (_BYTES * nbytes).from_address(address)
    # This module's own attribute on the ctypes array it just made (never read: it only keeps
    # ``owner`` alive), named for the package like warp_buffer's on objects it does not own.
    raw._rosidl_buffer_owner = owner  # type: ignore[attr-defined]
    return np.frombuffer(raw, dtype=np.uint8)


_RANGES: dict[tuple[np.dtype, np.dtype], tuple[int, int] | None] = {}


def _range_to_check(source: np.dtype, target: np.dtype) -> tuple[int, int] | None:
    """``(low, high)`` of integer (or bool) ``target`` when a ``source`` integer array may hold
    values outside it, None when the cast is safe. Cached: NumPy's can_cast and iinfo cost
    about a microsecond each."""
    key = (source, target)
    if key not in _RANGES:
        if np.can_cast(source, target):
            _RANGES[key] = None
        elif target.kind == "b":
            _RANGES[key] = (0, 1)
        else:
            info = np.iinfo(target)
            _RANGES[key] = (int(info.min), int(info.max))
    return _RANGES[key]


def exact_array(value: Any, dtype: np.dtype, *, same_kind: bool = False) -> np.ndarray:
    """``value`` as an array of ``dtype`` (any shape), never cast silently.

    An ndarray already of ``dtype`` comes back as it is (no work: the common case). For an
    integer or bool ``dtype`` only integer and bool values are taken, and only when every value
    is in range (a min/max check, not per element): a float (1.9), 300 for a uint8 or -1 for a
    uint16 raise ``ValueError`` (``OverflowError`` for such a Python int), as NumPy's own
    conversion of a Python int list does for 300 but its casts do not (they wrap and truncate).
    For a float ``dtype`` ints and floats are converted as NumPy does; an array of another kind
    (complex, str, object) is refused. ``same_kind``: an ndarray must also cast ``same_kind``
    (a buffer's rule: an int64 array is not narrowed into uint8 even when its values fit).
    Callers check the shape and raise their typed error.
    """
    if value.__class__ is np.ndarray and value.dtype == dtype:
        return value
    is_array = isinstance(value, np.ndarray)
    if is_array and same_kind and not np.can_cast(value.dtype, dtype, "same_kind"):
        raise ValueError(f"{value.dtype} values are not {dtype} (never cast silently)")
    target = dtype.kind
    if target not in "biu":
        if is_array and target in "fc" and value.dtype.kind not in ("biufc" if target == "c"
                                                                    else "biuf"):
            raise ValueError(f"{value.dtype} values are not {dtype}")
        try:
            with np.errstate(over="raise"):  # 1e300 into float32: inf is not the value given
                return np.asarray(value, dtype=dtype)
        except FloatingPointError:
            raise ValueError(f"a value is out of the range of {dtype}") from None
    array = value if is_array else np.asarray(value)
    kind = array.dtype.kind
    if kind == "b":
        return array.astype(dtype, copy=False)
    if kind in "iu":
        bounds = _range_to_check(array.dtype, dtype)
        if bounds is not None and array.size:
            low, high = bounds
            if array.size <= 32:  # Python's min/max of a few ints beat two NumPy reductions
                values = array.ravel().tolist()
                smallest, largest = min(values), max(values)
            else:
                smallest, largest = int(array.min()), int(array.max())
            if smallest < low or largest > high:
                bad = smallest if smallest < low else largest
                raise ValueError(f"{bad} is out of the range [{low}, {high}] of {dtype}")
        return array.astype(dtype, copy=False)
    if not is_array:
        if array.size == 0:  # [] / (): NumPy infers float64, but there is no value to cast
            return array.astype(dtype)
        # Python ints beyond int64 (2**63 for a uint64) make NumPy infer float64 or object;
        # the typed conversion takes them, and raises OverflowError for one out of range.
        if target != "b" and (isinstance(value, (int, np.integer)) or (
                isinstance(value, (list, tuple))
                and all(isinstance(item, (int, np.integer)) for item in value))):
            # as Python ints: NumPy wraps a NumPy integer scalar out of range (np.int64(-1)
            # into uint8 is 255), and raises OverflowError for a Python int
            items = int(value) if isinstance(value, (int, np.integer)) else [int(v) for v in value]
            return np.asarray(items, dtype=dtype)
    raise ValueError(f"{array.dtype} values are not {dtype} (never cast silently)")


class BufferImplBase(abc.ABC):
    """Storage behind a :class:`~rosidl_buffer.Buffer`. Subclassed once per backend."""

    #: NumPy dtype of one element. Backends that only store bytes keep the uint8 default.
    dtype: np.dtype = np.dtype(np.uint8)

    @abc.abstractmethod
    def get_backend_type(self) -> str:
        """Short backend name, the same the plugin is registered under (``"cpu"``, ``"warp"``)."""

    @abc.abstractmethod
    def size(self) -> int:
        """Number of elements (bytes only when the element type is uint8)."""

    @abc.abstractmethod
    def to_cpu(self) -> CpuBufferImpl:
        """Return a populated CPU copy of the contents (the escape hatch of ``to_numpy``)."""

    @abc.abstractmethod
    def clone(self) -> BufferImplBase:
        """Return a deep copy in the same backend (used by ``copy.copy`` of a Buffer)."""

    @property
    def nbytes(self) -> int:
        """Size of the contents in bytes (:meth:`size` times the item size of ``dtype``)."""
        return self.size() * self.dtype.itemsize

    # -- lifetime hooks the transport calls (defaults: nothing to do) --------------------------
    def seal(self) -> None:
        """The publisher is done writing: end write access before the bytes leave.

        Every publish route calls it (intra-process, CPU serialization and descriptor alike), so
        a backend that orders writes (an event, a write handle) closes them here. Idempotent.
        """

    def seal_for_publish(self) -> tuple[str, int]:
        """:meth:`seal`, then the backend type and :meth:`size`: what a publish asks of each
        buffer, in one call (a backend may override it to answer without three)."""
        self.seal()
        return self.get_backend_type(), self.size()

    def end_publish(self) -> None:
        """Every route of a publish has sent the message (called once per publish, after
        :meth:`seal` and the last send, also when sending failed). A backend that fences off
        writes through views kept past publish does it here, off the path a reader waits on
        (warp_buffer makes a loan's pages read-only). Default: nothing."""

    def release(self) -> None:
        """Give back what this impl holds (shared-memory holds, device memory) now, rather than
        when it is garbage collected. Idempotent; data access afterwards raises a backend error.
        """

    def as_released(self) -> BufferImplBase:
        """What a released share of this storage keeps (see ``Buffer.release``): an impl of
        this backend, size and dtype that holds nothing, whose data access raises
        :class:`BufferReleasedError` (or the backend's subclass of it). This impl and every
        other holder of the storage are untouched. A backend whose users reach past the
        generic API (to attributes of its impl) overrides it with an impl of its own class."""
        return _ReleasedImpl(self.get_backend_type(), self.size(), self.dtype)

    def reclaim(self) -> bool:
        """May this memory be written again for a new message (a publisher's loan)? True when
        no reader holds it any more (no reader's token alive, nothing in flight to a peer); the
        impl is then re-armed (writable, not published).

        The loan pool of a publisher (``buffer_pubsub``) calls it before it hands the same
        storage out again, after it checked that no ``Buffer`` an earlier loan handed out is
        still held. Default: False (the backend cannot tell), so a loan takes new storage.
        """
        return False


class _Readers:
    """The tokens of the views a :class:`CpuBufferImpl` handed out since it tracks them."""

    __slots__ = ("lock", "refs")

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.refs: list[weakref.ref[Any]] = []


class CpuBufferImpl(BufferImplBase):
    """Host storage in a NumPy array that grows like ``std::vector`` (amortised appends).

    ``_storage`` may be longer than the logical size (spare capacity) and may be a read-only view
    of received bytes: the first mutation then takes a private copy (copy-on-write), so a
    deserialized message never pays for a copy it does not need.

    Reuse (:meth:`reclaim`, for a publisher's loans) is decided by tokens, never by counting
    references: from the first ``reclaim`` on, every view :meth:`view` / :meth:`writable_view`
    hands out holds a token of its own (the ``base`` of the view and of everything made from it),
    and the storage is reusable when no token is alive. Views handed out before are left with a
    copy: the first ``reclaim`` moves the storage into new memory.
    """

    __slots__ = ("_storage", "_size", "dtype", "_readers")

    def __init__(self, data: npt.ArrayLike | None = None, dtype: npt.DTypeLike = np.uint8) -> None:
        self._readers: _Readers | None = None  # tokens of handed-out views, once reclaimed
        self.dtype = np.dtype(dtype)
        if data is None:
            self._storage = np.empty(0, dtype=self.dtype)
        elif isinstance(data, (bytes, bytearray, memoryview)) and self.dtype == np.uint8:
            self._storage = np.frombuffer(data, dtype=np.uint8)
        else:
            # Arrays and Python sequences alike: floats for an integer buffer, values out of its
            # range raise (exact_array); an array of the buffer's dtype is not copied.
            array = exact_array(data, self.dtype, same_kind=True)
            if array.ndim == 0:
                raise ValueError("a scalar is not a sequence")
            # Contiguous storage: serialization and the buffer protocol need one flat block.
            self._storage = np.ascontiguousarray(array.reshape(-1))
        self._size = self._storage.shape[0]

    @classmethod
    def wrap(cls, array: np.ndarray) -> CpuBufferImpl:
        """Adopt a 1-D array without copying (it may be read-only: writes then copy first)."""
        impl = cls.__new__(cls)
        impl._readers = None
        impl.dtype = array.dtype
        impl._storage = array
        impl._size = array.shape[0]
        return impl

    def get_backend_type(self) -> str:
        return CPU_BACKEND

    def seal_for_publish(self) -> tuple[str, int]:
        if type(self) is not CpuBufferImpl:  # a subclass may seal, name or size its own way
            return super().seal_for_publish()
        return CPU_BACKEND, self._size  # (host storage has nothing to seal)

    def size(self) -> int:
        return self._size

    def to_cpu(self) -> CpuBufferImpl:
        return self.clone()

    def clone(self) -> CpuBufferImpl:
        return CpuBufferImpl.wrap(self.view().copy())

    # -- CPU-only access, used by Buffer -------------------------------------------------------
    def view(self) -> np.ndarray:
        """The logical contents as a 1-D array view (read-only if the storage is borrowed)."""
        if self._readers is None:
            return self._storage[: self._size]
        return self._tracked_view()

    def writable_view(self) -> np.ndarray:
        """The logical contents as a writable 1-D array view; borrowed read-only storage is
        copied into memory of its own first (copy-on-write)."""
        self._ensure_writable(self._size)
        if self._readers is None:
            return self._storage[: self._size]
        return self._tracked_view()

    def _tracked_view(self) -> np.ndarray:
        """A view whose base is a token of its own (see the class docstring)."""
        storage = self._storage
        size = self._size
        if size == 0:
            return storage[:0]
        view = array_at(storage.ctypes.data, size * self.dtype.itemsize, storage)
        readers = self._readers
        with readers.lock:  # type: ignore[union-attr]
            readers.refs.append(weakref.ref(view.base))  # type: ignore[union-attr]
        view = view.view(self.dtype)
        if not storage.flags.writeable:
            view.flags.writeable = False
        return view

    def capacity(self) -> int:
        """Elements the storage holds before growing reallocates (spare capacity included)."""
        return self._storage.shape[0]

    def reserve(self, capacity: int) -> None:
        """Make room for at least ``capacity`` elements, like ``vector::reserve`` (borrowed
        read-only storage is copied into memory of its own); the size is unchanged."""
        if capacity > self._storage.shape[0] or not self._storage.flags.writeable:
            self._reallocate(max(capacity, self._size))

    def resize(self, size: int, value: int | float = 0) -> None:
        """Set the logical size, like ``vector::resize``: new elements are ``value``; growing
        past the capacity at least doubles it (amortised appends). ``ValueError`` if negative."""
        if size < 0:
            raise ValueError(f"size must be >= 0, got {size}")
        old = self._size
        if size > self._storage.shape[0]:
            self._reallocate(max(size, 2 * self._storage.shape[0]))
        else:
            self._ensure_writable(size)
        if size > old:
            self._storage[old:size] = value
        self._size = size

    def reclaim(self) -> bool:
        """Reusable when no view handed out since the first ``reclaim`` holds its token (see
        the class docstring); the first call moves the storage into memory of its own, so views
        handed out before keep reading what they were made over. Borrowed read-only bytes are
        never rewritten (False)."""
        storage = self._storage
        if not storage.flags.writeable:
            return False
        readers = self._readers
        if readers is None:
            self._storage = storage.copy()
            self._readers = _Readers()
            return True
        with readers.lock:
            refs = readers.refs
            for ref in refs:
                if ref() is not None:
                    return False
            refs.clear()
        return True

    def as_released(self) -> CpuBufferImpl:
        return _ReleasedCpuBufferImpl(self._size, self.dtype)

    def _ensure_writable(self, capacity: int) -> None:
        if not self._storage.flags.writeable:
            self._reallocate(max(capacity, self._size))

    def _reallocate(self, capacity: int) -> None:
        storage = np.empty(capacity, dtype=self.dtype)
        storage[: self._size] = self._storage[: self._size]
        self._storage = storage


_RELEASED = "this buffer was released (release() or its `with` block): it holds no storage"


def _refuse(*_args: Any, **_kwargs: Any) -> NoReturn:
    raise BufferReleasedError(_RELEASED)


class _ReleasedImpl(BufferImplBase):
    """:meth:`BufferImplBase.as_released` of a backend that has no impl of its own for it."""

    def __init__(self, backend: str, size: int, dtype: np.dtype) -> None:
        self._backend, self._size, self.dtype = backend, size, dtype

    def get_backend_type(self) -> str:
        return self._backend

    def size(self) -> int:
        return self._size

    to_cpu = clone = _refuse


class _ReleasedCpuBufferImpl(CpuBufferImpl):
    """A released share of CPU storage: still a CPU buffer (its size and dtype answer, so
    ``Buffer``'s CPU operations reach it), every access to the bytes refused."""

    __slots__ = ()

    def __init__(self, size: int, dtype: np.dtype) -> None:
        self._readers = None
        self.dtype = dtype
        self._storage = np.empty(0, dtype)
        self._size = size

    def seal_for_publish(self) -> tuple[str, int]:
        _refuse()

    view = writable_view = to_cpu = clone = reserve = resize = _refuse

    def capacity(self) -> int:
        return self._size

    def reclaim(self) -> bool:
        return False
