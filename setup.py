"""The native core: the C extensions through the CPython API (no build dependency beyond a C
compiler and Python's headers; see docs/native.md, which also has the AddressSanitizer build:
setuptools adds the ``CFLAGS`` and ``LDFLAGS`` of the environment to these)."""

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.errors import CCompilerError, CompileError, ExecError, LinkError


class BuildExt(build_ext):
    """build_ext whose failure says what the machine lacks, after the compiler's own output."""

    def run(self) -> None:
        try:
            super().run()
        except (CCompilerError, CompileError, ExecError, LinkError) as exc:
            raise SystemExit(
                "warp-buffer: building its C extensions failed (the output above says why). They "
                "need a C compiler and Python's headers: on Debian or Ubuntu `apt install gcc "
                "python3-dev`, on Fedora `dnf install gcc python3-devel`; or install a prebuilt "
                "wheel (docs/native.md).") from exc

# -Werror=implicit-function-declaration: a CPython function this Python lacks fails the build
# (pip install), not the import (an undefined symbol).
CFLAGS = ["-O2", "-std=gnu11", "-Wall", "-Wextra", "-Wno-unused-parameter",
          "-Wno-missing-field-initializers", "-fvisibility=hidden",
          "-Werror=implicit-function-declaration"]

setup(cmdclass={"build_ext": BuildExt}, ext_modules=[
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
