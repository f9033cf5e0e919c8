"""The "warp" backend plugin against the backend guide's ship checklist, without a transport:
discovery, metadata, refusals (None = CPU fallback), descriptor CDR round trip and size bound,
cross-process import with zero payload copies, and typed errors for bad descriptors."""

from __future__ import annotations

import gc
import itertools
import os

import numpy as np
import pytest

import warp_buffer
from rosidl_buffer import (
    MAX_BUFFER_DESCRIPTOR_SIZE,
    Buffer,
    BufferOverwrittenError,
    CpuBufferImpl,
    EndpointInfo,
    EndpointType,
    RosidlBufferError,
    local_host_id,
    registry,
)
from rosidl_buffer.messages import deserialize_message, get_message_type, serialize_message
from tests._warp_helpers import Child, checksum, expected_pattern, fill_pattern
from warp_buffer import descriptor as wire_layout
from warp_buffer import (
    DescriptorError,
    ExportBoundsError,
    ExportUnavailableError,
    ForeignExportError,
    RecycledBufferError,
    StaleBufferError,
    WarpBufferImpl,
    allocate_buffer,
    from_output_buffer,
)
from warp_buffer_backend import (
    DESCRIPTOR_TYPE,
    PeerMetadata,
    WarpBufferBackend,
    format_metadata,
    parse_metadata,
)

IMAGE = "sensor_msgs/msg/Image"
_gids = itertools.count(1)

pytestmark = pytest.mark.usefixtures("warp_pool_drained")



@pytest.fixture
def backend():
    instance = registry.create_backend_instance("warp")
    yield instance
    for gid in list(instance._peers):  # as the transport reports departures: slots go back
        instance.on_endpoint_gone(_info(gid=gid))


def _info(kind=EndpointType.SUBSCRIPTION, supported=None, **changes) -> EndpointInfo:
    fields = dict(gid=next(_gids).to_bytes(16, "little"), node_name="n", node_namespace="/",
                  topic_name="/t", topic_type=IMAGE, endpoint_type=kind, host_id=local_host_id(),
                  process_id=os.getpid(), user_id=os.getuid(), supported_backends=supported or {})
    fields.update(changes)
    return EndpointInfo(**fields)


def _subscriber(backend, **changes) -> EndpointInfo:
    return _info(supported={"warp": backend.get_backend_metadata(), "cpu": ""}, **changes)


def _written(nbytes=4096, seed=5) -> Buffer:
    buffer = allocate_buffer(nbytes, "cpu")
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, seed)
    return buffer


def test_plugin_is_discoverable(backend):
    assert "warp" in registry.get_backend_names()
    assert isinstance(backend, WarpBufferBackend) and backend.get_backend_type() == "warp"
    assert backend.get_descriptor_type() is get_message_type(DESCRIPTOR_TYPE)
    assert isinstance(backend.create_empty_descriptor(), backend.get_descriptor_type())


def test_metadata_says_what_a_peer_needs(backend, monkeypatch):
    meta = parse_metadata(backend.get_backend_metadata())
    assert meta.version == 2 and meta.host_id == local_host_id() and meta.user_id == os.getuid()
    assert "shm" in meta.ipc and meta.devices[0] == "cpu"
    monkeypatch.setenv("WARP_BUFFER_DISABLE_IPC", "1")
    assert parse_metadata(backend.get_backend_metadata()).ipc == frozenset()
    uuid = "GPU-5a1b2c3d-0000-1111-2222-333344445555"
    sample = PeerMetadata(1, "h@x", 7, frozenset({"shm", "cuda_ipc"}), ("cpu", f"cuda:0@{uuid}"))
    assert parse_metadata(format_metadata(sample)) == sample
    assert sample.cuda_uuids == {uuid}
    for bad in ("", "v=1", "v=x;host=h;uid=1;ipc=;dev=", "v=1;v=1;host=h;uid=1;ipc=;dev="):
        with pytest.raises(ValueError):
            parse_metadata(bad)


def test_same_host_same_user_warp_subscriber_is_served(backend):
    sub = _subscriber(backend)
    assert backend.on_discovering_endpoint(sub, [], sub.supported_backends) == (True, [])
    buffer = _written()
    descriptor = backend.create_descriptor_with_endpoint(buffer.get_impl(), sub)
    assert isinstance(descriptor, backend.get_descriptor_type())
    assert descriptor.size == 4096 and descriptor.kind == descriptor.KIND_HOST
    assert buffer.get_impl().is_published
    with pytest.raises(warp_buffer.WriteHandleError):
        from_output_buffer(buffer)
    imported = backend.from_descriptor_with_endpoint(descriptor, _info(EndpointType.PUBLISHER))
    assert isinstance(imported, WarpBufferImpl)
    np.testing.assert_array_equal(imported.to_cpu().view(), expected_pattern(4096, 5))


def _refusals(backend):
    meta = parse_metadata(backend.get_backend_metadata())
    other = lambda **c: format_metadata(PeerMetadata(**{**meta.__dict__, **c}))  # noqa: E731
    return {
        "no warp advertised": _info(supported={"cpu": ""}),
        "another host": _subscriber(backend, host_id="elsewhere"),
        "another user": _subscriber(backend, user_id=os.getuid() + 1),
        "metadata: another host": _info(supported={"warp": other(host_id="elsewhere")}),
        "metadata: another user": _info(supported={"warp": other(user_id=os.getuid() + 1)}),
        "metadata: IPC disabled there": _info(supported={"warp": other(ipc=frozenset())}),
        "metadata: unknown version": _info(supported={"warp": other(version=1)}),
        "metadata: unreadable": _info(supported={"warp": "garbage"}),
    }


def test_every_refused_peer_gets_none(backend):
    for reason, peer in _refusals(backend).items():
        buffer = _written()
        accepted, groups = backend.on_discovering_endpoint(peer, [], peer.supported_backends)
        assert (accepted, groups) == (False, []), reason
        assert backend.create_descriptor_with_endpoint(buffer.get_impl(), peer) is None, reason
        # Without discovery first, the decision is made (and cached) on the first publish.
        fresh = _info(supported=dict(peer.supported_backends), host_id=peer.host_id,
                      user_id=peer.user_id)
        assert backend.create_descriptor_with_endpoint(buffer.get_impl(), fresh) is None, reason
        assert not backend.peer_decision(fresh).accepted


@pytest.mark.parametrize("switch", ["WARP_BUFFER_DISABLE_IPC", "WARP_BUFFER_TEST_HOST_ID",
                                    "WARP_BUFFER_TEST_USER_ID"])
def test_environment_switches_force_cpu_fallback(backend, monkeypatch, switch):
    sub = _subscriber(backend)  # advertised before the switch: a normal same-host peer
    buffer = _written()
    monkeypatch.setenv(switch, {"WARP_BUFFER_DISABLE_IPC": "1", "WARP_BUFFER_TEST_HOST_ID":
                                "pretend-host", "WARP_BUFFER_TEST_USER_ID": "4242"}[switch])
    assert backend.on_discovering_endpoint(sub, [], sub.supported_backends)[0] is False
    assert backend.create_descriptor_with_endpoint(buffer.get_impl(), sub) is None


def test_non_warp_and_private_buffers_get_none(backend, monkeypatch):
    sub = _subscriber(backend)
    assert backend.create_descriptor_with_endpoint(CpuBufferImpl(b"abc"), sub) is None
    monkeypatch.setenv("WARP_BUFFER_DISABLE_IPC", "1")
    private = _written()  # allocated while IPC was off: private memory
    monkeypatch.delenv("WARP_BUFFER_DISABLE_IPC")
    assert backend.create_descriptor_with_endpoint(private.get_impl(), sub) is None


def test_decisions_are_cached_per_peer(backend):
    sub = _subscriber(backend)
    assert backend.on_discovering_endpoint(sub, [], sub.supported_backends)[0]
    same_gid_now_refusing = _info(gid=sub.gid, supported={"cpu": ""})
    assert backend.peer_decision(same_gid_now_refusing).accepted  # the cached answer


def _worst_case_descriptor(backend):
    top = (1 << 64) - 1
    values = [255, 255, 65535, (1 << 32) - 1] + [top] * (len(wire_layout.FIELDS) - 4)
    return wire_layout.make(tuple(values))


def test_descriptor_is_one_fixed_struct_byte_identical_to_the_cdr_codec(backend):
    Image = get_message_type(IMAGE)
    sub = _subscriber(backend)
    buffer = _written(640 * 480 * 3 // 4 * 4)
    real = backend.create_descriptor_with_endpoint(buffer.get_impl(), sub)
    for descriptor in (real, _worst_case_descriptor(backend)):
        data = serialize_message(descriptor)
        assert bytes(data[4:]) == wire_layout.pack(descriptor)  # the precompiled layout
        assert len(data) - 4 == wire_layout.LAYOUT.size <= MAX_BUFFER_DESCRIPTOR_SIZE
        assert deserialize_message(data, DESCRIPTOR_TYPE) == descriptor
        assert wire_layout.unpack(data[4:]) == descriptor
        # Inline in a message, through the buffer-field route, as a transport sends it.
        msg = Image(height=1, width=len(buffer), encoding="mono8", step=len(buffer), data=buffer)
        wire = serialize_message(msg, route=lambda b, d=descriptor: ("warp", d))
        assert len(wire) < 4096 + 200  # the payload did not travel
    with pytest.raises(RosidlBufferError):  # a value the layout cannot carry
        serialize_message(wire_layout.make((256,) + wire_layout.values_of(real)[1:]))
    with pytest.raises(DescriptorError):
        wire_layout.pack(wire_layout.make((256,) + wire_layout.values_of(real)[1:]))


def test_departed_peers_are_forgotten_so_the_cache_stays_bounded(backend):
    baseline = backend.known_peers
    for _ in range(3000):
        sub = _subscriber(backend)
        backend.on_discovering_endpoint(sub, [], sub.supported_backends)
        buffer = _written(64)
        assert backend.create_descriptor_with_endpoint(buffer.get_impl(), sub) is not None
        backend.on_endpoint_gone(sub)
    assert backend.known_peers == baseline
    del buffer
    gc.collect()
    assert warp_buffer.pool_stats()["cpu"]["free_blocks"] >= 1  # nothing left pinned


def test_descriptor_made_here_is_imported_in_another_process_with_zero_copies(backend):
    Image = get_message_type(IMAGE)
    nbytes = 1 << 20
    buffer = _written(nbytes, seed=77)
    msg = Image(height=1024, width=1024, encoding="mono8", step=1024, data=buffer)
    sub = _subscriber(backend)
    wire = serialize_message(msg, route=lambda b: ("warp", backend.create_descriptor_with_endpoint(
        b.get_impl(), sub)))
    assert len(wire) < 2048
    publisher = _info(EndpointType.PUBLISHER)
    argument = {"cdr": bytes(wire).hex(), "type": IMAGE, "field": "data", "publisher": {
        "gid": publisher.gid.hex(), "node_name": "n", "node_namespace": "/", "topic_name": "/t",
        "topic_type": IMAGE, "endpoint_type": "publisher", "host_id": publisher.host_id,
        "process_id": publisher.process_id, "user_id": publisher.user_id}}
    with Child("import", argument) as child:
        result = child.result()
        assert result["backend"] == "warp" and result["size"] == nbytes
        assert result["crc"] == checksum(expected_pattern(nbytes, 77))
        assert result["mapping"].startswith("/memfd:warp_buffer")  # the publisher's own pages
        assert child.finish() == 0


def _descriptor(backend):
    buffer = _written()
    return buffer, backend.create_descriptor_with_endpoint(buffer.get_impl(), _subscriber(backend))


def test_bad_descriptors_raise_typed_errors(backend, monkeypatch):
    publisher = _info(EndpointType.PUBLISHER)
    buffer, good = _descriptor(backend)

    def changed(**fields):
        values = dict(zip(wire_layout.FIELDS, wire_layout.values_of(good)))
        values.update(fields)
        return wire_layout.make(tuple(values[name] for name in wire_layout.FIELDS))

    cases = [
        (ForeignExportError, good, _info(EndpointType.PUBLISHER, host_id="another-host")),
        (ForeignExportError, good, _info(EndpointType.PUBLISHER, user_id=os.getuid() + 1)),
        (ForeignExportError, changed(owner_pid=good.owner_pid + 1), publisher),  # not its own
        (StaleBufferError, changed(generation=good.generation + 500), publisher),
        (StaleBufferError, changed(session=good.session ^ 0xFF), publisher),
        (ExportBoundsError, changed(size=good.capacity + 1), publisher),
        (ExportBoundsError, changed(capacity=good.capacity * 3), publisher),
        (ExportBoundsError, changed(offset=good.offset + 1), publisher),
        (DescriptorError, changed(kind=9), publisher),
        (DescriptorError, changed(version=1), publisher),
        (DescriptorError, changed(size="large"), publisher),
        (DescriptorError, changed(size=-1), publisher),
        (ExportUnavailableError, changed(kind=1), publisher),  # CUDA IPC: no such GPU here
        (DescriptorError, get_message_type(IMAGE)(), publisher),
    ]
    for error, descriptor, info in cases:
        with pytest.raises(error):
            backend.from_descriptor_with_endpoint(descriptor, info)
    monkeypatch.setenv("WARP_BUFFER_DISABLE_IPC", "1")
    with pytest.raises(ExportUnavailableError):  # judged once per publisher: a new one
        backend.from_descriptor_with_endpoint(good, _info(EndpointType.PUBLISHER))


def test_recycled_export_raises_stale(backend):
    sub = _subscriber(backend)
    publisher = _info(EndpointType.PUBLISHER)
    buffer = _written(3000)
    descriptor = backend.create_descriptor_with_endpoint(buffer.get_impl(), sub)
    block = buffer.get_impl().block
    backend.from_descriptor_with_endpoint(descriptor, publisher)  # imported (acknowledged), dropped
    del buffer
    gc.collect()
    recycled = allocate_buffer(3000, "cpu")
    assert recycled.get_impl().block is block
    with pytest.raises(StaleBufferError) as raised:
        backend.from_descriptor_with_endpoint(descriptor, publisher)
    # the generic form a transport counts as dropped (keep-last), not as an error
    assert isinstance(raised.value, RecycledBufferError)
    assert isinstance(raised.value, BufferOverwrittenError)


def test_an_imported_buffer_is_republished_from_a_local_copy(backend):
    sub = _subscriber(backend)
    publisher = _info(EndpointType.PUBLISHER)
    buffer = _written(2048, seed=4)
    imported = backend.from_descriptor_with_endpoint(
        backend.create_descriptor_with_endpoint(buffer.get_impl(), sub), publisher)
    again = backend.create_descriptor_with_endpoint(imported, sub)
    assert again is not None and again.offset != buffer.get_impl().block.offset
    relayed = backend.from_descriptor_with_endpoint(again, publisher)
    np.testing.assert_array_equal(relayed.to_cpu().view(), expected_pattern(2048, 4))


def test_cuda_fields_round_trip_through_the_fixed_layout():
    """What a CUDA IPC descriptor carries (no GPU needed): a 64-bit digest of the device UUID
    (distinct for two MIG instances of one GPU, which share a PCI bus id) and the 64-byte memory
    and event handles, as words."""
    mig_a, mig_b = "MIG-0e6a6b4c-1111-5e2f-9a40-8f3c6c2f0a01", "MIG-0e6a6b4c-1111-5e2f-9a40-8f3c6c2f0a02"
    words = {wire_layout.uuid_word(u) for u in (mig_a, mig_b)}
    assert len(words) == 2 and all(0 < w < 1 << 64 for w in words)
    assert wire_layout.uuid_word(mig_a) == wire_layout.uuid_word(mig_a)
    assert wire_layout.uuid_word("") == 0 and wire_layout.uuid_word(None) == 0
    handle = bytes(range(64))
    assert wire_layout.handle_bytes(wire_layout.handle_words(handle)) == handle
    with pytest.raises(DescriptorError):
        wire_layout.handle_words(bytes(65))
