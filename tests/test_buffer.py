"""Buffer: construction, the operations every backend supports, and the CPU-only vector API."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
from plugins.fake_backend import FakeBufferImpl

from rosidl_buffer.errors import BufferReleasedError, InvalidBufferDataError
from rosidl_buffer import Buffer, BufferImplBase, CpuBackendRequiredError, CpuBufferImpl
from rosidl_buffer.messages import deserialize_message, get_message_type, serialize_message

CONTENT = [3, 1, 4, 1, 5, 9, 2, 6]


def cpu_buffer(values=CONTENT) -> Buffer:
    return Buffer(list(values))


def fake_buffer(values=CONTENT) -> Buffer:
    return Buffer(FakeBufferImpl(values))


BACKENDS = {"cpu": cpu_buffer, "fake": fake_buffer}


@pytest.fixture(params=sorted(BACKENDS))
def make(request):
    """A factory of buffers in each backend."""
    return BACKENDS[request.param]


# ------------------------------------------------------------------------------- construction
def test_default_buffer_is_empty_cpu_uint8():
    buffer = Buffer()
    assert len(buffer) == 0 and buffer.size() == 0 and buffer.empty()
    assert buffer.get_backend_type() == "cpu"
    assert isinstance(buffer.get_impl(), CpuBufferImpl)
    assert buffer.dtype == np.uint8


@pytest.mark.parametrize(
    "data",
    [CONTENT, tuple(CONTENT), bytes(CONTENT), bytearray(CONTENT), np.array(CONTENT, np.uint8),
     np.array(CONTENT, np.uint8).reshape(2, 4), np.repeat(np.array(CONTENT, np.uint8), 2)[::2]],
    ids=["list", "tuple", "bytes", "bytearray", "ndarray", "2d-ndarray", "strided-ndarray"],
)
def test_array_like_makes_a_cpu_buffer(data):
    buffer = Buffer(data)
    assert buffer.get_backend_type() == "cpu"
    assert buffer.dtype == np.uint8
    assert buffer.to_numpy().tolist() == CONTENT
    assert bytes(buffer) == bytes(CONTENT)


def test_strided_array_is_stored_contiguous():
    buffer = Buffer(np.arange(16, dtype=np.uint8)[::2])
    assert buffer.numpy().flags.c_contiguous
    assert bytes(buffer.memoryview()) == bytes(range(0, 16, 2))


def test_none_is_rejected():
    with pytest.raises(TypeError, match="None"):
        Buffer(None)


def test_out_of_range_values_and_strings_are_rejected_typed():
    with pytest.raises(InvalidBufferDataError, match="256"):  # also a ValueError
        Buffer([1, 256])
    with pytest.raises(ValueError):
        Buffer([1, 256])
    with pytest.raises(InvalidBufferDataError, match="str"):
        Buffer("abc")


def test_float_values_are_refused_not_truncated():
    # Buffer([0.7, 255.9]) stored [0, 255], an Image's data [1.5, 2.9] [1, 2].
    for data in ([0.7, 255.9], [1, 2.0], np.array([1.5]), np.array([300], np.uint16), 5):
        with pytest.raises(InvalidBufferDataError):
            Buffer(data)
    with pytest.raises(InvalidBufferDataError, match="Image.data.*float64"):
        get_message_type("sensor_msgs/msg/Image")(data=[1.5, 2.9])
    for scalars in ([np.int64(-1), np.uint64(1)], [np.int16(300)]):  # NumPy scalars wrapped
        with pytest.raises(InvalidBufferDataError):
            Buffer(scalars)
    assert Buffer([np.int64(255), np.uint64(1)]) == [255, 1]
    assert Buffer(np.array([255], np.uint16)) == [255]  # in range, same kind: fine
    assert Buffer([1, 2.5], dtype=np.float32) == np.array([1, 2.5], np.float32)


def test_impl_selects_its_backend():
    impl = FakeBufferImpl(CONTENT)
    buffer = Buffer(impl)
    assert buffer.get_impl() is impl
    assert buffer.get_backend_type() == "fake"
    assert not buffer.is_cpu()


def test_impl_with_a_different_dtype_is_rejected():
    with pytest.raises(TypeError, match="float32"):
        Buffer(FakeBufferImpl(CONTENT), dtype=np.float32)


def test_impl_base_is_abstract():
    with pytest.raises(TypeError):
        BufferImplBase()  # type: ignore[abstract]


# ----------------------------------------------------------------------- every backend
def test_size_queries(make):
    buffer = make()
    assert len(buffer) == buffer.size() == len(CONTENT)
    assert not buffer.empty() and bool(buffer)
    assert make([]).empty() and not make([])


def test_backend_type_and_impl(make):
    buffer = make()
    assert buffer.get_backend_type() == buffer.get_impl().get_backend_type()
    assert isinstance(buffer.get_impl(), BufferImplBase)


def test_to_numpy_is_an_independent_copy(make):
    buffer = make()
    array = buffer.to_numpy()
    assert isinstance(array, np.ndarray) and array.tolist() == CONTENT
    array[0] = 200
    assert buffer.to_numpy()[0] == CONTENT[0]


def test_to_cpu_gives_a_cpu_buffer(make):
    cpu = make().to_cpu()
    assert cpu.get_backend_type() == "cpu" and cpu == CONTENT


@pytest.mark.parametrize("other_backend", sorted(BACKENDS))
def test_equality_by_value_across_backends(make, other_backend):
    other = BACKENDS[other_backend]
    assert make() == other()
    assert make() != other(CONTENT[:-1])
    assert make() != other([*CONTENT[:-1], 0])


@pytest.mark.parametrize("other", [CONTENT, tuple(CONTENT), bytes(CONTENT),
                                   np.array(CONTENT, np.uint8)],
                         ids=["list", "tuple", "bytes", "ndarray"])
def test_equality_with_array_likes(make, other):
    assert make() == other
    assert make(CONTENT[:-1]) != other


def test_buffer_is_unhashable(make):
    with pytest.raises(TypeError):
        hash(make())


@pytest.mark.parametrize("copier", [copy.copy, copy.deepcopy, Buffer.copy],
                         ids=["copy", "deepcopy", "method"])
def test_copy_is_a_deep_clone_in_the_same_backend(make, copier):
    original = make()
    clone = copier(original)
    assert clone == original and clone.get_backend_type() == original.get_backend_type()
    assert clone.get_impl() is not original.get_impl()
    _mutate_first_element(clone, 99)
    assert clone.to_numpy()[0] == 99
    assert original.to_numpy().tolist() == CONTENT


def _mutate_first_element(buffer: Buffer, value: int) -> None:
    impl = buffer.get_impl()
    if isinstance(impl, FakeBufferImpl):
        impl.device_array[0] = value
    else:
        buffer[0] = value


def test_pickle_round_trips_as_cpu(make):
    restored = pickle.loads(pickle.dumps(make()))
    assert restored.get_backend_type() == "cpu" and restored == CONTENT


@pytest.mark.parametrize(("backend", "expected"),
                         [("cpu", "Buffer([3 1 4"), ("fake", f"Buffer(<fake>, size={len(CONTENT)}")])
def test_repr_shows_contents_or_backend(backend, expected):
    text = repr(BACKENDS[backend]())
    assert text.startswith(expected) and text.endswith("dtype=uint8)")


# ----------------------------------------------------------------------- CPU-only operations
# name -> (operation on a buffer of CONTENT, its result or None, expected contents afterwards)
CPU_OPERATIONS = {
    "getitem": (lambda b: b[2], 4, CONTENT),
    "getitem-negative": (lambda b: b[-1], 6, CONTENT),
    "slice": (lambda b: b[1:3].tolist(), [1, 4], CONTENT),
    "setitem": (lambda b: b.__setitem__(0, 7), None, [7, *CONTENT[1:]]),
    "setitem-slice": (lambda b: b.__setitem__(slice(0, 2), [8, 8]), None, [8, 8, *CONTENT[2:]]),
    "iter": (lambda b: list(b), CONTENT, CONTENT),
    "contains": (lambda b: (9 in b, 7 in b), (True, False), CONTENT),
    "resize-grow": (lambda b: b.resize(10, 5), None, [*CONTENT, 5, 5]),
    "resize-shrink": (lambda b: b.resize(3), None, CONTENT[:3]),
    "append": (lambda b: b.append(42), None, [*CONTENT, 42]),
    "push_back": (lambda b: b.push_back(42), None, [*CONTENT, 42]),
    "extend-list": (lambda b: b.extend([7, 8]), None, [*CONTENT, 7, 8]),
    "extend-bytes": (lambda b: b.extend(b"\x07\x08"), None, [*CONTENT, 7, 8]),
    "extend-generator": (lambda b: b.extend(x for x in (7, 8)), None, [*CONTENT, 7, 8]),
    "extend-buffer": (lambda b: b.extend(Buffer([7, 8])), None, [*CONTENT, 7, 8]),
    "insert": (lambda b: b.insert(1, 0), None, [3, 0, *CONTENT[1:]]),
    "insert-end": (lambda b: b.insert(100, 0), None, [*CONTENT, 0]),
    "insert-negative": (lambda b: b.insert(-1, 0), None, [*CONTENT[:-1], 0, CONTENT[-1]]),
    "pop": (lambda b: b.pop(), 6, CONTENT[:-1]),
    "pop-index": (lambda b: b.pop(0), 3, CONTENT[1:]),
    "erase-one": (lambda b: b.erase(1), None, [3, *CONTENT[2:]]),
    "erase-range": (lambda b: b.erase(1, 4), None, [3, *CONTENT[4:]]),
    "clear": (lambda b: b.clear(), None, []),
    "reserve": (lambda b: (b.reserve(100), b.capacity() >= 100)[1], True, CONTENT),
    "numpy": (lambda b: b.numpy().tolist(), CONTENT, CONTENT),
    "numpy-write": (lambda b: b.numpy().__setitem__(1, 77), None, [3, 77, *CONTENT[2:]]),
    "memoryview": (lambda b: b.memoryview().tolist(), CONTENT, CONTENT),
    "memoryview-write": (lambda b: b.memoryview().__setitem__(0, 11), None, [11, *CONTENT[1:]]),
    "bytes": (lambda b: bytes(b), bytes(CONTENT), CONTENT),
    "asarray": (lambda b: np.asarray(b).tolist(), CONTENT, CONTENT),
    "tobytes": (lambda b: b.tobytes(), bytes(CONTENT), CONTENT),
}
# Operations that work on every backend (through a CPU copy) are not refused on "fake".
REFUSED_ON_FAKE = sorted(set(CPU_OPERATIONS) - {"tobytes"})


@pytest.mark.parametrize("name", sorted(CPU_OPERATIONS))
def test_cpu_operation(name):
    operation, result, after = CPU_OPERATIONS[name]
    buffer = cpu_buffer()
    assert operation(buffer) == result
    assert buffer.to_numpy().tolist() == after


@pytest.mark.parametrize("name", REFUSED_ON_FAKE)
def test_cpu_operation_refused_on_other_backends(name):
    operation, _, _ = CPU_OPERATIONS[name]
    buffer = fake_buffer()
    with pytest.raises(CpuBackendRequiredError, match="Current backend: fake") as excinfo:
        operation(buffer)
    assert excinfo.value.backend == "fake"
    assert buffer.to_numpy().tolist() == CONTENT  # the refused operation changed nothing


def test_capacity_is_cpu_only():
    assert cpu_buffer([1, 2]).capacity() >= 2
    with pytest.raises(CpuBackendRequiredError, match="Current backend: fake"):
        fake_buffer().capacity()


def test_swap_exchanges_storage_across_backends():
    cpu, fake = cpu_buffer([1, 2]), fake_buffer()
    cpu.swap(fake)
    assert cpu.get_backend_type() == "fake" and cpu == CONTENT
    assert fake.get_backend_type() == "cpu" and fake == [1, 2]


def test_tobytes_works_on_every_backend():
    assert fake_buffer().tobytes() == bytes(CONTENT)


@pytest.mark.parametrize(
    ("operation", "error"),
    [(lambda b: b.pop(8), IndexError), (lambda b: Buffer().pop(), IndexError),
     (lambda b: b.erase(5, 20), IndexError), (lambda b: b.erase(3, 2), IndexError),
     (lambda b: b.resize(-1), ValueError), (lambda b: b[100], IndexError)],
    ids=["pop-out-of-range", "pop-empty", "erase-past-end", "erase-reversed", "resize-negative",
         "index-out-of-range"],
)
def test_cpu_operation_errors_leave_buffer_unchanged(operation, error):
    buffer = cpu_buffer()
    with pytest.raises(error):
        operation(buffer)
    assert buffer.to_numpy().tolist() == CONTENT


@pytest.mark.parametrize("operation", [
    lambda b: b.extend([300]), lambda b: b.extend([1.7]), lambda b: b.extend([-1]),
    lambda b: b.extend(np.array([1, 2])), lambda b: b.extend(np.zeros((2, 2), np.uint8)),
    lambda b: b.append(2.9), lambda b: b.append(300), lambda b: b.append(None),
    lambda b: b.insert(0, 300), lambda b: b.insert(1, 0.5), lambda b: b.resize(9, 1.5),
    lambda b: b.__setitem__(0, 300), lambda b: b.__setitem__(0, 2.9),
    lambda b: b.__setitem__(slice(0, 2), np.array([300, 1], np.uint16)),
], ids=["extend-300", "extend-float", "extend-negative", "extend-int64-array", "extend-2d",
        "append-float", "append-300", "append-none", "insert-300", "insert-float",
        "resize-float", "setitem-300", "setitem-float", "setitem-slice-out-of-range"])
def test_mutators_refuse_values_that_do_not_fit_and_leave_the_buffer_unchanged(operation):
    # They stored 300 as 44 and 2.9 as 2; insert(0, 300) raised OverflowError after growing.
    buffer = cpu_buffer()
    with pytest.raises(InvalidBufferDataError):  # also a ValueError and a TypeError
        operation(buffer)
    assert buffer.to_numpy().tolist() == CONTENT


def test_array_protocol_copy_false_refuses_a_conversion():
    buffer = cpu_buffer()
    with pytest.raises(ValueError, match="copy"):
        np.asarray(buffer, dtype=np.float32, copy=False)
    assert np.shares_memory(np.asarray(buffer, copy=False), buffer.numpy())
    assert np.asarray(buffer, dtype=np.float32).tolist() == CONTENT


def test_many_appends_keep_every_value():
    buffer = Buffer()
    for value in range(1000):
        buffer.append(value % 256)
    assert buffer.to_numpy().tolist() == [v % 256 for v in range(1000)]
    assert buffer.capacity() < 4 * 1000  # amortised growth, not one allocation per append


# ----------------------------------------------------------------------- dtypes other than uint8
def test_float32_buffer():
    values = [0.5, -1.25, 3.0]
    buffer = Buffer(values, dtype=np.float32)
    assert buffer.dtype == np.float32 and buffer.nbytes == 12
    assert buffer.to_numpy().dtype == np.float32
    assert buffer[1] == np.float32(-1.25)
    buffer.append(7.5)
    buffer.resize(6, 2.5)
    assert buffer.to_numpy().tolist() == [*values, 7.5, 2.5, 2.5]
    assert copy.copy(buffer).dtype == np.float32
    assert buffer == np.array([*values, 7.5, 2.5, 2.5], np.float32)


def test_float32_impl_in_another_backend():
    buffer = Buffer(FakeBufferImpl([1.5, 2.5], np.float32), dtype=np.float32)
    assert buffer.dtype == np.float32 and buffer.to_numpy().dtype == np.float32
    assert buffer.to_numpy().tolist() == [1.5, 2.5]


# ----------------------------------------------------------------------- copy-on-write
def _deserialized_image(payload: bytes):
    image_type = get_message_type("sensor_msgs/msg/Image")
    wire = bytes(serialize_message(image_type(data=payload)))
    return deserialize_message(wire, image_type), wire


@pytest.mark.parametrize(
    "write",
    [lambda b: b.__setitem__(0, 255), lambda b: b.numpy().__setitem__(0, 255),
     lambda b: b.append(255), lambda b: b.resize(2), lambda b: b.pop(),
     lambda b: b.memoryview().__setitem__(0, 255), lambda b: b.reserve(1)],
    ids=["setitem", "numpy", "append", "resize-shrink", "pop", "memoryview", "reserve"],
)
def test_write_to_a_view_of_received_bytes_copies_first(write):
    payload = bytes(range(1, 9))
    message, wire = _deserialized_image(payload)
    received = message.data
    assert np.shares_memory(np.asarray(received), np.frombuffer(wire, np.uint8))
    write(received)
    assert not np.shares_memory(np.asarray(received), np.frombuffer(wire, np.uint8))
    assert wire[-len(payload):] == payload  # the immutable input is untouched
    assert deserialize_message(wire, "sensor_msgs/msg/Image").data == payload


def test_the_buffer_protocol_reads_received_bytes_without_a_copy_and_refuses_writes():
    # Python 3.12+ calls __buffer__ for memoryview()/NumPy; called directly here so that every
    # version tests it. A writable request over borrowed bytes is refused (NumPy then asks
    # read-only): it would copy the payload, and a received view would stop being zero-copy.
    payload = bytes(range(1, 9))
    message, wire = _deserialized_image(payload)
    received = message.data
    WRITABLE, SIMPLE = 1, 0
    view = received.__buffer__(SIMPLE)
    assert view.readonly and bytes(view) == payload
    assert np.shares_memory(np.frombuffer(view, np.uint8), np.frombuffer(wire, np.uint8))
    with pytest.raises(BufferError, match="received bytes"):
        received.__buffer__(WRITABLE)
    assert np.shares_memory(np.asarray(received), np.frombuffer(wire, np.uint8))  # unchanged
    owned = Buffer(bytearray(payload))  # writable storage: writable through the protocol
    writable = owned.__buffer__(WRITABLE)
    writable[0] = 99
    assert not writable.readonly and owned[0] == 99


def test_buffer_over_bytes_copies_on_first_write():
    source = bytes(CONTENT)
    buffer = Buffer(source)
    assert np.shares_memory(np.asarray(buffer), np.frombuffer(source, np.uint8))
    buffer[0] = 0
    assert source == bytes(CONTENT) and buffer[0] == 0


# --------------------------------------------------------------------------- lifetime hooks
class _CountingImpl(CpuBufferImpl):
    __slots__ = ("sealed", "released")

    def __init__(self, data):
        super().__init__(data)
        self.sealed = 0
        self.released = 0

    def seal(self) -> None:
        self.sealed += 1

    def release(self) -> None:
        self.released += 1


def test_seal_and_release_reach_the_impl_and_the_context_manager_releases():
    impl = _CountingImpl(b"abc")
    buf = Buffer(impl)
    buf.seal()
    with buf as same:
        assert same is buf
    assert (impl.sealed, impl.released) == (1, 1)


def test_release_ends_this_buffers_access_alone():
    """A released Buffer refuses its bytes (whatever backend: here CPU storage, which has no
    hold to give back) and still answers its size; another Buffer over the same storage (a
    share, a view taken before) reads on."""
    buf = Buffer(b"xyz")
    other = buf.share()
    view = buf.numpy(writable=False)
    buf.seal()
    buf.release()
    buf.release()  # idempotent
    with pytest.raises(BufferReleasedError):
        buf.tobytes()
    with pytest.raises(BufferReleasedError):
        buf.numpy()
    assert len(buf) == 3 and buf.get_backend_type() == "cpu"
    assert other.tobytes() == b"xyz" and view.tobytes() == b"xyz"


def test_message_buffer_walk_reaches_nested_and_sequence_fields():
    from rosidl_buffer.messages import get_message_type, iter_buffers, release_buffers, seal_buffers

    Image = get_message_type("sensor_msgs/msg/Image")
    Pair = get_message_type("stereo_msgs/msg/DisparityImage")  # nests an Image
    impls = [_CountingImpl(b"a"), _CountingImpl(b"b")]
    image = Image(data=Buffer(impls[0]))
    pair = Pair(image=Image(data=Buffer(impls[1])))
    assert [b.get_impl() for b in iter_buffers(image)] == [impls[0]]
    assert [b.get_impl() for b in iter_buffers(pair)] == [impls[1]]
    seal_buffers(image)
    release_buffers(pair)
    assert (impls[0].sealed, impls[0].released, impls[1].sealed, impls[1].released) == (1, 0, 0, 1)
