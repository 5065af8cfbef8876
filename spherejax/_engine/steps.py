"""The jitted steps of a correction, as functions of prepared constants (`PixelConstants`,
`PatchConstants`) rather than of a `Calibration`: one compiled program per signature (shapes,
dtypes, the patch box's shape and the static options), whichever calibration it serves.

    patch_ratio_step   raw frames (or their patch box) -> p (..., B)        Eq. 14-15
    patch_ratio_std_step                              -> u(p) (..., B)
    pixels_step        raw, p -> reflectance, Lab, quality (+ intermediates, + uncertainties)
    image_step         both, traced together: one dispatch, no wait between them
    image_step_into    image_step writing into the memory of donated outputs (CPU, `buffers`)

The equations are `spherejax.equations`'s (`pixel_outputs`, `patch_ratio_of_box`); which kernel
runs the per-pixel part is the plan's choice (`kernels.choose`), passed in as the static `kernel`
(a `kernels.PixelKernel`), so that each kernel compiles its own program.

jax.jit rather than eqx.filter_jit: every array is a leaf and everything else static, so plain
jit applies, and its C++ dispatch saves about 0.3 ms a call (6 % of a 256 x 256 correction).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from .. import equations, uncertainty
from ..correction_result import CorrectionResult
from ..pixel_constants import PatchConstants, PixelConstants
from . import kernels


def box_of_frames(raw, box_origin, box_shape):
    """raw (..., H, W, B) cut to the patch's box (..., h, w, B), the origin (2,) an argument and
    the shape static, so that patches of one size share a compiled program."""
    height, width = box_shape
    lead = raw.ndim - 3
    zero = jnp.zeros((), box_origin.dtype)  # dynamic_slice wants one index dtype
    start = (zero,) * lead + (box_origin[0], box_origin[1], zero)
    return jax.lax.dynamic_slice(raw, start, (*raw.shape[:lead], height, width, raw.shape[-1]))


@functools.partial(jax.jit, static_argnames=("box_shape", "saturation", "raw_is_box"))
def patch_ratio_step(raw, patch: PatchConstants, box_origin, *, box_shape, saturation, raw_is_box: bool = False):
    """Eq. 14-15 over the usable pixels of the patch's box: p (..., B) in the compute dtype.

    `correct` traces this same function into its own program, so the ratio it uses is the one
    `patch_ratio` returns, bit for bit (strips rely on it). raw_is_box: raw is already the box of
    the frames, (..., h, w, B) (the fused kernel's direct route)."""
    raw_box = raw if raw_is_box else box_of_frames(raw, box_origin, box_shape)
    return equations.patch_ratio_of_box(raw_box, patch, saturation)


@functools.partial(jax.jit, static_argnames=("box_shape", "saturation"))
def patch_ratio_std_step(raw, patch: PatchConstants, noise, box_origin, *, box_shape, saturation):
    """u(p) (..., B) over the same pixels as `patch_ratio_step` (`uncertainty.patch_ratio_std`)."""
    raw_f, weights = equations.patch_box_inputs(box_of_frames(raw, box_origin, box_shape), patch, saturation)
    return uncertainty.patch_ratio_std(raw_f, patch.dark, patch.white, weights, noise)


def _pixels_plain(raw, p, constants: PixelConstants, *, saturation, intermediates, kernel, out=None,
                  no_flat_field=None, prepared=None) -> CorrectionResult:
    """`pixels_step` without uncertainties (traced inside it): the plan's kernel, and with
    `intermediates` the cubes it never forms (v, v_stage1, v_stage2) from the definition, whose
    own reflectance and Lab XLA drops as unused. The main outputs stay the kernel's whatever else
    is asked for."""
    p = p.astype(constants.dtype)
    if intermediates:
        reflectance, lab, quality, *cubes = equations.pixel_outputs(
            raw, p, constants, saturation=saturation, intermediates=True, no_flat_field=no_flat_field
        )
        if kernel != kernels.DEFINITION:
            reflectance, lab, quality = kernel.pixel_outputs(raw, p, constants, saturation=saturation,
                                                             prepared=prepared)
        return CorrectionResult(reflectance, lab, quality, p, *cubes)
    reflectance, lab, quality = kernel.pixel_outputs(
        raw, p, constants, saturation=saturation, out=out, no_flat_field=no_flat_field, prepared=prepared
    )
    return CorrectionResult(reflectance, lab, quality, p)


@functools.partial(jax.jit, static_argnames=("saturation", "intermediates", "kernel"))
def pixels_step(raw, p, constants: PixelConstants, *, saturation, intermediates: bool, kernel: kernels.PixelKernel,
                noise=None, p_u=None, out=None, no_flat_field=None, prepared=None) -> CorrectionResult:
    """Every pixel of `raw` (..., H, W, B) given the white-patch ratio p (..., B).

    `kernel` (static): the per-pixel kernel the plan chose (`kernels.choose`). With a
    `NoiseModel` (and p's uncertainty p_u (..., B)) the result also carries the uncertainties
    (`uncertainty.pixel_uncertainty`); None traces none of that. `out`: None, or donated arrays
    of the three outputs' shapes whose memory the jax.numpy path's outputs take on CPU
    (`pixel_outputs_in_blocks`; the kernel's take it through XLA's buffer assignment).
    no_flat_field: None, or the constants' (H, W) `_no_flat_field` mask, which the jax.numpy path
    then reads instead of working it out from dark and white again. prepared: the kernel's
    constants made once by the plan (`kernels.PixelKernel.prepare`), or None.
    """
    result = _pixels_plain(
        raw, p, constants, saturation=saturation, intermediates=intermediates, kernel=kernel, out=out,
        no_flat_field=no_flat_field, prepared=prepared,
    )
    if noise is None:
        return result
    c = constants
    p_u = p_u.astype(c.dtype)
    reflectance_u, lab_covariance = uncertainty.pixel_uncertainty(
        raw.astype(c.dtype), (result.quality == 0)[..., None], result.p, p_u, c, noise
    )
    lab_u = jnp.sqrt(jnp.diagonal(lab_covariance, axis1=-2, axis2=-1))
    return dataclasses.replace(
        result, reflectance_u=reflectance_u, lab_u=lab_u, lab_covariance=lab_covariance, p_u=p_u
    )


@functools.partial(jax.jit, static_argnames=("box_shape", "saturation", "intermediates", "kernel"))
def image_step(raw, constants: PixelConstants, patch: PatchConstants, box_origin, *, box_shape, saturation,
               intermediates: bool, kernel: kernels.PixelKernel, noise=None, out=None,
               no_flat_field=None, prepared=None) -> CorrectionResult:
    """`correct` of whole frames as one program: p over the patch's box, then every pixel.

    The same two steps as `patch_ratio_step` then `pixels_step`, traced together: one dispatch
    instead of two and no wait between them, 1.5-2.5 ms a call (benchmarks/README.md).
    """
    p = patch_ratio_step(raw, patch, box_origin, box_shape=box_shape, saturation=saturation)
    p_u = None
    if noise is not None:
        p_u = patch_ratio_std_step(raw, patch, noise, box_origin, box_shape=box_shape, saturation=saturation)
    return pixels_step(
        raw, p, constants, saturation=saturation, intermediates=intermediates, kernel=kernel, noise=noise,
        p_u=p_u, out=out, no_flat_field=no_flat_field, prepared=prepared,
    )


# keep_unused: jit would otherwise drop the unused donated arguments from the program, and their
# memory with them.
@functools.partial(
    jax.jit, static_argnames=("box_shape", "saturation", "kernel"),
    donate_argnames=("out_reflectance", "out_lab", "out_quality"), keep_unused=True,
)
def image_step_into(raw, constants: PixelConstants, patch: PatchConstants, box_origin, out_reflectance, out_lab,
                    out_quality, no_flat_field=None, *, box_shape, saturation, kernel: kernels.PixelKernel):
    """`image_step` with the memory of three donated arrays of the outputs' shapes and dtypes
    (dropped outputs of earlier calls, `spherejax._engine.buffers`): their values are not read,
    and their memory becomes the outputs' (XLA's buffer assignment gives it to the kernel's
    outputs of the same shapes; the jax.numpy path's loop writes its blocks into them). The same
    program otherwise, and the same numbers."""
    out = (out_reflectance, out_lab, out_quality)
    return image_step(
        raw, constants, patch, box_origin, box_shape=box_shape, saturation=saturation, intermediates=False,
        kernel=kernel, out=out, no_flat_field=no_flat_field,
    )
