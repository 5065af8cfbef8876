"""The fused CPU kernel of `correct`'s per-pixel step, and when it is used.

On CPU, `spherejax.correct` runs its per-pixel step (flat field, Stage I and II, Wiener, Lab and
the quality mask) as one XLA custom call into a compiled kernel (the sources in `kernel/`, whose
header `fused_correct.h` says which does what), instead of the jitted jax.numpy path in
`pipeline.py`. XLA does not fuse a matrix product with elementwise
work on CPU, so the jax.numpy path writes and reads back the whole Stage II cube; the kernel reads
each pixel once and writes its outputs once: 2.3 times faster at 1024 x 1024 x 16
(benchmarks/README.md). It computes the same equations; the jax.numpy path stays the definition
it is tested against (tests/test_fused.py), and it is what runs:

- on GPUs and any platform other than CPU (`jax.lax.platform_dependent` picks at lowering time);
- in float64 (a float64 calibration or raw), and for raw other than uint16 or float32;
- when the extension was not built (no C++ compiler at install: setup.py builds it as optional),
  when the running jaxlib refuses it (compiled against newer XLA FFI headers than that jaxlib
  speaks: setup.py says when this can happen; `unavailable_reason` says so, and it is logged
  once), or when the environment variable SPHEREJAX_FUSED is "0" (to compare the two, or to rule
  the kernel out when something looks wrong).

A calibration whose estimator has a kernel residual (E8-E12, `estimation.kernel_residual`) goes to
the kernel too (`residual_constants`: its whitening, inducing points and rank-8 weights), where the
kernel computes a block's outputs 16 pixels a vector (fused_correct.h, residual_of_16): 2.8 times
the affine calibration's time at 1024 x 1024 x 16 on 2 Zen 4 cores (benchmarks/bench_wiener.py),
against 21 times on the jax.numpy path. The AVX-512 and generic code have it; a plan whose variant
is AVX2 (no residual code in its own block), a traced calibration and a residual of rank above 8
take the jax.numpy path (`spherejax._engine.plan`, `residual_fits`).

With `intermediates=True` the main outputs still come from the kernel, so that they do not depend
on what else was asked for; the cubes it never forms (v, v_stage1, v_stage2) come from the
jax.numpy path, whose own reflectance and Lab XLA then drops as unused.

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
code's target_clones still take the CPU's widest level, as before); "avx512", "avx2" or
"generic": that variant, without measuring (refused with a ValueError where the CPU does not run
it, rather than run something else under its name); "0": the jax.numpy path. Any other value is
refused (`switch`), so that a typo such as "off" cannot leave the kernel on.

NumPy frames given to `correct` (whole frames, concrete calibration, nothing but the main outputs
asked for) go to the kernel without XLA (`correct_arrays`, from `pipeline._correct_directly`): XLA
takes its inputs only in memory of its own, on a 64-byte boundary, so a NumPy frame had to be
copied first (32 MB a megapixel of uint16, a tenth of the call); the kernel reads it where it
lies. The same kernel, the same constants and p: the same bits (tests/test_buffers.py).

Derivatives: the kernel's outputs carry a custom JVP that is the JVP of the jax.numpy path, so
`jax.grad` and `jax.jacfwd` through `correct` give what they gave before the kernel existed.
Batches of images given as leading axes of `raw` go to the kernel in one call, and so do frames
mapped with `jax.vmap` over one calibration (`_batched_kernel_call`); a mapped calibration runs
the kernel once per mapped element.
"""

from __future__ import annotations

import functools
import glob
import logging
import math
import os
import threading
import time
import types
from collections.abc import Callable, Iterable, Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import variant_cache

try:  # built by setup.py as an optional extension
    from . import _fused_correct
except ImportError:  # pragma: no cover - exercised only where the build failed
    _fused_correct = None

#: The name the kernel is registered under with XLA (jax.ffi).
TARGET = "spherejax_fused_correct"

#: The kernel keeps one pixel's bands in a fixed-size buffer.
MAX_BANDS = 64

#: Raw dtypes the kernel reads directly; others take the jax.numpy path.
RAW_DTYPES = (np.dtype(np.uint16), np.dtype(np.float32))

#: Environment variable: "0" turns the kernel off (read when `correct` is traced).
SWITCH = "SPHEREJAX_FUSED"


_log = logging.getLogger(__name__)


def _try_register(register: Callable) -> str | None:
    """Register the kernel with XLA through `register` (jax.ffi.register_ffi_target's signature);
    None if XLA took it, else why not, in one line.

    The CPU backend is started first: before it exists jax only queues a registration, and a
    handler XLA refuses would then fail whatever first starts the backend instead of here.
    XLA refuses a handler compiled against a newer FFI API than its own (setup.py).
    """
    try:
        jax.devices("cpu")
    except RuntimeError as error:  # JAX_PLATFORMS without "cpu" (a GPU-only process)
        return f"the fused kernel runs on XLA's CPU backend, which this process does not have ({error})"
    try:
        register(TARGET, _fused_correct.handler(), platform="cpu")
    except Exception as error:  # noqa: BLE001 -- XLA's refusal (JaxRuntimeError) or any other: the kernel is then not used
        import jaxlib

        major, minor = _fused_correct.ffi_api_version()
        message = " ".join(str(error).split("\n")[0].split()).rstrip(".")
        reason = (
            f"the fused kernel (XLA FFI API {major}.{minor}) was refused by jaxlib {jaxlib.__version__}: {message}; "
            "correct runs its jax.numpy path (the same numbers, slower). Rebuild the kernel against this jaxlib: "
            "pip install --no-build-isolation --force-reinstall --no-deps spherejax (from its source)"
        )
        _log.warning("%s", reason)  # unexpected, and it costs speed: said once (`_registration` caches)
        return reason
    return None


@functools.cache
def _registration() -> str | None:
    """Registers the kernel once per process: None if registered, else the reason it is not."""
    if _fused_correct is None:
        return "the fused kernel was not built (no C++17 compiler or no jaxlib headers at install: setup.py)"
    return _try_register(jax.ffi.register_ffi_target)


def _register() -> bool:
    return _registration() is None


def built() -> bool:
    """True if the compiled kernel was built and imported."""
    return _fused_correct is not None


def unavailable_reason() -> str | None:
    """Why `correct` does not use the kernel on CPU, in one line, or None where it does."""
    if switch() == "0":
        return f"{SWITCH}=0 switches the fused kernel off"
    return _registration()


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


@functools.cache
def supported_variants() -> tuple[str, ...]:
    """The variants this build has and this CPU runs, widest first ("generic" always), or () where
    the kernel was not built."""
    return tuple(_fused_correct.supported_variants()) if _fused_correct is not None else ()


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
    codes = [(name, _variant_code(name)) for name in variants]
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


def _resolve(kernel_mode: str, bands: int) -> str:
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


def _variant_code(name: str) -> int:
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
    return VariantChoice(_resolve(setting, VARIANT_BANDS), setting, measurement())


def enabled() -> bool:
    """True if `correct` uses the kernel on CPU: built, taken by the running jaxlib's XLA, and not
    switched off by SPHEREJAX_FUSED=0."""
    return built() and switch() != "0" and _register()


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
    return _resolve(switch(), bands)


def _kernel_call(raw, dark, white, p, coeffs, projection, bias, white_xyz, saturation: float | None,
                 kernel_mode: str, residual=None):
    """The custom call on arrays shaped as the kernel wants them (see kernel/fused_correct.h).

    raw (N, P, B); dark, white (P, B); p (N, B); coeffs (B, 4); projection (B, 34) = [W^T |
    W^T weights]; bias (34,) = [r0 | r0 weights], the affine estimator's offset; white_xyz (3,);
    residual: the kernel residual's four arrays (`residual_constants`), None for none.
    Returns reflectance (N, P, 31), lab (N, P, 3) float32 and quality (N, P) uint8.

    Under `jax.vmap` (`_batched_kernel_call`): when only raw and p are mapped, the mapped images
    are more images of one call, as `correct` on a stack is; otherwise one call per element.
    """
    call = jax.custom_batching.custom_vmap(
        functools.partial(_ffi_call, saturation=saturation, kernel_mode=kernel_mode)
    )
    call.def_vmap(functools.partial(_batched_kernel_call, call))
    if residual is None:
        residual = residual_constants(None, None, raw.shape[-1])
    return call(raw, dark, white, p, coeffs, projection, bias, white_xyz, *residual)


def _batched_kernel_call(call, axis_size: int, in_batched, raw, dark, white, p, *constants):
    """The batching rule of `_kernel_call` (`call`, its custom_vmap): mapped arrays have the
    mapped axis first, of length `axis_size`.

    Why not the custom call's own `vmap_method="sequential"`: that runs the kernel once per
    element in an XLA loop, copying each element's raw out into a buffer of its own first.
    Images mapped over one calibration are what `correct` takes as a stack, (M, N, P, B) ->
    (M N, P, B): one call, the same numbers (benchmarks/bench_batch.py times both). A mapped
    calibration (dark, white, Stage II or the estimator) keeps one call per element: the kernel
    takes one calibration a call.
    """
    _, dark_batched, white_batched, _, *constants_batched = in_batched
    if dark_batched or white_batched or any(constants_batched):
        arrays = (raw, dark, white, p, *constants)
        axes = tuple(0 if batched else None for batched in in_batched)
        return jax.vmap(call.fun, in_axes=axes)(*arrays), (True, True, True)
    images, pixels, bands = raw.shape[-3:]
    raw = jnp.broadcast_to(raw, (axis_size, images, pixels, bands)).reshape(axis_size * images, pixels, bands)
    p = jnp.broadcast_to(p, (axis_size, images, bands)).reshape(axis_size * images, bands)
    reflectance, lab, quality = call(raw, dark, white, p, *constants)
    return (
        reflectance.reshape(axis_size, images, pixels, -1), lab.reshape(axis_size, images, pixels, 3),
        quality.reshape(axis_size, images, pixels),
    ), (True, True, True)


def _ffi_call(raw, dark, white, p, coeffs, projection, bias, white_xyz, whitening, inducing, factor, basis, *,
              saturation: float | None, kernel_mode: str):
    """The XLA custom call itself (`_kernel_call`)."""
    _register()
    images, pixels, _ = raw.shape
    out_types = (
        jax.ShapeDtypeStruct((images, pixels, 31), jnp.float32),
        jax.ShapeDtypeStruct((images, pixels, 3), jnp.float32),
        jax.ShapeDtypeStruct((images, pixels), jnp.uint8),
    )
    call = jax.ffi.ffi_call(TARGET, out_types, vmap_method="sequential")
    # NaN saturation: the kernel's `value >= saturation` is then never true, i.e. no check.
    level = np.float32(np.nan if saturation is None else saturation)
    code = np.int32(_variant_code(_resolve(kernel_mode, raw.shape[2])))
    return call(raw, dark, white, p, coeffs, projection, bias, white_xyz, whitening, inducing, factor, basis,
                saturation=level, variant=code)


def kernel_constants(wiener, wiener_offset, weights):
    """What the kernel takes of the estimator and the illuminant: projection (B, 34) = [W^T | W^T
    weights], bias (34,) = [r0 | r0 weights] and white_xyz (3,), the column sums of weights.

    XYZ = reflectance weights = v_tilde (W^T weights) + r0 weights: the (31, 3) weights folded
    into the Wiener matrix, so that one (B, 34) product gives reflectance and XYZ.
    """
    hi = jax.lax.Precision.HIGHEST
    projection = jnp.concatenate([wiener.T, jnp.matmul(wiener.T, weights, precision=hi)], axis=1)
    bias = jnp.concatenate([wiener_offset, jnp.matmul(wiener_offset, weights, precision=hi)])
    return projection, bias, jnp.sum(weights, axis=0)


#: The rank of a kernel residual's weights A (31, m) the kernel applies (kernel/fused_correct.h,
#: kResidualRank): A = P G with P (31, 8) and G (8, m), eight multiply-adds per inducing point and
#: pixel. The fit keeps A at this rank or less (`estimation.kernel_residual.RESIDUAL_RANK`); a
#: residual of higher rank (a file not made by the fit) takes the jax.numpy path (`residual_fits`).
RESIDUAL_RANK = 8


def _padded_rows(x, multiple: int):
    """x (n, ...) with zero rows appended up to a multiple of `multiple` rows."""
    return jnp.pad(x, [(0, -x.shape[0] % multiple)] + [(0, 0)] * (x.ndim - 1))


def residual_fits(residual) -> bool:
    """True if the kernel applies this kernel residual (`estimation.KernelResidual`, concrete)
    exactly: weights of rank RESIDUAL_RANK or less (the singular values beyond it below 1e-5 of
    the largest: float32 round-off of a rank-8 A). None (an affine estimator): True."""
    if residual is None:
        return True
    A = np.asarray(residual.weights, np.float64)
    singular = np.linalg.svd(A, compute_uv=False)
    return len(singular) <= RESIDUAL_RANK or not singular[0] > 0 or singular[RESIDUAL_RANK] <= 1e-5 * singular[0]


def residual_constants(residual, weights, bands: int):
    """What the kernel takes of a kernel residual (E8-E10, `estimation.KernelResidual`: centre mu,
    whitening S (d, B), inducing z (m, d), weights A (31, m)), float32, traceable:

    whitening (D, B + 1): row i [S_i | -(S mu)_i] (u = S (v - mu));
    inducing (M, B + 1): row j [Y_j | c_j] with Y = S^T z^T and c = -mu . Y - |z|^2 / 2, so that
      -|u - z_j|^2 / 2 = Y_j . v + c_j - |u|^2 / 2;
    factor (M, 8): G^T, basis (8, 34): [P | P^T weights]^T, from A's singular value
      decomposition at rank RESIDUAL_RANK (A = P G, P = U Sigma, G = V^T): exact for the fit's A
      (`residual_fits`);
    D and M: d and m rounded up to multiples of 8 (the kernel takes rows in eights), the padding
    zero (a padding inducing point has factor 0). None (an affine estimator): no rows, nothing
    applied.
    """
    if residual is None:
        return (jnp.zeros((0, bands + 1), jnp.float32), jnp.zeros((0, bands + 1), jnp.float32),
                jnp.zeros((0, RESIDUAL_RANK), jnp.float32), jnp.zeros((RESIDUAL_RANK, 34), jnp.float32))
    hi = jax.lax.Precision.HIGHEST
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    mu, S, Z, A = (f32(x) for x in (residual.centre, residual.whitening, residual.inducing, residual.weights))
    whitening = _padded_rows(jnp.concatenate([S, -jnp.matmul(S, mu, precision=hi)[:, None]], axis=1), 8)
    Y = jnp.matmul(Z, S, precision=hi)  # (m, B): row j is S^T z_j
    c = -jnp.matmul(Y, mu, precision=hi) - 0.5 * jnp.sum(Z * Z, axis=1)
    inducing = _padded_rows(jnp.concatenate([Y, c[:, None]], axis=1), 8)
    U, singular, Vt = jnp.linalg.svd(A, full_matrices=False)
    rank = min(RESIDUAL_RANK, singular.shape[0])
    P = jnp.pad(U[:, :rank] * singular[:rank], ((0, 0), (0, RESIDUAL_RANK - rank)))  # (31, 8)
    G = jnp.pad(Vt[:rank], ((0, RESIDUAL_RANK - rank), (0, 0)))  # (8, m)
    factor = _padded_rows(G.T, 8)
    basis = jnp.concatenate([P.T, jnp.matmul(P.T, f32(weights), precision=hi)], axis=1)
    return whitening, inducing, factor, basis


def correct_arrays(raw: np.ndarray, dark: np.ndarray, white: np.ndarray, p: np.ndarray, coeffs: np.ndarray,
                   projection: np.ndarray, bias: np.ndarray, white_xyz: np.ndarray, saturation: float | None,
                   kernel_mode: str, out: tuple[np.ndarray, np.ndarray, np.ndarray], threads: int,
                   residual: tuple[np.ndarray, ...] | None = None) -> None:
    """The kernel on NumPy arrays, called directly rather than from XLA: the caller's frames are
    read where they lie (no copy into XLA's memory) and the outputs written into `out`.

    Args:
      raw: (N, P, B) uint16 or float32, C-contiguous (any alignment).
      dark, white: (P, B) float32; p: (N, B) float32; coeffs: (B, 4) float32; projection (B, 34),
        bias (34,), white_xyz (3,) float32 (`kernel_constants`).
      saturation: the saturation level, or None for no check.
      kernel_mode: the variant (`mode`), or AUTO or PORTABLE for the process's measured choice.
      out: reflectance (N, P, 31) float32, lab (N, P, 3) float32, quality (N, P) uint8,
        C-contiguous and writable.
      threads: how many threads share the work (the calling one and threads - 1 more).
      residual: the kernel residual's whitening, inducing, factor and basis float32
        (`residual_constants`), or None for an affine estimator.

    Raises:
      ValueError: a dtype, shape or layout the kernel does not take, or a variant this CPU does
        not run.
    """
    images, pixels, bands = raw.shape
    if residual is None:
        residual = tuple(np.asarray(x) for x in residual_constants(None, None, bands))
    whitening, inducing, factor, basis = residual
    whitened_rows, inducing_rows = whitening.shape[0], inducing.shape[0]
    expected = {
        "raw": (raw, raw.dtype if raw.dtype in RAW_DTYPES else RAW_DTYPES[0], (images, pixels, bands)),
        "dark": (dark, np.float32, (pixels, bands)), "white": (white, np.float32, (pixels, bands)),
        "p": (p, np.float32, (images, bands)), "coeffs": (coeffs, np.float32, (bands, 4)),
        "projection": (projection, np.float32, (bands, 34)), "bias": (bias, np.float32, (34,)),
        "white_xyz": (white_xyz, np.float32, (3,)),
        "whitening": (whitening, np.float32, (whitened_rows, bands + 1)),
        "inducing": (inducing, np.float32, (inducing_rows, bands + 1)),
        "factor": (factor, np.float32, (inducing_rows, RESIDUAL_RANK)),
        "basis": (basis, np.float32, (RESIDUAL_RANK, 34)),
        "reflectance": (out[0], np.float32, (images, pixels, 31)), "lab": (out[1], np.float32, (images, pixels, 3)),
        "quality": (out[2], np.uint8, (images, pixels)),
    }
    for name, (array, dtype, shape) in expected.items():
        if array.dtype != dtype or array.shape != shape or not array.flags.c_contiguous:
            raise ValueError(f"{name}: expected a C-contiguous {np.dtype(dtype)} array of shape {shape}, "
                             f"got {array.dtype} {array.shape}")
    level = np.float32(np.nan if saturation is None else saturation)  # NaN: no check
    code = _variant_code(_resolve(kernel_mode, bands))
    _fused_correct.correct_arrays(
        raw, raw.dtype == np.uint16, dark, white, p, coeffs, projection, bias, white_xyz, whitening, inducing,
        factor, basis, images, pixels, bands, whitened_rows, inducing_rows, float(level), code, int(threads), *out,
    )


def correct_pixels(plain: Callable, raw, dark, white, p, coeffs, wiener, wiener_offset, weights, saturation,
                   kernel_mode=AUTO, residual=None):
    """reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W): the kernel on CPU,
    `plain` elsewhere, with `plain`'s JVP everywhere (so also with respect to wiener_offset).

    Args:
      plain: the jax.numpy definition, called as plain(raw, dark, white, p, coeffs, wiener,
        wiener_offset, weights, residual) -> (reflectance, lab, quality), with `saturation`
        already bound.
      raw: (..., H, W, B) uint16 or float32.
      dark, white: (H, W, B) float32.
      p: (..., B) float32, the white-patch ratio of each image.
      coeffs: (B, 4) float32, Stage II c1..c4.
      wiener: (31, B) float32, the Wiener matrix W.
      wiener_offset: (31,) float32, the estimator's offset r0 (reflectance = W v_tilde + r0).
      weights: (31, 3) float32 tristimulus weights (white = their column sums).
      saturation: the saturation level, or None for no check.
      kernel_mode: the variant (`mode`), or AUTO or PORTABLE for the process's measured choice.
      residual: the estimator's kernel residual (`estimation.KernelResidual`, float32, of rank
        RESIDUAL_RANK or less: `residual_fits`) or None.
    """
    arrays = (raw, dark, white, p, coeffs, wiener, wiener_offset, weights, residual)

    @jax.custom_jvp
    def outputs(*arrays):
        return jax.lax.platform_dependent(*arrays, cpu=on_cpu, default=plain)

    @outputs.defjvp
    def outputs_jvp(primals, tangents):
        _, tangents_out = jax.jvp(plain, primals, tangents)
        return outputs(*primals), tangents_out

    def on_cpu(raw, dark, white, p, coeffs, wiener, wiener_offset, weights, residual):
        height, width, bands = raw.shape[-3:]
        batch = raw.shape[:-3]
        images, pixels = int(np.prod(batch, dtype=np.int64)), height * width
        projection, bias, white_xyz = kernel_constants(wiener, wiener_offset, weights)
        reflectance, lab, quality = _kernel_call(
            raw.reshape(images, pixels, bands), dark.reshape(pixels, bands),
            white.reshape(pixels, bands), jnp.broadcast_to(p, (*batch, bands)).reshape(images, bands),
            coeffs, projection, bias, white_xyz, saturation, kernel_mode,
            residual=residual_constants(residual, weights, bands),
        )
        return (
            reflectance.reshape(*batch, height, width, 31),
            lab.reshape(*batch, height, width, 3),
            quality.reshape(*batch, height, width),
        )

    return outputs(*arrays)


__all__ = [
    "AUTO",
    "AVX2",
    "AVX512",
    "GENERIC",
    "MARGIN",
    "MAX_BANDS",
    "PORTABLE",
    "PROBE_PIXELS",
    "PROBE_REPEATS",
    "RESIDUAL_RANK",
    "SWITCH",
    "SWITCH_VALUES",
    "TARGET",
    "VARIANTS",
    "VARIANT_BANDS",
    "Measurement",
    "VariantChoice",
    "built",
    "choose_variant",
    "correct_arrays",
    "correct_pixels",
    "enabled",
    "kernel_constants",
    "measure_variants",
    "measurement",
    "mode",
    "residual_constants",
    "residual_fits",
    "supported_variants",
    "switch",
    "unavailable_reason",
    "variant",
]
