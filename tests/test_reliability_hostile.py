"""Stale and hostile warp descriptors: on a real subscription (a forged, discovered publisher
puts hand-made CDR payloads on the subscription's own channel) and through the backend directly,
plus hypothesis fuzzing of descriptor decoding and import.

Every bad input must raise a typed error (a ``RosidlBufferError``), be counted on the
subscription, not be delivered, and leave the subscription working: a good message sent right
after each one is delivered. A successful import must always be the exported bytes.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import secrets
import struct
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
    ExportError,
    ForeignExportError,
    StaleBufferError,
    SyncTimeoutError,
    ipc,
    shm,
)
from warp_buffer_backend import WarpBufferBackend

pytestmark = pytest.mark.multiprocess

BLOCK = 4096  # the good frames fill a whole block, so every offset/size maps known bytes
LONG_RUN = os.environ.get("HYPOTHESIS_PROFILE") == "long"
FIELD_EXAMPLES = 20_000 if LONG_RUN else 1_500
BYTE_EXAMPLES = 20_000 if LONG_RUN else 1_500
_domains = itertools.count(4500 + os.getpid() % 50 * 40)


@pytest.fixture(autouse=True)
def _pool_memory_back(monkeypatch):
    monkeypatch.setenv("WARP_BUFFER_SYNC_TIMEOUT_S", "0.05")  # a wrong stamp fails fast
    yield
    stats = release_pool_memory()
    assert all(s["leased"] == 0 for s in stats.values()), f"buffers left alive: {stats}"


# --------------------------------------------------------------------------- descriptors
def good_frame(index: int):
    """A warp ExperimentalTensor filling one whole block, with a descriptor of its export."""
    frame = make_frame(9, index, BLOCK, "warp")
    return frame, BACKEND.record_to_descriptor(ipc.export_buffer(frame.data))


def mutated(descriptor: Any, **changes: Any) -> Any:
    fields = {name: getattr(descriptor, name) for name in descriptor.get_fields_and_field_types()}
    copy = type(descriptor)(**fields)
    for name, value in changes.items():
        setattr(copy, name, value)
    return copy


def payload_for(frame: Any, descriptor: Any, backend: str = "warp") -> bytes:
    return bytes(serialize_message(frame, route=lambda _buffer: (backend, descriptor)))


def oversize_host(payload: bytes, host: str, length: int = 5000) -> bytes:
    """``payload`` with its host_id string replaced by a ``length``-byte one (bound is 255)."""
    encoded = host.encode() + b"\0"
    old = struct.pack("<I", len(encoded)) + encoded
    assert payload.count(old) == 1
    return payload.replace(old, struct.pack("<I", length + 1) + b"h" * length + b"\0")


def truncated_in_descriptor(payload: bytes, host: str) -> bytes:
    """``payload`` cut in the middle of the descriptor's host_id string."""
    return payload[:payload.index(host.encode()) + 3]


def dead_pid() -> int:
    pid = 4_000_000
    while shm.pid_alive(pid):
        pid -= 1
    return pid


@contextlib.contextmanager
def forged_block(capacity: int = BLOCK, *, file_size: int | None = None, mode: int = 0o600,
                 owner: int | None = None, magic: bytes = shm.MAGIC, symlink: bool = False,
                 ) -> Iterator[dict[str, int]]:
    """A hand-made block file under our prefix (this pid, a fresh session): a valid header
    unless told otherwise. Yields the descriptor fields that name it. Always removed."""
    session = secrets.randbits(63) | 1
    path = shm.block_path(os.getpid(), session, 1)
    target = f"{shm.SHM_DIR}/outside_prefix_{uuid.uuid4().hex}" if symlink else path
    fd = os.open(target, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        header = shm.BlockHeader(magic=magic, version=shm.HEADER_VERSION,
                                 header_size=shm.HEADER_SIZE, uid=7, generation=1,
                                 capacity=capacity, session=session, owner_pid=os.getpid(),
                                 block_id=1, kind=shm.KIND_HOST_DATA)
        os.pwrite(fd, bytes(header), 0)
        os.ftruncate(fd, shm.HEADER_SIZE + capacity if file_size is None else file_size)
        os.fchmod(fd, mode)
        if owner is not None:
            os.fchown(fd, owner, owner)
        if symlink:
            os.symlink(target, path)
        yield {"session": session, "owner_pid": os.getpid(), "block_id": 1, "uid": 7,
               "generation": 1, "capacity": capacity, "size": min(capacity, BLOCK), "offset": 0}
    finally:
        os.close(fd)
        for name in {path, target}:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(name)


BACKEND = WarpBufferBackend()
OTHER_UID = 65534


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
    Case("recycled uid", StaleBufferError, lambda f, g: payload_for(f, mutated(g, uid=g.uid ^ 1))),
    Case("missing export (block id)", StaleBufferError, _field(block_id=99_999)),
    Case("missing export (dead owner)", StaleBufferError, _field(owner_pid=dead_pid())),
    Case("missing export (session)", StaleBufferError, _field(session=12345)),
    Case("descriptor of another user", ForeignExportError,
         lambda f, g: payload_for(f, mutated(g, user_id=g.user_id + 1))),
    Case("host id with path separators", ForeignExportError, _field(host_id="../../etc/x")),
    Case("size beyond the block", ExportBoundsError, _field(size=BLOCK + 1)),
    Case("offset beyond the block", ExportBoundsError, _field(offset=BLOCK)),
    Case("offset + size beyond the block", ExportBoundsError, _field(offset=1, size=BLOCK)),
    Case("huge size", ExportBoundsError, _field(size=2**64 - 1)),
    Case("huge offset", ExportBoundsError, _field(offset=2**64 - 1)),
    Case("capacity larger than the file", ExportBoundsError, _field(capacity=2 * BLOCK)),
    Case("capacity not a block size", ExportBoundsError, _field(capacity=3000, size=100)),
    Case("zero size", ExportBoundsError, _field(size=0)),
    Case("unknown version", DescriptorError, _field(version=2)),
    Case("unknown kind", DescriptorError, _field(kind=9)),
    Case("owner pid 0", DescriptorError, _field(owner_pid=0)),
    Case("writer stamp never arrives", SyncTimeoutError,
         lambda f, g: payload_for(f, mutated(g, generation=g.generation + 1))),
    Case("truncated serialized descriptor", DeserializationError,
         lambda f, g: truncated_in_descriptor(payload_for(f, g), g.host_id)),
    Case("oversize serialized descriptor", DeserializationError,
         lambda f, g: oversize_host(payload_for(f, g), g.host_id)),
    Case("unknown backend name", DeserializationError, lambda f, g: payload_for(f, g, "nope")),
    *([Case("export file owned by another user", ForeignExportError, _forged,
            {"owner": OTHER_UID})] if os.geteuid() == 0 else []),  # chown needs root
    Case("export file with group/other access", ForeignExportError, _forged, {"mode": 0o644}),
    Case("symlink out of the prefix", ForeignExportError, _forged, {"symlink": True}),
    Case("truncated export file", StaleBufferError, _forged,
         {"file_size": shm.HEADER_SIZE + BLOCK // 2}),
    Case("file shorter than a header", StaleBufferError, _forged, {"file_size": 100}),
    Case("not a block header", StaleBufferError, _forged, {"magic": b"NOTWARP!"}),
    # A 1 TiB sparse block passes every size check; mapping it fails (ENOMEM under the default
    # overcommit heuristic), which must be a typed error too.
    Case("huge sparse block", ExportError, _forged, {"capacity": 1 << 40}),
]


@contextlib.contextmanager
def hostile_payload(case: Case, frame: Any, good: Any) -> Iterator[bytes]:
    """The case's payload; a forged block file exists until the block exits."""
    if case.forge is None:
        yield case.build(frame, good)
        return
    with forged_block(**case.forge) as names:
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
    ({"size": -1}, ExportBoundsError),
    ({"offset": -4096}, ExportBoundsError),
    ({"capacity": -BLOCK}, ExportBoundsError),
    ({"block_id": -1}, DescriptorError),
    ({"uid": -1}, DescriptorError),
    ({"owner_pid": -1}, DescriptorError),
    ({"ack_slot": -1}, DescriptorError),
    ({"size": 2**80}, ExportBoundsError),
    ({"device": "d" * 100}, DescriptorError),
    ({"kind": -3}, DescriptorError),
])
def test_values_the_wire_cannot_carry_are_refused_by_the_backend(changes, expected):
    """Negative and over-wide values (a Python object can hold them; CDR cannot)."""
    frame, good = good_frame(0)
    with pytest.raises(expected):
        BACKEND.from_descriptor_with_endpoint(mutated(good, **changes), PUBLISHER)
    imported = Buffer(BACKEND.from_descriptor_with_endpoint(good, PUBLISHER))
    assert np.array_equal(imported.to_numpy(), pattern(9, 0, BLOCK))  # the good one still works
    del frame


def test_a_foreign_publisher_and_a_wrong_type_are_refused():
    frame, good = good_frame(0)
    foreign = EndpointInfo(**{**{f: getattr(PUBLISHER, f) for f in (
        "gid", "node_name", "node_namespace", "topic_name", "topic_type", "endpoint_type",
        "process_id")}, "host_id": "elsewhere", "user_id": os.getuid()})
    with pytest.raises(ForeignExportError):
        BACKEND.from_descriptor_with_endpoint(good, foreign)
    with pytest.raises(DescriptorError):
        BACKEND.from_descriptor_with_endpoint(object(), PUBLISHER)
    del frame


# --------------------------------------------------------------------------- fuzzing
FIELD_VALUES = {
    "version": st.integers(0, 255), "kind": st.integers(0, 255),
    "size": st.integers(0, 2**64 - 1) | st.integers(0, BLOCK + 1),
    "offset": st.integers(0, 2**64 - 1) | st.integers(0, BLOCK + 1),
    "capacity": st.integers(0, 2**64 - 1) | st.sampled_from([0, 2048, 4096, 8192, 1 << 40]),
    "block_id": st.integers(0, 2**32 - 1), "uid": st.integers(0, 2**64 - 1),
    "generation": st.integers(0, 2**64 - 1), "ack_slot": st.integers(0, 2**16 - 1),
    "owner_pid": st.integers(0, 2**32 - 1), "session": st.integers(0, 2**64 - 1),
    "user_id": st.integers(0, 2**32 - 1),
    "host_id": st.text(max_size=255).filter(lambda s: "\0" not in s
                                            and len(s.encode()) <= 255),
    "device": st.text(max_size=32).filter(lambda s: "\0" not in s and len(s.encode()) <= 32),
    "device_pci_bus_id": st.text(max_size=32).filter(
        lambda s: "\0" not in s and len(s.encode()) <= 32),
}
_NAME = re.compile(r"^warp_buffer\.\d+\.\d+-[0-9a-f]{16}\.b\d+$")


def fuzz_settings(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.function_scoped_fixture])


@pytest.fixture
def exported(monkeypatch):
    """One exported good frame, and a spy on every export path the importer builds."""
    frame, good = good_frame(0)
    paths: list[str] = []
    real = shm.block_path

    def spy(pid: int, session: int, block_id: int) -> str:
        paths.append(real(pid, session, block_id))
        return paths[-1]

    monkeypatch.setattr(shm, "block_path", spy)
    held = [frame, good, paths]
    yield held
    held.clear()  # pytest keeps the fixture value until the end of the teardown


def decode_checked(payload: bytes, good: Any, paths: list[str]) -> None:
    """Decode + import: a typed error, or exactly the good export's bytes. Every path the
    importer built is under our prefix, with no separator of its own."""
    try:
        msg = deserialize_message(payload, TENSOR, backends={"warp": BACKEND},
                                  endpoint_info=PUBLISHER)
    except RosidlBufferError:
        msg = None
    for path in paths:
        assert path.startswith(shm.shm_prefix()) and _NAME.match(os.path.basename(path)), path
    paths.clear()
    if msg is None or msg.data.get_backend_type() != "warp":
        return  # an error, or a mutation that turned the field into plain CPU bytes
    impl = msg.data.get_impl()
    record = impl._import
    assert (record.owner_pid, record.session, record.block_id, record.uid) == (
        good.owner_pid, good.session, good.block_id, good.uid), "imported another block"
    expected = pattern(9, 0, BLOCK)[record.offset:record.offset + record.size]
    assert np.array_equal(msg.data.to_numpy(), expected), "imported the wrong bytes"


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
