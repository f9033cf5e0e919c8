"""Child programs of tests/test_cuda_ipc.py (run as ``python -m tests._cuda_child ROLE``).

``export``: allocate exportable device memory, fill it with :func:`pattern`, print one JSON line
with its CUDA IPC memory and event handles, wait for a line on stdin, exit.
``vmm_export SOCKET``: make VMM memory, fill it, send its fd over the Unix socket SOCKET, exit
at once (the parent maps it after we are gone).
``vmm_write_readonly SOCKET``: receive a VMM fd, map it read-only, try to write through it and
print whether the write was refused.
``vmm_publish``: allocate a warp buffer on cuda:0 from the pool (a VMM block where the device
exports POSIX fds), fill it with :func:`pattern`, export it for a same-GPU peer, print one JSON
line (descriptor bytes as hex, its kind), wait for a line on stdin, exit.
``vmm_import DESCRIPTOR``: import the descriptor (the block's fd comes over the publisher's
hand-off socket), print the CRC it reads, then launch a write kernel through the import and
print whether it was refused.
"""

from __future__ import annotations

import json
import socket
import sys

import numpy as np

NBYTES = 1 << 20


def pattern(nbytes: int = NBYTES, seed: int = 3) -> np.ndarray:
    return ((np.arange(nbytes, dtype=np.uint64) * 7 + seed) & 255).astype(np.uint8)


def _fill(target, data: np.ndarray) -> None:
    import warp as wp

    wp.copy(target, wp.array(data, dtype=wp.uint8, device=target.device))
    wp.synchronize_device(target.device)


def export() -> int:
    import warp as wp

    from warp_buffer import cuda

    wp.config.quiet = True
    memory = cuda.alloc_ipc_memory("cuda:0", NBYTES)
    _fill(memory, pattern())
    event = cuda.new_ipc_event("cuda:0")
    wp.get_stream("cuda:0").record_event(event)
    print(json.dumps({"mem": cuda.ipc_mem_handle(memory).hex(),
                      "event": cuda.ipc_event_handle(event).hex()}), flush=True)
    sys.stdin.readline()
    return 0


def vmm_export(path: str) -> int:
    import warp as wp

    from warp_buffer import cuda

    wp.config.quiet = True
    memory = cuda.VmmMemory.create("cuda:0", NBYTES)
    _fill(memory.array(0, NBYTES), pattern())
    fd = memory.export_fd()
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.connect(path)
        socket.send_fds(sock, [json.dumps({"nbytes": memory.nbytes}).encode()], [fd])
    return 0  # exits with the memory still imported by the parent


def vmm_write_readonly(path: str) -> int:
    import warp as wp

    from warp_buffer import cuda

    wp.config.quiet = True
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.connect(path)
        msg, fds, _flags, _addr = socket.recv_fds(sock, 1024, 1)
    nbytes = json.loads(msg)["nbytes"]
    memory = cuda.VmmMemory.import_fd(fds[0], nbytes, "cuda:0", read_only=True)
    view = memory.array(0, NBYTES)
    refused = False
    try:
        view.fill_(7)
        wp.synchronize_device("cuda:0")
    except Exception:  # noqa: BLE001 - a fault is the expected outcome
        refused = True
    print(json.dumps({"refused": refused}), flush=True)
    return 0


def vmm_publish() -> int:
    import warp as wp

    import warp_buffer
    from warp_buffer import descriptor, ipc

    wp.config.quiet = True
    device = wp.get_device("cuda:0")
    buffer = warp_buffer.allocate_buffer(NBYTES, "cuda:0")
    with warp_buffer.from_output_buffer(buffer) as out:
        wp.copy(out.array, wp.array(pattern(), dtype=wp.uint8, device=device))
    exported = ipc.export_buffer(buffer, peer_device_uuids={device.uuid})
    print(json.dumps({"descriptor": descriptor.pack(exported).hex(), "kind": exported.kind}),
          flush=True)
    sys.stdin.readline()
    return 0


def vmm_import(hexed: str) -> int:
    import zlib

    import warp as wp

    from benchmarks import gpu_check
    from warp_buffer import descriptor, ipc

    wp.config.quiet = True
    impl = ipc.import_buffer(descriptor.unpack(bytes.fromhex(hexed)))
    crc = zlib.crc32(impl.to_cpu().view().tobytes())
    print(json.dumps({"crc": crc, "device": str(impl.device)}), flush=True)
    target = wp.array(ptr=impl.array.ptr, dtype=wp.uint8, shape=(NBYTES,), device="cuda:0")
    refused = False
    try:  # a kernel writing through the read-only mapping must fault, not change the bytes
        wp.launch(gpu_check.kernels()["slow_fill"], dim=NBYTES, inputs=[target, 7, 1],
                  device="cuda:0")
        wp.synchronize_device("cuda:0")
    except Exception:  # noqa: BLE001 - a fault is the expected outcome
        refused = True
    print(json.dumps({"refused": refused}), flush=True)
    return 0


if __name__ == "__main__":
    role = sys.argv[1]
    if role == "export":
        sys.exit(export())
    if role == "vmm_export":
        sys.exit(vmm_export(sys.argv[2]))
    if role == "vmm_write_readonly":
        sys.exit(vmm_write_readonly(sys.argv[2]))
    if role == "vmm_publish":
        sys.exit(vmm_publish())
    if role == "vmm_import":
        sys.exit(vmm_import(sys.argv[2]))
    raise SystemExit(f"unknown role {role!r}")

