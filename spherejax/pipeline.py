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

On CPU the per-pixel step in float32 is one fused compiled kernel (`spherejax._engine.fused`); the
jax.numpy code here (`_pixel_outputs`) is its definition, runs everywhere else and gives its
derivatives. For Lab the Wiener matrix and the XYZ weights are folded into one (B, 3) matrix, so
XYZ is computed from v_tilde directly; that equals reflectance @ weights up to rounding (tested).
The estimator's offset r0 is folded the same way: XYZ = v_tilde (W^T weights) + r0 weights.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks, colorimetry, uncertainty
from ._engine import buffers, fused
from .colorimetry import delta_e_2000, xyz_to_lab
from .flatfield import flat_field_unchecked, patch_ratio_weighted
from .grid import N_WAVELENGTHS
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
        Last among the fields so that positional construction keeps its meaning.
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
        patch or when the patch is traced."""
        return None if self.patch is None else patch_bounding_box(self.patch)

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


class CorrectionResult(eqx.Module):
    """Output of `correct`. NaN wherever `quality` != 0.

    Fields:
      reflectance: (..., H, W, 31), 400..700 nm step 10.
      lab: (..., H, W, 3) under the calibration's illuminant.
      quality: (..., H, W) uint8 bit mask, see the QUALITY_* constants; 0 = good.
      p: white-patch ratio (..., B) (Eq. 15).
      v: flat-fielded response (..., H, W, B) (Eq. 10), or None unless intermediates=True.
      v_stage1: Stage I response p v (Eq. 17), or None.
      v_stage2: Stage II response (Eq. 23), the input of the Wiener step, or None.
      reflectance_u: standard uncertainty of `reflectance` (..., H, W, 31), or None unless
        `correct` was given a noise model (`spherejax.uncertainty`).
      lab_u: standard uncertainties of L*, a*, b* (..., H, W, 3), or None.
      lab_covariance: the covariance of Lab (..., H, W, 3, 3) (L*, a* and b* are correlated: they
        share X, Y and Z), or None.
      p_u: standard uncertainty of p (..., B), or None.
    """

    reflectance: jax.Array
    lab: jax.Array
    quality: jax.Array
    p: jax.Array
    v: jax.Array | None = None
    v_stage1: jax.Array | None = None
    v_stage2: jax.Array | None = None
    reflectance_u: jax.Array | None = None
    lab_u: jax.Array | None = None
    lab_covariance: jax.Array | None = None
    p_u: jax.Array | None = None

    @property
    def valid(self) -> jax.Array:
        """Boolean (..., H, W): True where the pixel is good."""
        return self.quality == 0

    def delta_e_map(self, reference):
        """ΔE00 of every pixel against `reference` (see `delta_e_map`)."""
        return delta_e_map(self.lab, reference)

    def delta_e_u(self, reference, reference_covariance=None):
        """Standard uncertainty of `delta_e_map(reference)`, (..., H, W), by first order
        (`uncertainty.delta_e_uncertainty`); needs a result of `correct(..., noise=)`.

        Args:
          reference: one Lab colour (3,) or a Lab image of `lab`'s shape.
          reference_covariance: the reference's covariance, (3, 3) or (..., H, W, 3, 3) (e.g.
            another result's `lab_covariance`), or None for an exact reference.

        0 where ΔE00 is 0, and an understatement near it: ΔE00 is a distance, whose spread about
        0 is not what its first-order term says (docs/uncertainty.md).
        """
        if self.lab_covariance is None:
            raise ValueError("delta_e_u: this result has no uncertainties; expected correct(raw, calibration, noise=NoiseModel(...))")
        reference = _checks.as_array("reference", reference)
        _checks.require_last_axis("reference", reference, 3, "one Lab colour or a Lab image")
        if reference.ndim != 1:
            _checks.require_shape("reference", reference, self.lab.shape, "one Lab colour (3,) or lab's shape")
        if reference_covariance is not None:
            reference_covariance = _checks.as_array("reference_covariance", reference_covariance)
            if reference_covariance.shape not in ((3, 3), tuple(self.lab_covariance.shape)):
                raise ValueError(
                    f"reference_covariance: expected shape (3, 3) or {tuple(self.lab_covariance.shape)}, "
                    f"got {tuple(reference_covariance.shape)}"
                )
        return _delta_e_u(self.lab, self.lab_covariance, reference, reference_covariance)

    def to_xarray(self, attrs=None):
        """The result as an `xarray.Dataset` (copied to host memory): reflectance (..., y, x,
        wavelength) with wavelength in nm, lab (..., y, x, lab), quality (..., y, x), p (...,
        band), and the uncertainties and intermediates this result holds; names and coordinates
        in `spherejax.labelled`. `attrs`: the dataset's attributes (e.g. the illuminant)."""
        from . import labelled

        arrays = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        return labelled.dataset(arrays, attrs=attrs)


@jax.jit
def _delta_e_u(lab, lab_covariance, reference, reference_covariance):
    return uncertainty.delta_e_uncertainty(lab, lab_covariance, reference, reference_covariance)


def delta_e_map(lab, reference):
    """CIEDE2000 map of a Lab image against a reference Lab image or one Lab colour.

    Args:
      lab: (..., H, W, 3), e.g. `correct(...).lab`.
      reference: (3,) for one colour, or a Lab image of the same shape as `lab`.

    Returns:
      ΔE00, shape (..., H, W); NaN where either input is NaN.
    """
    lab = _checks.as_array("lab", lab)
    reference = _checks.as_array("reference", reference)
    _checks.require_last_axis("lab", lab, 3, "L*, a*, b*")
    _checks.require_last_axis("reference", reference, 3, "one Lab colour or a Lab image")
    if reference.ndim != 1:
        _checks.require_shape("reference", reference, lab.shape, "one Lab colour (3,) or lab's shape")
    return delta_e_2000(lab, reference)


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

    def box_of_patch():
        mask = np.asarray(patch) != 0
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        return None if rows.size == 0 else (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)

    if isinstance(patch, jax.Array):  # immutable: its box is worked out once
        return _boxes.get_or_compute((patch,), None, box_of_patch)
    return box_of_patch()  # a NumPy mask may change in place: never remembered


class _RememberedByIdentity:
    """Values worked out from immutable jax.Arrays, remembered for the last `size` sets of arrays
    by their ids and a key, with weak references that tell whether an id is still that array's
    (a freed array's id may be given to a new one). Thread-safe; the value is computed outside
    the lock, so two threads may both compute it once."""

    def __init__(self, size: int):
        self._size = size
        self._entries: dict[tuple, tuple[tuple[weakref.ref, ...], object]] = {}
        self._lock = threading.Lock()

    def get_or_compute(self, arrays: tuple, key, compute):
        index = (*(id(array) for array in arrays), key)
        with self._lock:
            known = self._entries.get(index)
            if known is not None and all(ref() is array for ref, array in zip(known[0], arrays)):
                return known[1]
        value = compute()
        with self._lock:
            self._entries[index] = (tuple(weakref.ref(array) for array in arrays), value)
            while len(self._entries) > self._size:
                del self._entries[next(iter(self._entries))]
        return value


#: Boxes of the last few patches (jax.Arrays): finding the box reads the whole mask, about 0.9 ms
#: a megapixel, which `correct` needs on every call.
_boxes = _RememberedByIdentity(8)


@functools.partial(jax.jit, static_argnames="dtype")
def _no_flat_field_program(dark, white, dtype):
    return _no_flat_field(dark.astype(dtype), white.astype(dtype))


def _flat_field_mask(calibration: Calibration, dtype) -> jax.Array:
    """(H, W) bool `_no_flat_field` of a concrete calibration's dark and white frames in the
    compute dtype (as `_correct_pixels` casts them), worked out once for each pair of arrays and
    dtype (jax.Arrays are immutable: the same ids, while both are alive, are the same values).

    Why. Working it out takes a reduction over the bands of white - dark, which XLA on CPU runs
    as a fusion of its own that reads both frames (128 bytes a pixel in float32) besides the one
    that flat-fields: a fifth of the jax.numpy path's CPU time (12 of 60 ms a megapixel on 2 Zen
    5 cores). Read from here it is one byte a pixel, and the same flags.
    """
    dark, white, dtype = calibration.dark, calibration.white, np.dtype(dtype)
    return _masks.get_or_compute((dark, white), dtype.name, lambda: _no_flat_field_program(dark, white, dtype))


#: `_flat_field_mask` of the last few calibrations (their dark and white frames, and the dtype).
_masks = _RememberedByIdentity(4)


def _patch_flags(raw, raw_f, dark, white, saturation):
    saturated, nonfinite, no_flat_field, below_dark = _pixel_flags(raw, raw_f, dark, white, saturation)
    return saturated | nonfinite | no_flat_field | below_dark


@functools.partial(jax.jit, static_argnames=("box_shape", "raw_is_box"))
def _patch_ratio(raw, calibration: Calibration, box_origin, box_shape, raw_is_box: bool = False):
    """Eq. 14-15 over the usable pixels of the patch's box: p (..., B) in the compute dtype.

    The box is cut here, with its origin (2,) an argument and its shape static, so that patches of
    one size share a compiled program, and `correct` traces this same function into its own:
    the ratio `correct` uses is the one `patch_ratio` returns, bit for bit (strips rely on it).
    raw_is_box: raw is already the box of the frames, (..., h, w, B) (`_correct_directly`).
    """
    raw_f, dark, white, weights = _patch_box_inputs(raw, calibration, box_origin, box_shape, raw_is_box)
    return patch_ratio_weighted(raw_f, dark, white, weights[..., None])


def _patch_box_inputs(raw, calibration: Calibration, box_origin, box_shape, raw_is_box: bool = False):
    """The inputs of Eq. 14-15 over the patch's box: raw (..., h, w, B), dark and white (h, w, B)
    in the compute dtype, and the weights (..., h, w) with unusable pixels at 0. `raw_is_box`: raw
    is that box already."""
    height, width = box_shape

    def box(x, trailing: int):
        lead = x.ndim - 2 - trailing
        zero = jnp.zeros((), box_origin.dtype)  # dynamic_slice wants one index dtype
        start = (zero,) * lead + (box_origin[0], box_origin[1]) + (zero,) * trailing
        return jax.lax.dynamic_slice(x, start, (*x.shape[:lead], height, width, *x.shape[lead + 2:]))

    dtype = _compute_dtype(raw, calibration)
    raw_box = raw if raw_is_box else box(raw, 1)
    raw_f = raw_box.astype(dtype)
    dark, white = box(calibration.dark, 1).astype(dtype), box(calibration.white, 1).astype(dtype)
    # One saturated or non-finite pixel in the patch must not shift p for the whole image.
    bad = _patch_flags(raw_box, raw_f, dark, white, _saturation_level(raw, calibration))
    weights = jnp.where(bad, 0.0, box(calibration.patch, 0).astype(dtype))
    return raw_f, dark, white, weights


@functools.partial(jax.jit, static_argnames=("box_shape",))
def _patch_ratio_std(raw, calibration: Calibration, noise, box_origin, box_shape):
    """u(p) (..., B) over the same pixels as `_patch_ratio` (`uncertainty.patch_ratio_std`)."""
    raw_f, dark, white, weights = _patch_box_inputs(raw, calibration, box_origin, box_shape)
    return uncertainty.patch_ratio_std(raw_f, dark, white, weights, noise)


def _patch_box_arguments(raw, calibration: Calibration):
    """(origin (2,) int32, shape) of the patch's bounding box; the whole frame if the patch is
    traced (`patch_bounding_box`)."""
    box = calibration.patch_box
    r0, r1, c0, c1 = box if box is not None else (0, raw.shape[-3], 0, raw.shape[-2])
    return np.array([r0, c0], np.int32), (r1 - r0, c1 - c0)


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


def _pixel_outputs(raw, dark, white, p, coeffs, wiener, wiener_offset, weights, *, saturation, intermediates=False,
                   no_flat_field=None):
    """The per-pixel path in jax.numpy: the definition the fused CPU kernel is tested against.

    Args: raw (..., H, W, B); dark, white (H, W, B); p (..., B); coeffs (B, 4); wiener W (31, B);
    wiener_offset r0 (31,); weights (31, 3) tristimulus weights; all but raw in the compute dtype.
    no_flat_field: None, or the (H, W) bool `_no_flat_field(dark, white)` (`_flat_field_mask`).

    reflectance = v_tilde W^T + r0 and XYZ = v_tilde (W^T weights) + r0 weights, the latter
    being reflectance @ weights (ASTM E308) regrouped so that the 31-channel cube is not read
    back; both on good pixels only.

    Returns (reflectance, lab, quality), then v, v_stage1 and v_stage2 if `intermediates`.
    """
    dtype = dark.dtype
    raw_f = raw.astype(dtype)
    quality = _quality(raw, raw_f, dark, white, p, saturation, no_flat_field)
    good = (quality == 0)[..., None]

    p_pixel = p[..., None, None, :]
    v = flat_field_unchecked(raw_f, dark, white)
    # Safe-where: bad pixels continue as 0 and become NaN in the projections below. A NaN
    # carried into Stage II would make d(output)/d(coeffs) NaN even where the cotangent is 0.
    v_safe = jnp.where(good, v, 0.0)
    v_stage2_safe = stage2_unchecked(v_safe, p_pixel, coeffs)

    # Lab from v_tilde through the folded (B, 3) matrix W^T @ weights: XYZ never goes through the
    # 31-channel cube. (One (B, 34) matmul sliced into the two outputs measured twice as slow:
    # the slices are copies.)
    reflectance = _project_good_pixels(good, v_stage2_safe, wiener.T, wiener_offset)
    xyz = _project_good_pixels(
        good, v_stage2_safe, jnp.matmul(wiener.T, weights, precision=_HIGHEST),
        jnp.matmul(wiener_offset, weights, precision=_HIGHEST),
    )
    lab = xyz_to_lab(xyz, jnp.sum(weights, axis=0))
    if not intermediates:
        return reflectance, lab, quality
    v_out = jnp.where(good, v, jnp.nan)
    v_stage2_out = jnp.where(good, v_stage2_safe, jnp.nan)
    return reflectance, lab, quality, v_out, v_out * p_pixel, v_stage2_out


#: Pixels per block of the jax.numpy path on CPU (`_pixel_outputs_in_blocks`): a block's
#: intermediates (16 + 34 channels of float32, about 3.5 MB) stay in the L2/L3 caches.
CPU_BLOCK_PIXELS = 16384


def _pixel_outputs_in_blocks(raw, dark, white, p, coeffs, wiener, wiener_offset, weights, *, saturation, out=None,
                             block_pixels=CPU_BLOCK_PIXELS, no_flat_field=None):
    """`_pixel_outputs` (without intermediates) over blocks of `CPU_BLOCK_PIXELS` pixels in one
    XLA loop: the jax.numpy path as it runs on CPU.

    Why. XLA on CPU does not fuse the Wiener projection (a matmul) with the elementwise steps
    around it, so on a whole image the Stage II cube (64 MB a megapixel) and the projections
    before their offset (136 MB) are written to memory and read back, and XLA allocates those
    temporaries afresh on every call, from pages the kernel must fault and zero (glibc maps
    blocks that large). Block by block the same steps stay in cache and the temporaries are a
    few MB, which malloc reuses.

    Each block runs `_pixel_outputs` on (N, 1, S, B) rows of pixels: the same equations on
    every pixel, and the same numbers as the whole image up to the matmul's rounding (tested).

    Args: as `_pixel_outputs`, raw (..., H, W, B); out: None, or arrays of the outputs' shapes
    and dtypes whose memory the outputs take (donated; their values are never read). Without
    them the outputs start as zeros (one write pass). block_pixels: pixels per block, over all
    images of a batch (each block takes the same rows of every image). no_flat_field: as
    `_pixel_outputs`.

    Returns (reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W)).
    """
    *batch, height, width, bands = raw.shape
    pixels = height * width
    images = int(np.prod(batch, dtype=np.int64))
    block = max(1, block_pixels // max(images, 1))
    plain = functools.partial(_pixel_outputs, saturation=saturation, intermediates=False)
    if block >= pixels or images == 0:
        return plain(raw, dark, white, p, coeffs, wiener, wiener_offset, weights, no_flat_field=no_flat_field)
    dtype = dark.dtype
    raw_rows = raw.reshape(images, pixels, bands)
    dark_rows, white_rows = dark.reshape(pixels, bands), white.reshape(pixels, bands)
    p_rows = jnp.broadcast_to(p, (*batch, bands)).reshape(images, bands)
    mask_rows = None if no_flat_field is None else no_flat_field.reshape(pixels)

    def outputs_of(start, size):
        def rows(x, axis):
            return jax.lax.dynamic_slice_in_dim(x, start, size, axis=axis)

        reflectance, lab, quality = plain(
            rows(raw_rows, 1)[:, None], rows(dark_rows, 0)[None], rows(white_rows, 0)[None], p_rows, coeffs,
            wiener, wiener_offset, weights, no_flat_field=None if mask_rows is None else rows(mask_rows, 0)[None],
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
    # call after a pause took 47-51 ms a megapixel, now 35-39, and back to back 34, now 32
    # (benchmarks/README.md, seventh speed session). The blocks are the same, so the numbers are.
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


# jax.jit rather than eqx.filter_jit, here and for _patch_ratio: every array in a Calibration is a
# leaf and everything else static, so plain jit applies, and its C++ dispatch saves about 0.3 ms a
# call (6 % of a 256 x 256 correction).
@functools.partial(jax.jit, static_argnames=("intermediates", "kernel_mode"))
def _correct_pixels(raw, calibration: Calibration, p, intermediates: bool, kernel_mode: str | None, noise=None, p_u=None, out=None,
                    no_flat_field=None):
    """Every pixel of `raw` (..., H, W, B) given the white-patch ratio p (..., B).

    `kernel_mode` (static; `fused.mode`, decided by the caller so that the environment switch is
    part of the cache key): None for the jax.numpy path, else the fused CPU kernel's mode
    (`spherejax._engine.fused`). With a `NoiseModel` (and p's uncertainty p_u (..., B)) the result also
    carries the uncertainties (`uncertainty.pixel_uncertainty`); None traces none of that. `out`:
    None, or donated arrays of the three outputs' shapes whose memory the jax.numpy path's
    outputs take on CPU (`_pixel_outputs_in_blocks`; the kernel's take it through XLA's buffer
    assignment). no_flat_field: None, or the calibration's (H, W) `_flat_field_mask`, which the
    jax.numpy path then reads instead of working it out from dark and white again.
    """
    result = _correct_pixels_plain(raw, calibration, p, intermediates, kernel_mode, out, no_flat_field)
    if noise is None:
        return result
    dtype = _compute_dtype(raw, calibration)
    weights = jnp.asarray(colorimetry.tristimulus_weights(calibration.illuminant, observer=calibration.observer), dtype)
    p_u = p_u.astype(dtype)
    reflectance_u, lab_covariance = uncertainty.pixel_uncertainty(
        raw.astype(dtype), calibration.dark.astype(dtype), calibration.white.astype(dtype),
        (result.quality == 0)[..., None], result.p, p_u, calibration.coeffs.astype(dtype),
        calibration.wiener.astype(dtype), calibration.wiener_offset.astype(dtype), weights, noise,
    )
    lab_u = jnp.sqrt(jnp.diagonal(lab_covariance, axis1=-2, axis2=-1))
    return dataclasses.replace(
        result, reflectance_u=reflectance_u, lab_u=lab_u, lab_covariance=lab_covariance, p_u=p_u
    )


def _correct_pixels_plain(raw, calibration: Calibration, p, intermediates: bool, kernel_mode: str | None, out=None,
                          no_flat_field=None):
    """`_correct_pixels` without uncertainties (traced inside it)."""
    dtype = _compute_dtype(raw, calibration)
    weights = colorimetry.tristimulus_weights(calibration.illuminant, observer=calibration.observer)
    arrays = (
        raw, calibration.dark.astype(dtype), calibration.white.astype(dtype), p.astype(dtype),
        calibration.coeffs.astype(dtype), calibration.wiener.astype(dtype),
        calibration.wiener_offset.astype(dtype), jnp.asarray(weights, dtype),
    )
    saturation = _saturation_level(raw, calibration)
    plain = functools.partial(
        _pixel_outputs, saturation=saturation, intermediates=intermediates, no_flat_field=no_flat_field
    )
    p = arrays[3]
    if kernel_mode is not None:
        main = functools.partial(_pixel_outputs, saturation=saturation, intermediates=False)
        reflectance, lab, quality = fused.correct_pixels(main, *arrays, saturation=saturation, kernel_mode=kernel_mode)
        cubes = ()
        if intermediates:
            # The main outputs stay the kernel's whatever else is asked for; the cubes it never
            # forms come from the jax.numpy path, whose reflectance and Lab XLA drops as unused.
            _, _, _, *cubes = plain(*arrays)
        return CorrectionResult(reflectance, lab, quality, p, *cubes)
    if intermediates:
        reflectance, lab, quality, *cubes = plain(*arrays)
        return CorrectionResult(reflectance, lab, quality, p, *cubes)

    def on_cpu(*arrays):
        return _pixel_outputs_in_blocks(*arrays, saturation=saturation, out=out, no_flat_field=no_flat_field)

    reflectance, lab, quality = jax.lax.platform_dependent(*arrays, cpu=on_cpu, default=plain)
    return CorrectionResult(reflectance, lab, quality, p)


@functools.partial(jax.jit, static_argnames=("box_shape", "intermediates", "kernel_mode"))
def _correct_image(raw, calibration: Calibration, box_origin, box_shape, intermediates: bool, kernel_mode: str | None, noise=None, out=None,
                   no_flat_field=None):
    """`correct` of whole frames as one program: p over the patch's box, then every pixel.

    The same two steps as `patch_ratio` then `_correct_pixels`, traced together: one dispatch
    instead of two and no wait between them, 1.5-2.5 ms a call (benchmarks/README.md).
    """
    p = _patch_ratio(raw, calibration, box_origin, box_shape)
    p_u = None if noise is None else _patch_ratio_std(raw, calibration, noise, box_origin, box_shape)
    return _correct_pixels(
        raw, calibration, p, intermediates=intermediates, kernel_mode=kernel_mode, noise=noise, p_u=p_u, out=out,
        no_flat_field=no_flat_field,
    )


# keep_unused: jit would otherwise drop the unused donated arguments from the program, and their
# memory with them.
@functools.partial(
    jax.jit, static_argnames=("box_shape", "kernel_mode"), donate_argnames=("out_reflectance", "out_lab", "out_quality"),
    keep_unused=True,
)
def _correct_image_into(raw, calibration: Calibration, box_origin, out_reflectance, out_lab, out_quality, no_flat_field=None, *, box_shape, kernel_mode: str | None):
    """`_correct_image` with the memory of three donated arrays of the outputs' shapes and dtypes
    (dropped outputs of earlier calls, `spherejax._engine.buffers`): their values are not read, and
    their memory becomes the outputs' (XLA's buffer assignment gives it to the kernel's outputs
    of the same shapes; the jax.numpy path's loop writes its blocks into them). The same program
    otherwise, and the same numbers. no_flat_field: as `_correct_pixels`."""
    out = (out_reflectance, out_lab, out_quality)
    return _correct_image(
        raw, calibration, box_origin, box_shape, intermediates=False, kernel_mode=kernel_mode, out=out,
        no_flat_field=no_flat_field,
    )


#: Compiled `_correct_image_into` per signature (raw, calibration's structure and shapes, patch
#: box, kernel mode): compiled ahead, with the first large image of a signature, so that later
#: calls never compile (tests/test_compilation.py).
_into_executables: dict = {}
_into_lock = threading.Lock()


def _signature(raw, calibration: Calibration, box_shape, kernel_mode):
    leaves, structure = jax.tree_util.tree_flatten(calibration)
    return (
        tuple(raw.shape), str(raw.dtype), structure,
        tuple((tuple(x.shape), str(x.dtype), getattr(x, "weak_type", False)) for x in leaves), box_shape, kernel_mode,
    )


def _correct_recycling(raw, calibration: Calibration, box_origin, box_shape, kernel_mode: str | None) -> CorrectionResult:
    """`_correct_image` for large images on CPU, reusing the memory of outputs the caller has
    dropped (`spherejax._engine.buffers`); the same numbers bit for bit (tested). The jax.numpy path
    (kernel_mode None) reads the calibration's `_flat_field_mask`."""
    outputs_shape = tuple(raw.shape[:-1])
    dtype = _compute_dtype(raw, calibration)  # float32, or float64 on the jax.numpy path
    mask = _flat_field_mask(calibration, dtype) if kernel_mode is None else None
    signature = _signature(raw, calibration, box_shape, kernel_mode)
    with _into_lock:
        executable = _into_executables.get(signature)
        if executable is None:
            out_types = (
                jax.ShapeDtypeStruct((*outputs_shape, N_WAVELENGTHS), dtype),
                jax.ShapeDtypeStruct((*outputs_shape, 3), dtype),
                jax.ShapeDtypeStruct(outputs_shape, jnp.uint8),
            )
            executable = _correct_image_into.lower(
                raw, calibration, box_origin, *out_types, mask, box_shape=box_shape, kernel_mode=kernel_mode
            ).compile()
            _into_executables[signature] = executable
    key = (outputs_shape, str(dtype))
    out = buffers.take(key)
    if out is None:
        result = _correct_image(
            raw, calibration, box_origin, box_shape, intermediates=False, kernel_mode=kernel_mode, no_flat_field=mask
        )
    else:
        result = executable(raw, calibration, box_origin, *out, mask)
    buffers.give(key, (result.reflectance, result.lab, result.quality))
    return result


def _direct(raw, calibration: Calibration, kernel_mode: str | None) -> bool:
    """True when `_correct_directly` applies: NumPy frames the kernel reads as they are (uint16
    or float32, C-contiguous), whole frames of a concrete float32 calibration on the CPU, the
    kernel on, outputs large enough to be worth keeping (`buffers.MIN_BYTES`)."""
    return (
        kernel_mode is not None and isinstance(raw, np.ndarray) and buffers.stageable(raw)
        and raw.dtype in fused.RAW_DTYPES and raw.flags.c_contiguous and raw.ndim >= 3
        and raw.shape[-3:] == (*calibration.image_shape, calibration.bands)
        and calibration.patch_box is not None
        and calibration.dark.dtype == np.float32 and calibration.white.dtype == np.float32
        and _concrete_on_one_cpu(jax.tree_util.tree_leaves(calibration))
        and int(np.prod(raw.shape[:-1], dtype=np.int64)) * (4 * (N_WAVELENGTHS + 3) + 1) >= buffers.MIN_BYTES
    )


@jax.jit
def _kernel_constants(calibration: Calibration):
    """coeffs (B, 4), projection (B, 34), bias (34,) and white_xyz (3,) in float32, as
    `fused.correct_pixels` gives them to the kernel (`fused.kernel_constants`)."""
    f32 = jnp.float32
    weights = colorimetry.tristimulus_weights(calibration.illuminant, observer=calibration.observer)
    constants = fused.kernel_constants(
        calibration.wiener.astype(f32), calibration.wiener_offset.astype(f32), jnp.asarray(weights, f32)
    )
    return calibration.coeffs.astype(f32), *constants


def _correct_directly(raw: np.ndarray, calibration: Calibration, box_origin, box_shape, kernel_mode: str) -> CorrectionResult:
    """`correct` of NumPy frames (..., H, W, B) by the fused kernel called directly
    (`fused.correct_arrays`), without XLA: the same numbers as `_correct_image` bit for bit
    (tested), but the kernel reads the frames where they lie, where `_correct_image` needs them
    copied into XLA's memory first (32 MB a megapixel of uint16). The outputs are written into
    reused NumPy memory (`buffers.take_host`) and handed to JAX without a copy.

    p comes from `_patch_ratio` on the patch's box of the frames (a small copy), the kernel's
    constants from `_kernel_constants`: the programs `_correct_image` traces into its own.
    """
    (r0, c0), (h, w) = box_origin, box_shape
    p = _patch_ratio(raw[..., r0:r0 + h, c0:c0 + w, :], calibration, box_origin, box_shape, raw_is_box=True)
    coeffs, projection, bias, white_xyz = (np.asarray(x) for x in _kernel_constants(calibration))
    *batch, height, width, bands = raw.shape
    images, pixels = int(np.prod(batch, dtype=np.int64)), height * width
    pairs = buffers.take_host(
        tuple(raw.shape[:-1]),
        (((*batch, height, width, N_WAVELENGTHS), np.float32), ((*batch, height, width, 3), np.float32),
         ((*batch, height, width), np.uint8)),
    )
    (reflectance, _), (lab, _), (quality, _) = pairs
    fused.correct_arrays(
        raw.reshape(images, pixels, bands), np.asarray(calibration.dark).reshape(pixels, bands),
        np.asarray(calibration.white).reshape(pixels, bands), np.asarray(p).reshape(images, bands), coeffs,
        projection, bias, white_xyz, _saturation_level(raw, calibration), kernel_mode,
        (reflectance.reshape(images, pixels, N_WAVELENGTHS), lab.reshape(images, pixels, 3),
         quality.reshape(images, pixels)),
        threads=buffers.cpus(),
    )
    cpu = jax.devices("cpu")[0]
    outputs = tuple(jax.device_put(view, cpu, may_alias=True) for view, _ in pairs)
    del reflectance, lab, quality  # only the pool and the jax.Arrays refer to the memory now
    buffers.give(("host", tuple(raw.shape[:-1])), pairs)
    return CorrectionResult(*outputs, p)


def _mapped_over_frames(raw, calibration: Calibration) -> bool:
    """True when `raw` is traced and the calibration is not: possibly `jax.vmap` over frames of
    one calibration (`_correct_mappable`); or `jit` or a derivative with respect to raw, which
    `_correct_mappable` passes through unchanged."""
    return not _checks.is_concrete(raw) and all(_checks.is_concrete(x) for x in jax.tree_util.tree_leaves(calibration))


def _correct_mappable(raw, calibration: Calibration, box_origin, box_shape, kernel_mode: str | None) -> CorrectionResult:
    """`_correct_image` of traced frames and a concrete calibration, so that `jax.vmap` over the
    frames reuses dropped outputs' memory as `correct` on the stack does.

    Why. `jax.vmap(lambda r: sj.correct(r, calibration).lab)(frames)` runs `correct` on tracers,
    so `_correct_recycling` cannot apply and every call writes its outputs into fresh pages: 3.5
    times slower per pixel than `correct(frames, calibration)` (benchmarks/bench_batch.py). Here
    the frames' mapping rule (`jax.custom_batching.custom_vmap`) sees the stacked frames and
    corrects them as one stack (`_correct_frames`): without an enclosing `jit` they are concrete
    and reuse memory; under `jit` they are traced and XLA owns the memory.

    Derivatives: `custom_vmap` has no transpose, so the whole sits in a `custom_jvp` whose JVP is
    `_correct_image`'s: `jax.grad` and `jax.jvp` with respect to raw see what they saw before.
    Without a mapping the value is `_correct_image`'s, traced as before.
    """
    def image(frames):
        return _correct_image(frames, calibration, box_origin, box_shape, intermediates=False, kernel_mode=kernel_mode)

    @jax.custom_batching.custom_vmap
    def mappable(frames):
        return image(frames)

    @mappable.def_vmap
    def over_frames(axis_size, in_batched, frames):
        del axis_size, in_batched  # the only argument, so mapped, with the mapped axis first
        if buffers.stageable(frames):  # vmap hands NumPy frames on as they are
            frames = buffers.stage(frames)
        result = _correct_frames(frames, calibration, box_origin, box_shape, kernel_mode)
        return result, jax.tree_util.tree_map(lambda _: True, result)

    @jax.custom_jvp
    def differentiable(frames):
        return mappable(frames)

    @differentiable.defjvp
    def differentiable_jvp(primals, tangents):
        return jax.jvp(image, primals, tangents)

    return differentiable(raw)


def _correct_frames(raw, calibration: Calibration, box_origin, box_shape, kernel_mode: str | None) -> CorrectionResult:
    """Whole frames (..., H, W, B), no noise, no intermediates: into the memory of dropped outputs
    where `_recyclable`, else `_correct_image`."""
    if _recyclable(raw, calibration):
        return _correct_recycling(raw, calibration, box_origin, box_shape, kernel_mode)
    return _correct_image(raw, calibration, box_origin, box_shape, intermediates=False, kernel_mode=kernel_mode)


def _recyclable(raw, calibration: Calibration) -> bool:
    """True when `correct` may reuse dropped outputs' memory (`spherejax._engine.buffers`): concrete
    arrays, all on one CPU device, outputs of at least `buffers.MIN_BYTES`."""
    pixels = int(np.prod(raw.shape[:-1], dtype=np.int64))
    if pixels * (4 * (N_WAVELENGTHS + 3) + 1) < buffers.MIN_BYTES:
        return False
    return _concrete_on_one_cpu((raw, *jax.tree_util.tree_leaves(calibration)))


def _concrete_on_one_cpu(arrays) -> bool:
    """True when every array is a concrete jax.Array and all are on one CPU device."""
    if not all(_checks.is_concrete(x) for x in arrays):
        return False
    try:
        devices = set().union(*(x.devices() for x in arrays))
    except AttributeError:  # not a jax.Array
        return False
    return len(devices) == 1 and next(iter(devices)).platform == "cpu"


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
    box_origin, box_shape = _patch_box_arguments(raw, calibration)
    return _patch_ratio(raw, calibration, box_origin, box_shape)


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
    box_origin, box_shape = _patch_box_arguments(raw, calibration)
    return _patch_ratio_std(raw, calibration, noise, box_origin, box_shape)


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
    """
    _check_calibration(calibration)
    what = "the calibration's H, W, B" if calibration.patch is not None else "the calibration rows' H, W, B"
    if p is None and noise is None and not intermediates and p_u is None:
        kernel_mode = fused.mode(raw.dtype, _compute_dtype(raw, calibration), calibration.bands) if isinstance(raw, np.ndarray) else None
        if _direct(raw, calibration, kernel_mode):  # NumPy frames: the kernel reads them in place
            return _correct_directly(raw, calibration, *_patch_box_arguments(raw, calibration), kernel_mode)
    if buffers.stageable(raw) and raw.shape[-3:] == (*calibration.image_shape, calibration.bands):
        raw = buffers.stage(raw)  # NumPy frames into reused, aligned memory (`spherejax._engine.buffers`)
    raw = _check_raw(raw, calibration, what)
    intermediates = bool(intermediates)
    noise = uncertainty.check_noise(noise, calibration.bands)
    kernel_mode = fused.mode(raw.dtype, _compute_dtype(raw, calibration), calibration.bands)
    if p is None:
        if calibration.patch is None:
            raise ValueError(
                "p: expected the whole image's white-patch ratio with rows of a calibration "
                "(patch_ratio of the whole image), got None"
            )
        if p_u is not None:
            raise ValueError("p_u: expected None without p (u(p) is computed with p from the patch)")
        box_origin, box_shape = _patch_box_arguments(raw, calibration)
        if noise is None and not intermediates:
            if _mapped_over_frames(raw, calibration):
                return _correct_mappable(raw, calibration, box_origin, box_shape, kernel_mode)
            return _correct_frames(raw, calibration, box_origin, box_shape, kernel_mode)
        return _correct_image(
            raw, calibration, box_origin, box_shape, intermediates=intermediates, kernel_mode=kernel_mode, noise=noise
        )
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
    return _correct_pixels(raw, calibration, p, intermediates=intermediates, kernel_mode=kernel_mode, noise=noise, p_u=p_u)


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
    "patch_ratio",
    "patch_ratio_u",
    "patch_bounding_box",
    "delta_e_map",
]
