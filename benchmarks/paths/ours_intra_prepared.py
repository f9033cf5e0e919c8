"""Ours: in-process one-way of a prepared message (publish to callback).

One CPU tensor message per size is built untimed and reused; each send stamps it in place and
publishes it to a subscription of the same process, whose callback reads the stamp from the
message's buffer. This times buffer_pubsub's own hand-off (validation, sealing, routing, the
keep-last queue, the executor's wake-up), comparable with the bare thread hand-off of the run.
"""

from __future__ import annotations

from benchmarks.paths.ours_common import make_prepared_pair

LABEL = "ours: intra-process, prepared message"
KIND = "ours"
TOPOLOGY = "thread"

make_sender, make_receiver = make_prepared_pair()
