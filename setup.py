"""Build of spherejax's one compiled part: the fused CPU kernel of `correct` (spherejax/fused.py).

Everything else is in pyproject.toml. The kernel is an XLA FFI handler, compiled against the XLA
FFI headers that jaxlib ships (jaxlib/include, header-only), so jaxlib is a build requirement at
the same pinned version as at run time. The extension is optional: where no C++17 compiler is
found the install still succeeds and `correct` runs its jax.numpy path (slower, same numbers).
"""

import os

from setuptools import Extension, setup


def jaxlib_include_dir() -> str:
    import jaxlib  # a build requirement (pyproject.toml [build-system])

    return os.path.join(os.path.dirname(jaxlib.__file__), "include")


setup(
    ext_modules=[
        Extension(
            "spherejax._fused_correct",
            sources=["spherejax/_fused_correct.cc"],
            include_dirs=[jaxlib_include_dir()],
            language="c++",
            # No -march: the kernel picks its instruction set at run time (target attributes),
            # so a wheel built here runs on any x86-64. -fno-math-errno lets sqrt/div vectorise;
            # no -ffast-math, which would drop the NaN and infinity checks the quality mask needs.
            extra_compile_args=["-std=c++17", "-O3", "-fno-math-errno", "-Wno-attributes", "-Wno-return-type", "-Wno-psabi"],
            optional=True,
        )
    ],
)
