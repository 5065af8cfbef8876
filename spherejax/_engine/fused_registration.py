"""The band registration (`spherejax.band_resampling.registered_frames`) on CPU as a compiled
custom call ("spherejax_register_bands", kernel/register_bands.cc), with the jax.numpy
definition's JVP and the definition itself off the CPU.

Why: XLA's CPU gather, which the definition's bilinear taps become, takes about 1 ns an element:
250 ms a megapixel of 16 bands on 2 Zen 4 cores for the registration alone, ten times the
correction after it. The loop reads each tap where it lies (benchmarks/README.md, "Bands in
register"). It computes the definition's values (float32, the same operations; products by the
inverse white signal where the definition divides, so equal to a few ulps) and the same bits.

`registered_frames(...)` is what `spherejax._engine.registered.registration_step` calls when the
plan's frames and calibration suit the kernel (`applies`): float32, uint16 or float32 raw, the
extension built and registered with XLA, the fused kernels' switch not off.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import band_resampling
from . import fused
from .fused_extension import _fused_correct

#: The name the registration is registered under with XLA (jax.ffi).
TARGET = "spherejax_register_bands"


@functools.cache
def _registered_with_xla() -> bool:
    """Register the handler once per process (after the fused correction's: the CPU backend is
    up and XLA took the extension); False where it cannot be."""
    if not fused.register() or not hasattr(_fused_correct, "registration_handler"):
        return False
    try:
        jax.ffi.register_ffi_target(TARGET, _fused_correct.registration_handler(), platform="cpu")
    except Exception:  # noqa: BLE001 -- XLA's refusal: the definition runs instead
        return False
    return True


def applies(raw_dtype, compute_dtype, bands: int) -> bool:
    """True if the compiled registration takes frames of `raw_dtype` computed in `compute_dtype`
    with `bands` bands in this process (where the fused correction would: `fused.mode`)."""
    if np.dtype(compute_dtype) != np.float32 or np.dtype(raw_dtype).name not in ("uint16", "float32"):
        return False
    if bands > 256 or fused.mode(raw_dtype, compute_dtype, bands) is None:
        return False
    return _registered_with_xla()


@jax.jit
def inverse_signal(dark, white):
    """1 / (white - dark) where that is finite and > 0, else 0 (no flat field): (H, W, B)."""
    signal = white - dark
    usable = (signal > 0) & jnp.isfinite(signal)
    return jnp.where(usable, 1 / jnp.where(usable, signal, 1), 0)


def _ffi(raw, dark, inverse, registered_signal, transforms, *, saturation):
    height, width, bands = dark.shape
    images = int(np.prod(raw.shape[:-3], dtype=np.int64))
    out_types = (
        jax.ShapeDtypeStruct((images, height, width, bands), jnp.float32),
        jax.ShapeDtypeStruct((images, height, width), jnp.uint8),
    )
    call = jax.ffi.ffi_call(TARGET, out_types, vmap_method="sequential")
    level = np.float32(np.nan if saturation is None else saturation)  # NaN: no check
    frames, bits = call(raw.reshape(images, height, width, bands), dark, inverse, registered_signal,
                        transforms.astype(jnp.float32).reshape(bands, 6), saturation=level)
    return frames.reshape(*raw.shape[:-3], height, width, bands), bits.reshape(*raw.shape[:-3], height, width)


def registered_frames(raw, dark, white, inverse, transforms, registered_signal, *, saturation):
    """`band_resampling.registered_frames(raw, dark, white, transforms, registered_signal,
    saturation=saturation)` by the compiled loop on CPU (`inverse` = `inverse_signal(dark,
    white)`, made once by the plan), the definition elsewhere; the definition's JVP everywhere."""
    def definition(raw, dark, white, inverse, transforms, registered_signal):
        del inverse  # made from dark and white, whose tangents the definition carries
        return band_resampling.registered_frames(raw, dark, white, transforms, registered_signal,
                                                 saturation=saturation)

    def on_cpu(raw, dark, white, inverse, transforms, registered_signal):
        return _ffi(raw, dark, inverse, registered_signal, transforms, saturation=saturation)

    return fused.compiled_on_cpu(definition, on_cpu, raw, dark, white, inverse, transforms, registered_signal)


__all__ = ["TARGET", "applies", "inverse_signal", "registered_frames"]
