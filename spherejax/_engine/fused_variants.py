"""Which instruction-set variant of the fused CPU kernel a process runs, and the switch that
controls it (SPHEREJAX_FUSED).

Instruction-set variants. For 16 bands (the instrument's) the kernel has code of its own per
instruction set (`VARIANTS`, widest first): "avx512" (AVX-512 intrinsics), "avx2" (AVX2 + FMA
intrinsics, in another order of summation: its last bits may differ) and "generic" (the
compiler-vectorised code, built for three x86-64 levels with target_clones), which every other
band count runs under every variant. Which one a process runs is chosen once, at its first use
(`mode`), by timing every variant the CPU runs (`supported_variants`) on a small synthetic
problem (`measure_variants`: 32k pixels of 16 bands a call, one thread, best of 5, with inputs
and outputs in memory the cache has dropped, as a frame's are; about 45 ms of CPU time on a
2-core Zen 4 and, for that moment, one and a half times the last-level cache in memory) and
taking the widest unless a narrower one is faster by more than `MARGIN` (10 %, `choose_variant`),
so that noise between near-equal variants cannot flip the choice from one run to the next.

Why measured, not looked up in a table of CPU models: the widest instruction set is not always the
fastest (on a 2-core Intel Xeon with AVX-512, family 6 model 167, the AVX-512 code was no faster
than the AVX2 code; on AMD Zen 5 it is clearly faster; on Zen 4, which runs AVX-512 as two 256-bit
halves, it is faster from memory and slower in the cache), and a measurement covers the CPUs
nobody has tabled, virtual machines that hide or throttle features, and the kernel's own future
changes, where a table would go stale. `variant` reports the choice and the times; they are
logged at DEBUG on this module's logger. The timings are measured once per machine and kept in
spherejax's cache folder (`variant_cache`), because the variants round differently: measured in
every process, a loaded machine picked another variant in about one run in eight, and an
archive's outputs differed in their last bits between runs, resumes and dask workers. `mode`
returns the variant itself, so the XLA route and the direct NumPy route (`correct_arrays`) run
the same code and give the same bits.

SPHEREJAX_FUSED takes "auto" (the default, as when unset) or "1": the kernel, its variant
measured as above; "portable": the same measurement without the AVX-512 intrinsics code, so that
the code CPUs without AVX-512 run can be tested and timed on a machine that has it (the generic
code's target_clones still take the CPU's widest level); "avx512", "avx2" or
"generic": that variant, without measuring (refused with a ValueError where the CPU does not run
it, rather than run something else under its name); "0": the jax.numpy path. Any other value is
refused (`switch`), so that a typo such as "off" cannot leave the kernel on.
"""

from __future__ import annotations

import functools
import logging
import glob
import math
import os
import threading
import time
import types
from collections.abc import Iterable, Mapping
from typing import NamedTuple

import numpy as np

from . import variant_cache
from .fused_constants import residual_constants
from .fused_extension import _fused_correct, built, register, registration_refusal, supported_variants

#: The kernel keeps one pixel's bands in a fixed-size buffer.
MAX_BANDS = 64

#: Raw dtypes the kernel reads directly; others take the jax.numpy path.
RAW_DTYPES = (np.dtype(np.uint16), np.dtype(np.float32))

#: Environment variable: "0" turns the kernel off (read when a plan is made).
SWITCH = "SPHEREJAX_FUSED"

_log = logging.getLogger("spherejax._engine.fused")


#: The kernel's instruction-set variants, widest first (kernel/fused_correct.h): 16 bands with
#: AVX-512 intrinsics, with AVX2 + FMA intrinsics, and the generic code (target_clones), which
#: other band counts run under every variant. The values `mode` returns for the kernel.
VARIANTS = AVX512, AVX2, GENERIC = ("avx512", "avx2", "generic")

#: The band count that has code of its own per variant.
VARIANT_BANDS = 16

#: Settings of SWITCH that choose a variant by measurement: all the CPU runs, or all but AVX-512.
#: `correct_arrays` and `correct_pixels` take them as `kernel_mode` too (the measured variant).
AUTO, PORTABLE = "auto", "portable"

#: The values SWITCH may take; unset means AUTO.
SWITCH_VALUES = (AUTO, "1", PORTABLE, *VARIANTS, "0")

#: A narrower variant is chosen over a wider one only when it is faster by more than this
#: fraction (`choose_variant`): well above the noise of the measurement (the ratio of two variants'
#: times stayed within +-4 % over 12 measurements on a 2-core machine under a load of 4), so that
#: near-equal variants keep the wider one, run after run.
MARGIN = 0.10

#: The measured problem (`measure_variants`): slices of this many pixels, 16 bands of uint16, one
#: call a slice on one thread, the best of this many calls of each variant. 32k pixels take about
#: 1 ms a call; each call reads and writes 9.7 MB (297 bytes a pixel, as a frame does).
PROBE_PIXELS = 32 * 1024
PROBE_REPEATS = 5

#: What one pixel of the kernel reads and writes, in bytes: raw 16 x 2, dark and white 16 x 4
#: each, reflectance 31 x 4, Lab 3 x 4, quality 1.
_BYTES_PER_PIXEL = 32 + 64 + 64 + 124 + 12 + 1

#: The last-level cache assumed where /sys does not say (a common per-CCD L3), and the most memory
#: the measurement's slices may take together.
_DEFAULT_CACHE_BYTES = 32 << 20
_MAX_PROBE_BYTES = 256 << 20


def switch() -> str:
    """The value of SPHEREJAX_FUSED ("auto" if unset).

    Raises:
      ValueError: any value but those of SWITCH_VALUES, naming the variable; or a variant this CPU
        does not run (where the kernel was built), naming the ones it does.
    """
    value = os.environ.get(SWITCH, AUTO)
    if value not in SWITCH_VALUES:
        raise ValueError(
            f"{SWITCH}: expected one of {', '.join(repr(v) for v in SWITCH_VALUES)} or unset, got {value!r}"
        )
    if value in VARIANTS and built() and value not in supported_variants():
        raise ValueError(
            f"{SWITCH}={value!r}: this CPU does not run the fused kernel's {value} code; it runs "
            f"{', '.join(repr(v) for v in supported_variants())} ({AUTO!r} takes the fastest of them)"
        )
    return value


def choose_variant(times_s: Mapping[str, float], margin: float = MARGIN) -> str:
    """The variant to run, from the seconds each took on the same problem (`measure_variants`).

    The widest of `times_s` (in the order of VARIANTS) unless a narrower one is faster by more
    than `margin`: from the widest down, a narrower variant replaces the choice so far only when
    its time x (1 + margin) is below the choice's. A pure function of the times, so that a tie or
    a near-tie keeps the wider variant whatever the noise, and only a clear gain moves the choice.

    Raises:
      ValueError: no times, or a name that is no variant.
    """
    unknown = set(times_s) - set(VARIANTS)
    if not times_s or unknown:
        raise ValueError(f"times_s: expected seconds for some of {VARIANTS}, got {dict(times_s)!r}")
    ordered = [name for name in VARIANTS if name in times_s]
    choice = ordered[0]
    for narrower in ordered[1:]:
        if times_s[narrower] * (1.0 + margin) < times_s[choice]:
            choice = narrower
    return choice


def _last_level_cache_bytes() -> int:
    """The size of CPU 0's last-level cache in bytes (Linux /sys), or _DEFAULT_CACHE_BYTES."""
    best_level, size = 0, _DEFAULT_CACHE_BYTES
    for folder in glob.glob("/sys/devices/system/cpu/cpu0/cache/index*"):
        try:
            with open(os.path.join(folder, "level")) as f:
                level = int(f.read())
            with open(os.path.join(folder, "size")) as f:
                text = f.read().strip()  # "32768K"
        except (OSError, ValueError):
            continue
        scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1:], 1)
        digits = text.rstrip("KMG")
        if level > best_level and digits.isdigit():
            best_level, size = level, int(digits) * scale
    return size


def _probe_slices(pixels: int) -> int:
    """How many slices of `pixels` pixels the measurement goes round: enough that a slice has left
    the last-level cache before its next turn (the slices between take one and a half times the
    cache), so that every timed call reads its inputs from memory and writes its outputs there,
    as a call on a frame does; at least 3, and no more than _MAX_PROBE_BYTES in all."""
    per_slice = pixels * _BYTES_PER_PIXEL
    wanted = math.ceil(1.5 * _last_level_cache_bytes() / per_slice) + 1
    return max(3, min(wanted, _MAX_PROBE_BYTES // per_slice))


def _probe_problems(pixels: int, slices: int) -> list[tuple[tuple, tuple]]:
    """(arguments, outputs) of `_fused_correct.correct_arrays` for each of `slices` problems of one
    image of `pixels` pixels of 16 bands, in memory of their own, the variant and the thread count
    left out. Counts of a flat field between 1 % and 100 % of white, no bad pixels (the path every
    good pixel takes), no saturation check. The values repeat every 4096 pixels (np.tile: the
    setup costs little more than writing the memory once)."""
    rng = np.random.default_rng(0)
    bands, pattern = VARIANT_BANDS, 4096
    tiles = math.ceil(pixels * slices / pattern)
    dark = rng.uniform(95.0, 105.0, (pattern, bands)).astype(np.float32)
    white = (dark + rng.uniform(8000.0, 12000.0, (pattern, bands))).astype(np.float32)
    raw = np.rint(dark + (white - dark) * rng.uniform(0.01, 1.0, (pattern, 1))).astype(np.uint16)
    raw, dark, white = (np.tile(x, (tiles, 1)) for x in (raw, dark, white))
    p = np.ones((1, bands), np.float32)
    coeffs = np.tile(np.float32([0.01, 1.0, 0.0, 0.001]), (bands, 1))
    projection = rng.uniform(0.0, 1.0 / bands, (bands, 34)).astype(np.float32)
    bias = np.zeros(34, np.float32)
    white_xyz = projection.sum(axis=0)[31:].astype(np.float32)
    no_residual = tuple(np.asarray(x) for x in residual_constants(None, None, bands))
    total = pixels * slices
    reflectance = np.empty((total, 31), np.float32)
    lab = np.empty((total, 3), np.float32)
    quality = np.empty(total, np.uint8)
    problems = []
    for k in range(slices):
        rows = slice(k * pixels, (k + 1) * pixels)
        arguments = (raw[rows][None], True, dark[rows], white[rows], p, coeffs, projection, bias, white_xyz,
                     *no_residual, 1, pixels, bands, 0, 0, math.nan)
        outputs = (reflectance[rows][None], lab[rows][None], quality[rows][None])
        problems.append((arguments, outputs))
    return problems


def measure_variants(variants: Iterable[str] | None = None, *, pixels: int = PROBE_PIXELS,
                     repeats: int = PROBE_REPEATS) -> dict[str, float]:
    """Seconds of CPU time one call of the kernel takes, the best of `repeats`, for each of
    `variants` (default: all this CPU runs), on a synthetic 16-band problem of `pixels` pixels.

    What it measures is what a frame costs, not what the caches allow: the calls go round
    `_probe_slices` problems in memory of their own, so that each reads and writes memory the
    last-level cache has dropped. (In the cache the ranking can turn over: on a 2-core Zen 4 the
    AVX2 code took 20 ns a pixel against AVX-512's 26 with 32k pixels in the cache, 33 against 27
    from memory, as in a 1-megapixel frame.) One untimed round over all slices first (page
    faults, the code's first run), then the variants take turns, A B C A B C ..., and each call's
    time is its thread's CPU time (time.thread_time): another process that takes the core for a
    while does not count, as it would in wall-clock time on a shared machine. One thread: the
    variants differ in their instructions, which the other cores run alike.

    Raises:
      ValueError: a variant this CPU does not run (or the kernel was not built).
    """
    variants = supported_variants() if variants is None else tuple(variants)
    codes = [(name, variant_code(name)) for name in variants]
    problems = _probe_problems(pixels, _probe_slices(pixels))
    turn = 0

    def call(code: int) -> float:
        nonlocal turn
        arguments, outputs = problems[turn % len(problems)]
        turn += 1
        start = time.thread_time()
        _fused_correct.correct_arrays(*arguments, code, 1, *outputs)
        return time.thread_time() - start

    for k in range(len(problems)):
        call(codes[k % len(codes)][1])
    best = dict.fromkeys(variants, math.inf)
    for _ in range(repeats):
        for name, code in codes:
            best[name] = min(best[name], call(code))
    return best


class Measurement(NamedTuple):
    """The per-process measurement of the variants (`measure_variants`) and what it chose."""

    times_s: Mapping[str, float]  # CPU seconds a call of `pixels` pixels, best of `repeats`, per variant the CPU runs
    auto: str  # choose_variant(times_s): what SPHEREJAX_FUSED=auto (or 1, or unset) runs
    portable: str  # the same rule without AVX-512: what SPHEREJAX_FUSED=portable runs
    pixels: int
    repeats: int


class VariantChoice(NamedTuple):
    """Which variant the kernel runs for 16 bands under the current SPHEREJAX_FUSED (`variant`)."""

    name: str  # one of VARIANTS
    setting: str  # the value of SPHEREJAX_FUSED ("auto" if unset)
    measurement: Measurement  # the process's measurement (a forced variant runs whatever it says)


_measurement_lock = threading.Lock()


def _spherejax_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("spherejax")
    except PackageNotFoundError:  # a source tree on sys.path
        return "source"


@functools.cache
def _measured() -> Measurement:
    supported = supported_variants()
    key = variant_cache.machine_key(supported, _spherejax_version())
    times = variant_cache.timings(key, supported, measure_variants)
    if times is None:  # no cache folder: the widest, the same in every process (variant_cache)
        widest = {name: 1.0 for name in supported}
        return Measurement(types.MappingProxyType({}), choose_variant(widest),
                           choose_variant({n: t for n, t in widest.items() if n != AVX512}), 0, 0)
    portable_times = {name: t for name, t in times.items() if name != AVX512}
    chosen = Measurement(types.MappingProxyType(times), choose_variant(times), choose_variant(portable_times),
                         PROBE_PIXELS, PROBE_REPEATS)
    _log.debug(
        "fused kernel variants, %d pixels x %d bands on one thread, best of %d: %s; auto runs %s, portable %s "
        "(a narrower variant only when more than %.0f %% faster)",
        chosen.pixels, VARIANT_BANDS, chosen.repeats, ", ".join(f"{name} {1e3 * t:.2f} ms" for name, t in times.items()),
        chosen.auto, chosen.portable, 100 * MARGIN,
    )
    return chosen


def measurement() -> Measurement:
    """The variants' timings and the choice: measured once per machine (at the first call ever:
    about 45 ms of CPU time on a 2-core Zen 4; `measure_variants`) and kept in spherejax's cache
    folder, which every later process reads (`variant_cache`: one choice per machine, so the same
    bits from every run), then cached for the process's life. Under a lock: threads that first use
    the kernel together wait for one reading rather than each making one of their own."""
    with _measurement_lock:
        return _measured()


def resolve(kernel_mode: str, bands: int) -> str:
    """The variant that runs for `kernel_mode` (a variant, AUTO, "1" or PORTABLE) and `bands`."""
    if kernel_mode not in (*VARIANTS, AUTO, "1", PORTABLE):
        raise ValueError(f"kernel_mode: expected one of {(*VARIANTS, AUTO, PORTABLE)}, got {kernel_mode!r}")
    if bands != VARIANT_BANDS:
        return GENERIC  # the only code other band counts have
    if kernel_mode in VARIANTS:
        return kernel_mode
    if kernel_mode in (AUTO, "1"):
        return measurement().auto
    return measurement().portable


def variant_code(name: str) -> int:
    """The kernel's code of a variant this CPU runs (`_fused_correct.VARIANT_<NAME>`).

    Raises:
      ValueError: a variant this CPU does not run, or the kernel was not built.
    """
    if name not in supported_variants():
        raise ValueError(f"the fused kernel's {name!r} variant: not among those this CPU runs, "
                         f"{supported_variants()}")
    return getattr(_fused_correct, f"VARIANT_{name.upper()}")


def variant() -> VariantChoice | None:
    """The variant 16-band calls of `correct` run under the current SPHEREJAX_FUSED, with the
    process's measurement (made now if it was not yet); None where `correct` does not use the
    kernel (`unavailable_reason` says why). Other band counts run the generic code."""
    if not enabled():
        return None
    setting = switch()
    return VariantChoice(resolve(setting, VARIANT_BANDS), setting, measurement())


def enabled() -> bool:
    """True if `correct` uses the kernel on CPU: built, taken by the running jaxlib's XLA, and not
    switched off by SPHEREJAX_FUSED=0."""
    return built() and switch() != "0" and register()


def mode(raw_dtype, compute_dtype, bands: int) -> str | None:
    """How `correct` computes this call on CPU: the kernel's variant (one of VARIANTS: for 16
    bands as SPHEREJAX_FUSED says, measured once per machine for "auto", "1" and "portable"; the
    generic code for other band counts), or None (the jax.numpy path; see the module docstring).
    A static argument of the jitted step, so that a change of the environment variable traces
    again, and one value for the XLA route and the direct one, so that both run the same code."""
    usable = (
        enabled()
        and np.dtype(compute_dtype) == np.float32
        and np.dtype(raw_dtype) in RAW_DTYPES
        and 1 <= bands <= MAX_BANDS
    )
    if not usable:
        return None
    return resolve(switch(), bands)

def unavailable_reason() -> str | None:
    """Why `correct` does not use the kernel on CPU, in one line, or None where it does."""
    if switch() == "0":
        return f"{SWITCH}=0 switches the fused kernel off"
    return registration_refusal()




__all__ = [
    "AUTO", "AVX2", "AVX512", "GENERIC", "MARGIN", "MAX_BANDS", "PORTABLE", "PROBE_PIXELS", "PROBE_REPEATS",
    "RAW_DTYPES", "SWITCH", "SWITCH_VALUES", "VARIANTS", "VARIANT_BANDS", "Measurement", "VariantChoice",
    "choose_variant", "enabled", "measure_variants", "measurement", "mode", "resolve", "switch",
    "unavailable_reason", "variant", "variant_code",
]
