"""copy_bytes against wp.copy: odd sizes and offsets, launches split below 2**31 threads
(on cpu, and on CUDA where a GPU exists)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from warp_buffer import kernels

SIZES = [1, 15, 16, 17, 4095, 4096 + 3, (1 << 20) + 1, (5 << 20) + 7]
OFFSETS = [(0, 0), (1, 0), (0, 3), (7, 9), (16, 32)]


def _copy_case(device: str, nbytes: int, src_off: int, dst_off: int) -> None:
    rng = np.random.default_rng(nbytes + 31 * src_off + dst_off)
    data = rng.integers(0, 256, size=nbytes + 64, dtype=np.uint8)
    src_base = wp.array(data, dtype=wp.uint8, device=device)
    dst_base = wp.zeros(nbytes + 64, dtype=wp.uint8, device=device)
    ref_base = wp.zeros(nbytes + 64, dtype=wp.uint8, device=device)
    src = src_base[src_off:src_off + nbytes]
    kernels.copy_bytes(dst_base[dst_off:dst_off + nbytes], src)
    wp.copy(ref_base, src_base, dest_offset=dst_off, src_offset=src_off, count=nbytes)
    got, want = dst_base.numpy(), ref_base.numpy()
    assert np.array_equal(got, want), f"{device}: {nbytes} bytes at +{src_off} -> +{dst_off}"
    # Nothing outside the destination range was touched.
    assert not got[:dst_off].any() and not got[dst_off + nbytes:].any()


@pytest.mark.parametrize("nbytes", SIZES)
@pytest.mark.parametrize("offsets", OFFSETS)
def test_copy_bytes_matches_wp_copy_on_cpu(nbytes: int, offsets: tuple[int, int]) -> None:
    _copy_case("cpu", nbytes, *offsets)


@pytest.mark.parametrize("nbytes", [(3 << 20) + 5, (5 << 20) + 7])
def test_copy_bytes_split_into_several_launches(monkeypatch: pytest.MonkeyPatch,
                                                nbytes: int) -> None:
    # Two threads (two 1 MiB chunks on cpu) per launch: every launch starts at its own offset.
    monkeypatch.setattr(kernels, "MAX_LAUNCH_THREADS", 2)
    assert len(kernels.launch_slices(nbytes, kernels.CPU_CHUNK)) >= 2
    for offsets in [(0, 0), (3, 1), (16, 0)]:
        _copy_case("cpu", nbytes, *offsets)


@pytest.mark.parametrize("nbytes", [1, 16, (1 << 35) + 3, 40 << 30, 1 << 40])
def test_launch_slices_stay_below_int32_and_cover_every_byte(nbytes: int) -> None:
    chunk = kernels.CUDA_CHUNK
    slices = kernels.launch_slices(nbytes, chunk)
    assert all(0 < threads <= kernels.MAX_LAUNCH_THREADS < 2**31 for _, threads in slices)
    covered = 0
    for base, threads in slices:
        assert base == covered  # contiguous, in order
        covered += threads * chunk
    assert nbytes <= covered < nbytes + chunk


def test_copy_bytes_rejects_mismatched_arrays() -> None:
    a = wp.zeros(16, dtype=wp.uint8, device="cpu")
    b = wp.zeros(17, dtype=wp.uint8, device="cpu")
    with pytest.raises(ValueError):
        kernels.copy_bytes(a, b)


@pytest.mark.cuda
@pytest.mark.parametrize("nbytes", SIZES)
@pytest.mark.parametrize("offsets", OFFSETS)
def test_copy_bytes_matches_wp_copy_on_cuda(nbytes: int, offsets: tuple[int, int]) -> None:
    _copy_case("cuda:0", nbytes, *offsets)


@pytest.mark.cuda
def test_copy_bytes_split_launches_on_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kernels, "MAX_LAUNCH_THREADS", 1000)  # 16,000 bytes per launch
    for offsets in [(0, 0), (3, 5), (16, 32)]:
        _copy_case("cuda:0", 123_457, *offsets)
