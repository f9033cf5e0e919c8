"""The paths under test: ours and the peers a Python user would pick instead.

Each path is a module with ``LABEL``, ``KIND`` ("ours" or "peer"), ``TOPOLOGY`` and the factories
``make_sender(settings, shared)`` / ``make_receiver(settings, shared)``:

- ``"pair"``: the runner starts a receiving and a sending child process;
- ``"thread"``: one child process, the receiver on a thread of it (intra-process delivery);
- ``"spawn"``: one child that starts the receiver itself through the peer's own process
  machinery (``make_shared(settings)`` builds what both sides share, e.g. a torch queue).

A factory raises ``PathUnavailable`` when the path cannot run here (missing package or API).
"""

from __future__ import annotations

import dataclasses
import importlib
from types import ModuleType

# Order = table / plot order.
PATH_MODULES: dict[str, str] = {
    "warp_zero_copy": "benchmarks.paths.ours_warp",
    "cpu_fallback": "benchmarks.paths.ours_cpu",
    "intra_process": "benchmarks.paths.ours_intra",
    "intra_prepared": "benchmarks.paths.ours_intra_prepared",
    "thread_handoff": "benchmarks.paths.thread_handoff",
    "lane": "benchmarks.paths.lane",
    "lane_busy": "benchmarks.paths.lane_busy",
    "zenoh_copy": "benchmarks.paths.zenoh_copy",
    "cpu_codec_floor": "benchmarks.paths.cpu_codec_floor",
    "zenoh_shm": "benchmarks.paths.zenoh_shm",
    "iceoryx2": "benchmarks.paths.iceoryx2_pubsub",
    "iceoryx2_listener": "benchmarks.paths.iceoryx2_listener",
    "torch_mp": "benchmarks.paths.torch_mp",
}


class PathUnavailable(RuntimeError):
    """The path cannot run on this machine or tree (the message says why)."""


@dataclasses.dataclass(frozen=True)
class PathSettings:
    """What both sides of a path agree on before they start."""

    name: str
    run_id: str  # unique per run: topic / service / key names derive from it
    max_nbytes: int  # largest payload of the run (pool and segment sizing)
    port: int = 0  # a free loopback TCP port for transports that need one
    domain_id: int = 0  # a domain of its own for buffer_pubsub


def load_path(name: str) -> ModuleType:
    """The module implementing path ``name``."""
    try:
        return importlib.import_module(PATH_MODULES[name])
    except KeyError:
        raise ValueError(f"unknown path {name!r}; known: {', '.join(PATH_MODULES)}") from None
