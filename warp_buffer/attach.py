"""The importer's side of a session: the arena mapped once per (this process, publisher session),
and the reader holds on its blocks.

:func:`attach` returns the cached :class:`AttachedArena` of a session, fetching and mapping it on
first use (:mod:`warp_buffer.handoff`). It is kept while the process lives (imports are then a
dict lookup plus a lock), and let go once its owner is gone and nothing here holds a block of it.
Its mapping keeps the memory alive: frames held or queued here stay readable after the publisher
exits or dies.

Letting a session go only drops this module's reference: the mappings and the file description
are released when the last object using them is gone (a hold keeps its arena), so a NumPy view
kept past ``release()`` keeps reading the bytes it was made over, never whatever a later mapping
puts at that address, and an import racing the let-go still finds the arena mapped.

A hold (:class:`Hold`, an import's token) is a read lock (OFD) on one byte of the block's lock
range (its first 4 KiB of the file: :data:`LOCK_SPAN`), taken on this process's own open file
description of the arena; each hold of this process locks a byte of its own, so a hold ends by
unlocking its byte, without counting the others and without a Python lock: its finalizer only
makes that system call. The publisher's reclaim probe write-locks the whole range. The kernel
drops the locks if the process dies.
"""

from __future__ import annotations

import ctypes
import fcntl
import itertools
import os
import threading
from typing import Any

import numpy as np

from . import handoff, memory
from .arena import (
    ACKS_OFFSET,
    GENS_OFFSET,
    LOCK_SPAN,
    MAX_PEERS,
    SLOT_STRIDE,
    Arena,
    Geometry,
    alive,
    existing_arena,
)
from .errors import ExportError, StaleBufferError

__all__ = ["AttachedArena", "Hold", "attach", "attached", "attached_sessions", "forget_idle"]

_SETLK, _request = memory.F_OFD_SETLK, memory.lock_request


class _DataMapping:
    """The data region of an attached arena, unmapped when the last array over it is gone (the
    arena's ``data`` array holds it as its base; every view of an import derives from that)."""

    __slots__ = ("__array_interface__", "_region")

    def __init__(self, address: int, nbytes: int, owned: bool) -> None:
        self.__array_interface__ = {"data": (address, True), "shape": (nbytes,),
                                    "typestr": "|u1", "version": 3}
        self._region = (address, nbytes) if owned else None  # None: our own arena's mapping

    def __del__(self) -> None:
        region, self._region = self._region, None
        if region is not None:
            try:
                memory.unmap(*region)
            except Exception:  # pragma: no cover - interpreter shutdown
                pass


class AttachedArena:
    """A publisher session's arena as this process sees it. Its header mapping and file
    description are released when the object is collected: holds and imports in progress keep
    it (see the module docstring)."""

    def __init__(self, owner_pid: int, session: int, geometry: Geometry, fd: int,
                 base: int, data_base: int, owned: bool) -> None:
        self.owner_pid = owner_pid
        self.session = session
        self.geometry = geometry
        self.fd = fd  # our own open file description: our locks (-1 once closed)
        # A forked child shares the description, and so its locks: only this process unlocks
        self._pid = os.getpid()
        self.base = base
        # ``owned``: the mappings are ours to unmap (False for our own arena, imported here)
        self._head = (base, geometry.data_offset) if owned else None
        self.data_offset = geometry.data_offset
        self.data_base = data_base  # where file offset data_offset is mapped here
        self.gens = (ctypes.c_uint64 * (geometry.data_bytes // 4096)).from_address(
            base + GENS_OFFSET)
        self.acks = (ctypes.c_uint64 * (MAX_PEERS * SLOT_STRIDE // 8)).from_address(
            base + ACKS_OFFSET)
        # Views of imports are read-only slices of this array (their base): while one lives,
        # the data stays mapped (_DataMapping).
        self.data = np.asarray(_DataMapping(data_base, geometry.data_bytes, owned))
        # (block offset, lock byte) of every hold alive here: a new hold takes a byte none of
        # them has (taken under _lock; a hold's end removes its own, without a lock).
        self._live: set[tuple[int, int]] = set()
        self._keys = itertools.count()
        self._lock = threading.Lock()

    @classmethod
    def fetch(cls, owner_pid: int, session: int) -> AttachedArena:
        received, geometry = handoff.fetch_arena(owner_pid, session)
        try:
            fd = memory.reopen(received)
        except OSError as exc:
            raise ExportError(f"cannot open the arena of process {owner_pid}: {exc}") from None
        finally:
            os.close(received)  # it shares the publisher's description (and its locks)
        try:
            size = geometry.file_size
            # Header, acknowledgement slots and generations writable (we acknowledge imports);
            # the data read-only: a reader can never change the publisher's bytes by mistake.
            head = memory.map_fd(fd, geometry.data_offset)
            try:
                    data = memory.map_fd(fd, size - geometry.data_offset, geometry.data_offset,
                                     writable=False)
            except BaseException:
                memory.unmap(head, geometry.data_offset)
                raise
        except OSError as exc:
            os.close(fd)
            raise ExportError(f"cannot map the arena of process {owner_pid}: {exc}") from None
        return cls(owner_pid, session, geometry, fd, head, data, owned=True)

    @classmethod
    def local(cls, arena: Arena) -> AttachedArena:
        """Our own session, imported in this very process: our mapping, a new description."""
        fd = memory.reopen(arena.fd)
        return cls(arena.pid, arena.session, arena.geometry, fd, arena.base,
                   arena.base + arena.data_offset, owned=False)

    def address(self, offset: int) -> int:
        """Address of file offset ``offset`` (in the data region) in this process."""
        return self.data_base + (offset - self.data_offset)

    # -- holds ------------------------------------------------------------------------------
    def hold(self, offset: int, slot: int = -1, sequence: int = 0) -> Hold:
        """Take a read lock on a byte of the block at ``offset`` of its own and return the hold;
        raises :class:`StaleBufferError` while the publisher is recycling the block. With a
        peer ``slot``, then record that this process imported delivery ``sequence`` of that peer
        (also when the lock fails: the descriptor was consumed either way). The lock comes
        first: once the publisher sees the acknowledgement, its write-lock probe meets it."""
        live = self._live
        with self._lock:
            try:
                key = next(self._keys) % LOCK_SPAN
                while (offset, key) in live:  # (only when LOCK_SPAN holds of one block live here)
                    key = next(self._keys) % LOCK_SPAN
                try:  # (memory.try_lock, inline: once per import)
                    fcntl.fcntl(self.fd, _SETLK, _request(fcntl.F_RDLCK, os.SEEK_SET,
                                                          offset + key, 1, 0))
                except OSError as exc:
                    if exc.errno not in memory.BUSY:
                        raise
                    raise StaleBufferError(f"block {offset:#x} of process {self.owner_pid} "
                                           "is being recycled") from None
                live.add((offset, key))
            finally:
                if slot >= 0:
                    index = slot * (SLOT_STRIDE // 8)
                    if self.acks[index] < sequence:
                        self.acks[index] = sequence
        hold = _new_hold(Hold)  # (Hold's __init__, inline: once per import)
        hold.arena, hold.offset, hold._key = self, offset, [key]
        return hold

    @property
    def held(self) -> int:
        """Holds alive in this process."""
        return len(self._live)

    def take_own_locks(self) -> None:
        """In a forked child: move this process's holds onto a description of its own. The
        inherited one is shared with the parent, so each side's unlock would end the other's
        hold (the publisher could recycle a block a view here still reads), and it would keep
        a dead parent's locks alive for as long as the child lives. No lock is taken: another
        thread may have held ``_lock`` at the fork (the child has a new one)."""
        self._lock = threading.Lock()
        inherited = self.fd
        if inherited < 0 or self._pid == os.getpid():
            return
        try:
            fd = memory.reopen(inherited)
        except OSError:
            return  # out of fds: the shared description stays (the parent's locks cover us)
        for offset, key in list(self._live):
            try:
                memory.try_lock(fd, offset + key, exclusive=False)
            except OSError:  # pragma: no cover - a read lock beside the parent's never conflicts
                pass
        self.fd, self._pid = fd, os.getpid()
        os.close(inherited)  # the parent's locks now live on its copy alone

    def __del__(self) -> None:
        head, self._head = self._head, None
        fd, self.fd = getattr(self, "fd", -1), -1  # first: a hold dropped later must not unlock it
        try:
            if head is not None:
                memory.unmap(*head)
            if fd >= 0:
                os.close(fd)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class Hold:
    """An import's token: its read lock on one byte of the block (see the module docstring).
    It keeps its arena (its mappings and description) alive, and ends when it is collected
    (everything made of the import is gone) or released (:meth:`release`), whichever comes
    first."""

    __slots__ = ("arena", "offset", "_key", "__weakref__")

    def __init__(self, arena: AttachedArena, offset: int, key: int = 0) -> None:
        self.arena = arena
        self.offset = offset
        self._key = [key]  # emptied by the one release that ends the hold (list.pop is atomic)

    @property
    def live(self) -> bool:
        return bool(self._key)

    def release(self) -> None:
        """End the hold now (idempotent): one unlock, no Python lock (it is also the token's
        finalizer). Not in a forked child that kept its parent's description, nor on a closed
        one (its locks went with it; the number may be another file's now). The byte is free
        for a new hold of this process only after the unlock. Whatever still uses the import's
        memory then reads bytes the publisher may recycle: drop the token instead if you can."""
        try:
            key = self._key.pop()
        except IndexError:
            return
        arena = self.arena
        fd, offset = arena.fd, self.offset
        try:
            if fd >= 0 and arena._pid == os.getpid():  # (memory.unlock, inline)
                fcntl.fcntl(fd, _SETLK, _request(fcntl.F_UNLCK, os.SEEK_SET, offset + key, 1, 0))
        except Exception:  # pragma: no cover - interpreter shutdown: nothing left to unlock
            pass
        finally:
            arena._live.discard((offset, key))

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        """As the ``deleter`` of an array over the import: it only keeps the hold alive."""

    __del__ = release  # every import ends here: the token is gone


_new_hold = object.__new__
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
    # views inherited here move onto descriptions of the child's own, and later imports attach
    # afresh.
    global _sessions_lock
    for arena in list(_sessions.values()):
        arena.take_own_locks()
    _sessions.clear()
    _sessions_lock = threading.Lock()


os.register_at_fork(after_in_child=_after_fork_in_child)
