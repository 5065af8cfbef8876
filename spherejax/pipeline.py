"""The whole per-pixel path of an image in one jitted call.

    raw (H, W, B) uint16 or float
      -> quality mask (saturated, non-finite, white <= dark)
      -> v = flat field (Eq. 10)            with the calibration's dark frame and white standard
      -> p = white-patch ratio (Eq. 14-15)  over the calibration's patch mask (or weights), usable
                                            pixels only
      -> v_check = p v (Stage I, Eq. 16-17)
      -> v_tilde = Stage II (Eq. 23)
      -> reflectance = W v_tilde + r0 (the affine Wiener estimator, 16 -> 31)
      -> Lab under the calibration's illuminant (ASTM E308 XYZ, perfect-diffuser white)

Bad pixels never raise: they become NaN in every output and carry bits in `quality`. Shapes and
configuration are checked before tracing and raise ValueError naming the argument.

Two steps, so that an image too large for memory can be corrected in strips with the same
compiled code (`spherejax.stripwise`): `patch_ratio` reads only the white patch's bounding box,
and the per-pixel step takes p as an argument. `correct(raw, calibration)` traces both into one
program; `correct(strip, calibration_rows, p=p)` runs the second on rows of an image with the
whole image's p, and gives the same numbers bit for bit as the whole-image call (tested).

This module holds the types, the equations and the public functions. How a correction runs is
the private engine's (`spherejax._engine`): `correct` looks up the calibration's plan for the
frames' shape and dtype (`plan`, `spherejax._engine.plan`), which holds the calibration's arrays
cast once (`spherejax.pixel_constants.PixelConstants`) on their device and picks the route; the
jitted steps are `spherejax._engine.steps`. On CPU the per-pixel step in float32 is one fused
compiled kernel (`spherejax._engine.fused`); the jax.numpy code here (`_pixel_outputs`) is its
definition, runs everywhere else and gives its derivatives.

For Lab the Wiener matrix and the XYZ weights are folded into one (B, 3) matrix, so XYZ is computed from v_tilde directly; that equals reflectance @ weights up to rounding (tested).
The estimator's offset r0 is folded the same way: XYZ = v_tilde (W^T weights) + r0 weights.
"""

from __future__ import annotations

import dataclasses
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks, colorimetry, uncertainty
from ._engine import buffers
from .colorimetry import xyz_to_lab
from .correction_result import CorrectionResult, delta_e_map
from .estimation.kernel_residual import KernelResidual
from .flatfield import flat_field_unchecked, patch_ratio_weighted
from .grid import N_WAVELENGTHS
from .pixel_constants import PatchConstants, PixelConstants
from .polynomial import stage2_unchecked

_HIGHEST = jax.lax.Precision.HIGHEST

#: Bits of `CorrectionResult.quality` (uint8); 0 = good pixel.
QUALITY_SATURATED = 1  #: raw at or above the saturation level in some band
QUALITY_NONFINITE = 2  #: raw NaN or infinite in some band (float input)
QUALITY_WHITE_NOT_ABOVE_DARK = 4  #: white <= dark (or not finite) in some band: no flat field
QUALITY_PATCH_UNUSABLE = 8  #: the white-patch ratio of some band is not finite: whole image bad
QUALITY_BELOW_DARK = 16  #: raw below the dark level by more than noise allows in some band

#: The flat-fielded response (Eq. 10) below which a band's raw value is taken as below the dark
#: level by more than noise allows (`QUALITY_BELOW_DARK`): v < -BELOW_DARK_LIMIT, i.e. raw more
#: than 2 % of the white standard's signal (white - dark) below the dark frame. A pixel at the dark
#: level varies by its read and dark-current noise, a few counts, against a white signal of
#: thousands of counts in any usable exposure: 2 % is tens of standard deviations away, so noise
#: alone never reaches it, while a raw value of -1000 counts (a float input gone wrong, a dark
#: frame taken under other conditions than the captures) does, and would otherwise come out as a
#: reflectance far below 0 with quality 0. The fused CPU kernel (_fused_correct.cc,
#: kBelowDarkLimit) uses the same number.
BELOW_DARK_LIMIT = 0.02


#: The calibration's parameters every pixel goes through: a NaN or infinity in any of them makes
#: every output NaN while the quality flags, which describe pixels, stay 0. Refused when concrete.
PARAMETERS = ("coeffs", "wiener", "wiener_offset")


#: Plans a calibration keeps (`Calibration._plan`): the frame shapes of a batch, a stack and its
#: frames, a few strip heights.
_PLANS_KEPT = 8
_plans_lock = threading.Lock()


class Calibration(eqx.Module):
    """Everything `correct` needs, as a pytree (its arrays are leaves; the names are static).

    Fields:
      dark: dark frame, (H, W, B), in raw counts.
      white: white-standard frame, (H, W, B), in raw counts, same exposure as the samples.
      patch: the reference white patch (Eq. 14-15), (H, W): a boolean mask, True on the patch
        (the normal case, and the only one a calibration file stores), or floating weights >= 0
        (0 = not in the patch), so that p, and all that follows, can be differentiated with
        respect to the patch: p is the weighted sum of white-standard signals over the weighted
        sum of sample signals. None for rows of a calibration (`rows`): `correct` then needs
        the whole image's p.
      coeffs: Stage II coefficients (B, 4), ordered c1..c4 (Eq. 23).
      wiener: Wiener matrix W (31, B) (`wiener.fit_wiener`): reflectance per unit of the Stage II
        response.
      illuminant: "D65", "A" or "F2" for Lab.
      observer: colour-matching functions for Lab (`colorimetry.OBSERVERS`).
      saturation: raw level at or above which a pixel counts as saturated; None = the full scale
        of an integer raw dtype (65535 for uint16) and no check for float raw.
      wiener_offset: the estimator's offset r0 (31,), reflectance (dimensionless, 400..700 nm
        step 10): the estimate is r = W v_tilde + r0 (`wiener.fit_wiener`). Default zeros, the
        plain linear Wiener estimate, which gives the same numbers as before the offset existed.
      wiener_residual: the estimator's kernel residual (`estimation.KernelResidual`, from
        `estimation.fit_kernel_estimator`): the estimate is then r = W v_tilde + r0 + A k(v_tilde)
        (E8). None (default): the affine estimator. `correct` applies it on the jax.numpy path:
        the fused CPU kernel and the GPU kernel apply affine estimators only.
      wiener_offset and wiener_residual come last among the fields, so that positional
      construction keeps its meaning.
    """

    dark: jax.Array = eqx.field(converter=jnp.asarray)
    white: jax.Array = eqx.field(converter=jnp.asarray)
    patch: jax.Array | None = eqx.field(converter=lambda x: None if x is None else jnp.asarray(x))
    coeffs: jax.Array = eqx.field(converter=jnp.asarray)
    wiener: jax.Array = eqx.field(converter=jnp.asarray)
    illuminant: str = eqx.field(static=True, default="D65")
    observer: str = eqx.field(static=True, default=colorimetry.DEFAULT_OBSERVER)
    saturation: float | None = eqx.field(static=True, default=None)
    # A factory, not an array default: dataclasses refuse unhashable defaults. float32 zeros
    # promote nothing, so a float64 calibration without an offset still computes in float64.
    wiener_offset: jax.Array = eqx.field(
        converter=jnp.asarray, default_factory=lambda: np.zeros(N_WAVELENGTHS, np.float32)
    )
    wiener_residual: KernelResidual | None = None

    def __check_init__(self):
        # Unknown names raise here, at construction, rather than at the first correction.
        colorimetry.tristimulus_weights(self.illuminant, observer=self.observer)
        # jnp.asarray keeps complex values and a later cast drops their imaginary part; the patch
        # has a dtype check of its own (a boolean mask or real weights).
        for name in ("dark", "white", "coeffs", "wiener", "wiener_offset"):
            _checks.require_real(name, getattr(self, name))
        if self.dark.ndim != 3:
            raise ValueError(f"dark: expected shape (H, W, B), got {tuple(self.dark.shape)}")
        height, width, bands = self.dark.shape
        if 0 in self.dark.shape:
            raise ValueError(f"dark: expected at least one pixel and one band, got shape {tuple(self.dark.shape)}")
        _checks.require_shape("white", self.white, self.dark.shape, "the dark frame's (H, W, B)")
        if self.patch is not None:
            _checks.require_mask_or_weights("patch", self.patch, (height, width))
        _checks.require_shape(
            "coeffs", self.coeffs, (bands, 4), f"c1..c4 for each of the {bands} bands"
        )
        _checks.require_shape(
            "wiener", self.wiener, (N_WAVELENGTHS, bands), f"31 wavelengths x the {bands} bands"
        )
        _checks.require_shape(
            "wiener_offset", self.wiener_offset, (N_WAVELENGTHS,), "one reflectance offset r0 per wavelength, 400..700 nm step 10"
        )
        if self.wiener_residual is not None:
            if not isinstance(self.wiener_residual, KernelResidual):
                raise ValueError(f"wiener_residual: expected an estimation.KernelResidual or None, got {type(self.wiener_residual).__name__}")
            if self.wiener_residual.bands != bands:
                raise ValueError(f"wiener_residual: expected a residual of the {bands} bands, got one of {self.wiener_residual.bands}")
        if self.saturation is not None and not float(self.saturation) > 0:
            raise ValueError(f"saturation: expected a level > 0 or None, got {self.saturation!r}")
        for name in PARAMETERS:
            _checks.require_finite(name, getattr(self, name))

    @property
    def bands(self) -> int:
        return int(self.dark.shape[-1])

    @property
    def image_shape(self) -> tuple[int, int]:
        return int(self.dark.shape[0]), int(self.dark.shape[1])

    @property
    def patch_box(self) -> tuple[int, int, int, int] | None:
        """(row0, row1, col0, col1) bounding the patch (`patch_bounding_box`); None without a
        patch or when the patch is traced.

        Worked out once per calibration (finding it reads the whole mask, about 0.9 ms a
        megapixel): the patch is an immutable jax.Array, so its box cannot change."""
        if self.patch is None or not _checks.is_concrete(self.patch):
            return None
        known = self.__dict__.get("_patch_box")
        if known is None:
            known = (patch_bounding_box(self.patch),)
            object.__setattr__(self, "_patch_box", known)  # a frozen dataclass: its own memo
        return known[0]

    def _plan(self, key: tuple, make):
        """The plan this calibration keeps under `key` (frames' shape, dtype and kernel mode:
        `spherejax._engine.plan.plan_for`), made with `make()` at first use.

        The plans live and die with the calibration (an attribute of the instance, not a field:
        not part of the pytree, not pickled, not copied by `dataclasses.replace` or tree_map,
        whose new calibration gets plans of its own). The last `_PLANS_KEPT` shapes are kept."""
        with _plans_lock:
            plans = self.__dict__.get("_plans")
            if plans is None:
                plans = {}
                object.__setattr__(self, "_plans", plans)
            plan = plans.get(key)
        if plan is None:
            plan = make()  # outside the lock: it may compile
            with _plans_lock:
                plan = plans.setdefault(key, plan)
                while len(plans) > _PLANS_KEPT:
                    del plans[next(iter(plans))]
        return plan

    def __getstate__(self):
        # A pickled calibration (a dask worker's) carries its arrays, never its plans, which
        # hold compiled programs and device memory.
        return {name: value for name, value in self.__dict__.items() if name not in ("_plans", "_patch_box")}

    def rows(self, row0: int, row1: int) -> Calibration:
        """This calibration for image rows row0:row1 only, without the patch (None).

        For correcting an image in strips: `correct(raw[row0:row1], calibration.rows(row0, row1),
        p=patch_ratio(raw, calibration))` equals rows row0:row1 of `correct(raw, calibration)`.
        """
        height = self.image_shape[0]
        if not 0 <= row0 < row1 <= height:
            raise ValueError(f"rows: expected 0 <= row0 < row1 <= {height}, got {row0}:{row1}")
        # dataclasses.replace carries every other field (the Wiener offset included) and runs
        # the checks again.
        return dataclasses.replace(self, dark=self.dark[row0:row1], white=self.white[row0:row1], patch=None)


def _compute_dtype(raw, calibration: Calibration):
    return _checks.float_dtype(
        raw, calibration.dark, calibration.white, calibration.coeffs, calibration.wiener,
        calibration.wiener_offset,
    )


def _saturation_level(raw, calibration: Calibration):
    if calibration.saturation is not None:
        return float(calibration.saturation)
    if jnp.issubdtype(raw.dtype, jnp.integer):
        return float(jnp.iinfo(raw.dtype).max)
    return None


def _pixel_flags(raw, raw_f, dark, white, saturation, no_flat_field=None):
    """Per-pixel (saturated, non-finite, no flat field, below dark) flags, each (..., H, W) bool.

    A pixel is flagged if any band is: reflectance mixes all bands. +inf counts as non-finite,
    not as saturated, so the bits say what went wrong. no_flat_field: `_no_flat_field(dark,
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
        no_flat_field = _no_flat_field(dark, white)
    # Finite values of v only: a raw -inf is non-finite (bit 2), not below dark, as +inf is not
    # saturated, and v is NaN where the flat field is unusable (bit 4). One minimum over the bands
    # with the others replaced by +inf, not `any` of a comparison: XLA's CPU code for `any` over
    # the short band axis doubled the jax.numpy path's time (67 -> 130 ms a megapixel), the minimum
    # costs a few percent (`_no_flat_field` says the same of its own reduction).
    v = flat_field_unchecked(raw_f, dark, white)
    below_dark = jnp.min(jnp.where(jnp.isfinite(v), v, jnp.inf), axis=-1) < -BELOW_DARK_LIMIT
    return saturated, nonfinite, jnp.broadcast_to(no_flat_field, pixel_shape), below_dark


def _no_flat_field(dark, white):
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


def patch_bounding_box(patch) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1) bounding the patch's nonzero entries (True or weight != 0), or
    None if the patch is traced.

    The white-patch ratio needs only the patch's pixels (0.1 % of the image in the paper's
    layout): slicing to this box keeps the ratio from making three passes over the whole cube.
    Pixels of weight 0 contribute nothing to the ratio's value, so leaving them out is exact.
    Differentiating with respect to the weights makes them tracers, so the ratio is then taken
    over the whole image and a weight of 0 gets its gradient too (which is not 0).
    """
    if not _checks.is_concrete(patch):
        return None
    mask = np.asarray(patch) != 0
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return None if rows.size == 0 else (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)


def _patch_flags(raw, raw_f, dark, white, saturation):
    saturated, nonfinite, no_flat_field, below_dark = _pixel_flags(raw, raw_f, dark, white, saturation)
    return saturated | nonfinite | no_flat_field | below_dark


def _patch_box_inputs(raw_box, patch: PatchConstants, saturation):
    """The inputs of Eq. 14-15 over the patch's box: raw (..., h, w, B) in the compute dtype and
    the weights (..., h, w) with unusable pixels at 0.

    raw_box: the frames over the box, (..., h, w, B), raw counts; patch: the calibration over
    the same box (`PatchConstants`); saturation: `_saturation_level`.
    """
    raw_f = raw_box.astype(patch.dark.dtype)
    # One saturated or non-finite pixel in the patch must not shift p for the whole image.
    bad = _patch_flags(raw_box, raw_f, patch.dark, patch.white, saturation)
    weights = jnp.where(bad, 0.0, patch.weights)
    return raw_f, weights


def _patch_ratio_of_box(raw_box, patch: PatchConstants, saturation):
    """Eq. 14-15 over the usable pixels of the patch's box: p (..., B) in the compute dtype.
    Pixels of weight 0 in the box add nothing to the ratio, so the crop is exact."""
    raw_f, weights = _patch_box_inputs(raw_box, patch, saturation)
    return patch_ratio_weighted(raw_f, patch.dark, patch.white, weights[..., None])


@jax.custom_jvp
def _project_good_pixels(good, v, matrix, bias):
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
    would no longer give the numbers it gave before the offset existed. The CPU kernel of
    `spherejax._engine.fused`, the default path in float32, starts its accumulators at the bias instead,
    for free.
    """
    return jnp.matmul(jnp.where(good, v, jnp.nan), matrix, precision=_HIGHEST) + bias


@_project_good_pixels.defjvp
def _project_good_pixels_jvp(primals, tangents):
    good, v, matrix, bias = primals
    _, v_dot, matrix_dot, bias_dot = tangents
    out = _project_good_pixels(good, v, matrix, bias)
    out_dot = (
        jnp.matmul(v_dot, matrix, precision=_HIGHEST) + jnp.matmul(v, matrix_dot, precision=_HIGHEST) + bias_dot
    )
    return out, jnp.where(good, out_dot, 0.0)


def _quality(raw, raw_f, dark, white, p, saturation, no_flat_field=None):
    """(..., H, W) uint8 bit mask of the QUALITY_* flags (no_flat_field: see `_pixel_flags`)."""
    saturated, nonfinite, no_flat_field, below_dark = _pixel_flags(raw, raw_f, dark, white, saturation, no_flat_field)
    patch_unusable = jnp.any(~jnp.isfinite(p), axis=-1)  # (...,)
    return (
        saturated.astype(jnp.uint8) * QUALITY_SATURATED
        | nonfinite.astype(jnp.uint8) * QUALITY_NONFINITE
        | no_flat_field.astype(jnp.uint8) * QUALITY_WHITE_NOT_ABOVE_DARK
        | below_dark.astype(jnp.uint8) * QUALITY_BELOW_DARK
        | jnp.broadcast_to(patch_unusable[..., None, None], saturated.shape).astype(jnp.uint8)
        * QUALITY_PATCH_UNUSABLE
    )


def _pixel_outputs(raw, p, constants: PixelConstants, *, saturation, intermediates=False, no_flat_field=None):
    """The per-pixel path in jax.numpy: the definition the fused CPU kernel is tested against.

    Args: raw (..., H, W, B) counts or floats; p (..., B) and the constants (`PixelConstants`,
    H and W those of raw) in the compute dtype; saturation: `_saturation_level`. no_flat_field:
    None, or the (H, W) bool `_no_flat_field(constants.dark, constants.white)` worked out once
    (`spherejax._engine.plan`).

    reflectance = v_tilde W^T + r0 and XYZ = v_tilde (W^T weights) + r0 weights, the latter
    being reflectance @ weights (ASTM E308) regrouped so that the 31-channel cube is not read
    back; both on good pixels only.

    Returns (reflectance, lab, quality), then v, v_stage1 and v_stage2 if `intermediates`.
    """
    dark, white = constants.dark, constants.white
    dtype = dark.dtype
    raw_f = raw.astype(dtype)
    quality = _quality(raw, raw_f, dark, white, p, saturation, no_flat_field)
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
    reflectance = _project_good_pixels(good, v_stage2_safe, constants.wiener.T, constants.wiener_offset)
    xyz = _project_good_pixels(good, v_stage2_safe, *constants.xyz_projection())
    if constants.wiener_residual is not None:
        # The kernel residual (E8) of every pixel (NaN stays NaN on the bad ones), and its XYZ.
        residual = constants.wiener_residual(v_stage2_safe)
        reflectance = reflectance + residual
        xyz = xyz + jnp.matmul(residual, constants.tristimulus_weights, precision=_HIGHEST)
    lab = xyz_to_lab(xyz, constants.white_xyz())
    if not intermediates:
        return reflectance, lab, quality
    v_out = jnp.where(good, v, jnp.nan)
    v_stage2_out = jnp.where(good, v_stage2_safe, jnp.nan)
    return reflectance, lab, quality, v_out, v_out * p_pixel, v_stage2_out


def _check_calibration(calibration) -> None:
    if not isinstance(calibration, Calibration):
        raise ValueError(
            f"calibration: expected a spherejax.Calibration, got {type(calibration).__name__}"
        )


def _check_raw(raw, calibration: Calibration, what: str) -> jax.Array:
    raw = _checks.as_array("raw", raw)
    if raw.ndim < 3:
        raise ValueError(f"raw: expected shape (H, W, B) or (..., H, W, B), got {tuple(raw.shape)}")
    expected = (*calibration.image_shape, calibration.bands)
    if tuple(raw.shape[-3:]) != expected:
        raise ValueError(f"raw: expected frames of shape {expected} ({what}), got {tuple(raw.shape)}")
    if not (jnp.issubdtype(raw.dtype, jnp.integer) or jnp.issubdtype(raw.dtype, jnp.floating)):
        raise ValueError(f"raw: expected integer counts or floats, got dtype {raw.dtype}")
    return raw


def _prepared(raw, calibration: Calibration):
    """The calibration's plan for raw's shape and dtype (`spherejax._engine.plan`)."""
    from ._engine.plan import plan_for  # the engine imports this module

    return plan_for(calibration, raw.shape, raw.dtype)


def patch_ratio(raw, calibration: Calibration) -> jax.Array:
    """The white-patch ratio p (Eq. 14-15) of whole frames, from the patch's pixels only.

    Pixels of the patch that are saturated, not finite or whose white is not above dark are left
    out; a band with no usable pixel gives NaN (and `correct` then flags the whole image).

    Args:
      raw: (H, W, B) or (..., H, W, B), uint16 counts or float, the calibration's size; or only
        the patch's bounding box of it, (..., r1 - r0, c1 - c0, B), with `calibration` cropped
        to the same box (what an out-of-core reader passes: `Calibration.patch_box`).
      calibration: a `Calibration` with a patch.

    Returns:
      p, (..., B), in the dtype `correct` computes in.
    """
    _check_calibration(calibration)
    if calibration.patch is None:
        raise ValueError("calibration: has no patch (rows of a calibration): p needs the whole one")
    raw = _check_raw(raw, calibration, "the calibration's H, W, B")
    # Only the patch's bounding box is read: the ratio then costs nothing next to the per-pixel
    # path. Pixels of weight 0 in the box add nothing to it, so the crop is exact.
    return _prepared(raw, calibration).patch_ratio(raw)


def patch_ratio_u(raw, calibration: Calibration, noise) -> jax.Array:
    """The standard uncertainty of `patch_ratio(raw, calibration)`, (..., B), under a
    `NoiseModel` (`uncertainty.patch_ratio_std`): what `correct(strip, rows, p=, p_u=, noise=)`
    needs for strips of an image."""
    _check_calibration(calibration)
    if calibration.patch is None:
        raise ValueError("calibration: has no patch (rows of a calibration): u(p) needs the whole one")
    raw = _check_raw(raw, calibration, "the calibration's H, W, B")
    noise = uncertainty.check_noise(noise, calibration.bands)
    if noise is None:
        raise ValueError("noise: expected a spherejax.NoiseModel, got None")
    return _prepared(raw, calibration).patch_ratio_u(raw, noise)


def plan(calibration: Calibration, shape, *, dtype=np.uint16):
    """Prepare the correction of frames of `shape` and `dtype` with `calibration`, once.

    `correct(raw, calibration)` does this itself at its first call for a shape and keeps the plan
    with the calibration; call `plan` to pay that cost up front (before a batch's timing starts,
    or in a dask worker's set-up), or to hold the plan and call it directly. The plan holds the
    calibration's arrays cast to the compute dtype on the device they are on, the tristimulus
    weights, the white patch's box, the (H, W) flat-field mask, the route its calls take and,
    on CPU, the compiled program that writes into reused output memory.

    Args:
      calibration: a `Calibration` (rows of one need `p` at every call).
      shape: the frames' shape, (H, W, B) or (..., H, W, B), with the calibration's H, W, B.
      dtype: the frames' dtype: unsigned or signed integer counts (uint16 by default) or float.

    Returns:
      A plan: call it as `correct` without the calibration, `plan(raw, p=None,
      intermediates=False, noise=None, p_u=None)`, with frames of that shape and dtype; it also
      has `patch_ratio(raw)` and `patch_ratio_u(raw, noise)`. The numbers are `correct`'s, bit
      for bit.

    Raises:
      ValueError: not a Calibration, a shape that is not the calibration's frames, or a dtype
        that is neither integer nor float.
    """
    _check_calibration(calibration)
    try:
        shape = tuple(int(n) for n in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape: expected a tuple of ints (..., H, W, B), got {shape!r}") from None
    expected = (*calibration.image_shape, calibration.bands)
    if len(shape) < 3 or shape[-3:] != expected or min(shape) < 0:
        raise ValueError(f"shape: expected (H, W, B) or (..., H, W, B) with H, W, B = {expected}, got {shape}")
    try:
        dtype = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"dtype: expected a NumPy dtype, got {dtype!r}") from None
    if dtype.kind not in "uif":
        raise ValueError(f"dtype: expected integer counts or floats, got {dtype}")
    return _prepared(jax.ShapeDtypeStruct(shape, dtype), calibration)


def correct(raw, calibration: Calibration, *, p=None, intermediates: bool = False, noise=None, p_u=None) -> CorrectionResult:
    """Correct camera frames into reflectance and CIELAB (flat field -> Stage I -> Stage II ->
    Wiener -> Lab), jitted.

    Args:
      raw: sample frames, (H, W, B) or (..., H, W, B), uint16 counts or float, same exposure as
        the calibration's white standard.
      calibration: a `Calibration` with matching (H, W, B); rows of one (`Calibration.rows`)
        when `raw` holds those rows of an image.
      p: the white-patch ratio (B,) or (..., B) of the whole image(s) (`patch_ratio`); None =
        computed here from `raw`, which then must be whole frames.
      intermediates: also return v, v_stage1 and v_stage2 (costs three more (H, W, B) cubes).
      noise: a `spherejax.NoiseModel`: the result then also carries reflectance_u, lab_u,
        lab_covariance and p_u, standard uncertainties by first-order propagation through this
        same path (`spherejax.uncertainty`; the sample's, dark and white frames' noise, p's, and
        the model's systematic terms). None (default): nothing of it is computed.
      p_u: with `p` and `noise`, the standard uncertainty of that p (`patch_ratio_u` of the
        whole image).

    Returns:
      `CorrectionResult`: reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W),
      p (..., B), if asked the intermediates, and with `noise` the uncertainties. float32 unless
      the calibration is float64.

    The work is prepared once per calibration and frame shape (`plan`) and kept with the
    calibration, so the first call of a shape costs more than the next ones.
    """
    _check_calibration(calibration)
    what = "the calibration's H, W, B" if calibration.patch is not None else "the calibration rows' H, W, B"
    if isinstance(raw, np.ndarray) and _frames_of(raw, calibration):
        if p is None and noise is None and not intermediates and p_u is None and _direct_numpy(raw):
            prepared = _prepared(raw, calibration)
            if prepared.route == "direct":  # NumPy frames: the fused kernel reads them in place
                return prepared(raw)
        if buffers.stageable(raw):
            raw = buffers.stage(raw)  # NumPy frames into reused, aligned memory (`buffers`)
    raw = _check_raw(raw, calibration, what)
    intermediates = bool(intermediates)
    noise = uncertainty.check_noise(noise, calibration.bands)
    if p is None:
        if calibration.patch is None:
            raise ValueError(
                "p: expected the whole image's white-patch ratio with rows of a calibration "
                "(patch_ratio of the whole image), got None"
            )
        if p_u is not None:
            raise ValueError("p_u: expected None without p (u(p) is computed with p from the patch)")
        return _prepared(raw, calibration)(raw, intermediates=intermediates, noise=noise)
    p = _checks.as_array("p", p)
    bands = calibration.bands
    _checks.require_last_axis("p", p, bands, f"one ratio per band, B = {bands}")
    _checks.require_shape("p", p, (*raw.shape[:-3], bands), "one ratio per band of each image")
    if noise is not None:
        if p_u is None:
            raise ValueError("p_u: expected u(p) (patch_ratio_u of the whole image) with p and noise, got None")
        p_u = _checks.as_array("p_u", p_u)
        _checks.require_shape("p_u", p_u, p.shape, "one standard uncertainty per ratio, like p")
    elif p_u is not None:
        raise ValueError("p_u: expected None without noise (u(p) is used only with a NoiseModel)")
    return _prepared(raw, calibration)(raw, p=p, intermediates=intermediates, noise=noise, p_u=p_u)


def _direct_numpy(raw) -> bool:
    """True for NumPy frames the fused kernel may read where they lie (uint16 or float32,
    C-contiguous): `correct` then leaves them NumPy (the plan decides whether it applies)."""
    return isinstance(raw, np.ndarray) and raw.dtype in (np.dtype(np.uint16), np.dtype(np.float32)) and (
        raw.flags.c_contiguous and raw.ndim >= 3
    )


def _frames_of(raw: np.ndarray, calibration: Calibration) -> bool:
    """True when NumPy raw has the calibration's frame shape (else `_check_raw` says why not)."""
    return raw.ndim >= 3 and tuple(raw.shape[-3:]) == (*calibration.image_shape, calibration.bands)


__all__ = [
    "QUALITY_SATURATED",
    "QUALITY_NONFINITE",
    "QUALITY_WHITE_NOT_ABOVE_DARK",
    "QUALITY_PATCH_UNUSABLE",
    "QUALITY_BELOW_DARK",
    "BELOW_DARK_LIMIT",
    "Calibration",
    "CorrectionResult",
    "correct",
    "plan",
    "patch_ratio",
    "patch_ratio_u",
    "patch_bounding_box",
    "delta_e_map",
]
