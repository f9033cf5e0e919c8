"""Fake installed buffer backends (stand-ins for e.g. ``cuda_buffer_backend``).

What rmw_zenoh sees of a backend (``rosidl_buffer_backend_registry/backend_utils.hpp``): its
name, ``get_backend_metadata()`` (advertised in tokens), ``on_discovering_endpoint`` (told the
peer's advertised backends), ``create_descriptor_with_endpoint`` (null = send CPU bytes to that
peer) and the descriptor type. The fake makes a descriptor for a peer whose advertised backends
name it, and carries the bytes inline in ``FAKE_DESCRIPTOR``: enough to exercise the wire.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

from tests.upstream_model.messages import FAKE_DESCRIPTOR, default_message


class FakeBackend:
    """One installed backend of a model participant."""

    descriptor_type = FAKE_DESCRIPTOR

    def __init__(self, name: str, metadata: str, store: Typestore) -> None:
        if not name or name == "cpu":
            raise ValueError(f"a fake backend needs a name other than 'cpu', not {name!r}")
        self.name = name
        self.metadata = metadata
        self._store = store
        self._peer_accepts: dict[bytes, bool] = {}

    def on_discovering_endpoint(self, gid: bytes, peer_backends: dict[str, str]) -> None:
        self._peer_accepts[gid] = self.name in peer_backends

    def create_descriptor_with_endpoint(self, data: bytes, peer_gid: bytes) -> Any | None:
        if not self._peer_accepts.get(peer_gid):
            return None
        return default_message(self._store, FAKE_DESCRIPTOR, version=1, size=len(data),
                               origin=self.metadata,
                               data=np.frombuffer(data, dtype=np.uint8).copy())

    @staticmethod
    def from_descriptor(descriptor: Any) -> bytes:
        data = bytes(np.asarray(descriptor.data, dtype=np.uint8))
        if descriptor.size != len(data):
            raise ValueError(f"descriptor says {descriptor.size} bytes, carries {len(data)}")
        return data


def parse_backend_options(options: list[str]) -> dict[str, str]:
    """``NAME`` or ``NAME=METADATA`` (metadata may hold any character) -> {name: metadata}."""
    out: dict[str, str] = {}
    for option in options:
        name, _, metadata = option.partition("=")
        out[name] = metadata
    return out
