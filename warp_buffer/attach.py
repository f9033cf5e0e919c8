"""The importer's side of a session: the arena mapped once per (this process, publisher session),
and the reader holds on its blocks.

:func:`attach` returns the cached :class:`AttachedArena` of a session, fetching and mapping it on
first use (:mod:`warp_buffer.handoff`). It is kept while the process lives (imports are then a
dict lookup), and let go once its owner is gone. Its mapping keeps the memory alive: frames held
or queued here stay readable after the publisher exits or dies.

The mappings and this process's own open file description of the arena belong to the session's
native core (:class:`warp_buffer._core.Session`), which imports: it checks a descriptor against
the geometry, takes the hold, acknowledges the delivery and compares the generation, in one C
call. A hold (:class:`Hold`, an import's token, also native) keeps its session: letting a
session go only drops this module's reference, and the mappings and the description are
released when the last hold is gone, so a NumPy view kept past ``release()`` keeps reading the
bytes it was made over, never whatever a later mapping puts at that address, and an import
racing the let-go still finds the arena mapped.

A hold is a read lock (OFD) on the block's lock range (its first 4 KiB of the file:
:data:`~warp_buffer.arena.LOCK_SPAN`), taken on the session's description when this process's
first hold of the block starts and dropped when its last ends (counted in C; a hold's end is one
C function under the GIL: no Python lock, no finalizer). The publisher's reclaim probe
write-locks the whole range. The kernel drops the locks if the process dies.
"""

from __future__ import annotations

import os
import threading
from typing import Any

from . import handoff, memory
from .arena import Arena, Geometry, alive, existing_arena
from .descriptor import _core
from .errors import ExportError

__all__ = ["AttachedArena", "Hold", "attach", "attached", "attached_sessions", "forget_idle"]

#: An import's token (see the module docstring).
Hold = _core.Hold


class AttachedArena:
    """A publisher session's arena as this process sees it: its geometry and its native core
    (:attr:`core`, a :class:`warp_buffer._core.Session`, which owns the mappings and the
    description and imports)."""

    def __init__(self, owner_pid: int, session: int, geometry: Geometry, core: Any) -> None:
        self.owner_pid = owner_pid
        self.session = session
        self.geometry = geometry
        self.core = core
        self.data_offset = geometry.data_offset
        #: Imports from this session: ``import_block(values) -> Hold`` (the core's, one C call)
        self.import_block = core.import_block

    @classmethod
    def fetch(cls, owner_pid: int, session: int) -> AttachedArena:
        received, geometry = handoff.fetch_arena(owner_pid, session)
        try:
            fd = memory.reopen(received)
        except OSError as exc:
            raise ExportError(f"cannot open the arena of process {owner_pid}: {exc}") from None
        finally:
            os.close(received)  # it shares the publisher's description (and its locks)
        head_len, size = geometry.data_offset, geometry.file_size
        try:
            # Header, acknowledgement slots and generations writable (we acknowledge imports);
            # the data read-only: a reader can never change the publisher's bytes by mistake.
            head = memory.map_fd(fd, head_len)
            try:
                data = memory.map_fd(fd, size - head_len, head_len, writable=False)
            except BaseException:
                memory.unmap(head, head_len)
                raise
        except OSError as exc:
            os.close(fd)
            raise ExportError(f"cannot map the arena of process {owner_pid}: {exc}") from None
        core = _core.Session(owner_pid, session, fd, head, head_len, data, size - head_len,
                             head_len, True)
        return cls(owner_pid, session, geometry, core)

    @classmethod
    def local(cls, arena: Arena) -> AttachedArena:
        """Our own session, imported in this very process: our mapping, a new description."""
        fd = memory.reopen(arena.fd)
        g = arena.geometry
        core = _core.Session(arena.pid, arena.session, fd, arena.base, g.data_offset,
                             arena.base + g.data_offset, g.data_bytes, g.data_offset, False)
        return cls(arena.pid, arena.session, g, core)

    @property
    def fd(self) -> int:
        """This process's description of the arena (its holds' locks; -1 once closed)."""
        return self.core.fd

    @property
    def data_base(self) -> int:
        """Where file offset :attr:`data_offset` is mapped here."""
        return self.core.data_address

    def address(self, offset: int) -> int:
        """Address of file offset ``offset`` (in the data region) in this process."""
        return self.core.data_address + (offset - self.data_offset)

    @property
    def held(self) -> int:
        """Blocks this process holds now."""
        return self.core.held


_sessions: dict[tuple[int, int], AttachedArena] = {}
_sessions_lock = threading.Lock()
#: The arena of a session attached already (None otherwise): one dict lookup per import.
attached = _sessions.get


def attach(owner_pid: int, session: int) -> AttachedArena:
    """The arena of session ``(owner_pid, session)`` in this process (fetched once)."""
    key = (owner_pid, session)
    arena = _sessions.get(key)
    if arena is not None:
        return arena
    with _sessions_lock:
        arena = _sessions.get(key)
        if arena is None:
            own = existing_arena()
            if own is not None and own.pid == owner_pid and own.session == session:
                arena = AttachedArena.local(own)
            else:
                forget_idle()
                arena = AttachedArena.fetch(owner_pid, session)
            _sessions[key] = arena
        return arena


def forget_idle() -> int:
    """Let go of sessions whose owner is gone; returns how many (called when a new session is
    attached, so the address space stays bounded). Each is unmapped once nothing of this
    process uses it any more (its holds keep it: see the module docstring); a descriptor of a
    session let go is refused as stale."""
    dropped = 0
    for key, arena in list(_sessions.items()):
        if not alive(arena.owner_pid):
            _sessions.pop(key, None)
            del arena
            dropped += 1
            handoff.session_gone(key)  # caches keyed by session (CUDA imports) forget it too
    return dropped


def attached_sessions() -> list[AttachedArena]:
    return list(_sessions.values())


def _after_fork_in_child() -> None:
    # Inherited descriptions are shared with the parent (so are their locks): the holds of
    # views inherited here, of every session still alive (attached or let go), move onto
    # descriptions of the child's own, and later imports attach afresh.
    global _sessions_lock
    _core.sessions_after_fork()
    _sessions.clear()
    _sessions_lock = threading.Lock()


os.register_at_fork(after_in_child=_after_fork_in_child)
