"""The per-pixel equations of a correction in jax.numpy: the definition every kernel is tested
against (`spherejax._engine.kernels`), and what runs where no compiled kernel applies.

    raw (..., H, W, B) uint16 or float
      -> quality bits (`spherejax.quality`: saturated, non-finite, no flat field, below dark,
         unusable patch)
      -> v = flat field (Eq. 10)            with the calibration's dark frame and white standard
      -> p = white-patch ratio (Eq. 14-15)  over the patch's usable pixels (`patch_ratio_of_box`)
      -> v_tilde = Stage I and II (Eq. 16-17, 23)
      -> reflectance = W v_tilde + r0 (+ A k(v_tilde), the kernel residual E8)
      -> Lab under the calibration's illuminant (ASTM E308 XYZ, perfect-diffuser white)
      -> quality bit 2 and NaN where an output of a good pixel is not finite (`flag_nonfinite_outputs`)

For Lab the Wiener matrix and the XYZ weights are folded into one (B, 3) matrix, so XYZ is
computed from v_tilde directly; that equals reflectance @ weights up to rounding (tested). The
estimator's offset r0 is folded the same way: XYZ = v_tilde (W^T weights) + r0 weights.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .colorimetry import xyz_to_lab
from .flatfield import flat_field_unchecked, patch_ratio_weighted
from .pixel_constants import PatchConstants, PixelConstants
from .polynomial import stage2_unchecked
from .quality import (
    BELOW_DARK_LIMIT,
    QUALITY_BELOW_DARK,
    QUALITY_NONFINITE,
    QUALITY_PATCH_UNUSABLE,
    QUALITY_SATURATED,
    QUALITY_WHITE_NOT_ABOVE_DARK,
)

_HIGHEST = jax.lax.Precision.HIGHEST


def pixel_flags(raw, raw_f, dark, white, saturation, no_flat_field=None):
    """Per-pixel (saturated, non-finite, no flat field, below dark) flags, each (..., H, W) bool.

    A pixel is flagged if any band is: reflectance mixes all bands. +inf counts as non-finite,
    not as saturated, so the bits say what went wrong. no_flat_field: `flat_field_unusable(dark,
    white)` when the caller already has it (`_flat_field_mask`), else None. Below dark: the
    flat-fielded response (raw - dark) / (white - dark) of some band with a finite raw value and a
    usable flat field is below -BELOW_DARK_LIMIT, computed as Eq. 10 computes it, so that the
    fused kernel's bits are these bits.
    """
    pixel_shape = jnp.broadcast_shapes(raw.shape, dark.shape)[:-1]
    if jnp.issubdtype(raw.dtype, jnp.integer):
        nonfinite = jnp.zeros(pixel_shape, dtype=bool)  # counts are always finite: skip a pass
    else:
        nonfinite = jnp.any(~jnp.isfinite(raw_f), axis=-1)
    if saturation is None:
        saturated = jnp.zeros(pixel_shape, dtype=bool)
    else:
        saturated = jnp.any(jnp.isfinite(raw_f) & (raw_f >= saturation), axis=-1)
    if no_flat_field is None:
        no_flat_field = flat_field_unusable(dark, white)
    # Finite values of v only: a raw -inf is non-finite (bit 2), not below dark, as +inf is not
    # saturated, and v is NaN where the flat field is unusable (bit 4). One minimum over the bands
    # with the others replaced by +inf, not `any` of a comparison: XLA's CPU code for `any` over
    # the short band axis doubled the jax.numpy path's time (67 -> 130 ms a megapixel), the minimum
    # costs a few percent (`flat_field_unusable` says the same of its own reduction).
    v = flat_field_unchecked(raw_f, dark, white)
    below_dark = jnp.min(jnp.where(jnp.isfinite(v), v, jnp.inf), axis=-1) < -BELOW_DARK_LIMIT
    return saturated, nonfinite, jnp.broadcast_to(no_flat_field, pixel_shape), below_dark


def flat_field_unusable(dark, white):
    """(..., H, W) bool: True where some band's white signal (white - dark) is not both finite
    and above 0.

    The same as `jnp.any(~flatfield.white_signal_usable(dark, white), axis=-1)`, written as one
    minimum over the bands, of the white signal with every non-finite value replaced by -1:
    XLA's CPU code for `any` over the short band axis measured 3x slower (17 ms against 5 ms per
    megapixel, 16 bands). The replacement comes first because the minimum kernel XLA uses on CPU
    (YNNPACK) does not propagate NaN from every position (found by the tests).
    """
    white_signal = white - dark
    return ~(jnp.min(jnp.where(jnp.isfinite(white_signal), white_signal, -1.0), axis=-1) > 0)



def patch_flags(raw, raw_f, dark, white, saturation):
    saturated, nonfinite, no_flat_field, below_dark = pixel_flags(raw, raw_f, dark, white, saturation)
    return saturated | nonfinite | no_flat_field | below_dark


def patch_box_inputs(raw_box, patch: PatchConstants, saturation):
    """The inputs of Eq. 14-15 over the patch's box: raw (..., h, w, B) in the compute dtype and
    the weights (..., h, w) with unusable pixels at 0.

    raw_box: the frames over the box, (..., h, w, B), raw counts; patch: the calibration over
    the same box (`PatchConstants`); saturation: `calibration.saturation_level`.
    """
    raw_f = raw_box.astype(patch.dark.dtype)
    # One saturated or non-finite pixel in the patch must not shift p for the whole image.
    bad = patch_flags(raw_box, raw_f, patch.dark, patch.white, saturation)
    weights = jnp.where(bad, 0.0, patch.weights)
    return raw_f, weights


def patch_ratio_of_box(raw_box, patch: PatchConstants, saturation):
    """Eq. 14-15 over the usable pixels of the patch's box: p (..., B) in the compute dtype.
    Pixels of weight 0 in the box add nothing to the ratio, so the crop is exact."""
    raw_f, weights = patch_box_inputs(raw_box, patch, saturation)
    return patch_ratio_weighted(raw_f, patch.dark, patch.white, weights[..., None])


@jax.custom_jvp
def project_good_pixels(good, v, matrix, bias):
    """v @ matrix + bias for good pixels and NaN in every output channel of the others.

    Args:
      good: (..., H, W, 1) bool.
      v: (..., H, W, B), finite everywhere (0 on bad pixels: the safe-where convention).
      matrix: (B, K).
      bias: (K,), added to every good pixel's product (the affine estimator's offset).

    Returns:
      (..., H, W, K).

    Why not `jnp.where(good, v @ matrix, nan)`: XLA on CPU does not fuse an elementwise step
    into a matmul's output, so that `where` is one more pass over the 31-channel reflectance
    (124 MB a megapixel). NaN put into v's rows before the product (a pass XLA does fuse, into
    the Stage II step) comes out in every channel of the row, whatever the matrix holds, because
    NaN x anything is NaN (tested). The custom JVP keeps the derivative of the masked form,
    which is 0 on bad pixels; differentiating the NaN rows would give NaN x 0 = NaN.

    The bias is added after the product: x + 0 == x, so a zero bias leaves the product's bits
    as they were (only a -0 would become +0), and NaN + bias keeps bad pixels NaN. It costs one
    more elementwise pass over the output, which XLA on CPU does not fuse into the matmul:
    about 15 ms a megapixel on 2 cores (70 -> 85 ms). Folding the bias into the product as a
    row of the matrix against a column of ones costs nothing, but changes the product's
    rounding for most band counts (XLA picks another dot kernel for K + 1), so a zero offset
    would no longer give the bits of the plain linear estimate W v_tilde. The CPU kernel of
    `spherejax._engine.fused`, the default path in float32, starts its accumulators at the bias instead,
    for free.
    """
    return jnp.matmul(jnp.where(good, v, jnp.nan), matrix, precision=_HIGHEST) + bias


@project_good_pixels.defjvp
def _project_good_pixels_jvp(primals, tangents):
    good, v, matrix, bias = primals
    _, v_dot, matrix_dot, bias_dot = tangents
    out = project_good_pixels(good, v, matrix, bias)
    out_dot = (
        jnp.matmul(v_dot, matrix, precision=_HIGHEST) + jnp.matmul(v, matrix_dot, precision=_HIGHEST) + bias_dot
    )
    return out, jnp.where(good, out_dot, 0.0)


def quality_bits(raw, raw_f, dark, white, p, saturation, no_flat_field=None):
    """(..., H, W) uint8 bit mask of the QUALITY_* flags (no_flat_field: see `pixel_flags`)."""
    saturated, nonfinite, no_flat_field, below_dark = pixel_flags(raw, raw_f, dark, white, saturation, no_flat_field)
    patch_unusable = jnp.any(~jnp.isfinite(p), axis=-1)  # (...,)
    return (
        saturated.astype(jnp.uint8) * QUALITY_SATURATED
        | nonfinite.astype(jnp.uint8) * QUALITY_NONFINITE
        | no_flat_field.astype(jnp.uint8) * QUALITY_WHITE_NOT_ABOVE_DARK
        | below_dark.astype(jnp.uint8) * QUALITY_BELOW_DARK
        | jnp.broadcast_to(patch_unusable[..., None, None], saturated.shape).astype(jnp.uint8)
        * QUALITY_PATCH_UNUSABLE
    )


def flag_nonfinite_outputs(reflectance, lab, quality):
    """(reflectance, lab, quality) with every pixel of quality 0 whose reflectance (..., 31) or
    Lab (..., 3) holds a value that is not finite flagged `QUALITY_NONFINITE` and made NaN in both.

    Why. The flags describe the inputs; finite inputs can still give outputs that are not finite:
    a raw value of 1e38 over a white signal of one count, or an estimator whose product overflows
    float32 (weights of 3e38 in a calibration made without its checks), gave reflectance up to
    infinity with quality 0. Every kernel (the fused CPU kernel's flag_nonfinite_outputs, the
    Pallas GPU kernel) applies this same rule to its own outputs, so that every output is NaN
    exactly where quality says so.

    x * 0 is +-0 for a finite x and NaN otherwise: one sum over the channels tells, without the
    slower `any` over a short axis (`pixel_flags`) and without overflow. The test is made on the
    values alone (no derivative flows through it), so gradients stay those of the outputs.
    """
    probe = jnp.sum(reflectance * 0.0, axis=-1) + jnp.sum(lab * 0.0, axis=-1)
    overflowed = (quality == 0) & ~jnp.isfinite(jax.lax.stop_gradient(probe))
    quality = quality | overflowed.astype(jnp.uint8) * QUALITY_NONFINITE
    keep = ~overflowed[..., None]
    return jnp.where(keep, reflectance, jnp.nan), jnp.where(keep, lab, jnp.nan), quality


def pixel_outputs(raw, p, constants: PixelConstants, *, saturation, intermediates=False, no_flat_field=None):
    """The per-pixel path in jax.numpy: the definition the fused CPU kernel is tested against.

    Args: raw (..., H, W, B) counts or floats; p (..., B) and the constants (`PixelConstants`,
    H and W those of raw) in the compute dtype; saturation: `calibration.saturation_level`. no_flat_field:
    None, or the (H, W) bool `flat_field_unusable(constants.dark, constants.white)` worked out once
    (`spherejax._engine.plan`).

    reflectance = v_tilde W^T + r0 and XYZ = v_tilde (W^T weights) + r0 weights, the latter
    being reflectance @ weights (ASTM E308) regrouped so that the 31-channel cube is not read
    back; both on good pixels only.

    Returns (reflectance, lab, quality), then v, v_stage1 and v_stage2 if `intermediates`.
    """
    dark, white = constants.dark, constants.white
    dtype = dark.dtype
    raw_f = raw.astype(dtype)
    quality = quality_bits(raw, raw_f, dark, white, p, saturation, no_flat_field)
    good = (quality == 0)[..., None]

    p_pixel = p[..., None, None, :]
    v = flat_field_unchecked(raw_f, dark, white)
    # Safe-where: bad pixels continue as 0 and become NaN in the projections below. A NaN
    # carried into Stage II would make d(output)/d(coeffs) NaN even where the cotangent is 0.
    v_safe = jnp.where(good, v, 0.0)
    v_stage2_safe = stage2_unchecked(v_safe, p_pixel, constants.coeffs)

    # Lab from v_tilde through the folded (B, 3) matrix W^T @ weights: XYZ never goes through the
    # 31-channel cube. (One (B, 34) matmul sliced into the two outputs measured twice as slow:
    # the slices are copies.)
    reflectance = project_good_pixels(good, v_stage2_safe, constants.wiener.T, constants.wiener_offset)
    xyz = project_good_pixels(good, v_stage2_safe, *constants.xyz_projection())
    if constants.wiener_residual is not None:
        # The kernel residual (E8) of every good pixel, and its XYZ; the bad ones stay NaN through
        # the affine part. Safe-where on both sides: v_stage2_safe is NaN on every pixel of an image
        # whose p is not finite, and a NaN inside the kernel would make d(output)/d(weights) NaN.
        residual = jnp.where(good, constants.wiener_residual(jnp.where(good, v_stage2_safe, 0.0)), 0.0)
        reflectance = reflectance + residual
        xyz = xyz + jnp.matmul(residual, constants.tristimulus_weights, precision=_HIGHEST)
    lab = xyz_to_lab(xyz, constants.white_xyz())
    reflectance, lab, quality = flag_nonfinite_outputs(reflectance, lab, quality)
    if not intermediates:
        return reflectance, lab, quality
    good = (quality == 0)[..., None]  # without the pixels whose outputs overflowed
    v_out = jnp.where(good, v, jnp.nan)
    v_stage2_out = jnp.where(good, v_stage2_safe, jnp.nan)
    return reflectance, lab, quality, v_out, v_out * p_pixel, v_stage2_out


__all__ = [
    "pixel_flags", "flat_field_unusable", "patch_flags", "patch_box_inputs", "patch_ratio_of_box", "project_good_pixels",
    "quality_bits", "flag_nonfinite_outputs", "pixel_outputs",
]
