"""The fused CPU kernel of `correct`'s per-pixel step, and when it is used.

On CPU, `spherejax.correct` runs its per-pixel step (flat field, Stage I and II, Wiener, Lab and
the quality mask) as one XLA custom call into a compiled kernel (`_fused_correct.cc`), instead of
the jitted jax.numpy path in `pipeline.py`. XLA does not fuse a matrix product with elementwise
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

With `intermediates=True` the main outputs still come from the kernel, so that they do not depend
on what else was asked for; the cubes it never forms (v, v_stage1, v_stage2) come from the
jax.numpy path, whose own reflectance and Lab XLA then drops as unused.

SPHEREJAX_FUSED takes "auto" (the default, as when unset) or "1": the kernel with the best code
the CPU runs; "portable": the kernel without its AVX-512 code, so that the portable code, which
CPUs without AVX-512 run, can be tested and timed on a machine that has it; "0": the jax.numpy
path. Any other value is refused (`switch`), so that a typo such as "off" cannot leave the
kernel on.

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
import logging
import os
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

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


#: Values of `mode`: the kernel with the best code the CPU runs, or its portable code only.
AUTO, PORTABLE = "auto", "portable"

#: The values SWITCH may take; unset means AUTO.
SWITCH_VALUES = (AUTO, "1", PORTABLE, "0")


def switch() -> str:
    """The value of SPHEREJAX_FUSED ("auto" if unset).

    Raises:
      ValueError: any value but those of SWITCH_VALUES, naming the variable.
    """
    value = os.environ.get(SWITCH, AUTO)
    if value not in SWITCH_VALUES:
        raise ValueError(
            f"{SWITCH}: expected one of {', '.join(repr(v) for v in SWITCH_VALUES)} or unset, got {value!r}"
        )
    return value


def enabled() -> bool:
    """True if `correct` uses the kernel on CPU: built, taken by the running jaxlib's XLA, and not
    switched off by SPHEREJAX_FUSED=0."""
    return built() and switch() != "0" and _register()


def mode(raw_dtype, compute_dtype, bands: int) -> str | None:
    """How `correct` computes this call on CPU: AUTO or PORTABLE (the kernel, see SWITCH), or
    None (the jax.numpy path; see the module docstring). A static argument of the jitted step,
    so that a change of the environment variable traces again."""
    usable = (
        enabled()
        and np.dtype(compute_dtype) == np.float32
        and np.dtype(raw_dtype) in RAW_DTYPES
        and 1 <= bands <= MAX_BANDS
    )
    if not usable:
        return None
    return PORTABLE if switch() == PORTABLE else AUTO


def _kernel_call(raw, dark, white, p, coeffs, projection, bias, white_xyz, saturation: float | None, kernel_mode: str):
    """The custom call on arrays shaped as the kernel wants them (see `_fused_correct.cc`).

    raw (N, P, B); dark, white (P, B); p (N, B); coeffs (B, 4); projection (B, 34) = [W^T |
    W^T weights]; bias (34,) = [r0 | r0 weights], the affine estimator's offset; white_xyz (3,).
    Returns reflectance (N, P, 31), lab (N, P, 3) float32 and quality (N, P) uint8.

    Under `jax.vmap` (`_batched_kernel_call`): when only raw and p are mapped, the mapped images
    are more images of one call, as `correct` on a stack is; otherwise one call per element.
    """
    call = jax.custom_batching.custom_vmap(
        functools.partial(_ffi_call, saturation=saturation, kernel_mode=kernel_mode)
    )
    call.def_vmap(functools.partial(_batched_kernel_call, call))
    return call(raw, dark, white, p, coeffs, projection, bias, white_xyz)


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


def _ffi_call(raw, dark, white, p, coeffs, projection, bias, white_xyz, *, saturation: float | None, kernel_mode: str):
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
    portable = np.int32(kernel_mode == PORTABLE)
    return call(raw, dark, white, p, coeffs, projection, bias, white_xyz, saturation=level, portable=portable)


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


def correct_arrays(raw: np.ndarray, dark: np.ndarray, white: np.ndarray, p: np.ndarray, coeffs: np.ndarray,
                   projection: np.ndarray, bias: np.ndarray, white_xyz: np.ndarray, saturation: float | None,
                   kernel_mode: str, out: tuple[np.ndarray, np.ndarray, np.ndarray], threads: int) -> None:
    """The kernel on NumPy arrays, called directly rather than from XLA: the caller's frames are
    read where they lie (no copy into XLA's memory) and the outputs written into `out`.

    Args:
      raw: (N, P, B) uint16 or float32, C-contiguous (any alignment).
      dark, white: (P, B) float32; p: (N, B) float32; coeffs: (B, 4) float32; projection (B, 34),
        bias (34,), white_xyz (3,) float32 (`kernel_constants`).
      saturation: the saturation level, or None for no check.
      kernel_mode: AUTO or PORTABLE (`mode`).
      out: reflectance (N, P, 31) float32, lab (N, P, 3) float32, quality (N, P) uint8,
        C-contiguous and writable.
      threads: how many threads share the work (the calling one and threads - 1 more).

    Raises:
      ValueError: a dtype, shape or layout the kernel does not take.
    """
    images, pixels, bands = raw.shape
    expected = {
        "raw": (raw, raw.dtype if raw.dtype in RAW_DTYPES else RAW_DTYPES[0], (images, pixels, bands)),
        "dark": (dark, np.float32, (pixels, bands)), "white": (white, np.float32, (pixels, bands)),
        "p": (p, np.float32, (images, bands)), "coeffs": (coeffs, np.float32, (bands, 4)),
        "projection": (projection, np.float32, (bands, 34)), "bias": (bias, np.float32, (34,)),
        "white_xyz": (white_xyz, np.float32, (3,)),
        "reflectance": (out[0], np.float32, (images, pixels, 31)), "lab": (out[1], np.float32, (images, pixels, 3)),
        "quality": (out[2], np.uint8, (images, pixels)),
    }
    for name, (array, dtype, shape) in expected.items():
        if array.dtype != dtype or array.shape != shape or not array.flags.c_contiguous:
            raise ValueError(f"{name}: expected a C-contiguous {np.dtype(dtype)} array of shape {shape}, "
                             f"got {array.dtype} {array.shape}")
    level = np.float32(np.nan if saturation is None else saturation)  # NaN: no check
    _fused_correct.correct_arrays(
        raw, raw.dtype == np.uint16, dark, white, p, coeffs, projection, bias, white_xyz, images, pixels, bands,
        float(level), kernel_mode == PORTABLE, int(threads), *out,
    )


def correct_pixels(plain: Callable, raw, dark, white, p, coeffs, wiener, wiener_offset, weights, saturation,
                   kernel_mode=AUTO):
    """reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W): the kernel on CPU,
    `plain` elsewhere, with `plain`'s JVP everywhere (so also with respect to wiener_offset).

    Args:
      plain: the jax.numpy definition, called as plain(raw, dark, white, p, coeffs, wiener,
        wiener_offset, weights) -> (reflectance, lab, quality), with `saturation` already bound.
      raw: (..., H, W, B) uint16 or float32.
      dark, white: (H, W, B) float32.
      p: (..., B) float32, the white-patch ratio of each image.
      coeffs: (B, 4) float32, Stage II c1..c4.
      wiener: (31, B) float32, the Wiener matrix W.
      wiener_offset: (31,) float32, the estimator's offset r0 (reflectance = W v_tilde + r0).
      weights: (31, 3) float32 tristimulus weights (white = their column sums).
      saturation: the saturation level, or None for no check.
      kernel_mode: AUTO or PORTABLE (`mode`).
    """
    arrays = (raw, dark, white, p, coeffs, wiener, wiener_offset, weights)

    @jax.custom_jvp
    def outputs(*arrays):
        return jax.lax.platform_dependent(*arrays, cpu=on_cpu, default=plain)

    @outputs.defjvp
    def outputs_jvp(primals, tangents):
        _, tangents_out = jax.jvp(plain, primals, tangents)
        return outputs(*primals), tangents_out

    def on_cpu(raw, dark, white, p, coeffs, wiener, wiener_offset, weights):
        height, width, bands = raw.shape[-3:]
        batch = raw.shape[:-3]
        images, pixels = int(np.prod(batch, dtype=np.int64)), height * width
        projection, bias, white_xyz = kernel_constants(wiener, wiener_offset, weights)
        reflectance, lab, quality = _kernel_call(
            raw.reshape(images, pixels, bands), dark.reshape(pixels, bands),
            white.reshape(pixels, bands), jnp.broadcast_to(p, (*batch, bands)).reshape(images, bands),
            coeffs, projection, bias, white_xyz, saturation, kernel_mode,
        )
        return (
            reflectance.reshape(*batch, height, width, 31),
            lab.reshape(*batch, height, width, 3),
            quality.reshape(*batch, height, width),
        )

    return outputs(*arrays)


__all__ = [
    "TARGET", "MAX_BANDS", "SWITCH", "SWITCH_VALUES", "AUTO", "PORTABLE", "built", "enabled", "mode", "switch",
    "unavailable_reason",
    "correct_pixels", "correct_arrays", "kernel_constants",
]
