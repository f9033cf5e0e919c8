"""``WarpBufferBackend``: the ``"warp"`` rosidl_buffer backend plugin.

Thin by design: the memory domain, the exports and the imports live in :mod:`warp_buffer`; this
module negotiates with peers and converts export records to and from the descriptor message
``warp_buffer_backend_msgs/msg/WarpBufferDescriptor`` (``msg/WarpBufferDescriptor.msg``).

Who is served (decided once per peer gid, in ``on_discovering_endpoint`` or on first publish):
a subscription that advertises ``warp``, on this host, under this user, whose metadata says it
can import by shared memory, while IPC is enabled here. Everyone else gets ``None`` from
``create_descriptor_with_endpoint``, i.e. CPU bytes. See the README next to this file for the
transport-support matrix.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rosidl_buffer import BufferBackend, BufferImplBase, EndpointInfo, EndpointType
from rosidl_buffer.messages import get_message_type
from warp_buffer import WARP_BACKEND, WarpBufferImpl
from warp_buffer import shm as _shm
from warp_buffer.errors import DescriptorError, ExportUnavailableError, ForeignExportError
from warp_buffer.ipc import (
    DEVICE_MAX,
    HOST_ID_MAX,
    ExportKind,
    ExportRecord,
    export_buffer,
    import_export,
    ipc_disabled,
    local_host_id,
    local_user_id,
)

__all__ = [
    "DESCRIPTOR_TYPE",
    "METADATA_VERSION",
    "PeerDecision",
    "PeerMetadata",
    "WarpBufferBackend",
    "format_metadata",
    "parse_metadata",
]

_log = logging.getLogger(__name__)

DESCRIPTOR_TYPE = "warp_buffer_backend_msgs/msg/WarpBufferDescriptor"
METADATA_VERSION = 1
IPC_SHM = "shm"
IPC_CUDA = "cuda_ipc"
_PEER_CACHE_SIZE = 4096
_HANDLE_SIZE = 64


# ------------------------------------------------------------------------------------ metadata
@dataclass(frozen=True)
class PeerMetadata:
    """What a warp peer advertises (``get_backend_metadata``), parsed."""

    version: int
    host_id: str
    user_id: int
    ipc: frozenset[str]
    devices: tuple[str, ...]  # "cpu", "cuda:0@<pci bus id>", ...

    @property
    def cuda_pci_bus_ids(self) -> frozenset[str]:
        return frozenset(d.split("@", 1)[1] for d in self.devices if "@" in d)


def format_metadata(meta: PeerMetadata) -> str:
    """``v=1;host=<host id>;uid=<uid>;ipc=shm+cuda_ipc;dev=cpu+cuda:0@<pci>``: no ``/``, ``,``,
    spaces or quotes of its own (the transport percent-encodes it anyway)."""
    return (f"v={meta.version};host={meta.host_id};uid={meta.user_id};"
            f"ipc={'+'.join(sorted(meta.ipc))};dev={'+'.join(meta.devices)}")


def parse_metadata(text: str) -> PeerMetadata:
    """Inverse of :func:`format_metadata`; raises ``ValueError`` on anything else."""
    fields: dict[str, str] = {}
    for part in text.split(";"):
        key, sep, value = part.partition("=")
        if not sep or key in fields:
            raise ValueError(f"malformed warp metadata field {part!r}")
        fields[key] = value
    try:
        version = int(fields["v"])
        user_id = int(fields["uid"])
        host_id = fields["host"]
        ipc = frozenset(x for x in fields["ipc"].split("+") if x)
        devices = tuple(x for x in fields["dev"].split("+") if x)
    except (KeyError, ValueError) as exc:
        raise ValueError(f"malformed warp metadata {text!r}: {exc}") from None
    return PeerMetadata(version, host_id, user_id, ipc, devices)


@dataclass(frozen=True)
class PeerDecision:
    """Whether the backend serves a peer by IPC, and why (for logs and tests)."""

    accepted: bool
    reason: str
    cuda_pci_bus_ids: frozenset[str] = frozenset()


def _refuse(reason: str) -> PeerDecision:
    return PeerDecision(False, reason)


# ------------------------------------------------------------------------------------ backend
class WarpBufferBackend(BufferBackend):
    """The ``warp`` buffer backend: same-host zero-copy delivery of warp buffers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._peers: collections.OrderedDict[bytes, PeerDecision] = collections.OrderedDict()
        self._local: dict[bytes, EndpointInfo] = {}
        self._devices: tuple[str, ...] | None = None
        self._cuda_ipc = False

    # -- identity ------------------------------------------------------------------------------
    def get_backend_type(self) -> str:
        return WARP_BACKEND

    def _device_list(self) -> tuple[str, ...]:
        if self._devices is None:
            import warp as wp

            devices = ["cpu"]
            cuda_ipc = False
            for device in wp.get_cuda_devices():
                devices.append(f"{device.alias}@{device.pci_bus_id}")
                cuda_ipc = cuda_ipc or bool(device.is_ipc_supported)
            self._devices = tuple(devices)
            self._cuda_ipc = cuda_ipc
        return self._devices

    def local_metadata(self) -> PeerMetadata:
        devices = self._device_list()
        if ipc_disabled():
            ipc: frozenset[str] = frozenset()
        else:
            ipc = frozenset({IPC_SHM, IPC_CUDA} if self._cuda_ipc else {IPC_SHM})
        return PeerMetadata(METADATA_VERSION, local_host_id(), local_user_id(), ipc, devices)

    def get_backend_metadata(self) -> str:
        """Version, host id, user id, IPC mechanisms (empty when disabled) and devices."""
        return format_metadata(self.local_metadata())

    def get_descriptor_type(self) -> type:
        return get_message_type(DESCRIPTOR_TYPE)

    # -- discovery -----------------------------------------------------------------------------
    def on_creating_endpoint(self, endpoint_info: EndpointInfo) -> None:
        """Remember the local endpoint; the first one sweeps exports of dead processes."""
        _shm.sweep_once()
        with self._lock:
            self._local[endpoint_info.gid] = endpoint_info

    def on_discovering_endpoint(
        self,
        endpoint_info: EndpointInfo,
        existing_endpoints: Sequence[EndpointInfo],
        endpoint_supported_backends: Mapping[str, str],
    ) -> tuple[bool, list[set[int]]]:
        """Serve the peer by IPC? Decided (and cached per gid) from its advertised backends, its
        locality and its metadata. No endpoint groups."""
        decision = self._decide(endpoint_info, endpoint_supported_backends)
        self._remember(endpoint_info.gid, decision)
        return decision.accepted, []

    def peer_decision(self, endpoint_info: EndpointInfo) -> PeerDecision:
        """The cached decision for a peer (made now from its info if not seen before)."""
        with self._lock:
            decision = self._peers.get(endpoint_info.gid)
            if decision is not None:
                self._peers.move_to_end(endpoint_info.gid)
                return decision
        decision = self._decide(endpoint_info, endpoint_info.supported_backends)
        self._remember(endpoint_info.gid, decision)
        return decision

    def _remember(self, gid: bytes, decision: PeerDecision) -> None:
        with self._lock:
            self._peers[gid] = decision
            self._peers.move_to_end(gid)
            while len(self._peers) > _PEER_CACHE_SIZE:
                self._peers.popitem(last=False)
        if not decision.accepted:
            _log.debug("warp backend serves peer %s by CPU: %s", gid.hex(), decision.reason)

    def _decide(self, info: EndpointInfo, supported: Mapping[str, str]) -> PeerDecision:
        if ipc_disabled():
            return _refuse("IPC is disabled here (WARP_BUFFER_DISABLE_IPC)")
        # Only subscriptions advertise accepted backends (as in ROS 2); a publisher peer is
        # judged on its locality alone.
        if info.endpoint_type is EndpointType.SUBSCRIPTION and WARP_BACKEND not in supported:
            return _refuse("the peer does not accept the warp backend")
        host, user = local_host_id(), local_user_id()
        if len(host.encode()) > HOST_ID_MAX:
            return _refuse(f"this host id is longer than {HOST_ID_MAX} bytes")
        if info.host_id != host:
            return _refuse(f"the peer is on another host ({info.host_id!r})")
        if info.user_id != user:
            return _refuse(f"the peer runs as another user ({info.user_id})")
        text = supported.get(WARP_BACKEND, "")
        if not text:
            # A peer that names warp without metadata gets the baseline: host shared memory.
            return PeerDecision(True, "same host and user (no metadata: shared memory only)")
        try:
            meta = parse_metadata(text)
        except ValueError as exc:
            return _refuse(f"unreadable warp metadata: {exc}")
        if meta.version != METADATA_VERSION:
            return _refuse(f"warp metadata version {meta.version} (this is {METADATA_VERSION})")
        if meta.host_id != host:
            return _refuse(f"the peer says it is on host {meta.host_id!r}")
        if meta.user_id != user:
            return _refuse(f"the peer says it runs as user {meta.user_id}")
        if IPC_SHM not in meta.ipc:
            return _refuse("the peer cannot import by IPC (disabled there)")
        pcis = meta.cuda_pci_bus_ids if IPC_CUDA in meta.ipc else frozenset()
        return PeerDecision(True, "same host and user", pcis)

    # -- descriptors ---------------------------------------------------------------------------
    def create_descriptor_with_endpoint(
        self, impl: BufferImplBase, endpoint_info: EndpointInfo
    ) -> Any | None:
        """A descriptor of ``impl`` for the subscription ``endpoint_info``, or None (CPU bytes)
        when the peer cannot be served. A warp buffer is marked published either way."""
        if not isinstance(impl, WarpBufferImpl):
            return None
        impl._mark_published()
        decision = self.peer_decision(endpoint_info)
        if not decision.accepted or ipc_disabled():
            return None
        if not impl.is_exportable:
            return None
        try:
            record = export_buffer(impl, peer_pci_bus_ids=decision.cuda_pci_bus_ids)
        except ExportUnavailableError as exc:
            _log.debug("warp backend falls back to CPU for %s: %s", endpoint_info.gid.hex(), exc)
            return None
        return self.record_to_descriptor(record)

    def from_descriptor_with_endpoint(
        self, descriptor: Any, endpoint_info: EndpointInfo
    ) -> WarpBufferImpl:
        """Import the export ``descriptor`` names (the publisher is ``endpoint_info``) as a
        read-only :class:`WarpBufferImpl` over the shared memory, with zero payload copies.

        Raises the typed errors of :func:`warp_buffer.ipc.import_export`, plus
        :class:`ForeignExportError` for a publisher on another host or user and
        :class:`ExportUnavailableError` when IPC is disabled here.
        """
        if ipc_disabled():
            raise ExportUnavailableError("IPC is disabled here (WARP_BUFFER_DISABLE_IPC)")
        host, user = local_host_id(), local_user_id()
        if endpoint_info.host_id != host or endpoint_info.user_id != user:
            raise ForeignExportError(
                f"descriptor from a publisher on host {endpoint_info.host_id!r} as user "
                f"{endpoint_info.user_id}; this is host {host!r}, user {user}"
            )
        return import_export(self.descriptor_to_record(descriptor))

    # -- conversions ---------------------------------------------------------------------------
    def record_to_descriptor(self, record: ExportRecord) -> Any:
        cls = self.get_descriptor_type()
        return cls(
            version=record.version, kind=int(record.kind), size=record.size,
            offset=record.offset, capacity=record.capacity, block_id=record.block_id,
            uid=record.uid, generation=record.generation, ack_slot=record.ack_slot,
            owner_pid=record.owner_pid, session=record.session, user_id=record.user_id,
            host_id=record.host_id, device=record.device,
            device_pci_bus_id=record.device_pci_bus_id,
            cuda_ipc_mem_handle=_handle_array(record.cuda_ipc_mem_handle),
            cuda_ipc_event_handle=_handle_array(record.cuda_ipc_event_handle),
        )

    def descriptor_to_record(self, descriptor: Any) -> ExportRecord:
        if not isinstance(descriptor, self.get_descriptor_type()):
            raise DescriptorError(f"expected a {DESCRIPTOR_TYPE}, got {type(descriptor).__name__}")
        try:
            kind = ExportKind(int(descriptor.kind))
        except ValueError:
            raise DescriptorError(f"unknown export kind {descriptor.kind}") from None
        if len(descriptor.device) > DEVICE_MAX:
            raise DescriptorError("device name too long")
        cuda = kind is ExportKind.CUDA_IPC
        record = ExportRecord(
            kind=kind, size=int(descriptor.size), offset=int(descriptor.offset),
            capacity=int(descriptor.capacity), block_id=int(descriptor.block_id),
            uid=int(descriptor.uid), generation=int(descriptor.generation),
            ack_slot=int(descriptor.ack_slot), owner_pid=int(descriptor.owner_pid),
            session=int(descriptor.session), user_id=int(descriptor.user_id),
            host_id=descriptor.host_id, device=descriptor.device,
            device_pci_bus_id=descriptor.device_pci_bus_id,
            cuda_ipc_mem_handle=_handle_bytes(descriptor.cuda_ipc_mem_handle) if cuda else b"",
            cuda_ipc_event_handle=_handle_bytes(descriptor.cuda_ipc_event_handle) if cuda else b"",
            version=int(descriptor.version),
        )
        record.validate()
        return record

    def __repr__(self) -> str:
        return f"WarpBufferBackend(pid={os.getpid()})"


def _handle_array(handle: bytes) -> np.ndarray:
    if len(handle) > _HANDLE_SIZE:
        raise DescriptorError(f"a CUDA IPC handle is {_HANDLE_SIZE} bytes, not {len(handle)}")
    return np.frombuffer(handle.ljust(_HANDLE_SIZE, b"\0"), dtype=np.uint8).copy()


def _handle_bytes(array: Any) -> bytes:
    data = np.asarray(array, dtype=np.uint8)
    if data.shape != (_HANDLE_SIZE,):
        raise DescriptorError(f"a CUDA IPC handle is {_HANDLE_SIZE} bytes, not {data.shape}")
    return data.tobytes()
