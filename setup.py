"""Builds the CPU rasterizer's kernels (paradrive/kernels/_composite.cpp) at install, once per
instruction set: ``_kernels_base`` (the platform's baseline: SSE2 on x86-64, NEON on arm64),
and on x86-64 ``_kernels_avx2`` (AVX2 + FMA) and ``_kernels_avx512``. ``paradrive.kernels``
imports the widest one the CPU runs. Each is optional: where no C++ compiler builds them the
package still installs, and the torch-op rasterizer runs instead (with a warning naming the fix).
Everything else about the package is in pyproject.toml.
"""

import os
import platform

from setuptools import setup

try:
    from pybind11.setup_helpers import Pybind11Extension
except ImportError:  # a build without its requirements (--no-build-isolation, no pybind11)
    Pybind11Extension = None

# -ffp-contract=off: no fused multiply-adds the source does not write, so the arithmetic is the
# source's at any optimisation level; -std=c++17 is an ISO mode, which also implies it.
FLAGS = ["-O3", "-fno-math-errno", "-ffp-contract=off", "-pthread"]
X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")
VARIANTS = {"base": []}
if X86:
    VARIANTS["avx2"] = ["-mavx2", "-mfma"]
    VARIANTS["avx512"] = ["-mavx512f", "-mavx512bw", "-mavx512dq", "-mavx512vl", "-mavx2", "-mfma",
                          "-Wno-psabi"]


def extensions() -> list:
    if Pybind11Extension is None:
        print("paradrive: pybind11 is not installed; the CPU kernels are not built")
        return []
    # a source file of its own per variant (each includes _bindings.cpp, which includes
    # _composite.cpp): setuptools names an object file after its source, and the variants
    # compile side by side, so one shared source let a variant link another's object
    return [Pybind11Extension(f"paradrive.kernels._kernels_{name}",
                              [f"paradrive/kernels/_kernels_{name}.cpp"], cxx_std=17,
                              define_macros=[("PD_MODULE", f"_kernels_{name}")],
                              depends=["paradrive/kernels/_bindings.cpp", "paradrive/kernels/_composite.cpp"],
                              extra_compile_args=FLAGS + flags, extra_link_args=["-pthread"],
                              optional=True)
            for name, flags in VARIANTS.items()]


# the variants compile side by side
setup(ext_modules=extensions(), options={"build_ext": {"parallel": max(1, min(3, os.cpu_count() or 1))}})
