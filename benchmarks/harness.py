"""What every benchmark script shares: timing (first call, taking turns, back to back), the copy
bandwidth that sets the memory floor (a median with its spread), the machine (its CPU by model
name, family and model numbers, AVX-512 and AVX2, and the fused kernel's variant) and its other
load, the allocator option, and writing a record. Each script says what it compares; this module
only measures."""

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


#: Every copy-floor measurement of this process (`copy_bandwidth_stats`), in order: `write_record`
#: adds them to the record it writes, so that a floor's spread is kept beside the median the
#: script reports, whichever script measured it.
copy_measurements: list[dict] = []


def copy_bandwidth_stats(nbytes: int, threads: int, repeats: int = 7) -> dict:
    """Copy bandwidth in bytes/s, counting bytes read + bytes written (as STREAM), over `repeats`
    timed copies of `nbytes`: the median (what the floor is taken from) and its spread.

    Returns a dict: median_bytes_per_s, min_bytes_per_s and max_bytes_per_s (the slowest and the
    fastest copy), q1_bytes_per_s and q3_bytes_per_s (the quartiles: their gap, the IQR, is the
    spread to compare runs by), all_bytes_per_s (every copy, in order), and buffer_bytes, threads,
    repeats (buffer_bytes: the size of the buffer copied, half the bytes counted).

    Why a median of 7 and not the best of 5: the best copy of a few is the one no other
    process disturbed, and on a shared 2-core machine whether one such copy happens varies from
    run to run, so the floor (and every "% of the floor" figure) moved with it; the median of 7
    moves less, and the quartiles say how much it can. One untimed copy first: np.zeros_like
    maps its pages lazily, so the first copy into `dst` also page-faults it in.

    numpy's copy is single-threaded; with threads > 1 the buffer is split into contiguous chunks
    copied concurrently (np.copyto releases the GIL for plain dtypes), which is what a
    multi-threaded XLA kernel can draw on. Read + written is the convention that matches
    BYTES_PER_PIXEL, which also counts both directions.
    """
    src = np.ones(nbytes // 8, dtype=np.float64)  # ones, not empty: touch every page first
    dst = np.zeros_like(src)
    src_chunks = np.array_split(src, threads)
    dst_chunks = np.array_split(dst, threads)
    seconds = []
    with concurrent.futures.ThreadPoolExecutor(threads) as pool:
        list(pool.map(np.copyto, dst_chunks, src_chunks))  # untimed: dst's page faults
        for _ in range(repeats):
            start = time.perf_counter()
            list(pool.map(np.copyto, dst_chunks, src_chunks))
            seconds.append(time.perf_counter() - start)
    rates = [2 * src.nbytes / t for t in seconds]
    q1, _, q3 = statistics.quantiles(rates, n=4, method="inclusive") if len(rates) > 1 else (rates[0],) * 3
    stats = {
        "median_bytes_per_s": statistics.median(rates), "min_bytes_per_s": min(rates),
        "max_bytes_per_s": max(rates), "q1_bytes_per_s": q1, "q3_bytes_per_s": q3, "all_bytes_per_s": rates,
        "buffer_bytes": src.nbytes, "threads": threads, "repeats": repeats,
    }
    copy_measurements.append(stats)
    return stats


def copy_bandwidth(nbytes: int, threads: int, repeats: int = 7) -> float:
    """The median of `copy_bandwidth_stats` in bytes/s: the number a floor is computed from. Its
    spread goes into the record all the same (`copy_measurements`, `write_record`)."""
    return copy_bandwidth_stats(nbytes, threads, repeats)["median_bytes_per_s"]


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


def cpu_info() -> dict:
    """The CPU of this machine from /proc/cpuinfo (its first processor): model name, family and
    model numbers, and whether it has AVX-512 (avx512f) and AVX2, which decide the fused kernel's
    variants. The model name alone does not tell CPUs apart in a VM ("AMD EPYC" for Zen 1 to 5);
    the family and model numbers do (Zen 4: family 25, model 17; Zen 5: family 26). None for
    what the file does not say (or where there is no /proc/cpuinfo)."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break  # the end of the first processor's block
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    flags = set(fields.get("flags", "").split())

    def number(key):
        value = fields.get(key)
        return int(value) if value is not None and value.isdigit() else None

    return {
        "model_name": fields.get("model name", "unknown"),
        "family": number("cpu family"),
        "model": number("model"),
        "avx512f": "avx512f" in flags if flags else None,
        "avx2": "avx2" in flags if flags else None,
    }


def fused_variant_info() -> dict | None:
    """Which variant of the fused kernel `correct` runs for 16 bands in this process, and the
    times it was chosen by (spherejax._engine.fused.variant: measured once per process, so
    calling this before the timed runs also keeps that measurement out of a first-call time).
    None where the kernel is not used; {"refused": message} for a SPHEREJAX_FUSED it refuses."""
    from spherejax._engine import fused

    try:
        chosen = fused.variant()
    except ValueError as error:
        return {"refused": str(error)}
    if chosen is None:
        return None
    measured = chosen.measurement
    return {
        "name": chosen.name, "setting": chosen.setting, "auto": measured.auto, "portable": measured.portable,
        "times_s": dict(measured.times_s), "pixels": measured.pixels, "repeats": measured.repeats,
    }


def machine_info() -> dict:
    cpu = cpu_info()

    def version(dist):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    return {
        "platform": platform.platform(),
        "cpu_model": cpu["model_name"],  # the key the scripts print
        "cpu": cpu,
        "nproc": len(os.sched_getaffinity(0)),
        "jax_devices": [str(d) for d in jax.devices()],
        "python": platform.python_version(),
        "numpy": np.__version__,
        "jax": jax.__version__,
        "jaxlib": version("jaxlib"),
        "equinox": version("equinox"),
        "colour-science": version("colour-science"),
        "spherejax": spherejax.__version__,
        "fused_kernel_variant": fused_variant_info(),
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
    """Write a benchmark's record as indented JSON (its folder created if missing), with the copy
    floors this process measured and their spread (`copy_measurements`) where there were any."""
    if copy_measurements and "copy_bandwidth_measurements" not in record:
        record = {**record, "copy_bandwidth_measurements": copy_measurements}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(record, f, indent=2)
    print(f"\nwrote {path}")
