"""Stale and hostile warp descriptors: on a real subscription (a forged, discovered publisher
puts hand-made CDR payloads on the subscription's own channel) and through the backend directly,
plus hypothesis fuzzing of descriptor decoding and import.

Every bad input must raise a typed error (a ``RosidlBufferError``), be counted on the
subscription, not be delivered, and leave the subscription working: a good message sent right
after each one is delivered. A successful import must always be the exported bytes.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import os
import re
import secrets
import socket
import struct
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from buffer_pubsub import Node
from rosidl_buffer import (
    Buffer,
    DeserializationError,
    EndpointInfo,
    EndpointType,
    RosidlBufferError,
    local_host_id,
)
from rosidl_buffer.messages import deserialize_message, serialize_message
from tests._pubsub_helpers import TENSOR, check_frame, make_frame, pattern
from tests._reliability_helpers import ForgedPublisher, release_pool_memory, wait_until
from warp_buffer import (
    DescriptorError,
    ExportBoundsError,
    ForeignExportError,
    StaleBufferError,
    descriptor,
    handoff,
    ipc,
)
from warp_buffer.arena import HELLO, MAGIC, SEALS, VERSION, Geometry, alive
from warp_buffer_backend import WarpBufferBackend

pytestmark = pytest.mark.multiprocess

BLOCK = 4096  # the good frames fill a whole block, so every offset/size maps known bytes
LONG_RUN = os.environ.get("HYPOTHESIS_PROFILE") == "long"
FIELD_EXAMPLES = 20_000 if LONG_RUN else 1_500
BYTE_EXAMPLES = 20_000 if LONG_RUN else 1_500
_domains = itertools.count(4500 + os.getpid() % 50 * 40)


@pytest.fixture(autouse=True)
def _pool_memory_back():
    yield
    stats = release_pool_memory()
    assert all(s["leased"] == 0 for s in stats.values()), f"buffers left alive: {stats}"


# --------------------------------------------------------------------------- descriptors
def good_frame(index: int):
    """A warp ExperimentalTensor filling one whole block, with a descriptor of its export."""
    frame = make_frame(9, index, BLOCK, "warp")
    return frame, ipc.export_buffer(frame.data)


def mutated(desc: Any, **changes: Any) -> Any:
    values = dict(zip(descriptor.FIELDS, (getattr(desc, n) for n in descriptor.FIELDS)))
    values.update(changes)
    return descriptor.make(tuple(values[name] for name in descriptor.FIELDS))


def payload_for(frame: Any, desc: Any, backend: str = "warp") -> bytes:
    return bytes(serialize_message(frame, route=lambda _buffer: (backend, desc)))


def truncated_in_descriptor(payload: bytes, desc: Any) -> bytes:
    """``payload`` cut in the middle of the descriptor."""
    at = payload.index(struct.pack("<Q", desc.session))
    return payload[:at + 3]


def dead_pid() -> int:
    pid = 4_000_000
    while alive(pid):
        pid -= 1
    return pid


@contextlib.contextmanager
def forged_session(*, sealed: bool = True, owner_pid: int | None = None, magic: bytes = MAGIC,
                   size_delta: int = 0, hello_session: int | None = None,
                   serve_pid_of_ours: bool = True) -> Iterator[dict[str, int]]:
    """A hand-made publisher session served from this process: an abstract socket under the
    names the importer builds, handing over a memfd that may be unsealed, of the wrong size, or
    described by a wrong hello. Yields the descriptor fields naming its first block."""
    session = secrets.randbits(63) | 1
    pid = os.getpid() if owner_pid is None else owner_pid
    geometry = Geometry(1 << 20)
    fd = os.memfd_create("warp_buffer", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    os.ftruncate(fd, geometry.file_size + size_delta)
    if sealed:
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, SEALS)
    hello = HELLO.pack(magic, VERSION, pid, session if hello_session is None else hello_session,
                       geometry.data_offset, geometry.data_bytes, geometry.file_size)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(handoff.socket_name(os.getuid(), pid, session))
    sock.listen(4)

    def serve() -> None:
        with contextlib.suppress(OSError):
            while True:
                conn, _ = sock.accept()
                with conn:
                    socket.send_fds(conn, [hello], [fd])

    threading.Thread(target=serve, daemon=True).start()
    try:
        yield {"session": session, "owner_pid": pid, "offset": geometry.data_offset,
               "capacity": BLOCK, "size": BLOCK, "generation": 1}
    finally:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        sock.close()
        os.close(fd)


BACKEND = WarpBufferBackend()


# --------------------------------------------------------------------------- hostile cases
@dataclass(frozen=True)
class Case:
    name: str
    expected: type[Exception]
    build: Callable[[Any, Any], Any]  # (frame, good descriptor) -> payload bytes
    forge: dict[str, Any] | None = None  # forged_block(**forge) around the send


def _field(**changes: Any) -> Callable[[Any, Any], bytes]:
    return lambda frame, good: payload_for(frame, mutated(good, **changes))


def _forged(frame: Any, good: Any, names: dict[str, int]) -> bytes:
    return payload_for(frame, mutated(good, **names))


CASES = [
    Case("recycled block (generation)", StaleBufferError,
         lambda f, g: payload_for(f, mutated(g, generation=g.generation + 1))),
    # A publisher exports its own memory only: another pid is refused before any hand-off.
    Case("another process's export (dead owner)", ForeignExportError,
         _field(owner_pid=dead_pid())),
    Case("missing export (session)", StaleBufferError, _field(session=12345)),
    Case("size beyond the block", ExportBoundsError, _field(size=BLOCK + 1)),
    Case("offset inside a block", ExportBoundsError, lambda f, g: payload_for(
        f, mutated(g, offset=g.offset + 1))),
    Case("offset before the data", ExportBoundsError, _field(offset=0)),
    Case("huge size", ExportBoundsError, _field(size=2**64 - 1)),
    Case("huge offset", ExportBoundsError, _field(offset=2**64 - 4096)),
    Case("capacity larger than the arena", ExportBoundsError, _field(capacity=1 << 62)),
    Case("capacity not a block size", ExportBoundsError, _field(capacity=3000, size=100)),
    Case("zero size", ExportBoundsError, _field(size=0)),
    Case("unknown version", DescriptorError, _field(version=1)),
    Case("unknown kind", DescriptorError, _field(kind=9)),
    Case("owner pid 0", DescriptorError, _field(owner_pid=0)),
    Case("peer slot out of range", DescriptorError, _field(peer_slot=4000)),
    Case("truncated serialized descriptor", DeserializationError,
         lambda f, g: truncated_in_descriptor(payload_for(f, g), g)),
    Case("unknown backend name", DeserializationError, lambda f, g: payload_for(f, g, "nope")),
    Case("arena not sealed against shrinking", ForeignExportError, _forged, {"sealed": False}),
    Case("socket squatted by another process", ForeignExportError, _forged,
         {"owner_pid": os.getppid()}),
    Case("hello of another session", StaleBufferError, _forged, {"hello_session": 99}),
    Case("arena of the wrong size", StaleBufferError, _forged, {"size_delta": 4096}),
    Case("not an arena", DescriptorError, _forged, {"magic": b"NOTWARP!"}),
]


@contextlib.contextmanager
def hostile_payload(case: Case, frame: Any, good: Any) -> Iterator[bytes]:
    """The case's payload; a forged block file exists until the block exits."""
    if case.forge is None:
        yield case.build(frame, good)
        return
    with forged_session(**case.forge) as names:
        yield _forged(frame, good, names)


def test_hostile_descriptors_on_a_live_subscription_are_typed_counted_and_skipped():
    domain, topic = next(_domains), f"/reliability/hostile_{uuid.uuid4().hex[:8]}"
    got: list = []
    problems: list[str] = []
    with Node("victim", domain_id=domain) as node:
        sub = node.create_subscription(TENSOR, topic, got.append, depth=100,
                                       acceptable_buffer_backends="warp")
        forger = ForgedPublisher(domain, topic)
        try:
            assert wait_until(lambda: sub.get_publisher_count() == 1), "forger not discovered"
            for index, case in enumerate(CASES):
                frame, good = good_frame(index)
                errors, received = sub.errors, sub.received
                with hostile_payload(case, frame, good) as payload:
                    forger.send(sub, payload)
                    counted = wait_until(lambda: sub.errors == errors + 1, timeout=5)
                if not counted:
                    problems.append(f"{case.name}: not counted as an error")
                elif not isinstance(sub.last_error, case.expected):
                    problems.append(f"{case.name}: {sub.last_error!r}, expected "
                                    f"{case.expected.__name__}")
                forger.send(sub, payload_for(frame, good))  # the subscription goes on
                if not wait_until(lambda: sub.received == received + 1, timeout=5):
                    problems.append(f"{case.name}: the good message after it was not delivered")
                del frame, good
        finally:
            forger.close()
        counters = sub.counters
    assert not problems, "\n".join(problems)
    assert counters.errors == len(CASES) and counters.received == len(CASES)
    assert counters.callback_errors == 0 and counters.rejected == 0
    records = [check_frame(msg) for msg in got]
    assert [r["index"] for r in records] == list(range(len(CASES)))  # only the good ones
    assert all(r["ok"] and r["backend"] == "warp" and r["size"] == BLOCK for r in records)
    got.clear()  # log records of the dropped messages keep the subscription (and list) alive


# --------------------------------------------------------------------------- direct calls
PUBLISHER = EndpointInfo(
    gid=bytes(range(16)), node_name="talker", node_namespace="/", topic_name="/hostile",
    topic_type=TENSOR, endpoint_type=EndpointType.PUBLISHER, host_id=local_host_id(),
    process_id=os.getpid(), user_id=os.getuid())


@pytest.mark.parametrize("changes, expected", [
    ({"size": -1}, DescriptorError),
    ({"offset": -4096}, DescriptorError),
    ({"capacity": -BLOCK}, DescriptorError),
    ({"generation": -1}, DescriptorError),
    ({"owner_pid": -1}, DescriptorError),
    ({"peer_slot": -1}, DescriptorError),
    ({"size": 2**80}, DescriptorError),
    ({"kind": -3}, DescriptorError),
    ({"session": "abc"}, DescriptorError),
    ({"offset": 1.5}, DescriptorError),
])
def test_values_the_wire_cannot_carry_are_refused_by_the_backend(changes, expected):
    """Negative and over-wide values (a Python object can hold them; CDR cannot)."""
    frame, good = good_frame(0)
    with pytest.raises(expected):
        BACKEND.from_descriptor_with_endpoint(mutated(good, **changes), PUBLISHER)
    imported = Buffer(BACKEND.from_descriptor_with_endpoint(good, PUBLISHER))
    assert np.array_equal(imported.to_numpy(), pattern(9, 0, BLOCK))  # the good one still works
    del frame


def test_a_capacity_larger_than_the_block_is_refused_at_any_alignment():
    """A forged capacity twice the block's, at an offset aligned for it, passes the arena's
    geometry checks and the block's generation check; without the capacity in the generation
    the import would read the first bytes of the next block."""
    frames = [good_frame(i) for i in range(4)]  # two of four consecutive blocks are 8 KiB aligned
    aligned = [(frame, good) for frame, good in frames
               if (good.offset - _arena_data_offset(good)) % (2 * BLOCK) == 0]
    assert aligned, [good.offset for _, good in frames]
    frame, good = aligned[0]
    forged = mutated(good, capacity=2 * BLOCK, size=BLOCK + 1)
    with pytest.raises(ExportBoundsError, match="capacity"):
        BACKEND.from_descriptor_with_endpoint(forged, PUBLISHER)
    imported = Buffer(BACKEND.from_descriptor_with_endpoint(good, PUBLISHER))
    assert np.array_equal(imported.to_numpy(), pattern(9, frames.index((frame, good)), BLOCK))
    imported.release()
    del frames, aligned, frame


def _arena_data_offset(desc: Any) -> int:
    from warp_buffer.arena import current_arena

    return current_arena().data_offset


def test_a_foreign_publisher_and_a_wrong_type_are_refused():
    frame, good = good_frame(0)
    foreign = EndpointInfo(**{**{f: getattr(PUBLISHER, f) for f in (
        "gid", "node_name", "node_namespace", "topic_name", "topic_type", "endpoint_type",
        "process_id")}, "gid": bytes(16), "host_id": "elsewhere", "user_id": os.getuid()})
    with pytest.raises(ForeignExportError):
        BACKEND.from_descriptor_with_endpoint(good, foreign)
    with pytest.raises(DescriptorError):
        BACKEND.from_descriptor_with_endpoint(object(), PUBLISHER)
    del frame


# --------------------------------------------------------------------------- fuzzing
FIELD_VALUES = {
    "version": st.integers(0, 255), "kind": st.integers(0, 255),
    "peer_slot": st.integers(0, 2**16 - 1),
    "size": st.integers(0, 2**64 - 1) | st.integers(0, BLOCK + 1),
    "offset": st.integers(0, 2**64 - 1) | st.integers(0, 1 << 30),
    "capacity": st.integers(0, 2**64 - 1) | st.sampled_from([0, 2048, 4096, 8192, 1 << 40]),
    "generation": st.integers(0, 2**64 - 1) | st.integers(0, 50),
    "sequence": st.integers(0, 2**64 - 1),
    "owner_pid": st.integers(0, 2**32 - 1), "session": st.integers(0, 2**64 - 1),
    "device_uuid": st.integers(0, 2**64 - 1),
}
_NAME = re.compile(rb"^\0warp_buffer\.\d+\.\d+\.[0-9a-f]{16}$")


def fuzz_settings(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.function_scoped_fixture])


@pytest.fixture
def exported(monkeypatch):
    """One exported good frame, and a spy on every socket name the importer builds."""
    frame, good = good_frame(0)
    names: list[bytes] = []
    real = handoff.socket_name

    def spy(uid: int, pid: int, session: int) -> bytes:
        names.append(real(uid, pid, session))
        return names[-1]

    monkeypatch.setattr(handoff, "socket_name", spy)
    held = [frame, good, names]
    yield held
    held.clear()  # pytest keeps the fixture value until the end of the teardown


def decode_checked(payload: bytes, good: Any, names: list[bytes]) -> None:
    """Decode + import: a typed error, or exactly the good export's bytes. Every socket name the
    importer built is the numbers-only abstract name of this user."""
    try:
        msg = deserialize_message(payload, TENSOR, backends={"warp": BACKEND},
                                  endpoint_info=PUBLISHER)
    except RosidlBufferError:
        msg = None
    for name in names:
        assert _NAME.match(name) and name.split(b".")[1] == str(os.getuid()).encode(), name
    names.clear()
    if msg is None or msg.data.get_backend_type() != "warp":
        return  # an error, or a mutation that turned the field into plain CPU bytes
    impl = msg.data.get_impl()
    got = impl._import
    assert (got.owner_pid, got.session, got.offset, got.generation) == (
        good.owner_pid, good.session, good.offset, good.generation), "imported another block"
    expected = pattern(9, 0, BLOCK)[:got.size]
    assert np.array_equal(msg.data.to_numpy(), expected), "imported the wrong bytes"
    msg.data.release()


def _fuzz_fields(exported, data) -> None:
    frame, good, paths = exported
    names = data.draw(st.sets(st.sampled_from(sorted(FIELD_VALUES)), min_size=1, max_size=4))
    changes = {name: data.draw(FIELD_VALUES[name], label=name) for name in sorted(names)}
    decode_checked(payload_for(frame, mutated(good, **changes)), good, paths)


def _fuzz_bytes(exported, data) -> None:
    frame, good, paths = exported
    payload = bytearray(payload_for(frame, good))
    edits = data.draw(st.lists(st.tuples(st.integers(0, len(payload) - 1), st.integers(0, 255)),
                               min_size=1, max_size=6))
    for position, value in edits:
        payload[position] = value
    cut = data.draw(st.integers(0, len(payload)) | st.just(len(payload)))
    decode_checked(bytes(payload[:cut]), good, paths)


@fuzz_settings(FIELD_EXAMPLES)
@given(data=st.data())
def test_fuzz_descriptor_fields_only_typed_errors_or_the_right_bytes(exported, data):
    _fuzz_fields(exported, data)


@fuzz_settings(BYTE_EXAMPLES)
@given(data=st.data())
def test_fuzz_serialized_descriptor_bytes_only_typed_errors_or_the_right_bytes(exported, data):
    _fuzz_bytes(exported, data)


@pytest.mark.slow
def test_long_fuzz_of_descriptor_decoding_and_import(exported, request):
    if "slow" not in (request.config.option.markexpr or "") and not LONG_RUN:
        pytest.skip("long fuzz: opt in with `-m slow` or HYPOTHESIS_PROFILE=long")
    given(data=st.data())(fuzz_settings(50_000)(lambda data: _fuzz_fields(exported, data)))()
    given(data=st.data())(fuzz_settings(50_000)(lambda data: _fuzz_bytes(exported, data)))()
