"""``WarpBufferBackend``: the ``"warp"`` rosidl_buffer backend plugin.

Thin by design: the memory domain, the exports and the imports live in :mod:`warp_buffer`; this
module negotiates with peers. Its descriptor message is
``warp_buffer_backend_msgs/msg/WarpBufferDescriptor`` (``msg/WarpBufferDescriptor.msg``), built
and read by :mod:`warp_buffer.ipc` (the descriptor is the export record: one form).

Who is served (judged once per peer gid, in ``on_discovering_endpoint`` or on first publish, and
cached until ``on_endpoint_gone``): a subscription that advertises ``warp``, on this host, under
this user, whose metadata says it can import by shared memory, while IPC is enabled here.
Everyone else gets ``None`` from ``create_descriptor_with_endpoint``, i.e. CPU bytes. See the
README next to this file for the transport-support matrix.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from rosidl_buffer import BufferBackend, BufferImplBase, EndpointInfo, EndpointType
from warp_buffer import WARP_BACKEND, WarpBufferImpl
from warp_buffer import descriptor as _desc
from warp_buffer.errors import ExportUnavailableError, ForeignExportError
from warp_buffer.ipc import (
    export_buffer,
    forget_peer,
    forget_session,
    import_buffer,
    ipc_disabled,
    local_host_id,
    local_user_id,
    peer_slot,
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
_WARP_TYPES: dict[type, bool] = {}  # impl type -> is it a WarpBufferImpl
#: Descriptors a peer may hold beyond its delivery queue: taken off it, not yet imported (a
#: reader descheduled in between finds the oldest of them recycled if more than this are sent
#: meanwhile: RecycledBufferError, which its keep-last subscription counts as dropped).
IN_HAND = 16

DESCRIPTOR_TYPE = _desc.DESCRIPTOR_TYPE
METADATA_VERSION = 2
IPC_SHM = "shm"
IPC_CUDA = "cuda_ipc"
_PEER_CACHE_SIZE = 4096  # a bound even if the transport never reports departures
HOST_ID_MAX = 255


# ------------------------------------------------------------------------------------ metadata
@dataclass(frozen=True)
class PeerMetadata:
    """What a warp peer advertises (``get_backend_metadata``), parsed."""

    version: int
    host_id: str
    user_id: int
    ipc: frozenset[str]
    devices: tuple[str, ...]  # "cpu", "cuda:0@<device uuid>", ...

    @property
    def cuda_uuids(self) -> frozenset[str]:
        """The UUIDs of the peer's CUDA devices (one per GPU and per MIG instance: PCI bus ids
        are shared by MIG instances, so they cannot say "the same device")."""
        return frozenset(d.split("@", 1)[1] for d in self.devices if "@" in d)


def format_metadata(meta: PeerMetadata) -> str:
    """``v=2;host=<host id>;uid=<uid>;ipc=shm+cuda_ipc;dev=cpu+cuda:0@<uuid>``: no ``/``, ``,``,
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
    cuda_uuids: frozenset[str] = frozenset()


def _refuse(reason: str) -> PeerDecision:
    return PeerDecision(False, reason)


@dataclass
class _Peer:
    decision: PeerDecision
    pid: int
    slot: Any = field(default=None)  # its delivery slot in our arena, on first descriptor


# ------------------------------------------------------------------------------------ backend
class WarpBufferBackend(BufferBackend):
    """The ``warp`` buffer backend: same-host zero-copy delivery of warp buffers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._peers: dict[bytes, _Peer] = {}
        # Publishers judged on the import side: gid -> None (served) or (error class, message):
        # a fresh error per refusal (a raised one would keep its traceback's frames alive).
        self._publishers: dict[bytes, tuple[type[Exception], str] | None] = {}
        # The session (owner pid, tag) of each served publisher, from its first descriptor: when
        # a session's last publisher is gone, its cached CUDA imports are dropped.
        self._publisher_sessions: dict[bytes, tuple[int, int]] = {}
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
                if device.uuid:
                    devices.append(f"{device.alias}@{device.uuid}")
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
        return _desc.descriptor_type()

    # -- discovery -----------------------------------------------------------------------------
    def on_discovering_endpoint(
        self,
        endpoint_info: EndpointInfo,
        existing_endpoints: Sequence[EndpointInfo],
        endpoint_supported_backends: Mapping[str, str],
    ) -> tuple[bool, list[set[int]]]:
        """Serve the peer by IPC? Judged once (and cached per gid) from its advertised backends,
        its locality and its metadata. No endpoint groups."""
        decision = self._decide(endpoint_info, endpoint_supported_backends)
        self._remember(endpoint_info, decision)
        return decision.accepted, []

    def on_endpoint_gone(self, endpoint_info: EndpointInfo) -> None:
        """Forget a departed peer: its cached decision, and its delivery slot (what was sent to
        it no longer pins any block). A departed publisher that was its session's last known
        one takes the session's cached CUDA imports with it (:func:`warp_buffer.ipc.
        forget_session`)."""
        with self._lock:
            peer = self._peers.pop(endpoint_info.gid, None)
            self._publishers.pop(endpoint_info.gid, None)
            session = self._publisher_sessions.pop(endpoint_info.gid, None)
            last = session is not None and session not in self._publisher_sessions.values()
        if peer is not None and peer.slot is not None:
            forget_peer(endpoint_info.gid)
        if last:
            forget_session(*session)  # type: ignore[misc]

    def peer_decision(self, endpoint_info: EndpointInfo) -> PeerDecision:
        """The cached decision for a peer (judged now from its info if not seen before)."""
        return self._peer(endpoint_info).decision

    def _peer(self, info: EndpointInfo) -> _Peer:
        peer = self._peers.get(info.gid)
        if peer is None:
            peer = self._remember(info, self._decide(info, info.supported_backends))
        return peer

    def _remember(self, info: EndpointInfo, decision: PeerDecision) -> _Peer:
        evicted = []
        with self._lock:
            peer = self._peers.get(info.gid)
            if peer is None or peer.decision != decision:
                if peer is not None and peer.slot is not None:
                    evicted.append(info.gid)
                peer = self._peers[info.gid] = _Peer(decision, info.process_id)
            while len(self._peers) > _PEER_CACHE_SIZE:
                gid = next(iter(self._peers))
                if self._peers.pop(gid).slot is not None:
                    evicted.append(gid)
        for gid in evicted:
            forget_peer(gid)
        if not decision.accepted:
            _log.debug("warp backend serves peer %s by CPU: %s", info.gid.hex(), decision.reason)
        return peer

    @property
    def known_peers(self) -> int:
        """Peers with a cached decision (bounded; departed ones are forgotten)."""
        return len(self._peers)

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
        uuids = meta.cuda_uuids if IPC_CUDA in meta.ipc else frozenset()
        return PeerDecision(True, "same host and user", uuids)

    # -- descriptors ---------------------------------------------------------------------------
    def create_descriptor_with_endpoint(
        self, impl: BufferImplBase, endpoint_info: EndpointInfo
    ) -> Any | None:
        """A descriptor of ``impl`` for the subscription ``endpoint_info``, or None (CPU bytes)
        when the peer cannot be served. The publish sealed the buffer before (its lease's one
        transition); an export of a buffer nobody sealed seals it."""
        kind = type(impl)
        warp = _WARP_TYPES.get(kind)
        if warp is None:  # (isinstance against the ABC costs a Python call: judged once a type)
            warp = _WARP_TYPES[kind] = isinstance(impl, WarpBufferImpl)
        if not warp:
            return None
        peer = self._peers.get(endpoint_info.gid) or self._peer(endpoint_info)
        if not peer.decision.accepted or not impl.is_exportable:
            impl.seal()  # served by CPU bytes: still the end of its write (once: a no-op now)
            return None
        # Through a keep-last queue that overwrites (the transport says so, per route), a peer
        # can import only its latest descriptors: the queue's, and a few taken off it but not
        # imported yet; older ones pin no block (see warp_buffer.arena.PeerSlot.window).
        depth = endpoint_info.delivery_queue_depth
        window = depth + IN_HAND if depth > 0 else 0
        slot = peer.slot
        if slot is None:
            slot = peer.slot = peer_slot(endpoint_info.gid, endpoint_info.process_id, window)
            if slot is None:
                _log.warning("every delivery slot of this process is taken: peer %s is served "
                             "by CPU", endpoint_info.gid.hex())
                return None
        elif slot.window != window:  # the route changed (its lane failed: Zenoh carries it)
            slot.window = window
        try:
            return export_buffer(impl, peer=slot,
                                 peer_device_uuids=peer.decision.cuda_uuids)
        except ExportUnavailableError as exc:
            _log.debug("warp backend falls back to CPU for %s: %s", endpoint_info.gid.hex(), exc)
            return None

    def from_descriptor_with_endpoint(
        self, descriptor: Any, endpoint_info: EndpointInfo
    ) -> WarpBufferImpl:
        """Read the export ``descriptor`` names (the publisher is ``endpoint_info``) in place, as
        a read-only :class:`WarpBufferImpl` with zero payload copies; release it with
        ``Buffer.release()`` (or ``with``) or let it be collected.

        Raises the typed errors of :func:`warp_buffer.ipc.import_buffer`, plus
        :class:`ForeignExportError` for a publisher on another host or user and
        :class:`ExportUnavailableError` when IPC is disabled here (both judged once per
        publisher, on its first descriptor).
        """
        gid = endpoint_info.gid
        if not endpoint_info.host_id:
            # A publisher known by its gid alone (its token has not arrived: the transport does
            # not wait for it, as rmw_zenoh does not). Nothing to judge it by but the descriptor:
            # the import's hand-off checks with the kernel (SO_PEERCRED) that the memory's owner
            # is a process of this user reachable on this host. Not cached: its token may come.
            if ipc_disabled():
                raise ExportUnavailableError("IPC is disabled here (WARP_BUFFER_DISABLE_IPC)")
            return import_buffer(descriptor)
        try:
            refusal = self._publishers[gid]
        except KeyError:
            refusal = self._judge_publisher(endpoint_info, descriptor)
        if refusal is not None:
            raise refusal[0](refusal[1])
        owner = getattr(descriptor, "owner_pid", None)
        if (type(owner) is int and owner > 0 and endpoint_info.process_id
                and owner != endpoint_info.process_id):
            # A publisher exports its own memory only (an import is re-exported from a copy)
            raise ForeignExportError(
                f"descriptor names memory of process {owner}, but its publisher is process "
                f"{endpoint_info.process_id}")
        return import_buffer(descriptor)

    def _judge_publisher(self, info: EndpointInfo,
                         descriptor: Any = None) -> tuple[type[Exception], str] | None:
        refusal: tuple[type[Exception], str] | None = None
        if ipc_disabled():
            refusal = (ExportUnavailableError, "IPC is disabled here (WARP_BUFFER_DISABLE_IPC)")
        elif info.host_id != local_host_id() or info.user_id != local_user_id():
            refusal = (ForeignExportError,
                       f"descriptor from a publisher on host {info.host_id!r} as user "
                       f"{info.user_id}; this is host {local_host_id()!r}, user "
                       f"{local_user_id()}")
        session = (getattr(descriptor, "owner_pid", None), getattr(descriptor, "session", None))
        with self._lock:
            self._publishers[info.gid] = refusal
            while len(self._publishers) > _PEER_CACHE_SIZE:
                self._publishers.pop(next(iter(self._publishers)))
            if refusal is None and all(type(n) is int for n in session):
                self._publisher_sessions[info.gid] = session  # type: ignore[assignment]
                while len(self._publisher_sessions) > _PEER_CACHE_SIZE:
                    self._publisher_sessions.pop(next(iter(self._publisher_sessions)))
        return refusal

    def __repr__(self) -> str:
        return f"WarpBufferBackend(pid={os.getpid()})"
