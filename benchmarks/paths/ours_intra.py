"""Ours: intra-process delivery (publisher and subscription in one process).

Warp-backed tensors to a subscription in the same process that accepts ``"any"``: buffer_pubsub
hands the message object over without serializing it.
"""

from __future__ import annotations

from benchmarks.paths.ours_common import make_pair

LABEL = "ours: intra-process"
KIND = "ours"
TOPOLOGY = "thread"

make_sender, make_receiver = make_pair(backend="warp", accept="any")
