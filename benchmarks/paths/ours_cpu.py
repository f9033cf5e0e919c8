"""Ours: the CPU fallback between two processes (CDR bytes over Zenoh).

CPU tensors to a subscriber that accepts only ``"cpu"``: the publisher serializes the payload
into CDR and Zenoh carries it (with Zenoh's default configuration, as buffer_pubsub uses it).
"""

from __future__ import annotations

from benchmarks.paths.ours_common import make_pair

LABEL = "ours: CPU fallback"
KIND = "ours"
TOPOLOGY = "pair"

make_sender, make_receiver = make_pair(backend="cpu", accept="cpu")
