"""The native core: the C extensions through the CPython API (no build dependency beyond a C
compiler and Python's headers; see docs/native.md, which also has the AddressSanitizer build:
setuptools adds the ``CFLAGS`` and ``LDFLAGS`` of the environment to these)."""

from setuptools import Extension, setup

# -Werror=implicit-function-declaration: a CPython function this Python lacks fails the build
# (pip install), not the import (an undefined symbol).
CFLAGS = ["-O2", "-std=gnu11", "-Wall", "-Wextra", "-Wno-unused-parameter",
          "-Wno-missing-field-initializers", "-fvisibility=hidden",
          "-Werror=implicit-function-declaration"]

setup(ext_modules=[
    Extension("warp_buffer._core", sources=["warp_buffer/_core.c", "warp_buffer/_core_import.c",
                                            "warp_buffer/_core_lease.c"],
              depends=["warp_buffer/_core.h"], extra_compile_args=CFLAGS),
    Extension("buffer_pubsub._ring", sources=["buffer_pubsub/_ring.c"],
              depends=["buffer_pubsub/_ring.h"], extra_compile_args=CFLAGS),
    Extension("buffer_pubsub._streams", sources=["buffer_pubsub/_streams.c"],
              extra_compile_args=CFLAGS),
    Extension("buffer_pubsub._loans", sources=["buffer_pubsub/_loans.c"],
              extra_compile_args=CFLAGS),
    Extension("rosidl_buffer._cdr_native", sources=["rosidl_buffer/_cdr_native.c"],
              extra_compile_args=CFLAGS),
])
