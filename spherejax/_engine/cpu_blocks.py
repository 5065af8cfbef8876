"""The jax.numpy definition of the per-pixel step as it runs on CPU: in cache-sized blocks of
pixels inside one XLA loop (`pixel_outputs_in_blocks`), what `kernels.JaxNumpy` runs there.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import equations
from ..grid import N_WAVELENGTHS
from ..pixel_constants import PixelConstants

#: Pixels per block of the jax.numpy path on CPU (`pixel_outputs_in_blocks`): a block's
#: intermediates (16 + 34 channels of float32, about 3.5 MB) stay in the L2/L3 caches.
CPU_BLOCK_PIXELS = 16384



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


__all__ = ["CPU_BLOCK_PIXELS", "pixel_outputs_in_blocks"]
