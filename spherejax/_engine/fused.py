"""The fused CPU kernel of `correct`'s per-pixel step: its calls, from XLA and directly.

This module is the kernel as `kernels.FusedCpu` runs it: the XLA custom call with its batching
rule and custom JVP (`correct_pixels`), and the direct call on NumPy arrays (`correct_arrays`).
The rest of the fused kernel, by job: `fused_extension` (loading the compiled extension,
registering it with XLA, what it declares it supports), `fused_variants` (which instruction-set
variant runs: the SPHEREJAX_FUSED switch and the measurement), `fused_constants` (the
calibration's arrays as the kernel takes them). Their public names are re-exported here.

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
the kernel too (`residual_constants`: its whitening, inducing points and rank-8 weights), where
every variant computes a block's outputs many pixels a vector with one residual template
(fused_correct.h, `residual_of`, the variant's lanes a policy of it): 2.2-2.7 times the affine
calibration's time at 1024 x 1024 x 16 on 2 Zen 4 cores (benchmarks/bench_kernel_contract.py).
A traced calibration and a residual of rank above 8 take the jax.numpy path (the kernel contract,
`spherejax._engine.kernels`, reading what the extension declares: `capabilities`).

With `intermediates=True` the main outputs still come from the kernel, so that they do not depend
on what else was asked for; the cubes it never forms (v, v_stage1, v_stage2) come from the
jax.numpy path, whose own reflectance and Lab XLA then drops as unused.

NumPy frames given to `correct` (whole frames, concrete calibration, nothing but the main outputs
asked for) go to the kernel without XLA (`correct_arrays`, from `plan.Plan._correct_directly`): XLA
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
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .fused_constants import RESIDUAL_RANK, kernel_constants, residual_constants, residual_fits
from .fused_extension import TARGET, _fused_correct, built, capabilities, register, supported_variants
from .fused_variants import (
    AUTO,
    AVX2,
    AVX512,
    GENERIC,
    MARGIN,
    MAX_BANDS,
    PORTABLE,
    PROBE_PIXELS,
    PROBE_REPEATS,
    RAW_DTYPES,
    SWITCH,
    SWITCH_VALUES,
    VARIANT_BANDS,
    VARIANTS,
    Measurement,
    VariantChoice,
    choose_variant,
    enabled,
    measure_variants,
    measurement,
    mode,
    resolve,
    switch,
    unavailable_reason,
    variant,
    variant_code,
)


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
    register()
    images, pixels, _ = raw.shape
    out_types = (
        jax.ShapeDtypeStruct((images, pixels, 31), jnp.float32),
        jax.ShapeDtypeStruct((images, pixels, 3), jnp.float32),
        jax.ShapeDtypeStruct((images, pixels), jnp.uint8),
    )
    call = jax.ffi.ffi_call(TARGET, out_types, vmap_method="sequential")
    # NaN saturation: the kernel's `value >= saturation` is then never true, i.e. no check.
    level = np.float32(np.nan if saturation is None else saturation)
    code = np.int32(variant_code(resolve(kernel_mode, raw.shape[2])))
    return call(raw, dark, white, p, coeffs, projection, bias, white_xyz, whitening, inducing, factor, basis,
                saturation=level, variant=code)


def correct_arrays(raw: np.ndarray, dark: np.ndarray, white: np.ndarray, p: np.ndarray, coeffs: np.ndarray,
                   projection: np.ndarray, bias: np.ndarray, white_xyz: np.ndarray, saturation: float | None,
                   kernel_mode: str, out: tuple[np.ndarray, np.ndarray, np.ndarray], threads: int,
                   residual: tuple[np.ndarray, ...] | None = None,
                   registration: tuple[np.ndarray, np.ndarray, int, int] | None = None) -> None:
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
      registration: for a calibration with band maps, (inverse_signal (P, B), maps (B, 2, 3),
        height, width): raw and dark are then the native frames, inverse_signal their
        `fused_registration.inverse_signal`, and each row is registered into the reference band's
        geometry before it is corrected, inside the kernel's own loop (kernel/call.h,
        register_bands_first; white is not read). None: the frames are corrected as they are.

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
    if registration is not None:
        inverse, maps, height, width = registration
        expected["inverse_signal"] = (inverse, np.float32, (pixels, bands))
        expected["maps"] = (maps, np.float32, (bands, 2, 3))
        registration = (inverse, maps, int(height), int(width))
    for name, (array, dtype, shape) in expected.items():
        if array.dtype != dtype or array.shape != shape or not array.flags.c_contiguous:
            raise ValueError(f"{name}: expected a C-contiguous {np.dtype(dtype)} array of shape {shape}, "
                             f"got {array.dtype} {array.shape}")
    level = np.float32(np.nan if saturation is None else saturation)  # NaN: no check
    code = variant_code(resolve(kernel_mode, bands))
    _fused_correct.correct_arrays(
        raw, raw.dtype == np.uint16, dark, white, p, coeffs, projection, bias, white_xyz, whitening, inducing,
        factor, basis, images, pixels, bands, whitened_rows, inducing_rows, float(level), code, int(threads), *out,
        registration,
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

    return compiled_on_cpu(plain, on_cpu, *arrays)


def compiled_on_cpu(definition: Callable, on_cpu: Callable, *arrays):
    """`on_cpu(*arrays)` (a compiled custom call) on CPU and `definition(*arrays)` elsewhere
    (`jax.lax.platform_dependent`, decided when lowered), with the definition's JVP everywhere:
    derivatives are the jax.numpy definition's whichever runs."""
    @jax.custom_jvp
    def outputs(*arrays):
        return jax.lax.platform_dependent(*arrays, cpu=on_cpu, default=definition)

    @outputs.defjvp
    def outputs_jvp(primals, tangents):
        _, tangents_out = jax.jvp(definition, primals, tangents)
        return outputs(*primals), tangents_out

    return outputs(*arrays)


__all__ = [
    "AUTO", "AVX2", "AVX512", "GENERIC", "MARGIN", "MAX_BANDS", "PORTABLE", "PROBE_PIXELS", "PROBE_REPEATS",
    "RAW_DTYPES", "RESIDUAL_RANK", "SWITCH", "SWITCH_VALUES", "TARGET", "VARIANTS", "VARIANT_BANDS", "Measurement",
    "VariantChoice", "built", "capabilities", "choose_variant", "compiled_on_cpu", "correct_arrays", "correct_pixels", "enabled",
    "kernel_constants", "measure_variants", "measurement", "mode", "register", "residual_constants",
    "residual_fits", "resolve", "supported_variants", "switch", "unavailable_reason", "variant", "variant_code",
]
