"""The Warp kernels of the example pipelines.

In a module of their own, imported by name: Warp caches compiled kernels per module, so only
the first run compiles them (a few seconds on the CPU); kernels defined in a script's
``__main__`` would compile again in every process.
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def draw_test_pattern(image: wp.array3d(dtype=wp.uint8), phase: int):
    """An rgb8 frame: pixel ``(y, x, c)`` = ``(y + x + 64 * c + phase) % 256``."""
    y, x = wp.tid()
    for c in range(3):
        image[y, x, c] = wp.uint8((y + x + 64 * c + phase) % 256)


@wp.kernel
def scan_rings(points: wp.array(dtype=wp.vec4f), azimuths: int, rotation: float,
               range_m: float, ring_spacing_m: float):
    """A lidar scan of rings: point ``i`` is on ring ``i // azimuths`` (at ``range_m + ring *
    ring_spacing_m`` metres), rotated by ``rotation``; x, y, z, intensity (= the ring)."""
    i = wp.tid()
    ring = i // azimuths
    azimuth = 2.0 * wp.pi * float(i % azimuths) / float(azimuths) + rotation
    distance = range_m + float(ring) * ring_spacing_m
    points[i] = wp.vec4f(distance * wp.cos(azimuth), distance * wp.sin(azimuth),
                         0.05 * float(ring) - 1.0, float(ring))
