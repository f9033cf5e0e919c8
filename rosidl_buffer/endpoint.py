"""``EndpointInfo``: what a backend is told about a publisher or subscription, local or remote.

The transport fills one for every endpoint it creates or discovers; backends judge a peer from it
(same host? same user? which backends does it accept?) and key their per-peer caches by ``gid``.
"""

from __future__ import annotations

import enum
import functools
import os
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

__all__ = ["EndpointInfo", "EndpointType", "local_host_id", "parse_acceptable_backends"]

GID_SIZE = 16


class EndpointType(enum.Enum):
    """Which side of a topic an endpoint is: a ``PUBLISHER`` or a ``SUBSCRIPTION`` (as
    ``rmw_endpoint_type_t``)."""

    PUBLISHER = "publisher"
    SUBSCRIPTION = "subscription"


@dataclass(frozen=True, eq=True)
class EndpointInfo:
    """Identity and capabilities of one endpoint (``rmw_topic_endpoint_info_t`` plus locality).

    ``supported_backends`` maps each backend name the endpoint accepts to that backend's metadata
    string as the endpoint advertised it; publishers advertise none (as in ROS 2).
    """

    gid: bytes
    node_name: str
    node_namespace: str
    topic_name: str
    topic_type: str
    endpoint_type: EndpointType
    host_id: str
    process_id: int
    user_id: int
    supported_backends: Mapping[str, str] = field(default_factory=dict, hash=False, compare=False)
    #: Set by the transport when what it sends this endpoint travels through a keep-last queue
    #: of this many entries that overwrites its oldest (a same-host lane): only that many recent
    #: descriptors can still reach the endpoint, so a backend need not keep older ones' memory.
    #: 0: nothing bounds what is in flight (a network transport's buffers), or unknown.
    delivery_queue_depth: int = field(default=0, hash=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.gid, (bytes, bytearray)) or len(self.gid) != GID_SIZE:
            raise ValueError(f"gid must be {GID_SIZE} bytes, got {self.gid!r}")
        object.__setattr__(self, "gid", bytes(self.gid))
        object.__setattr__(
            self, "supported_backends", MappingProxyType(dict(self.supported_backends))
        )

    @property
    def is_publisher(self) -> bool:
        """True for a publisher, False for a subscription."""
        return self.endpoint_type is EndpointType.PUBLISHER

    def is_same_process(self) -> bool:
        """True if the endpoint lives in this very process (intra-process delivery applies)."""
        return self.host_id == local_host_id() and self.process_id == os.getpid()


@functools.lru_cache(maxsize=1)
def local_host_id() -> str:
    """A stable id of this machine: ``/etc/machine-id`` when present, else the host name.

    Two processes see the same id exactly when they can share memory through ``/dev/shm``
    (containers with their own machine-id but a shared /dev/shm are treated as other hosts, which
    errs on the safe side: CPU fallback).
    """
    for path in ("/etc/machine-id", "/var/lib/dbus/machine-id"):
        try:
            with open(path, encoding="ascii") as f:
                machine_id = f.read().strip()
        except OSError:
            continue
        if machine_id:
            return f"{machine_id}@{socket.gethostname()}"
    return socket.gethostname()


def parse_acceptable_backends(option: str | Sequence[str], available: list[str]) -> list[str]:
    """Resolve a subscription's ``acceptable_buffer_backends`` option to backend names.

    ``"cpu"`` (or empty) = CPU only; ``"any"`` = every available backend, also inside a list
    (as rmw_zenoh reads it: ``"cpu, any"`` is every backend); otherwise a comma separated list of
    names (or a list of them), each of which must be available. ``"cpu"`` is always included.
    Raises ValueError for anything else.
    """
    if isinstance(option, (list, tuple)) and all(isinstance(name, str) for name in option):
        option = ",".join(option)
    if option is not None and not isinstance(option, str):
        raise ValueError(f"acceptable_buffer_backends must be a str (or a list of names), got "
                         f"{type(option).__name__}")
    names = [name.strip() for name in (option or "cpu").split(",") if name.strip()]
    if "any" in names:
        names = list(available)
    else:
        unknown = [name for name in names if name not in available and name != "cpu"]
        if unknown:
            raise ValueError(
                f"acceptable_buffer_backends names unknown backends {unknown}; "
                f"available: {sorted(available)}"
            )
    if "cpu" not in names:
        names.append("cpu")
    return list(dict.fromkeys(names))
