"""Small helpers over the Zenoh API shared by nodes, publishers and subscriptions."""

from __future__ import annotations

from typing import Any

import zenoh


def undeclare_quietly(*entities: Any) -> None:
    """Undeclare Zenoh entities (publishers, subscribers, tokens), ignoring ones already gone:
    teardown runs on close, on destroy and on peer loss, in any order."""
    for entity in entities:
        try:
            entity.undeclare()
        except zenoh.ZError:
            pass
