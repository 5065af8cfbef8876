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
import numpy as np

from .. import equations, uncertainty
from ..correction_result import CorrectionResult
from ..grid import N_WAVELENGTHS
from ..pixel_constants import PatchConstants, PixelConstants
from . import kernels

#: Pixels per block of the jax.numpy path on CPU (`pixel_outputs_in_blocks`): a block's
#: intermediates (16 + 34 channels of float32, about 3.5 MB) stay in the L2/L3 caches.
CPU_BLOCK_PIXELS = 16384


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


def pixel_outputs_in_blocks(raw, p, constants: PixelConstants, *, saturation, out=None,
                            block_pixels=CPU_BLOCK_PIXELS, no_flat_field=None):
    """`equations.pixel_outputs` (without intermediates) over blocks of `CPU_BLOCK_PIXELS` pixels
    in one XLA loop: the jax.numpy path as it runs on CPU.

    Why. XLA on CPU does not fuse the Wiener projection (a matmul) with the elementwise steps
    around it, so on a whole image the Stage II cube (64 MB a megapixel) and the projections
    before their offset (136 MB) are written to memory and read back, and XLA allocates those
    temporaries afresh on every call, from pages the kernel must fault and zero (glibc maps
    blocks that large). Block by block the same steps stay in cache and the temporaries are a
    few MB, which malloc reuses.

    Each block runs `_pixel_outputs` on (N, 1, S, B) rows of pixels: the same equations on
    every pixel, and the same numbers as the whole image up to the matmul's rounding (tested).

    Args: raw (..., H, W, B); p (..., B); constants in the compute dtype; out: None, or arrays of
    the outputs' shapes and dtypes whose memory the outputs take (donated; their values are
    never read). Without them the outputs start as zeros (one write pass). block_pixels: pixels
    per block, over all images of a batch (each block takes the same rows of every image).
    no_flat_field: None, or the (H, W) bool `equations.flat_field_unusable` of the constants' frames.

    Returns (reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W)).
    """
    *batch, height, width, bands = raw.shape
    pixels = height * width
    images = int(np.prod(batch, dtype=np.int64))
    block = max(1, block_pixels // max(images, 1))
    plain = functools.partial(equations.pixel_outputs, saturation=saturation, intermediates=False)
    if block >= pixels or images == 0:
        return plain(raw, p, constants, no_flat_field=no_flat_field)
    dtype = constants.dtype
    raw_rows = raw.reshape(images, pixels, bands)
    dark_rows, white_rows = constants.dark.reshape(pixels, bands), constants.white.reshape(pixels, bands)
    p_rows = jnp.broadcast_to(p, (*batch, bands)).reshape(images, bands)
    mask_rows = None if no_flat_field is None else no_flat_field.reshape(pixels)

    def outputs_of(start, size):
        def rows(x, axis):
            return jax.lax.dynamic_slice_in_dim(x, start, size, axis=axis)

        reflectance, lab, quality = plain(
            rows(raw_rows, 1)[:, None], p_rows, constants.pixels(rows(dark_rows, 0)[None], rows(white_rows, 0)[None]),
            no_flat_field=None if mask_rows is None else rows(mask_rows, 0)[None],
        )
        return reflectance[:, 0], lab[:, 0], quality[:, 0]

    def put_computed(outputs, start, computed):
        return tuple(jax.lax.dynamic_update_slice_in_dim(o, x, start, axis=1) for o, x in zip(outputs, computed))

    def put(outputs, start, size):
        return put_computed(outputs, start, outputs_of(start, size))

    if out is None:
        out = (
            jnp.zeros((images, pixels, N_WAVELENGTHS), dtype), jnp.zeros((images, pixels, 3), dtype),
            jnp.zeros((images, pixels), jnp.uint8),
        )
    else:
        out = tuple(o.reshape(images, pixels, *o.shape[len(batch) + 2:]) for o in out)
    # Each turn of the loop corrects one block of each half of the pixels: two chains of steps
    # that depend on nothing of each other, which XLA's executor hands to its two threads
    # whole. With one block a turn the second thread joined only inside each step (a matmul's
    # or a fusion's parallel parts), hundreds of times a call, and after a pause of 0.1 s or
    # more (a frame read from disk) it joined late for most of them: on 2 Zen 5 cores the first
    # call after a pause took 47-51 ms a megapixel that way against 35-39 this way, and back to
    # back 34 against 32 (benchmarks/README.md). The blocks are the same, so the numbers are.
    whole_blocks, rest = divmod(pixels, block)
    per_half = whole_blocks // 2

    def two_blocks(k, outputs):
        first, second = outputs_of(k * block, block), outputs_of((per_half + k) * block, block)
        return put_computed(put_computed(outputs, k * block, first), (per_half + k) * block, second)

    out = jax.lax.fori_loop(0, per_half, two_blocks, out)
    for k in range(2 * per_half, whole_blocks):  # an odd block out
        out = put(out, k * block, block)
    if rest:
        out = put(out, whole_blocks * block, rest)
    reflectance, lab, quality = out
    return (
        reflectance.reshape(*batch, height, width, N_WAVELENGTHS), lab.reshape(*batch, height, width, 3),
        quality.reshape(*batch, height, width),
    )


def _pixels_plain(raw, p, constants: PixelConstants, *, saturation, intermediates, kernel, out=None,
                  no_flat_field=None) -> CorrectionResult:
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
            reflectance, lab, quality = kernel.pixel_outputs(raw, p, constants, saturation=saturation)
        return CorrectionResult(reflectance, lab, quality, p, *cubes)
    reflectance, lab, quality = kernel.pixel_outputs(
        raw, p, constants, saturation=saturation, out=out, no_flat_field=no_flat_field
    )
    return CorrectionResult(reflectance, lab, quality, p)


@functools.partial(jax.jit, static_argnames=("saturation", "intermediates", "kernel"))
def pixels_step(raw, p, constants: PixelConstants, *, saturation, intermediates: bool, kernel: kernels.PixelKernel,
                noise=None, p_u=None, out=None, no_flat_field=None) -> CorrectionResult:
    """Every pixel of `raw` (..., H, W, B) given the white-patch ratio p (..., B).

    `kernel` (static): the per-pixel kernel the plan chose (`kernels.choose`). With a
    `NoiseModel` (and p's uncertainty p_u (..., B)) the result also carries the uncertainties
    (`uncertainty.pixel_uncertainty`); None traces none of that. `out`: None, or donated arrays
    of the three outputs' shapes whose memory the jax.numpy path's outputs take on CPU
    (`pixel_outputs_in_blocks`; the kernel's take it through XLA's buffer assignment).
    no_flat_field: None, or the constants' (H, W) `_no_flat_field` mask, which the jax.numpy path
    then reads instead of working it out from dark and white again.
    """
    result = _pixels_plain(
        raw, p, constants, saturation=saturation, intermediates=intermediates, kernel=kernel, out=out,
        no_flat_field=no_flat_field,
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
               no_flat_field=None) -> CorrectionResult:
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
        p_u=p_u, out=out, no_flat_field=no_flat_field,
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
