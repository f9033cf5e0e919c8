"""Ours: warp-backed tensors between two processes, delivered by the warp backend (zero-copy).

The subscriber accepts ``"warp"``: the publisher exports the Warp buffer and sends a descriptor;
the subscriber imports (maps) it. Payload bytes copied: none, if the backend is zero-copy.
"""

from __future__ import annotations

from benchmarks.paths.ours_common import make_pair

LABEL = "ours: warp zero-copy"
KIND = "ours"
TOPOLOGY = "pair"

make_sender, make_receiver = make_pair(backend="warp", accept="warp")
