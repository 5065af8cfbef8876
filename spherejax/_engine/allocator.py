"""Keep freed memory in the process for the next image: glibc malloc settings for batch work.

Why this exists. XLA on CPU takes every buffer (outputs and temporaries) from the C allocator.
In glibc, blocks above 32 MiB come from fresh `mmap`s and are unmapped when freed. A 1-megapixel
correction needs about 200 MB of such blocks (reflectance alone is 124 MB), so each call
page-faults on about 50 000 fresh pages, and the kernel zeroes every one of them. On the 2-core
reference machine that took longer than the correction itself: 93 ms a call, against 38 ms with
the blocks reused (`benchmarks/bench_correct.py --allocator default|reuse`). numpy pays the same
cost for its own temporaries.

`keep_freed_memory()` asks glibc to serve large blocks from its heap, to keep freed memory rather
than returning it to the kernel, and to use one arena. One arena matters because XLA allocates
on its own worker threads, and each thread would otherwise get an arena that does not share
freed blocks with the others. The price: the process keeps its peak heap size until it exits,
which a batch job does not mind. The command line calls this before any JAX work. A library user
who corrects many images in one process can call it too, as early as possible, since glibc's
threads keep the arenas they already have.

No library does this for us. jemalloc or tcmalloc loaded with LD_PRELOAD behave alike, but they
are not pip-installable into a running interpreter. On other C libraries or systems the
function does nothing and returns False.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# mallopt parameter numbers from glibc's <malloc.h>.
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8

#: M_TRIM_THRESHOLD -1: never return the top of the heap to the kernel (mallopt(3)). A finite
#: threshold (1 GiB was tried) still lets a large free, such as numpy's temporaries of a
#: 4-megapixel image, trim the heap, and the next correction faults all of it back in: 127 000
#: faults and +230 ms of kernel time a call at 2048 x 2048, interleaved with the numpy reference.
NEVER_TRIM = -1

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Make glibc malloc keep and reuse freed memory instead of unmapping it (see module doc).

    Idempotent. Returns True if the settings were applied, False where the C library is not
    glibc (macOS, musl, Windows) or refused a setting.
    """
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # only glibc has it  # noqa: B018
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    settings = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, NEVER_TRIM))
    _applied = all(mallopt(param, value) == 1 for param, value in settings)  # mallopt: 1 = ok
    return _applied


__all__ = ["keep_freed_memory"]
