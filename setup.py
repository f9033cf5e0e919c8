"""The native core: two C extensions through the CPython API (no build dependency beyond a C
compiler and Python's headers; see docs/native.md). ``WARP_BUFFER_ASAN=1`` builds them with
AddressSanitizer (docs/native.md has the command that runs the native tests under it)."""

import os

from setuptools import Extension, setup

CFLAGS = ["-O2", "-std=gnu11", "-Wall", "-Wextra", "-Wno-unused-parameter",
          "-Wno-missing-field-initializers", "-fvisibility=hidden"]
LDFLAGS: list[str] = []
if os.environ.get("WARP_BUFFER_ASAN") == "1":
    CFLAGS += ["-fsanitize=address", "-fno-omit-frame-pointer", "-O1", "-g"]
    LDFLAGS += ["-fsanitize=address"]

setup(ext_modules=[
    Extension("warp_buffer._core", sources=["warp_buffer/_core.c", "warp_buffer/_core_import.c",
                       "warp_buffer/_core_lease.c"],
              depends=["warp_buffer/_core.h"], extra_compile_args=CFLAGS,
              extra_link_args=LDFLAGS),
    Extension("buffer_pubsub._ring", sources=["buffer_pubsub/_ring.c"],
              depends=["buffer_pubsub/_ring.h"], extra_compile_args=CFLAGS,
              extra_link_args=LDFLAGS),
])
