"""Buffer implementations: the abstract pimpl interface and the NumPy-backed CPU storage.

Mirrors ``rosidl::BufferImplBase<T>`` and ``rosidl::CpuBufferImpl<T>``: a backend subclasses
:class:`BufferImplBase` and keeps all of its state (device memory, IPC handles, sync objects) in it.
"""

from __future__ import annotations

import abc
import sys

import numpy as np
import numpy.typing as npt

__all__ = ["BufferImplBase", "CpuBufferImpl", "CPU_BACKEND"]

CPU_BACKEND = "cpu"


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
        return self.size() * self.dtype.itemsize

    # -- lifetime hooks the transport calls (defaults: nothing to do) --------------------------
    def seal(self) -> None:
        """The publisher is done writing: end write access before the bytes leave.

        Every publish route calls it (intra-process, CPU serialization and descriptor alike), so
        a backend that orders writes (an event, a write handle) closes them here. Idempotent.
        """

    def end_publish(self) -> None:
        """Every route of a publish has sent the message (called once per publish, after
        :meth:`seal` and the last send, also when sending failed). A backend that fences off
        writes through views kept past publish does it here, off the path a reader waits on
        (warp_buffer makes a loan's pages read-only). Default: nothing."""

    def release(self) -> None:
        """Give back what this impl holds (shared-memory holds, device memory) now, rather than
        when it is garbage collected. Idempotent; data access afterwards raises a backend error.
        """

    def reclaim(self) -> bool:
        """May this memory be written again for a new message (a publisher's loan)? True when
        no reader holds it any more; the impl is then re-armed (writable, not published).

        The loan pool of a publisher (``buffer_pubsub``) calls it before it hands the same
        storage out again, after it checked that nobody holds the message or the ``Buffer``.
        Default: False (the backend cannot tell), so a loan takes new storage.
        """
        return False


class CpuBufferImpl(BufferImplBase):
    """Host storage in a NumPy array that grows like ``std::vector`` (amortised appends).

    ``_storage`` may be longer than the logical size (spare capacity) and may be a read-only view
    of received bytes: the first mutation then takes a private copy (copy-on-write), so a
    deserialized message never pays for a copy it does not need.
    """

    __slots__ = ("_storage", "_size", "dtype")

    def __init__(self, data: npt.ArrayLike | None = None, dtype: npt.DTypeLike = np.uint8) -> None:
        self.dtype = np.dtype(dtype)
        if data is None:
            self._storage = np.empty(0, dtype=self.dtype)
        elif isinstance(data, (bytes, bytearray, memoryview)) and self.dtype == np.uint8:
            self._storage = np.frombuffer(data, dtype=np.uint8)
        elif isinstance(data, np.ndarray):
            array = data.reshape(-1)
            if array.dtype != self.dtype:
                array = array.astype(self.dtype, casting="same_kind")
            # Contiguous storage: serialization and the buffer protocol need one flat block.
            self._storage = np.ascontiguousarray(array)
        else:
            # Python sequences: () / [1, 2, 3] take the buffer's dtype (NumPy would infer float64
            # or int64, which a same_kind cast to uint8 refuses). Out-of-range ints raise.
            self._storage = np.asarray(data, dtype=self.dtype).reshape(-1)
        self._size = self._storage.shape[0]

    @classmethod
    def wrap(cls, array: np.ndarray) -> CpuBufferImpl:
        """Adopt a 1-D array without copying (it may be read-only: writes then copy first)."""
        impl = cls.__new__(cls)
        impl.dtype = array.dtype
        impl._storage = array
        impl._size = array.shape[0]
        return impl

    def get_backend_type(self) -> str:
        return CPU_BACKEND

    def size(self) -> int:
        return self._size

    def to_cpu(self) -> CpuBufferImpl:
        return self.clone()

    def clone(self) -> CpuBufferImpl:
        return CpuBufferImpl.wrap(self.view().copy())

    # -- CPU-only access, used by Buffer -------------------------------------------------------
    def view(self) -> np.ndarray:
        """The logical contents as a 1-D array view (read-only if the storage is borrowed)."""
        return self._storage[: self._size]

    def writable_view(self) -> np.ndarray:
        self._ensure_writable(self._size)
        return self._storage[: self._size]

    def capacity(self) -> int:
        return self._storage.shape[0]

    def reserve(self, capacity: int) -> None:
        if capacity > self._storage.shape[0] or not self._storage.flags.writeable:
            self._reallocate(max(capacity, self._size))

    def resize(self, size: int, value: int | float = 0) -> None:
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
        """Intra-process sharing is by reference: the memory is free when no NumPy view of the
        storage is alive besides our own (readers of a shared message hold such views, or the
        message, which the loan pool checks). Borrowed read-only bytes are never rewritten."""
        owner = self._storage
        if not owner.flags.writeable:
            return False
        while isinstance(owner.base, np.ndarray):  # NumPy views point at the owning array
            owner = owner.base
        # References: ``self._storage`` or the storage's ``base``, the local name, the argument.
        return sys.getrefcount(owner) <= 3

    def _ensure_writable(self, capacity: int) -> None:
        if not self._storage.flags.writeable:
            self._reallocate(max(capacity, self._size))

    def _reallocate(self, capacity: int) -> None:
        storage = np.empty(capacity, dtype=self.dtype)
        storage[: self._size] = self._storage[: self._size]
        self._storage = storage
