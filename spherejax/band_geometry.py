"""Where each band's image lands: the per-band geometry of a filter-wheel instrument.

The paper's instrument images each band through its own filter, rotated into the path between the
lens and the sensor (Zou et al. 2019, Section 5). No two filters are alike, and the lens does not
image every wavelength at the same scale, so each band's image is the scene under its own map
(Brauers, Schulte & Aach, "Multispectral filter-wheel cameras: geometric distortion model and
compensation algorithms", IEEE Trans. Image Processing 17(12), 2008). To first order the map is
affine; a band's pixel coordinates x_b (x = column, y = row, pixel centres at integers) are

    x_b = c + s_b (x - c) + d_b,    as a 2 x 3 matrix [[s_b, 0, e_x], [0, s_b, e_y]],

with c the frame's centre, x the reference geometry's coordinates and, per filter (all lengths on
the sensor, converted to frame pixels by the magnification and the design's pixels per cm):

  tilt    a plane-parallel plate of thickness t and index n tilted by θ displaces the converging
          beam laterally by t sin θ (1 - cos θ / sqrt(n² - sin² θ)) (the plate-displacement
          formula), perpendicular to the tilt's axis: d_b's main term;
  wedge   faces out of parallel by α deviate the beam by (n - 1) α, which moves the image by
          (n - 1) α L at the filter's distance L from the sensor;
  focus   a thickness t_b different from the reference filter's moves the focus by
          (t_b - t_ref)(1 - 1/n); the chief rays keep their direction, so the image scales by
          that over the image distance v (the lens is focused once, with the reference filter);
  colour  the lens's lateral colour: magnification changing by κ per nm of the band's centre
          from the reference band's.

The reference geometry is the reference band's (`REFERENCE_BAND_NM`): the camera is focused and
aligned with its filter in place, so its map is the identity and every other band's is relative
to it, as a calibration that registers bands to one of them finds them. Each filter's tilt axis,
tilt, wedge direction and thickness are drawn per seed within the instrument's tolerances
(`InstrumentModel`'s filter_* fields: see there for the values and their sources), as the
filters of one wheel are. `band_transforms` gives the 16 matrices, optionally rescaled so that
the largest displacement over the frame is a given number of pixels (`spherejax simulate
--band-misregistration PX`); `box_weights` gives, per band, how its pixels integrate the scene
(the renderer's). numpy, float64.
"""

from __future__ import annotations

import numpy as np

from .grid import BAND_CENTRES_NM
from .simulated_instrument import InstrumentModel

#: The band every other is registered to: 560 nm, near the middle of the 16, where the lamp, the
#: filters and the sensor's quantum efficiency give the most signal.
REFERENCE_BAND_NM = 560
REFERENCE_BAND = int(np.flatnonzero(BAND_CENTRES_NM == REFERENCE_BAND_NM)[0])

_ARCSEC = np.pi / (180.0 * 3600.0)


def plate_displacement_mm(thickness_mm, index, tilt_rad):
    """Lateral displacement (mm) of a ray crossing a plane-parallel plate tilted by `tilt_rad`:
    t sin θ (1 - cos θ / sqrt(n² - sin² θ))."""
    sin = np.sin(tilt_rad)
    return thickness_mm * sin * (1.0 - np.cos(tilt_rad) / np.sqrt(index**2 - sin**2))


def physical_transforms(instrument: InstrumentModel, image_shape: tuple[int, int], pixels_per_cm: float, seed: int) -> np.ndarray:
    """(16, 2, 3) maps from the reference geometry to each band's, from the filters' and the
    lens's parameters (module docstring), the reference band's the identity. `pixels_per_cm`:
    frame pixels per cm on the holder (the design's), which with the magnification sets a frame
    pixel's size on the sensor."""
    rng = np.random.default_rng([seed, 45])
    bands = len(BAND_CENTRES_NM)
    axis_angle = rng.uniform(0.0, 2.0 * np.pi, bands)  # direction of each filter's displacement
    tilt = np.radians(instrument.filter_tilt_deg) * rng.uniform(-1.0, 1.0, bands)
    wedge_angle = rng.uniform(0.0, 2.0 * np.pi, bands)
    wedge = instrument.filter_wedge_arcsec * _ARCSEC * rng.uniform(0.0, 1.0, bands)
    thickness = instrument.filter_thickness_mm + instrument.filter_thickness_tolerance_mm * rng.uniform(-1.0, 1.0, bands)
    n = instrument.filter_refractive_index

    pixel_mm = 10.0 / pixels_per_cm * instrument.magnification  # a frame pixel on the sensor
    shift_mm = plate_displacement_mm(thickness, n, tilt)[:, None] * np.stack([np.cos(axis_angle), np.sin(axis_angle)], 1)
    shift_mm += ((n - 1.0) * wedge * instrument.filter_to_sensor_mm)[:, None] * np.stack([np.cos(wedge_angle), np.sin(wedge_angle)], 1)
    focus_mm = (thickness - thickness[REFERENCE_BAND]) * (1.0 - 1.0 / n)
    scale = 1.0 + focus_mm / instrument.image_distance_mm
    scale *= 1.0 + instrument.lens_lateral_colour_per_nm * (BAND_CENTRES_NM - REFERENCE_BAND_NM)
    shift_px = (shift_mm - shift_mm[REFERENCE_BAND]) / pixel_mm
    scale = scale / scale[REFERENCE_BAND]
    return affine(scale, shift_px, image_shape)


def affine(scale: np.ndarray, shift_px: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """(B, 2, 3): x_b = c + s (x - c) + d for scales (B,) and shifts (B, 2) (x, y) about the
    centre c of a frame of `image_shape` (H, W)."""
    height, width = image_shape
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    matrices = np.zeros((len(scale), 2, 3))
    matrices[:, 0, 0] = scale
    matrices[:, 1, 1] = scale
    matrices[:, :, 2] = centre[None] * (1.0 - scale[:, None]) + shift_px
    return matrices


def displacements(transforms: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """(B, H, W, 2): x_b - x at every pixel of the reference geometry, per band."""
    height, width = image_shape
    y, x = np.mgrid[0:height, 0:width].astype(float)
    points = np.stack([x, y, np.ones_like(x)], axis=-1)  # (H, W, 3)
    mapped = np.einsum("bij,hwj->bhwi", transforms, points)
    return mapped - points[None, ..., :2]


def largest_displacement(transforms: np.ndarray, image_shape: tuple[int, int]) -> float:
    """The largest |x_b - x| over the frame and the bands, pixels (at a corner, maps being affine)."""
    height, width = image_shape
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1]], float)
    moved = np.einsum("bij,kj->bki", transforms, corners) - corners[None, :, :2]
    return float(np.max(np.linalg.norm(moved, axis=-1)))


def rms_displacement(transforms_a: np.ndarray, transforms_b: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """(B,) root mean square over the frame of the distance between where two sets of maps send
    each pixel: the measure by which a registration is compared with the truth."""
    difference = displacements(transforms_a, image_shape) - displacements(transforms_b, image_shape)
    return np.sqrt(np.mean(np.sum(difference**2, axis=-1), axis=(1, 2)))


def band_transforms(instrument: InstrumentModel, image_shape: tuple[int, int], pixels_per_cm: float, seed: int) -> np.ndarray:
    """(16, 2, 3) the per-band maps a simulated session renders and records: the physical ones
    (`physical_transforms`), as they are when `instrument.band_misregistration_px` is None (the
    default), rescaled so that their largest displacement over the frame is that when it is a
    number > 0; identities when it is 0."""
    identity = np.broadcast_to(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), (len(BAND_CENTRES_NM), 2, 3)).copy()
    target = instrument.band_misregistration_px
    if target == 0.0:
        return identity
    physical = physical_transforms(instrument, image_shape, pixels_per_cm, seed)
    if target is None:
        return physical
    largest = largest_displacement(physical, image_shape)
    return identity + (physical - identity) * (target / largest)


def box_weights(transforms: np.ndarray, image_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """How each band's pixel integrates a scene that is constant on each reference pixel:
    (indices, weights), each (B, 9, H W), the flat indices (row-major, clamped to the frame) of
    the 3 x 3 reference pixels its footprint can cover and the share of the footprint on each.

    The maps here scale and shift (`physical_transforms`: no rotation or shear), so a band pixel's
    footprint in the reference geometry is an axis-aligned square of side 1 / s centred at
    T⁻¹(x_b): the exact overlaps, per axis, of that square with the pixels k - 1/2 .. k + 1/2,
    normalised to sum to one. That is the sensor's box pixel imaging the scene through the map,
    with no interpolation (a resampling of the rendered reference image would blur it)."""
    linear = transforms[:, :, :2]
    if np.any(linear[:, 0, 1] != 0.0) or np.any(linear[:, 1, 0] != 0.0):
        raise ValueError("box_weights: expected maps that scale and shift (diagonal 2 x 2 parts)")
    height, width = image_shape
    bands = len(transforms)

    def axis(size, scale, offset):
        """(B, 3, size) pixel indices and overlaps along one axis."""
        band_x = np.arange(size, dtype=float)
        centre = (band_x[None] - offset[:, None]) / scale[:, None]  # (B, size): T⁻¹ along the axis
        side = 1.0 / scale[:, None]
        low, high = centre - side / 2.0, centre + side / 2.0
        first = np.floor(low + 0.5)
        index = first[:, None] + np.arange(3)[None, :, None]  # (B, 3, size)
        overlap = np.clip(np.minimum(high[:, None], index + 0.5) - np.maximum(low[:, None], index - 0.5), 0.0, None)
        return np.clip(index, 0, size - 1).astype(np.int64), overlap / side[:, None]

    cols, col_w = axis(width, linear[:, 0, 0], transforms[:, 0, 2])
    rows, row_w = axis(height, linear[:, 1, 1], transforms[:, 1, 2])
    # (B, 3, 3, H, W): rows[j] x cols[i].
    indices = rows[:, :, None, :, None] * width + cols[:, None, :, None, :]
    weights = row_w[:, :, None, :, None] * col_w[:, None, :, None, :]
    return indices.reshape(bands, 9, height * width).astype(np.int32), weights.reshape(bands, 9, height * width)


__all__ = [
    "REFERENCE_BAND",
    "REFERENCE_BAND_NM",
    "affine",
    "band_transforms",
    "box_weights",
    "displacements",
    "largest_displacement",
    "physical_transforms",
    "plate_displacement_mm",
    "rms_displacement",
]
