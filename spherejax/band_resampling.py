"""Bands in register in the correction: each band's flat-fielded response, taken in the band's
own geometry, resampled into the reference band's geometry before Stage I and II.

A filter-wheel instrument images each band through its own filter, so band b's image is the
scene under a 2 x 3 affine map A_b (`band_geometry` models why; `band_registration` estimates the
maps; the convention is the session manifest's: x = column, y = row, pixel centres at integers,
from the reference geometry to the band's):

    v_b(n)   = (u_b(n) - d_b(n)) / (w_b(n) - d_b(n))      Eq. 10 in the band's own geometry, n a
                                                           native pixel (dark and white frames
                                                           share the band's geometry)
    v'_b(y)  = bilinear(v_b, A_b [y; 1])                  y a pixel of the reference geometry

Bilinear, and why: the maps are near the identity (a few pixels of shift, 1e-3 of scale), so
every band is sampled at nearly its own pixel grid and the choice matters only between pixels.
Bilinear weights are non-negative, so an edge between a dark and a bright yarn never overshoots
into responses no material has (cubic and windowed-sinc kernels ring by 5-10 % at a step, which
Stage II and the estimator would turn into colour); its support is 2 x 2, so a strip needs only
ceil(largest displacement) + 1 rows above and below (`halo_px`); and it is continuous
in the sample position, so derivatives with respect to the frames, the calibration and the maps
themselves are finite (piecewise linear). What it costs: at a half-pixel offset it averages two
pixels, smoothing the image's finest detail by up to a quarter of its contrast.

Every kernel, unchanged: `registered_frames` makes frames u'_b = v'_b s'_b, where s' is the white
signal (w - d) resampled the same way (`registered_white`, once per calibration), and the kernels
correct u' with the registered calibration (`registered_calibration`: dark 0, white s', the
patch, Stage II and the estimator unchanged). What every kernel (jax.numpy, fused CPU, Pallas GPU:
`spherejax._engine.kernels`) computes of (u' - 0) / s' is v', so the white patch's ratio p (Eq.
14-15, weighted by the white signal as without registration), Stage I, Stage II and the estimator
all read registered pixels. With identity maps, u' = u - d and s' = w - d: the same numbers as
without registration, to float rounding (tested). This is the definition; on CPU the fused kernel
computes the same outputs (to float rounding) with each row's v' registered inside its own loop,
never writing u' (`spherejax._engine.registered`, kernel/call.h).

Quality (`quality.Quality`): a registered pixel takes the bits of the native pixels it is
interpolated from (any of the 2 x 2 with a weight above 0): saturated, not finite, white not above
dark; and NOT_COVERED where some band's map puts it outside that band's frame.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from .quality import QUALITY_BELOW_DARK, QUALITY_NONFINITE, QUALITY_SATURATED, QUALITY_WHITE_NOT_ABOVE_DARK, Quality

#: The largest displacement a band's map may give anywhere in the frame, pixels: a filter wheel's
#: bands lie within a few pixels of each other (`band_geometry`); 50 admits any instrument that
#: works and refuses a map in the wrong units or convention (a matrix of a 4000-pixel sensor in
#: another's coordinates).
MAX_DISPLACEMENT_PX = 50.0
#: The most the linear part of a map may differ from the identity (scale, rotation, shear): a
#: filter's focus shift scales by 1e-4 to 1e-3 and a tilt rotates by milliradians; 0.05 refuses a
#: map that mirrors, turns or zooms the image, which no filter wheel does.
MAX_LINEAR_DEVIATION = 0.05
#: Tolerance on "inside the band's frame", pixels: a pixel at the frame's border under an identity
#: map stored in float32 lands 1e-6 px outside it.
COVERAGE_TOLERANCE_PX = 1e-3


def check_transforms(transforms, bands: int, image_shape: tuple[int, int]) -> None:
    """Raise ValueError (one line naming the value and what was expected) unless `transforms` is
    (bands, 2, 3), real and finite, each linear part within MAX_LINEAR_DEVIATION of the identity
    and each map's displacement within MAX_DISPLACEMENT_PX over the frame. Traced maps pass."""
    _checks.require_real("band_transforms", transforms)
    if tuple(np.shape(transforms)) != (bands, 2, 3):
        raise ValueError(f"band_transforms: expected shape ({bands}, 2, 3), one 2 x 3 affine map per band, "
                         f"got {tuple(np.shape(transforms))}")
    if not _checks.is_concrete(transforms):
        return
    maps = np.asarray(transforms, np.float64)
    if not np.all(np.isfinite(maps)):
        raise ValueError("band_transforms: expected finite numbers, got a NaN or infinity")
    deviation = np.abs(maps[:, :, :2] - np.eye(2)).max(axis=(1, 2))
    if deviation.max() > MAX_LINEAR_DEVIATION:
        band = int(np.argmax(deviation))
        raise ValueError(f"band_transforms: band {band}'s linear part differs from the identity by {deviation[band]:.3g}, "
                         f"expected at most {MAX_LINEAR_DEVIATION} (a filter wheel shifts and scales its bands slightly)")
    largest = float(np.abs(displacements(maps, image_shape)).max())
    if largest > MAX_DISPLACEMENT_PX:
        raise ValueError(f"band_transforms: a band is displaced by {largest:.3g} px in the frame, expected at most "
                         f"{MAX_DISPLACEMENT_PX:g} px (maps in pixels of this calibration's frame, manifest convention)")


def displacements(transforms: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """(B, 4, 2) displacement (dx, dy) of each band's map at the frame's four corner pixels,
    pixels: an affine map's extremes over the frame."""
    height, width = image_shape
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1]], np.float64)
    return np.einsum("bij,cj->bci", np.asarray(transforms, np.float64), corners) - corners[None, :, :2]


def halo_px(transforms, image_shape: tuple[int, int]) -> int:
    """Pixels of native frames a strip or crop needs beyond its own on every side: the largest
    displacement of any band anywhere in the frame, rounded up, plus the bilinear kernel's one."""
    largest = float(np.abs(displacements(np.asarray(transforms), image_shape)).max())
    return int(math.ceil(largest - COVERAGE_TOLERANCE_PX)) + 1


def read_box(box: tuple[int, int, int, int], transforms, image_shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The native pixels (row0, row1, col0, col1) that the registered pixels of `box` are
    interpolated from: the box grown by `halo_px` on every side, within the frame."""
    halo = halo_px(transforms, image_shape)
    row0, row1, col0, col1 = box
    height, width = image_shape
    return max(row0 - halo, 0), min(row1 + halo, height), max(col0 - halo, 0), min(col1 + halo, width)


def local_transforms(transforms, row0: int, col0: int):
    """The maps of a crop whose pixel (0, 0) is the frame's (row0, col0), in the crop's own pixel
    coordinates, for the reference geometry and every band's alike: A' [x', y', 1] = A [x' + col0,
    y' + row0, 1] - [col0, row0]. (B, 2, 3), traceable; NumPy maps give NumPy maps (float64, and no
    XLA computation compiled for a few dozen numbers)."""
    if isinstance(transforms, np.ndarray):
        origin = np.array([col0, row0], np.float64)
        local = np.array(transforms, np.float64)
        local[:, :, 2] = local[:, :, :2] @ origin + local[:, :, 2] - origin
        return local
    transforms = jnp.asarray(transforms)
    origin = jnp.asarray([col0, row0], transforms.dtype)
    shift = transforms[:, :, :2] @ origin + transforms[:, :, 2] - origin
    return transforms.at[:, :, 2].set(shift)


def source_coordinates(transforms, image_shape: tuple[int, int], dtype):
    """(xs, ys), each (H, W, B) in `dtype`: where each reference pixel lies in each band's frame."""
    height, width = image_shape
    maps = jnp.asarray(transforms).astype(dtype)
    y = jnp.arange(height, dtype=dtype)[:, None, None]
    x = jnp.arange(width, dtype=dtype)[None, :, None]
    xs = maps[:, 0, 0] * x + maps[:, 0, 1] * y + maps[:, 0, 2]
    ys = maps[:, 1, 0] * x + maps[:, 1, 1] * y + maps[:, 1, 2]
    return xs, ys


def _taps(xs, ys, image_shape: tuple[int, int]):
    """The bilinear taps of sample positions (H, W, B): four flat indices into an (H, W, B) array
    (row-major, band last) and their weights, and whether each position lies in its band's frame.
    Positions are clamped into the frame, so the taps of an uncovered one are valid indices."""
    height, width = image_shape
    bands = xs.shape[-1]
    covered = ((xs >= -COVERAGE_TOLERANCE_PX) & (xs <= width - 1 + COVERAGE_TOLERANCE_PX)
               & (ys >= -COVERAGE_TOLERANCE_PX) & (ys <= height - 1 + COVERAGE_TOLERANCE_PX))
    xs = jnp.clip(xs, 0, width - 1)
    ys = jnp.clip(ys, 0, height - 1)
    # floor is piecewise constant (no derivative); the weights carry the position's derivative.
    x0 = jnp.minimum(jax.lax.stop_gradient(jnp.floor(xs)), max(width - 2, 0))
    y0 = jnp.minimum(jax.lax.stop_gradient(jnp.floor(ys)), max(height - 2, 0))
    fx, fy = xs - x0, ys - y0
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
    x1, y1 = jnp.minimum(x0 + 1, width - 1), jnp.minimum(y0 + 1, height - 1)
    band = jnp.arange(bands, dtype=jnp.int32)
    indices = [(yy * width + xx) * bands + band for yy, xx in ((y0, x0), (y0, x1), (y1, x0), (y1, x1))]
    weights = [(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx]
    return indices, weights, covered


def _sample(values, indices, weights):
    """Bilinear samples of `values` (H, W, B) at the taps: (H, W, B)."""
    flat = values.reshape(-1)
    return sum(weight * jnp.take(flat, index, mode="clip") for index, weight in zip(indices, weights))


def _touched(flags, indices, weights):
    """(H, W, B) bool: some tap with a weight above 0 falls on a flagged native pixel."""
    flat = flags.reshape(-1)
    hit = [jnp.take(flat, index, mode="clip") & (weight > 0) for index, weight in zip(indices, weights)]
    return hit[0] | hit[1] | hit[2] | hit[3]


def _white_signal(dark, white):
    """(signal w - d, its pixels without a flat field), native geometry (H, W, B)."""
    signal = white - dark
    unusable = ~(signal > 0) | ~jnp.isfinite(signal)
    return signal, unusable


def registered_white(dark, white, transforms):
    """s' (H, W, B): the white signal w - d resampled into the reference geometry; 1 where it would
    be interpolated from a pixel without a flat field or lies outside its band's frame (pixels
    `registered_frames` flags itself: a finite value there keeps every derivative through the
    kernels finite). dark and white in the compute dtype."""
    signal, unusable = _white_signal(dark, white)
    indices, weights, covered = _taps(*source_coordinates(transforms, dark.shape[:2], dark.dtype), dark.shape[:2])
    resampled = _sample(jnp.where(unusable, 0, signal), indices, weights)
    return jnp.where(covered & ~_touched(unusable, indices, weights), resampled, 1)


def registered_frames(raw, dark, white, transforms, registered_signal, *, saturation):
    """Native frames to registered ones: (u' (..., H, W, B) in the compute dtype, the registered
    pixels' quality bits (..., H, W) uint8).

    Args:
      raw: (..., H, W, B) frames in counts (or floats), each band in its own geometry.
      dark, white: (H, W, B) the calibration's, in the compute dtype (native geometry).
      transforms: (B, 2, 3) each band's map (module docstring).
      registered_signal: `registered_white(dark, white, transforms)`, made once per calibration.
      saturation: the raw level at or above which a pixel is saturated, or None (no check).

    u' = v' s' where a registered pixel's bits are 0; elsewhere u' = -s' (v' = -1), which every
    kernel flags as below dark and gives NaN outputs, finite in value and derivative (a NaN there
    would make the kernels' derivatives with respect to the calibration NaN: 0 * NaN);
    `merged_quality` then puts the registration's bits in place of that flag. Bits: SATURATED,
    NONFINITE, WHITE_NOT_ABOVE_DARK of the native pixels a pixel is interpolated from, NOT_COVERED.
    """
    dtype = dark.dtype
    image_shape = dark.shape[:2]
    signal, unusable = _white_signal(dark, white)
    indices, weights, covered = _taps(*source_coordinates(transforms, image_shape, dtype), image_shape)

    def one(frame):
        frame_f = frame.astype(dtype)
        nonfinite = ~jnp.isfinite(frame_f)
        saturated = (jnp.isfinite(frame_f) & (frame_f >= saturation)) if saturation is not None else jnp.zeros(frame.shape, bool)
        good = ~(nonfinite | saturated | unusable)
        # Safe-where: flagged pixels enter the interpolation as 0 (their own weight is 0 where
        # they matter, and a NaN there would make every derivative through the sum NaN).
        v = jnp.where(good, (frame_f - dark) / jnp.where(unusable, 1, signal), 0)
        resampled = _sample(v, indices, weights)
        def any_band(condition):
            return jnp.any(condition, axis=-1)

        bits = (_bit(any_band(_touched(saturated, indices, weights)), QUALITY_SATURATED)
                | _bit(any_band(_touched(nonfinite, indices, weights)), QUALITY_NONFINITE)
                | _bit(any_band(_touched(unusable, indices, weights)), QUALITY_WHITE_NOT_ABOVE_DARK)
                | _bit(any_band(~covered), int(Quality.NOT_COVERED)))
        usable = (bits == 0)[..., None]
        frames = jnp.where(usable, resampled, -1) * registered_signal
        return frames, bits

    lead = raw.shape[:-3]
    frames, bits = jax.lax.map(one, raw.reshape(-1, *raw.shape[-3:]))
    return frames.reshape(*lead, *frames.shape[-3:]), bits.reshape(*lead, *bits.shape[-2:])


def _bit(condition, bit: int):
    return jnp.where(condition, jnp.uint8(bit), jnp.uint8(0))


def merged_quality(kernel_quality, registration_quality):
    """The kernel's quality bits of registered frames with the registration's: where the
    registration flagged a pixel, its bits replace the BELOW_DARK that the placeholder it put there
    made the kernel set (`registered_frames`); elsewhere the kernel's bits stand. (..., H, W) uint8."""
    placeholder = jnp.uint8(QUALITY_BELOW_DARK)
    flagged = registration_quality != 0
    return jnp.where(flagged, (kernel_quality & ~placeholder) | registration_quality, kernel_quality)


__all__ = [
    "MAX_DISPLACEMENT_PX", "MAX_LINEAR_DEVIATION", "COVERAGE_TOLERANCE_PX", "check_transforms", "displacements",
    "halo_px", "read_box", "local_transforms", "source_coordinates", "registered_white", "registered_frames", "merged_quality",
]
