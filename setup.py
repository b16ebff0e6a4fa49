"""The package's one compiled part: the native kernels (``tactile/native``), an optional shared
library loaded through ctypes and, as a custom-op library, by onnxruntime. Everything
else is declared in ``pyproject.toml``.

``optional=True``: where no C compiler works, the build warns (pip shows it with ``-v``) and the
package installs without the library (``tactile.native.available()`` is then False).
"""

import sys

from setuptools import Extension, setup

UNIX = sys.platform != "win32"

setup(
    ext_modules=[
        Extension(
            "tactile.native._kernels",
            sources=["tactile/native/emd.c", "tactile/native/omp.c", "tactile/native/ort_ops.c"],
            depends=["tactile/native/tactile_native.h", "tactile/native/ort_api.h",
                     "tactile/native/omp_core.h"],
            libraries=["m"] if UNIX else [],
            # no fused multiply-add contraction: the same bits on x86 and ARM boards; -O3
            # vectorises the independent loops (no reassociation without -ffast-math: the same
            # bits as -O2; OMP of 46 rows 1.6 -> 1.2 ms)
            extra_compile_args=["-std=c99", "-O3", "-ffp-contract=off"] if UNIX else [],
            optional=True,
        )
    ]
)
