"""Registering a filter-wheel instrument's bands: each band's affine map from the reference
band's geometry, estimated from a session's frames, sub-pixel.

A filter wheel images each band through its own filter, so each band's image is the scene under
its own map (`band_geometry` models why). Bands differ in contrast, and an edge between two
materials may even change sign from band to band, so the bands are compared by where their
edges are, not by their values:

1. Flat-field each band in its own geometry, v_b = (u_b - d_b) / (w_b - d_b) (Eq. 10: the dark and
   white frames share the band's geometry), and take its edge map e_b: the gradient's magnitude
   over the median of the frame's strongest tenth, saturated (e / (1 + e)) so that no edge of
   unusual contrast outweighs the rest. Pixels near edges of the white frame itself (the
   holder's border, the white patch) are left out (`white_structure`), as is a border.
2. Coarse: the whole frame's phase correlation (Kuglin & Hines 1975) within 10 px of no shift.
3. Fine: the map maximising the enhanced correlation coefficient (ECC, Evangelidis & Psarakis
   2008) of e_ref and e_b sampled through it (bilinear), by Levenberg-Marquardt (optimistix) on
   the standardised difference, on edge maps blurred by 4, 2 and 1 px in turn; both ways (band
   onto reference and back), averaged, which cancels most of the pull of interpolation towards
   whole pixels.

Accuracy on simulated sessions (`tests/test_band_registration.py`): within 0.07 px RMS over the
frame of the truth, at 2 px of misregistration and in register alike; what is left comes from
edges one band shows and another does not.

`edge_strength` and `tile_shifts` check that a frame has structure enough (edges of at least
MIN_EDGE_STRENGTH in every band, at least 6 tiles of 48 px with edges), and the tiles' own shifts about the fitted map give each band's residual (pixels): what the map
leaves unexplained, plus the tiles' own scatter (~0.3 px). The reference band is 560 nm
(`band_geometry.REFERENCE_BAND`); the maps follow the session manifest's convention
(`spherejax.io`: x = column, y = row, pixel centres at integers, from the reference geometry to
the band's).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .band_geometry import REFERENCE_BAND
from .flatfield import flat_field

#: Tile size and step of the coarse search, pixels.
TILE_PX, TILE_STEP_PX = 48, 24
#: The least `edge_strength` (flat-fielded response per pixel) a band of the capture must have:
#: a capture of a uniform surface has only its noise's (thousandths); a target chart's is 0.05
#: and more in every band.
MIN_EDGE_STRENGTH = 0.01
#: Pixels left out at the frame's border in the fine fit (a map moves the border's content out).
BORDER_PX = 6


@dataclasses.dataclass(frozen=True)
class BandRegistration:
    """Each band's map from the reference band's geometry (manifest convention).

    transforms: (B, 2, 3) float64, the reference band's the identity.
    residual_px: (B,) rms of the coarse tiles' shifts about the fitted map, pixels (0 for the
      reference band).
    tiles: (B,) how many tiles held enough structure to be used.
    reference_band: index of the reference band.
    """

    transforms: np.ndarray
    residual_px: np.ndarray
    tiles: np.ndarray
    reference_band: int


def edge_strength(image: np.ndarray) -> float:
    """The median gradient magnitude of the strongest tenth of one band's pixels (response per
    pixel): how sharp the frame's edges are in that band."""
    gy, gx = np.gradient(image)
    magnitude = np.hypot(gx, gy)
    strong = magnitude[magnitude >= np.percentile(magnitude, 90)]
    return float(np.median(strong))


def edge_map(image: np.ndarray) -> np.ndarray:
    """(H, W) saturated gradient magnitude of one band (module docstring, step 1)."""
    gy, gx = np.gradient(image)
    e = np.hypot(gx, gy) / max(edge_strength(image), 1e-12)
    return e / (1.0 + e)


def _phase_correlation(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """(shift (dx, dy) of b relative to a, peak height) for two same-size windowed tiles."""
    cross = np.fft.fft2(b) * np.conj(np.fft.fft2(a))
    cross /= np.maximum(np.abs(cross), 1e-12)
    surface = np.real(np.fft.ifft2(cross))
    height, width = surface.shape
    peak = np.unravel_index(int(np.argmax(surface)), surface.shape)

    def refine(axis_values, centre):
        left, mid, right = axis_values
        denominator = left - 2.0 * mid + right
        return centre + (0.5 * (left - right) / denominator if denominator < 0 else 0.0)

    r, c = peak
    dy = refine((surface[(r - 1) % height, c], surface[r, c], surface[(r + 1) % height, c]), r)
    dx = refine((surface[r, (c - 1) % width], surface[r, c], surface[r, (c + 1) % width]), c)
    dy = dy - height if dy > height / 2 else dy
    dx = dx - width if dx > width / 2 else dx
    return np.array([dx, dy]), float(surface[r, c])


def tile_shifts(reference: np.ndarray, band: np.ndarray, tile: int = TILE_PX, step: int = TILE_STEP_PX):
    """Coarse step 2: (centres (n, 2) (x, y), shifts (n, 2), peak heights (n,)) of the tiles with
    structure (a tile whose reference edge map is nearly flat is left out)."""
    height, width = reference.shape
    window = np.outer(np.hanning(tile), np.hanning(tile))
    centres, shifts, peaks = [], [], []
    busy = np.percentile(reference, 75)
    for r0 in range(0, height - tile + 1, step):
        for c0 in range(0, width - tile + 1, step):
            a = reference[r0 : r0 + tile, c0 : c0 + tile]
            if a.mean() < 0.25 * busy:
                continue
            b = band[r0 : r0 + tile, c0 : c0 + tile]
            shift, peak = _phase_correlation((a - a.mean()) * window, (b - b.mean()) * window)
            centres.append((c0 + (tile - 1) / 2.0, r0 + (tile - 1) / 2.0))
            shifts.append(shift)
            peaks.append(peak)
    return np.asarray(centres, float).reshape(-1, 2), np.asarray(shifts, float).reshape(-1, 2), np.asarray(peaks, float)


@eqx.filter_jit
def _refine(reference, band, weights, start):
    """Fine step 3: the 2 x 3 map (from `start`) maximising the ECC of `band` sampled through it
    and `reference` over the pixels `weights` selects."""
    height, width = reference.shape
    y, x = jnp.mgrid[0:height, 0:width].astype(reference.dtype)

    total = jnp.sum(weights)

    def standardised(image):
        mean = jnp.sum(weights * image) / total
        centred = image - mean
        return centred / jnp.sqrt(jnp.sum(weights * centred**2) / total)

    target = standardised(reference)

    def residuals(params, _):
        matrix = params.reshape(2, 3)
        bx = matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2]
        by = matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2]
        seen = jax.scipy.ndimage.map_coordinates(band, [by, bx], order=1, mode="nearest")
        # Both standardised over the same pixels: the squared residual is 2 - 2 ECC (Evangelidis &
        # Psarakis 2008), blind to the bands' contrasts and to how much edge a map moves in or
        # out of the pixels compared (a plain least-squares misfit biased the scale by that).
        return (jnp.sqrt(weights) * (standardised(seen) - target)).reshape(-1)

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    solution = optx.least_squares(residuals, solver, start.reshape(-1), max_steps=100, throw=False)
    return solution.value.reshape(2, 3)


def blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    """A Gaussian blur of standard deviation `sigma` pixels (separable, the edges extended);
    sigma 0 returns the image."""
    if sigma <= 0:
        return image
    radius = int(np.ceil(3 * sigma))
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.pad(image, radius, mode="edge")
    rows = np.apply_along_axis(lambda r: np.convolve(r, kernel, mode="valid"), 1, padded)
    return np.apply_along_axis(lambda c: np.convolve(c, kernel, mode="valid"), 0, rows)


def global_shift(reference: np.ndarray, band: np.ndarray, max_shift_px: float = 10.0) -> np.ndarray:
    """(dx, dy): the whole frame's phase correlation peak within `max_shift_px` of no shift (a
    chart's regular grid makes peaks at multiples of its period too; a filter wheel's bands are
    a few pixels apart at most)."""
    window = np.outer(np.hanning(reference.shape[0]), np.hanning(reference.shape[1]))
    a, b = (reference - reference.mean()) * window, (band - band.mean()) * window
    cross = np.fft.fft2(b) * np.conj(np.fft.fft2(a))
    surface = np.real(np.fft.ifft2(cross / np.maximum(np.abs(cross), 1e-12)))
    height, width = surface.shape
    dy = np.fft.fftfreq(height) * height
    dx = np.fft.fftfreq(width) * width
    surface = np.where(np.hypot(dy[:, None], dx[None, :]) <= max_shift_px, surface, -np.inf)
    r, c = np.unravel_index(int(np.argmax(surface)), surface.shape)
    return np.array([dx[c], dy[r]])


def white_structure(level: np.ndarray, reach_px: int = 4) -> np.ndarray:
    """(H, W) bool: pixels within `reach_px` of an edge of the white frame itself (the holder's
    border against the mount, the white patch), in any band. Flat-fielding divides a partly
    covered pixel of such an edge by the white frame's own partly covered pixel, which moves the
    edge by a band-dependent fraction of a pixel; those pixels say nothing reliable about where
    a band lies. Elsewhere the white frame is smooth (vignetting, filter gradients)."""
    mask = np.zeros(level.shape[:2], bool)
    for b in range(level.shape[-1]):
        gy, gx = np.gradient(level[..., b])
        magnitude = np.hypot(gx, gy)
        mask |= magnitude > 0.05 * np.percentile(level[..., b], 99)
    grown = mask.copy()
    for _ in range(reach_px):  # dilation by a 3 x 3 square, reach_px times
        padded = np.pad(grown, 1)
        grown = np.any([padded[1 + dy : padded.shape[0] - 1 + dy, 1 + dx : padded.shape[1] - 1 + dx]
                        for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
    return grown


#: The fine fit's blurs, pixels: coarse to fine, each starting from the last's map (a blurred
#: edge map carries the fit to an edge several pixels away; the sharp one pins it).
BLUR_SCHEDULE_PX = (4.0, 2.0, 1.0)


def _inverse(matrix: np.ndarray) -> np.ndarray:
    """The inverse of a 2 x 3 affine map."""
    full = np.vstack([matrix, [0.0, 0.0, 1.0]])
    return np.linalg.inv(full)[:2]


def register_bands(frame: np.ndarray, dark: np.ndarray, white: np.ndarray, reference_band: int = REFERENCE_BAND) -> BandRegistration:
    """Each band's map from `reference_band`'s geometry, from one capture with structure (a chart
    of targets, a patterned sample, a registration target), its session's dark and white frames,
    all (H, W, B) (module docstring for the method).

    Raises:
      ValueError: a frame without enough structure to register a band (its edges weaker than
        MIN_EDGE_STRENGTH, or fewer than 6 tiles with edges), naming the band.
    """
    # Eq. 10 as everywhere (`flatfield.flat_field`); a pixel whose white is not above its dark
    # (NaN there) carries no edge.
    v = np.nan_to_num(np.asarray(flat_field(frame, dark, white), np.float64), nan=0.0)
    height, width, bands = v.shape
    for b in range(bands):
        strength = edge_strength(v[..., b])
        if not strength >= MIN_EDGE_STRENGTH:
            raise ValueError(f"band {b}: its strongest edges change the flat-fielded response by {strength:.2g} a pixel, "
                             f"expected at least {MIN_EDGE_STRENGTH}: a capture with structure across the frame "
                             "(a target chart or a patterned sample)")
    edges = np.stack([edge_map(v[..., b]) for b in range(bands)])
    weights = np.zeros((height, width))
    weights[BORDER_PX : height - BORDER_PX, BORDER_PX : width - BORDER_PX] = 1.0
    weights *= ~white_structure(white.astype(np.float64) - dark)
    identity = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    transforms = np.broadcast_to(identity, (bands, 2, 3)).copy()
    residual = np.zeros(bands)
    tiles = np.zeros(bands, int)
    pyramid = {sigma: np.stack([blurred(e, sigma) for e in edges]) for sigma in BLUR_SCHEDULE_PX}
    with jax.enable_x64(True):
        for b in range(bands):
            if b == reference_band:
                continue
            centres, shifts, _ = tile_shifts(edges[reference_band], edges[b])
            if len(centres) < 6:
                raise ValueError(f"band {b}: {len(centres)} tiles with edges to register it by, expected at least 6 "
                                 "(a capture with structure across the frame: a target chart or a patterned sample)")
            forward = identity.copy()
            forward[:, 2] = global_shift(edges[reference_band], edges[b])
            backward = identity.copy()
            backward[:, 2] = -forward[:, 2]
            for sigma in BLUR_SCHEDULE_PX:
                ref, moving = jnp.asarray(pyramid[sigma][reference_band]), jnp.asarray(pyramid[sigma][b])
                forward = np.asarray(_refine(ref, moving, jnp.asarray(weights), jnp.asarray(forward)))
                backward = np.asarray(_refine(moving, ref, jnp.asarray(weights), jnp.asarray(backward)))
            # Both ways, averaged: interpolating the moved image blurs it by an amount that depends
            # on the sub-pixel shift, which pulls each one-way estimate towards whole pixels by
            # about as much in the opposite sense.
            matrix = 0.5 * (forward + _inverse(backward))
            transforms[b] = matrix
            # The tiles' own shifts about the final map, those within a pixel of it (a regular
            # chart's tiles may lock onto a neighbouring period): what the map leaves unexplained.
            moved = centres @ matrix[:, :2].T + matrix[:, 2] - centres
            misfit = np.linalg.norm(shifts - moved, axis=1)
            near = misfit < 1.0
            residual[b] = float(np.sqrt(np.mean(misfit[near] ** 2))) if near.any() else float("nan")
            tiles[b] = int(near.sum())
    return BandRegistration(transforms, residual, tiles, reference_band)


__all__ = [
    "BLUR_SCHEDULE_PX",
    "BORDER_PX",
    "MIN_EDGE_STRENGTH",
    "TILE_PX",
    "TILE_STEP_PX",
    "BandRegistration",
    "blurred",
    "edge_map",
    "edge_strength",
    "global_shift",
    "register_bands",
    "tile_shifts",
    "white_structure",
]
