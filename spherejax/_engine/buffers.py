"""Reuse of `correct`'s output memory from one call to the next, owned by spherejax.

Why. A 1-megapixel `correct` writes 136 MB of outputs (reflectance, Lab, quality). XLA allocates
them with malloc, and glibc serves blocks that large with fresh mmap()s and returns them to the
kernel with munmap() when they are freed: every call then page-faults 33,000 new, zeroed pages,
which took longer than the correction itself (benchmarks/README.md: 200 ms against 38 ms a
megapixel on the 2-core reference machine). `allocator.keep_freed_memory()` fixes that by
changing glibc's settings for the whole process, which spherejax must not do behind a user's back.

What instead. `correct` keeps, for each output shape, the output arrays of its last two calls
(`RECENT`). When a new call finds among them a set that nobody but this pool refers to any more
(the user dropped that result: its arrays' reference counts are the pool's alone), it donates
that memory to the kernel, which writes the new outputs into it (`fused.correct_pixels(out=)`,
XLA's input-output aliasing). A plain loop,

    for raw in frames:
        result = sj.correct(raw, calibration)

then faults its output pages in the first two calls only. An output the user still holds, or
any view of it (`numpy.asarray(result.lab)` refers to the array too), is never touched.

NumPy frames whose outputs the kernel writes directly (`plan.Plan._correct_directly`) get their
output memory here too, as NumPy blocks handed to XLA without a copy (`take_host`): the same
reuse rule, keyed ("host", shape).

Confined: only large outputs (at least `MIN_BYTES`) of whole frames given to `correct` as
concrete arrays on the CPU; nothing process-wide changes. The cost: up to two unreferenced sets
of outputs of each of the last `SHAPES` shapes, at most `MAX_BYTES` in all, stay allocated until
reused or `release()`d (272 MB for 1-megapixel images).
"""

from __future__ import annotations

import collections
import concurrent.futures
import os
import sys
import threading

import jax
import numpy as np

#: Output sets kept per shape: a loop's previous result is still bound to its variable while the
#: next call runs, so the one before it is the one that is free.
RECENT = 2

#: Output shapes kept (the most recently used), of each kind (`_keep`).
SHAPES = 2

#: Smaller outputs are not kept: glibc reuses their memory without faults anyway (below its
#: mmap threshold), and keeping them would only hold memory.
MIN_BYTES = 8 << 20

#: At most this much output memory is kept (the oldest sets go first): a loop over 16-megapixel
#: images (2.3 GB of outputs each) is not made to hold two more sets than it asked for.
MAX_BYTES = 2 << 30

_lock = threading.Lock()
_pool: collections.OrderedDict = collections.OrderedDict()  # key -> deque of output tuples


def _unreferenced(arrays: tuple) -> bool:
    """True when only the pool's tuple refers to each array (and none was deleted, e.g. donated
    elsewhere). sys.getrefcount counts the tuple's reference and its own argument: 2."""
    return all(sys.getrefcount(arrays[k]) == 2 and not arrays[k].is_deleted() for k in range(len(arrays)))


def _take_free(pool: collections.OrderedDict, key, is_free) -> tuple | None:
    """Remove and return the first entry of pool[key] that `is_free` accepts, or None. Call with
    `_lock` held. `is_free` gets the entry straight from the deque, so that the reference counts
    it reads are the deque's and its argument's only."""
    kept = pool.get(key)
    for index in range(len(kept) if kept else 0):
        if is_free(kept[index]):
            entry = kept[index]
            del kept[index]
            return entry
    return None


def _is_host(key) -> bool:
    """True for the keys of NumPy output memory (`take_host`): ("host", shape)."""
    return isinstance(key, tuple) and len(key) == 2 and key[0] == "host"


def _keep(pool: collections.OrderedDict, key, entry: tuple) -> None:
    """Put `entry` first in pool[key] (at most `RECENT`), pool's most recent shape, and drop the
    least recent shapes of key's kind beyond `SHAPES`. Call with `_lock` held.

    Kinds: XLA's outputs and NumPy output memory (`_is_host`) count their shapes apart, so that
    a program alternating between NumPy frames and jax.Arrays (or `vmap`) of two shapes keeps
    both kinds of both (bench_batch.py: they evicted one another, and every call faulted)."""
    kept = pool.setdefault(key, collections.deque(maxlen=RECENT))
    kept.appendleft(entry)
    pool.move_to_end(key)
    same_kind = [k for k in pool if _is_host(k) == _is_host(key)]
    for oldest in same_kind[:max(0, len(same_kind) - SHAPES)]:
        del pool[oldest]


def take(key) -> tuple | None:
    """A set of outputs of shape `key` that nobody refers to any more, removed from the pool, or
    None."""
    with _lock:
        return _take_free(_pool, key, _unreferenced)


def _nbytes(entry: tuple) -> int:
    """Bytes of an output set: jax.Arrays, or (view, block) pairs of NumPy memory."""
    return sum(int(x[0].nbytes) if isinstance(x, tuple) else int(x.size) * x.dtype.itemsize for x in entry)


def give(key, arrays: tuple) -> None:
    """Keep `arrays` (the outputs just returned to the caller) for reuse once they are dropped,
    within `RECENT` per shape, `SHAPES` shapes and `MAX_BYTES` in all (the oldest go first)."""
    if _nbytes(arrays) > MAX_BYTES:
        return
    with _lock:
        _keep(_pool, key, arrays)
        while sum(_nbytes(entry) for entries in _pool.values() for entry in entries) > MAX_BYTES:
            oldest_key = next(iter(_pool))
            _pool[oldest_key].pop()  # the oldest set of the least recently used shape
            if not _pool[oldest_key]:
                del _pool[oldest_key]


def take_host(key, shapes: tuple) -> tuple:
    """NumPy output memory for `correct`'s direct path (`fused.correct_arrays`): one (view, block)
    pair per (shape, dtype) of `shapes`, each view C-contiguous on an `ALIGNMENT`-byte boundary,
    so that `jax.device_put(view, may_alias=True)` hands it to XLA without a copy. A set of
    `key` whose views nobody uses any more (the jax.Arrays made of them were dropped: XLA holds a
    reference to the block while one lives) is reused, else new memory is allocated. Give the
    set back with `give(("host", key), pairs)` once its views are wrapped."""
    with _lock:
        entry = _take_free(_pool, ("host", key), lambda pairs: all(_staging_free(pair) for pair in pairs))
    if entry is None:
        entry = tuple((view, view.base) for view in (_aligned_empty(shape, dtype) for shape, dtype in shapes))
    return entry


def release() -> None:
    """Drop every kept output set and staging buffer (their memory goes back to the allocator)."""
    with _lock:
        _pool.clear()
        _staging.clear()


# ------------------------------------------------------------------------------ the raw frames

#: Staging buffers for raw frames given as NumPy arrays, per (shape, dtype): the most recent
#: `RECENT` of each of the last `SHAPES` kinds.
_staging: collections.OrderedDict = collections.OrderedDict()

#: XLA's CPU buffers must start on this boundary to be used in place (jax.device_put(may_alias=)).
ALIGNMENT = 64


def _aligned_empty(shape, dtype) -> np.ndarray:
    """An uninitialised C-contiguous array whose data start on an `ALIGNMENT`-byte boundary
    (NumPy aligns to 16 only)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    block = np.empty(nbytes + ALIGNMENT, np.uint8)
    start = (-block.ctypes.data) % ALIGNMENT
    return block[start:start + nbytes].view(dtype).reshape(shape)


#: Threads that help copy frames into staging buffers (`_copy_in_parts`), made on first use.
_copiers: concurrent.futures.ThreadPoolExecutor | None = None
_copiers_lock = threading.Lock()

#: Each part of a staging copy is at least this large: smaller copies are not worth a thread.
COPY_PART_BYTES = 4 << 20


def _forget_copiers_after_fork() -> None:
    """A forked child has none of its parent's threads: a copy handed to the parent's executor
    would wait forever, so the child makes its own on first use."""
    global _copiers
    _copiers = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_copiers_after_fork)


def cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _copy_in_parts(destination: np.ndarray, source: np.ndarray) -> None:
    """np.copyto(destination, source) split over the first axis among up to 4 CPUs.

    Why: one thread's copy reaches part of the memory bandwidth only (NumPy's copyto releases
    the GIL, so the parts run at once): a 1-megapixel uint16 cube, 32 MB, took 6.2 ms on one
    thread and 4.8 on two on a 2-core EPYC, a tenth of what `correct` then costs.
    """
    parts = min(cpus(), 4, source.nbytes // COPY_PART_BYTES, source.shape[0] if source.ndim else 1)
    if parts < 2:
        np.copyto(destination, source, casting="no")
        return
    global _copiers
    with _copiers_lock:
        if _copiers is None:
            _copiers = concurrent.futures.ThreadPoolExecutor(max_workers=3, thread_name_prefix="spherejax-staging")
    bounds = np.linspace(0, source.shape[0], parts + 1).astype(np.int64)
    helpers = [
        _copiers.submit(np.copyto, destination[start:stop], source[start:stop], casting="no")
        for start, stop in zip(bounds[1:-1], bounds[2:])
    ]
    try:
        np.copyto(destination[:bounds[1]], source[:bounds[1]], casting="no")
    finally:
        for helper in helpers:  # never leave a copy running into a buffer handed on
            helper.result()


def stage(raw: np.ndarray):
    """`raw` as a jax.Array on the CPU, through a staging buffer that spherejax reuses.

    jnp.asarray copies a NumPy array into new XLA memory on every call (NumPy aligns its data to
    16 bytes; XLA uses memory in place only on a 64-byte boundary), and those fresh pages fault:
    32 MB a megapixel of uint16 frames. Here the frames are copied into an aligned buffer kept
    from an earlier call, whose last user (a computation of that call) is done, and handed to
    XLA in place. The caller's array is never touched.
    """
    key = (tuple(raw.shape), raw.dtype.str)
    with _lock:
        entry = _take_free(_staging, key, _staging_free)
    if entry is None:
        view = _aligned_empty(raw.shape, raw.dtype)
        entry = (view, view.base)
    _copy_in_parts(entry[0], raw)
    staged = jax.device_put(entry[0], jax.devices("cpu")[0], may_alias=True)
    with _lock:
        _keep(_staging, key, entry)
    return staged


def _staging_free(entry: tuple) -> bool:
    """True when nothing but the pool refers to a staging buffer (view, the block it views).

    XLA, while a jax.Array or a computation uses the memory in place, holds a reference to the
    block that owns it (measured; not to the view): free means the block's references are the
    view's base, the entry's and getrefcount's argument (3), and the view's the entry's and the
    argument (2)."""
    return sys.getrefcount(entry[0]) == 2 and sys.getrefcount(entry[1]) == 3


def stageable(raw) -> bool:
    """True for a NumPy array large enough to be worth staging (`stage`), when JAX's default
    backend is the CPU."""
    return (
        isinstance(raw, np.ndarray) and raw.dtype.kind in "uif" and raw.nbytes >= MIN_BYTES // 4
        and jax.default_backend() == "cpu"
    )


def kept() -> int:
    """The number of output sets kept now (for tests and diagnostics)."""
    with _lock:
        return sum(len(v) for v in _pool.values())


__all__ = [
    "RECENT", "SHAPES", "MIN_BYTES", "MAX_BYTES", "ALIGNMENT", "take", "take_host", "give", "release", "kept", "stage",
    "stageable",
]
