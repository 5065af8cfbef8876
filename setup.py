"""Build of spherejax's one compiled part: the fused CPU kernel of `correct` (spherejax/_engine/fused.py).

Everything else is in pyproject.toml. The kernel is an XLA FFI handler, compiled against the XLA
FFI headers that jaxlib ships (jaxlib/include, header-only). The extension is optional: where no
C++17 compiler is found the install still succeeds and `correct` runs its jax.numpy path (slower,
the same numbers).

Which jaxlib's headers, and why any jaxlib from spherejax's lower bound on is sound:

- XLA's FFI has a stable binary interface with a version (XLA_FFI_API_MAJOR.MINOR in
  xla/ffi/api/c_api.h; 0.3 in jaxlib 0.9.2 to 0.11.1, 0.4 in 0.11.2, 0.5 in 0.12.0). A handler
  records the version of the headers it was compiled against, and XLA registers a handler whose
  version lies between its own minimum (0.1 today; XLA keeps an old version working for at least
  12 months) and its own version. So a kernel compiled against jaxlib N's headers runs under jaxlib
  N and every later one in that window, and is refused by an earlier jaxlib whose FFI is older.
- Hence the headers are taken from the jaxlib of the environment spherejax is being installed into
  when it already has one (the jaxlib the kernel will run with; under pip's build isolation this
  is found through the interpreter's own site-packages, which the isolated build can still name),
  and otherwise from the build requirement's jaxlib (pyproject.toml: `jaxlib>=0.10.2`, which the
  resolver takes as the newest, the one it then installs beside jax).
- If a kernel still meets an older jaxlib (a jax downgraded after the install, a wheel built
  elsewhere), XLA refuses it at registration and spherejax runs the jax.numpy path, saying why
  once (spherejax._engine.fused.unavailable_reason). `pip install --no-build-isolation --force-reinstall
  --no-deps .` rebuilds it against the jaxlib in place.
"""

import os
import sys
import sysconfig

from setuptools import Extension, setup

FFI_HEADER = os.path.join("xla", "ffi", "api", "c_api.h")


def _jaxlib_include_dirs() -> list[str]:
    """Candidate jaxlib/include folders, the preferred first (see the module docstring)."""
    candidates = []
    # The environment being installed into. Under pip's build isolation the interpreter is that
    # environment's, and sysconfig still names its site-packages, though they are off sys.path.
    for key in ("platlib", "purelib"):
        candidates.append(os.path.join(sysconfig.get_paths()[key], "jaxlib", "include"))
    try:
        import jaxlib  # the build requirement (pyproject.toml [build-system])

        candidates.append(os.path.join(os.path.dirname(jaxlib.__file__), "include"))
    except ImportError:  # a build without isolation in an environment without jaxlib
        pass
    return candidates


def jaxlib_include_dir() -> str:
    for folder in _jaxlib_include_dirs():
        if os.path.isfile(os.path.join(folder, FFI_HEADER)):
            print(f"spherejax: compiling the fused kernel against the XLA FFI headers in {folder}", file=sys.stderr)
            return folder
    # No headers: the optional build fails and the install goes on without the kernel.
    print("spherejax: no jaxlib with XLA FFI headers found; the fused kernel is not built", file=sys.stderr)
    return ""


#: The kernel's sources, split by job (spherejax/_engine/kernel/fused_correct.h says which is which).
KERNEL = "spherejax/_engine/kernel"
KERNEL_SOURCES = [f"{KERNEL}/{name}" for name in
                  ("generic.cc", "avx512.cc", "avx2.cc", "call.cc", "ffi_handler.cc", "register_bands.cc", "registered_rows.cc",
                   "module.cc")]
#: Headers: a change rebuilds the extension, and they go into the sdist with the sources.
KERNEL_HEADERS = [f"{KERNEL}/fused_correct.h", f"{KERNEL}/call.h", f"{KERNEL}/band_taps.h"]

setup(
    ext_modules=[
        Extension(
            "spherejax._engine._fused_correct",
            sources=KERNEL_SOURCES,
            depends=KERNEL_HEADERS,
            include_dirs=[jaxlib_include_dir()],
            language="c++",
            # The same flags for every source, and no -march: each instruction-set variant carries
            # its instructions as function attributes (avx512.cc, avx2.cc, target_clones in
            # generic.cc) and the variant is chosen at run time (call.cc, spherejax._engine.fused),
            # so a wheel built here runs on any x86-64; a per-file -march would also let the
            # compiler put those instructions into the shared code that every CPU runs.
            # -fno-math-errno lets sqrt/div vectorise; no -ffast-math, which would drop the NaN
            # and infinity checks the quality mask needs.
            extra_compile_args=["-std=c++17", "-O3", "-fno-math-errno", "-Wno-attributes", "-Wno-return-type", "-Wno-psabi"],
            optional=True,
        )
    ],
)
