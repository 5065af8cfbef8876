"""The fused GPU kernel of `correct`'s per-pixel step, written with JAX Pallas (Triton), and when
it is used.

On an NVIDIA GPU (CUDA), a plan (`spherejax._engine.plan`) whose frames are uint16 or float32 counts
of a power-of-two number of bands >= 16 (the instrument's 16), computed in float32, runs its
per-pixel step as this kernel (`pixel_outputs`) instead of the jax.numpy path
(`equations.pixel_outputs`), which stays the definition it is tested against
(tests/test_gpu_kernel.py, in Pallas's interpret mode on the CPU) and what runs everywhere else:
in float64, on other GPUs (ROCm) and backends, for other band counts, and where the plan's first
compilation of the kernel fails (`mode`, `plan.Plan`: the plan then falls back to the jax.numpy
path and logs why at DEBUG). SPHEREJAX_GPU_KERNEL=0 switches it off (to compare the two, or to
rule the kernel out when something looks wrong); "1" or unset leaves it on.

Derivatives and mappings work as for the fused CPU kernel: the kernel's outputs carry a custom
JVP that is the jax.numpy path's, and frames mapped with `jax.vmap` over one calibration are
more images of one kernel call (a mapped calibration maps the jax.numpy path).

Why: on an H100 the jax.numpy path moves about 900 bytes a pixel through HBM (a pass for the
quality flags, a pass writing the masked Stage II cube, two cuBLAS products each reading it back,
a pass adding the estimator's offset to the 31-channel reflectance): 30 % of the memory floor of
297 bytes a pixel at 4096 x 4096 (raw uint16 x 16 bands, dark and white float32 x 16 read;
reflectance float32 x 31, Lab float32 x 3, quality uint8 written). This kernel reads each
pixel's inputs once and writes each output once, as the fused CPU kernel does
(`spherejax._engine.fused`).

Layout and grid
    The frames are flattened to pixels: raw (..., H, W, B) -> (images, P, B), P = H * W, dark
    and white (P, B), p (images, B); every reshape is free. The grid is (pixel blocks, images):
    the pixel blocks first because CUDA allows 2^31 - 1 blocks along x and 65535 along y, and a
    4096 x 4096 frame is 131072 blocks of 128 pixels. Program (j, i) corrects pixels
    j * block_pixels ... (j + 1) * block_pixels - 1 of image i. The outputs are allocated in their
    final shapes, (images, P, 31), (images, P, 3) and (images, P), and reshaped for free to
    (..., H, W, 31), (..., H, W, 3), (..., H, W): no slice or copy after the kernel.

Block shapes (what the installed Pallas does; jax 0.11.2 and 0.12 alike)
    The Triton lowering requires every loaded or stored array to have a power-of-two number of
    elements (`lowering._check_tensor_size`), and it does not pad a block: a BlockSpec of shape
    (block_pixels, 31) is accepted, but loading or storing it whole is refused with "requires
    that all operations have array arguments and results whose size is a power of 2". It does
    not mask a block that runs past the array's end either (interpret mode pads, Triton would
    read and write out of bounds). So no BlockSpec tiles the arrays here: each kernel sees whole
    arrays and indexes them itself with `pl.ds(start, size)` windows of power-of-two sizes and an
    explicit mask (`triton.load` / `triton.store`): (block_pixels, 32) over the 31 reflectance
    channels with channel < 31 and pixel < P, (block_pixels, 4) over the 3 Lab channels, and
    (block_pixels,) pixel rows for the inputs and the quality mask, which also takes care of a
    last, partial block of pixels. Triton computes addresses from the array's real strides (31,
    3), so the masked lanes touch no memory; interpret mode pads the window
    (`_pad_values_to_avoid_dynamic_slice_oob_shift`), so the same code runs on the CPU.

Arithmetic (float32 only; B a power of two >= 16 bands, else NotImplementedError)
    Per pixel, as `equations.pixel_outputs` computes it: the flags (saturated among finite raw,
    non-finite raw, no flat field, below dark, patch unusable) with the same reductions, so that
    the quality mask is the same bit for bit; v = (raw - dark) / (white - dark) (Eq. 10), with an
    IEEE-rounded division (PTX div.rn.f32 through inline assembly: Triton's `/` on float32 is
    div.full.f32, within 2 ulp, and a v that differs in its last bit from XLA's can flip the
    below-dark bit at its threshold); Stage II v_tilde = (c1 p + c2) v + c3 p + c4 (Eq. 23), 0
    on flagged pixels; reflectance = v_tilde W^T + r0 as one (block_pixels, B) x (B, 32) product
    in full float32 (Precision.HIGHEST: Triton's IEEE input precision, no TF32), W^T padded with a
    zero column; XYZ = v_tilde (W^T weights) + r0 weights as three row sums of v_tilde times a
    column of the folded (B, 3) matrix (`PixelConstants.xyz_projection`, the same fold as the
    jax.numpy path), cheaper than a second, 3/16-used product; Lab from XYZ with
    `colorimetry._lab_f`; NaN in every output channel of a flagged pixel. Sums run in another
    order than XLA's products, so reflectance and Lab agree to float32 rounding, not bit for bit.

Kernel residual (E8-E10, `Calibration.wiener_residual`)
    A calibration whose estimator has one adds A k(v_tilde) to the reflectance and its XYZ inside
    the same program (`spherejax._engine.gpu_residual`: three more products per block, the
    inducing points in chunks of at most 64, m up to `MAX_INDUCING_POINTS`; `applies_residual`
    says which residuals). A static branch: an affine calibration compiles the program above,
    unchanged. A plan makes the constants the kernel reads once (`prepare`) and passes them to
    every call (`pixel_outputs(prepared=...)`); without them each call makes them in its program.

Measured (benchmarks/bench_gpu_kernel.py, one H100 80GB HBM3, jax 0.11.2, make_inputs frames, 4096 x 4096
tiled from 1024 x 1024): quality equal bit for bit and NaN in the same places at both sizes,
max |diff| reflectance 4.8e-7, Lab 1.2e-4. 1024 x 1024: 0.284 ms against 0.695 ms for the
jax.numpy path; 4096 x 4096: 2.18 ms (68 % of the 297-byte HBM floor at 3.35 TB/s) against 4.68 ms
(32 %). block_pixels 32..128 with 1..4 warps were within run-to-run noise (2.16..2.48 ms); 256 and
512 were slower (2.5..3.2 ms). Triton's approximate division instead of div.rn.f32 made no
measurable difference (2.24 ms).

Deprecation: jax 0.11.2 and 0.12 warn (a DeprecationWarning), when this kernel is lowered for a
GPU, that the Pallas Triton backend is deprecated and will be removed in favour of Mosaic GPU (or
jax_triton with Triton's own bindings). The kernel will have to move before that happens; until
then a JAX without the backend, or one that turns the warning into an error, makes the plan's
first compilation fail, and the plan falls back to the jax.numpy path.
"""

from __future__ import annotations

import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from typing import NamedTuple

from .. import colorimetry
from ..grid import N_WAVELENGTHS
from .. import equations
from ..quality import (
    BELOW_DARK_LIMIT,
    QUALITY_BELOW_DARK,
    QUALITY_NONFINITE,
    QUALITY_PATCH_UNUSABLE,
    QUALITY_SATURATED,
    QUALITY_WHITE_NOT_ABOVE_DARK,
)
from ..pixel_constants import PixelConstants
from . import gpu_residual
from .gpu_residual import INDUCING_CHUNK, MAX_INDUCING_POINTS, ResidualConstants, applies_residual

#: Pixels a program corrects by default: 128 rows of 16 bands are 4 KiB of uint16 raw and 8 KiB
#: each of dark and white, and a (128, 32) float32 product of 16 KiB in registers with 4 warps.
DEFAULT_BLOCK_PIXELS = 128

#: Reflectance channels padded to a power of two (the product's and the store's width).
_REFLECTANCE_PAD = gpu_residual.REFLECTANCE_PAD
#: Lab channels padded to a power of two (the store's width).
_LAB_PAD = 4

_RAW_DTYPES = (np.dtype(np.uint16), np.dtype(np.float32))

#: The kernel modes a plan's steps take (their static `kernel_mode`, beside the fused CPU kernel's
#: variants): compiled by Triton for a GPU, or run by Pallas's interpreter (any backend; the tests').
GPU, INTERPRET = "pallas", "pallas-interpret"
MODES = (GPU, INTERPRET)

#: The environment variable that switches the kernel off ("0") or leaves it on ("1", or unset).
SWITCH = "SPHEREJAX_GPU_KERNEL"
SWITCH_VALUES = ("0", "1")


def switch() -> str:
    """SPHEREJAX_GPU_KERNEL's value, "1" when unset.

    Raises:
      ValueError: any other value than "0" or "1", so that a typo cannot leave the kernel on.
    """
    value = os.environ.get(SWITCH, "1").strip()
    if value not in SWITCH_VALUES:
        raise ValueError(f"{SWITCH}={value!r}: expected one of {', '.join(SWITCH_VALUES)}")
    return value


def supports(raw_dtype, compute_dtype, bands: int) -> bool:
    """Whether the kernel computes frames of this raw dtype, compute dtype and band count."""
    return (
        np.dtype(compute_dtype) == np.float32
        and np.dtype(raw_dtype) in _RAW_DTYPES
        and _is_power_of_two(bands)
        and bands >= 16
    )


def _is_cuda(device) -> bool:
    """True for an NVIDIA GPU (the Triton lowering's target; ROCm GPUs are "gpu" as well)."""
    if device is None or device.platform not in ("gpu", "cuda"):
        return False
    try:
        version = device.client.platform_version
    except AttributeError:
        return False
    return "cuda" in str(version).lower()


def mode(raw_dtype, compute_dtype, bands: int, device) -> str | None:
    """GPU when a plan on `device` runs its per-pixel step as this kernel, else None (the
    jax.numpy path): an NVIDIA GPU, frames the kernel computes (`supports`), and the switch on.
    The plan still falls back to None where the kernel's first compilation fails."""
    if not (_is_cuda(device) and supports(raw_dtype, compute_dtype, bands)):
        return None
    return GPU if switch() == "1" else None


def _is_power_of_two(n: int) -> bool:
    return n > 0 and n & (n - 1) == 0


def _pallas():
    """(jax.experimental.pallas, its Triton module), imported at the first kernel built: about
    60 ms of import that `correct` on CPU, which never builds one, does without."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plt

    return pl, plt


def _divide_ieee(x, y, exact: bool):
    """x / y rounded to nearest (IEEE), on float32 arrays of one shape.

    `exact` (GPU): PTX div.rn.f32, which is what XLA emits for a float32 division; Triton lowers
    `/` to div.full.f32 (within 2 ulp). Interpret mode has no inline assembly; its `/` is XLA's
    CPU division, IEEE already.
    """
    if not exact:
        return x / y
    _, plt = _pallas()
    (quotient,) = plt.elementwise_inline_asm(
        "div.rn.f32 $0, $1, $2;",
        args=[x, y],
        constraints="=f,f,f",
        pack=1,
        result_shape_dtypes=[jax.ShapeDtypeStruct(x.shape, jnp.float32)],
    )
    return quotient


def _any(condition, axis):
    """int32 0/1: whether `condition` holds anywhere along `axis` (a maximum of int32, which the
    Triton lowering reduces; it has no rule for reducing booleans)."""
    return jnp.max(condition.astype(jnp.int32), axis=axis)


def _make_kernel(*, block_pixels, pixels, bands, raw_is_float, saturation, has_mask, exact_division,
                 has_residual=False, residual_precision=jax.lax.Precision.HIGHEST):
    """The kernel for one configuration (everything static is closed over). Its refs: the frames
    and the affine constants (`KernelConstants`' first five), the six `ResidualConstants` if
    `has_residual`, the flat-field mask if `has_mask`, then the three outputs."""
    pl, plt = _pallas()
    below_dark_limit = -BELOW_DARK_LIMIT
    residual_count = len(ResidualConstants._fields) if has_residual else 0

    def kernel(*refs):
        (raw_ref, dark_ref, white_ref, p_ref, coeffs_ref, projection_ref, bias_ref, xyz_rows_ref,
         xyz_scalars_ref) = refs[:9]
        residual_refs = ResidualConstants(*refs[9:9 + residual_count]) if has_residual else None
        mask_ref = refs[9 + residual_count] if has_mask else None
        reflectance_ref, lab_ref, quality_ref = refs[-3:]
        block = pl.program_id(0)
        image = pl.program_id(1)
        start = block * block_pixels
        rows = pl.ds(start, block_pixels)
        row_index = start + jax.lax.broadcasted_iota(jnp.int32, (block_pixels,), 0)
        in_frame = row_index < pixels  # (bp,): the last block may be partial
        in_frame_bands = jnp.broadcast_to(in_frame[:, None], (block_pixels, bands))
        # The channel windows (32 of 31, 4 of 3) start at a traced 0: jax 0.12's NDIndexer refuses
        # a static window that overruns the dimension ("Out of bound slice"), though both the
        # Triton lowering (addresses from the real strides, masked lanes) and interpret mode
        # (which pads the window) handle it.
        channel0 = image * 0

        # Inputs, each read once. Rows past the frame read nothing (masked) and get harmless
        # values; their outputs are not stored.
        raw = plt.load(raw_ref.at[image, rows, :], mask=in_frame_bands, other=0)
        dark = plt.load(dark_ref.at[rows, :], mask=in_frame_bands, other=0.0)
        white = plt.load(white_ref.at[rows, :], mask=in_frame_bands, other=1.0)
        p = p_ref[image, :]  # (B,)
        c1, c2, c3, c4 = (coeffs_ref[k, :] for k in range(4))  # (B,) each

        raw_f = raw.astype(jnp.float32)
        # Eq. 10 as flatfield.flat_field_unchecked computes it.
        white_signal = white - dark
        usable = (white_signal > 0) & jnp.isfinite(white_signal)
        quotient = _divide_ieee(raw_f - dark, jnp.where(usable, white_signal, 1.0), exact_division)
        v = jnp.where(usable, quotient, jnp.nan)

        # The flags, as equations.pixel_flags and _quality compute them.
        if raw_is_float:
            raw_finite = jnp.isfinite(raw_f)
            nonfinite = _any(~raw_finite, axis=1)
        else:
            raw_finite = None  # counts are always finite
            nonfinite = jnp.zeros((block_pixels,), jnp.int32)
        if saturation is None:
            saturated = jnp.zeros((block_pixels,), jnp.int32)
        else:
            at_or_above = raw_f >= saturation
            saturated = _any(at_or_above if raw_finite is None else raw_finite & at_or_above, axis=1)
        if mask_ref is None:
            no_flat_field = _any(~usable, axis=1)
        else:
            no_flat_field = (plt.load(mask_ref.at[rows], mask=in_frame, other=0) != 0).astype(jnp.int32)
        lowest = jnp.min(jnp.where(jnp.isfinite(v), v, jnp.inf), axis=1)
        below_dark = (lowest < below_dark_limit).astype(jnp.int32)
        patch_unusable = jnp.max((~jnp.isfinite(p)).astype(jnp.int32))  # () for the whole image
        quality = (
            saturated * QUALITY_SATURATED
            | nonfinite * QUALITY_NONFINITE
            | no_flat_field * QUALITY_WHITE_NOT_ABOVE_DARK
            | below_dark * QUALITY_BELOW_DARK
            | patch_unusable * QUALITY_PATCH_UNUSABLE
        )
        good = quality == 0  # (bp,)

        # Stage II (Eq. 23) on good pixels, 0 on the others (the safe-where of _pixel_outputs),
        # written as polynomial.stage2_unchecked writes it.
        v_safe = jnp.where(good[:, None], v, 0.0)
        v_tilde = (c1[None, :] * p[None, :] + c2[None, :]) * v_safe + c3[None, :] * p[None, :] + c4[None, :]

        # reflectance = v_tilde W^T + r0: one product in full float32 (no TF32).
        product = jax.lax.dot(
            v_tilde, projection_ref[...], precision=jax.lax.Precision.HIGHEST, preferred_element_type=jnp.float32
        )
        estimate = product + bias_ref[...][None, :]
        if has_residual:  # + A k(v_tilde) (E8), and its XYZ below
            residual, residual_xyz = gpu_residual.residual_of_block(v_tilde, residual_refs, precision=residual_precision)
            estimate = estimate + residual
        channel = jax.lax.broadcasted_iota(jnp.int32, (block_pixels, _REFLECTANCE_PAD), 1)

        # XYZ = v_tilde (W^T weights) + r0 weights, one row sum per tristimulus value; then
        # colorimetry.xyz_to_lab.
        f = []
        for k in range(3):
            xyz = jnp.sum(v_tilde * xyz_rows_ref[k, :][None, :], axis=1) + xyz_scalars_ref[k]
            if has_residual:
                xyz = xyz + residual_xyz[k]
            white_xyz = jnp.broadcast_to(xyz_scalars_ref[_LAB_PAD + k], xyz.shape)
            f.append(colorimetry._lab_f(_divide_ieee(xyz, white_xyz, exact_division)))
        f_x, f_y, f_z = f
        lab_l = 116.0 * f_y - 16.0
        lab_a = 500.0 * (f_x - f_y)
        lab_b = 200.0 * (f_y - f_z)
        lab_channel = jax.lax.broadcasted_iota(jnp.int32, (block_pixels, _LAB_PAD), 1)
        lab = jnp.where(lab_channel == 0, lab_l[:, None], jnp.where(lab_channel == 1, lab_a[:, None], lab_b[:, None]))

        # Good pixels whose outputs are not finite (an estimate that overflows float32) get bit 2
        # and NaN, as equations.flag_nonfinite_outputs: x * 0 is NaN exactly for a value that is
        # not finite; the padding channels are left out.
        probe = (jnp.sum(jnp.where(channel < N_WAVELENGTHS, estimate * 0.0, 0.0), axis=1)
                 + jnp.sum(jnp.where(lab_channel < 3, lab * 0.0, 0.0), axis=1))
        overflowed = good & ~jnp.isfinite(probe)
        quality = quality | overflowed.astype(jnp.int32) * QUALITY_NONFINITE
        good = good & ~overflowed
        plt.store(quality_ref.at[image, rows], quality.astype(jnp.uint8), mask=in_frame)
        reflectance = jnp.where(good[:, None], estimate, jnp.nan)
        plt.store(
            reflectance_ref.at[image, rows, pl.ds(channel0, _REFLECTANCE_PAD)],
            reflectance,
            mask=in_frame[:, None] & (channel < N_WAVELENGTHS),
        )
        lab = jnp.where(good[:, None], lab, jnp.nan)
        plt.store(lab_ref.at[image, rows, pl.ds(channel0, _LAB_PAD)], lab, mask=in_frame[:, None] & (lab_channel < 3))

    return kernel


def kernel_constants(constants: PixelConstants):
    """What the kernel reads of the calibration besides the frames, all float32:

    coeffs (4, B): c1..c4 as rows; projection (B, 32): W^T with a zero column; bias (32,): r0 and
    a 0; xyz_rows (4, B): the columns of W^T weights (`PixelConstants.xyz_projection`, the jax.numpy
    path's own fold) as rows, and a zero row; xyz_scalars (8,): r0 weights, 0, then the white's
    XYZ (`PixelConstants.white_xyz`), 1.

    A few small XLA operations on (B, 34)-sized arrays; a plan makes them once (`prepare`).
    """
    bands = constants.bands
    f32 = jnp.float32
    xyz_matrix, xyz_offset = constants.xyz_projection()
    pad = _REFLECTANCE_PAD - N_WAVELENGTHS
    projection = jnp.concatenate([constants.wiener.T.astype(f32), jnp.zeros((bands, pad), f32)], axis=1)
    bias = jnp.concatenate([constants.wiener_offset.astype(f32), jnp.zeros((pad,), f32)])
    xyz_rows = jnp.concatenate([xyz_matrix.T.astype(f32), jnp.zeros((1, bands), f32)], axis=0)
    xyz_scalars = jnp.concatenate([
        xyz_offset.astype(f32), jnp.zeros((1,), f32), constants.white_xyz().astype(f32), jnp.ones((1,), f32),
    ])
    return constants.coeffs.T.astype(f32), projection, bias, xyz_rows, xyz_scalars


class KernelConstants(NamedTuple):
    """Everything the kernel reads of a calibration besides the frames (a pytree): the five arrays
    of `kernel_constants` and the kernel residual's `ResidualConstants` (None for an affine
    estimator)."""

    coeffs: jax.Array
    projection: jax.Array
    bias: jax.Array
    xyz_rows: jax.Array
    xyz_scalars: jax.Array
    residual: ResidualConstants | None = None


def prepare(constants: PixelConstants, *, inducing_chunk: int = INDUCING_CHUNK) -> KernelConstants:
    """The `KernelConstants` of float32 `PixelConstants` (traceable): what a plan makes once, with
    `jax.jit(prepare)(constants)`, and hands to every `pixel_outputs` call. `inducing_chunk`:
    inducing points per chunk at most (`gpu_residual.chunk_of`)."""
    residual = constants.wiener_residual
    if residual is not None:
        residual = gpu_residual.residual_constants(residual, constants.tristimulus_weights, chunk=inducing_chunk)
    return KernelConstants(*kernel_constants(constants), residual=residual)


def pixel_outputs_pallas(
    raw,
    p,
    constants: PixelConstants,
    *,
    saturation,
    no_flat_field=None,
    block_pixels: int = DEFAULT_BLOCK_PIXELS,
    interpret: bool = False,
    num_warps: int | None = None,
    exact_division: bool | None = None,
    prepared: KernelConstants | None = None,
    inducing_chunk: int = INDUCING_CHUNK,
    residual_precision=jax.lax.Precision.HIGHEST,
):
    """`equations.pixel_outputs(raw, p, constants, saturation=..., no_flat_field=...)` as one Pallas
    kernel: (reflectance (..., H, W, 31) float32, lab (..., H, W, 3) float32, quality (..., H, W)
    uint8).

    Args:
      raw: (..., H, W, B) uint16 or float32 frames; B a power of two >= 16 (the instrument's 16).
      p: (..., B) white-patch ratios, one per frame (broadcast to raw's leading axes).
      constants: the calibration's `PixelConstants` in float32, H and W those of raw.
      saturation: the saturation level (`calibration_module.saturation_level`), or None for no check.
      no_flat_field: None (worked out in the kernel from dark and white), or the (H, W) bool
        `equations.flat_field_unusable(dark, white)` (converted to uint8 here: one small pass).
      block_pixels: pixels per program, a power of two >= 16 (the product's smallest tile).
      interpret: run the kernel in Pallas's interpreter (any backend; how the tests run it).
      num_warps: Triton warps per program (None: Pallas's default, 4).
      exact_division: IEEE division through PTX inline assembly (see `_divide_ieee`); None = True
        unless `interpret`. False on a GPU gives Triton's division, within 2 ulp, whose quality
        bits may then differ from the jax.numpy path's at the below-dark threshold.
      prepared: `prepare(constants)` made once by the caller, or None to make it here.
      inducing_chunk: inducing points per chunk at most, when `prepared` is None.
      residual_precision: the kernel residual's products' precision (`gpu_residual`).

    Raises:
      NotImplementedError: a compute dtype other than float32, a raw dtype other than uint16 or
        float32, a band count that is not a power of two >= 16, or a kernel residual of more than
        `MAX_INDUCING_POINTS` inducing points (`applies_residual`).
      ValueError: shapes that do not fit together, a block_pixels that is not a power of two
        >= 16, or `prepared` with a residual where the constants have none or the other way round.
    """
    raw = jnp.asarray(raw)
    p = jnp.asarray(p)
    if constants.dtype != np.float32:
        raise NotImplementedError(f"pixel_outputs_pallas: float32 compute only, got {constants.dtype}")
    if np.dtype(raw.dtype) not in _RAW_DTYPES:
        raise NotImplementedError(f"pixel_outputs_pallas: raw uint16 or float32 only, got {raw.dtype}")
    if raw.ndim < 3:
        raise ValueError(f"raw: expected (..., H, W, B), got {tuple(raw.shape)}")
    *lead, height, width, bands = raw.shape
    lead = tuple(lead)
    if tuple(constants.dark.shape) != (height, width, bands):
        raise ValueError(f"constants: dark {tuple(constants.dark.shape)} does not fit raw {tuple(raw.shape)}")
    if not (_is_power_of_two(bands) and bands >= 16):
        raise NotImplementedError(f"pixel_outputs_pallas: B a power of two >= 16 bands, got {bands}")
    if not (_is_power_of_two(block_pixels) and block_pixels >= 16):
        raise ValueError(f"block_pixels: expected a power of two >= 16, got {block_pixels}")
    residual = constants.wiener_residual
    if not applies_residual(residual):
        raise NotImplementedError(
            f"pixel_outputs_pallas: a kernel residual of at most {MAX_INDUCING_POINTS} inducing points, "
            f"got {residual.inducing.shape[0]}"
        )
    if prepared is None:
        prepared = prepare(constants, inducing_chunk=inducing_chunk)
    if (prepared.residual is None) != (residual is None):
        raise ValueError("prepared: expected prepare(constants) of these constants (a kernel residual in both or neither)")
    if exact_division is None:
        exact_division = not interpret
    images = math.prod(lead)
    pixels = height * width

    raw_flat = raw.reshape(images, pixels, bands)
    p_flat = jnp.broadcast_to(p.astype(jnp.float32), (*lead, bands)).reshape(images, bands)
    dark = constants.dark.reshape(pixels, bands)
    white = constants.white.reshape(pixels, bands)
    inputs = [raw_flat, dark, white, p_flat, *prepared[:5], *(prepared.residual or ())]
    if no_flat_field is not None:
        inputs.append(jnp.asarray(no_flat_field).reshape(pixels).astype(jnp.uint8))

    kernel = _make_kernel(
        block_pixels=block_pixels, pixels=pixels, bands=bands, raw_is_float=raw.dtype == np.float32,
        saturation=None if saturation is None else float(saturation), has_mask=no_flat_field is not None,
        exact_division=bool(exact_division), has_residual=residual is not None, residual_precision=residual_precision,
    )
    out_shape = (
        jax.ShapeDtypeStruct((images, pixels, N_WAVELENGTHS), jnp.float32),
        jax.ShapeDtypeStruct((images, pixels, 3), jnp.float32),
        jax.ShapeDtypeStruct((images, pixels), jnp.uint8),
    )
    pl, plt = _pallas()
    compiler_params = None if interpret else plt.CompilerParams(num_warps=num_warps)
    reflectance, lab, quality = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(pl.cdiv(pixels, block_pixels), images),
        interpret=interpret,
        compiler_params=compiler_params,
        name="spherejax_pixel_outputs",
    )(*inputs)
    return (
        reflectance.reshape(*lead, height, width, N_WAVELENGTHS),
        lab.reshape(*lead, height, width, 3),
        quality.reshape(*lead, height, width),
    )


def pixel_outputs(raw, p, constants: PixelConstants, *, saturation, kernel_mode: str,
                  prepared: KernelConstants | None = None):
    """(reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W)) of
    `equations.pixel_outputs(raw, p, constants, saturation=...)` by the kernel, as `correct`'s
    steps call it (`steps.pixels_step`), with the jax.numpy path's JVP and a mapping rule.

    Args:
      raw: (..., H, W, B) uint16 or float32; p: (..., B); constants: float32 (`supports`), with
        a kernel residual or none (`applies_residual`).
      saturation: the saturation level, or None for no check.
      kernel_mode: GPU (Triton) or INTERPRET (Pallas's interpreter).
      prepared: `prepare(constants)`, made once by a plan; None makes it in this call's program.

    Derivatives: the outputs carry the JVP of the jax.numpy path (`jax.grad` through `correct`
    gives what it gives without the kernel), the primal outputs stay the kernel's; `prepared`'s
    tangents are not read (it is a function of `constants`, whose tangents are).
    Mappings (`jax.vmap`): frames and ratios mapped over one calibration are more images of one
    kernel call, which takes leading image axes; a mapped calibration (or mapped `prepared`) maps
    the jax.numpy path.
    """
    plain = functools.partial(equations.pixel_outputs, saturation=saturation, intermediates=False)
    kernel = functools.partial(pixel_outputs_pallas, saturation=saturation, interpret=kernel_mode == INTERPRET)
    if prepared is None:
        prepared = prepare(constants)

    @jax.custom_batching.custom_vmap
    def mappable(raw, p, constants, prepared):
        return kernel(raw, p, constants, prepared=prepared)

    @mappable.def_vmap
    def over_frames(axis_size, in_batched, raw, p, constants, prepared):
        raw_batched, p_batched, constants_batched, prepared_batched = in_batched
        if any(jax.tree_util.tree_leaves((constants_batched, prepared_batched))):  # a mapped calibration
            axes = jax.tree_util.tree_map(lambda batched: 0 if batched else None, in_batched[:3])
            return jax.vmap(plain, in_axes=axes)(raw, p, constants), (True, True, True)
        if not raw_batched:
            raw = jnp.broadcast_to(raw, (axis_size, *raw.shape))
        lead = raw.shape[:-3]  # (axis_size, ...raw's own leading axes)
        if p_batched:  # (axis_size, ...p's, B): p's own axes align with raw's from the right
            p = p.reshape(axis_size, *(1,) * (len(lead) - (p.ndim - 1)), *p.shape[1:])
        p = jnp.broadcast_to(p, (*lead, p.shape[-1]))
        return mappable(raw, p, constants, prepared), (True, True, True)

    @jax.custom_jvp
    def outputs(raw, p, constants, prepared):
        return mappable(raw, p, constants, prepared)

    @functools.partial(outputs.defjvp, symbolic_zeros=True)
    def outputs_jvp(primals, tangents):
        return outputs(*primals), _jvp_of_inputs_with_tangents(plain, primals[:3], tangents[:3])

    return outputs(raw, p, constants, prepared)


def _jvp_of_inputs_with_tangents(function, primals, tangents):
    """The output tangents of `function` (jax.jvp) with respect to the inputs that have tangents
    only; the others (SymbolicZero in `tangents`) are held constant.

    Why not jax.jvp with zeros for them: a zero tangent times an infinite partial derivative is
    NaN (the Lab of a pixel whose flat field divides by zero, say), and NaN would then appear in
    the tangents of outputs that depend on nothing differentiated."""
    def is_zero(tangent):
        return isinstance(tangent, jax.custom_derivatives.SymbolicZero)

    leaves, structure = jax.tree_util.tree_flatten(primals)
    tangent_leaves = jax.tree_util.tree_leaves(tangents, is_leaf=is_zero)
    live = [i for i, tangent in enumerate(tangent_leaves) if not is_zero(tangent)]

    def of_live(*values):
        arguments = list(leaves)
        for i, value in zip(live, values):
            arguments[i] = value
        return function(*jax.tree_util.tree_unflatten(structure, arguments))

    _, tangents_out = jax.jvp(of_live, [leaves[i] for i in live], [tangent_leaves[i] for i in live])
    return tangents_out


__all__ = [
    "DEFAULT_BLOCK_PIXELS",
    "GPU",
    "INDUCING_CHUNK",
    "INTERPRET",
    "KernelConstants",
    "MAX_INDUCING_POINTS",
    "MODES",
    "SWITCH",
    "SWITCH_VALUES",
    "applies_residual",
    "kernel_constants",
    "mode",
    "pixel_outputs",
    "pixel_outputs_pallas",
    "prepare",
    "supports",
    "switch",
]
