"""What every benchmark script shares: timing (first call, taking turns, back to back), the copy
bandwidth that sets the memory floor, the machine and its other load, the allocator option, and
writing a record. Each script says what it compares; this module only measures."""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import platform
import statistics
import time
from importlib import metadata

import jax
import numpy as np

import spherejax
from spherejax._engine.allocator import keep_freed_memory


# --------------------------------------------------------------------------------------------
# Timing


def time_first_call(fn) -> tuple[float, object]:
    """Seconds for one call including trace and compile, and its (ready) result."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - start, out


def time_interleaved(fns: dict, repeats: int) -> dict:
    """Median and minimum seconds of `repeats` calls of each function in `fns`.

    Each function gets one untimed warm-up call (caches, allocator, and for JAX the compiled
    executable), then the functions take turns, A B A B ..., rather than all A runs and then all
    B runs: on a 2-core machine a transient background load then hits both implementations
    alike instead of skewing the ratio. Every function must return only once its work is done
    (the JAX one wraps its call in block_until_ready). The minimum is the least-disturbed run;
    the median is what a batch job sees.
    """
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return {
        name: {"median_s": statistics.median(t), "min_s": min(t), "all_s": t}
        for name, t in times.items()
    }


def time_back_to_back(fns: dict, repeats: int) -> dict:
    """Median and minimum seconds of `repeats` consecutive calls of each function in turn (one
    untimed call first): what a plain loop over frames sees."""
    out = {}
    for name, fn in fns.items():
        fn()
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        out[name] = {"median_s": statistics.median(times), "min_s": min(times), "all_s": times}
    return out


def copy_bandwidth(nbytes: int, threads: int, runs: int = 5) -> float:
    """Best-of-`runs` copy bandwidth in bytes/s, counting bytes read + bytes written (as STREAM).

    numpy's copy is single-threaded; with threads > 1 the buffer is split into contiguous
    chunks copied concurrently (np.copyto releases the GIL for plain dtypes), which is what a
    multi-threaded XLA kernel can draw on. Read + written is the convention that matches
    BYTES_PER_PIXEL, which also counts both directions.
    """
    src = np.ones(nbytes // 8, dtype=np.float64)  # ones, not empty: touch every page first
    dst = np.zeros_like(src)
    src_chunks = np.array_split(src, threads)
    dst_chunks = np.array_split(dst, threads)
    best = float("inf")
    with concurrent.futures.ThreadPoolExecutor(threads) as pool:
        for _ in range(runs):
            start = time.perf_counter()
            list(pool.map(np.copyto, dst_chunks, src_chunks))
            best = min(best, time.perf_counter() - start)
    return 2 * src.nbytes / best


# --------------------------------------------------------------------------------------------
# The machine


class OtherProcessesLoad:
    """Context manager: the fraction of the machine's CPU time other processes used inside it.

    On a 2-core machine any other busy process (a test run, a build) shows up directly in the
    timings, so every result records whether its run was quiet: all CPUs' busy time from
    /proc/stat minus this process's own CPU time, over wall time x CPUs. None where /proc/stat
    is unavailable.
    """

    fraction: float | None = None

    @staticmethod
    def _machine_busy_s() -> float:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:8]]  # user .. softirq
        idle = fields[3] + fields[4]  # idle + iowait
        return (sum(fields) - idle) / os.sysconf("SC_CLK_TCK")

    @staticmethod
    def _own_s() -> float:
        t = os.times()
        return t.user + t.system

    def __enter__(self):
        try:
            self._start = (self._machine_busy_s(), self._own_s(), time.perf_counter())
        except (OSError, ValueError):
            self._start = None
        return self

    def __exit__(self, *exc):
        if self._start is not None:
            busy_0, own_0, wall_0 = self._start
            busy, own, wall = self._machine_busy_s() - busy_0, self._own_s() - own_0, time.perf_counter() - wall_0
            cpus = len(os.sched_getaffinity(0))
            self.fraction = max(0.0, busy - own) / (wall * cpus)
        return False


def machine_info() -> dict:
    cpu_model = "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu_model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass

    def version(dist):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    return {
        "platform": platform.platform(),
        "cpu_model": cpu_model,
        "nproc": len(os.sched_getaffinity(0)),
        "jax_devices": [str(d) for d in jax.devices()],
        "python": platform.python_version(),
        "numpy": np.__version__,
        "jax": jax.__version__,
        "jaxlib": version("jaxlib"),
        "equinox": version("equinox"),
        "colour-science": version("colour-science"),
        "spherejax": spherejax.__version__,
    }


# --------------------------------------------------------------------------------------------
# Options and records


def add_allocator_argument(parser: argparse.ArgumentParser) -> None:
    """--allocator reuse|default, shared by the benchmarks that time repeated calls."""
    parser.add_argument(
        "--allocator", choices=("reuse", "default"), default="default",
        help="default: glibc as it comes, what a user's script gets (spherejax reuses its own "
             "outputs' memory, spherejax._engine.buffers); reuse: glibc keeps freed blocks "
             "(spherejax._engine.allocator.keep_freed_memory, what the command line does), for both implementations",
    )


def apply_allocator_argument(args: argparse.Namespace) -> str:
    """Apply --allocator; call before any JAX work (glibc threads keep the arenas they have).
    Returns what is in effect, for the record."""
    if args.allocator == "reuse" and keep_freed_memory():
        return "reuse (keep_freed_memory)"
    return "glibc default"


def write_record(path: str, record: dict) -> None:
    """Write a benchmark's record as indented JSON (its folder created if missing)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(record, f, indent=2)
    print(f"\nwrote {path}")
