"""Which /dev/shm files a process maps, and removing the ones our children left behind."""

from __future__ import annotations

import os
import re
from typing import Iterable

SHM_DIR = "/dev/shm"
_noted: set[str] = set()


def _current_mappings() -> set[str]:
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            lines = maps.read().splitlines()
    except OSError:
        return set()
    found = set()
    for line in lines:
        parts = line.split(maxsplit=5)
        if len(parts) == 6 and parts[5].startswith(SHM_DIR + "/"):
            found.add(parts[5].removesuffix(" (deleted)"))
    return found


def note_mapped_shm_files() -> None:
    """Remember the /dev/shm files this process maps now (call while transports are live)."""
    _noted.update(_current_mappings())


def mapped_shm_files() -> list[str]:
    """Every /dev/shm file this process was seen mapping (noted earlier or mapped now)."""
    note_mapped_shm_files()
    return sorted(_noted)


def shm_entries() -> set[str]:
    """Names of the entries in /dev/shm now."""
    try:
        return set(os.listdir(SHM_DIR))
    except OSError:
        return set()


def owned_by_pids(names: Iterable[str], pids: Iterable[int]) -> set[str]:
    """Entries whose name carries one of ``pids`` the way Zenoh (``<pid>.zenoh``) and torch
    (``torch_<pid>_...``) name the segments a process creates."""
    wanted = {str(pid) for pid in pids}
    owned = set()
    for name in names:
        match = re.fullmatch(r"(\d+)\.zenoh", name) or re.match(r"torch_(\d+)_", name)
        if match and match.group(1) in wanted:
            owned.add(name)
    return owned


def remove_leftovers(before: set[str], reported: Iterable[str], pids: Iterable[int],
                     prefixes: tuple[str, ...] = ()) -> list[str]:
    """Remove /dev/shm files our dead children made: new since ``before`` and either reported as
    mapped by them, named after their pids, or starting with one of ``prefixes`` (a path's own
    namespace, e.g. iceoryx2's ``iox2_``). Files of other processes are left alone."""
    new = shm_entries() - before
    candidates = {os.path.basename(path) for path in reported} & new
    candidates |= owned_by_pids(new, pids)
    candidates |= {name for name in new if prefixes and name.startswith(prefixes)}
    removed = []
    for name in sorted(candidates):
        try:
            os.unlink(os.path.join(SHM_DIR, name))
            removed.append(name)
        except FileNotFoundError:
            pass
    return removed
