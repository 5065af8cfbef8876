"""Registering a filter-wheel instrument's bands: each band's affine map from the reference
band's geometry, estimated from a session's frames, sub-pixel.

A filter wheel images each band through its own filter, so each band's image is the scene under
its own map (`band_geometry` models why). Bands differ in contrast, and an edge between two
materials may even change sign from band to band, so the bands are compared by where their
edges are, not by their values:

1. Flat-field each band in its own geometry, v_b = (u_b - d_b) / (w_b - d_b) (Eq. 10: the dark and
   white frames share the band's geometry), and take its edge map e_b: the gradient's magnitude
   over its local mean, over the median of the frame's strongest tenth, saturated (e / (1 + e)),
   so that no edge of unusual contrast, here or there in the frame, outweighs the rest
   (`edge_map`). Pixels near edges of the white frame itself (the holder's border, the white
   patch) are left out (`white_structure`), as is a border.
2. Coarse: the whole frame's phase correlation (Kuglin & Hines 1975) within 10 px of no shift.
3. Fine: the similarity map (scale, rotation, shift: what filters and lens make) maximising the
   enhanced correlation coefficient (ECC, Evangelidis & Psarakis 2008) of e_ref and e_b sampled
   through it (bilinear), by Gauss-Newton steps (`_refine`), on edge maps blurred by 4, 2 and 1 px
   in turn; both ways (band onto reference and back), averaged, which cancels most of the pull
   of interpolation towards whole pixels.

Accuracy on simulated sessions (`tests/test_band_registration.py`; eight sessions, seeds 3, 5,
7, 11, 21): within 0.039 px RMS over the frame of the truth in register and 0.051 px at 2 px of
misregistration; what is left comes from noise (it grows with it) and from edges one band shows
and another does not. About 4 s a session of 192 x 272 pixels on one core.

`edge_strength` and `tile_shifts` check that a frame has structure enough (edges of at least
MIN_EDGE_STRENGTH in every band, at least 6 tiles of 48 px with edges), and the tiles' own shifts about the fitted map give each band's residual (pixels): what the map
leaves unexplained, plus the tiles' own scatter (~0.3 px). The reference band is 560 nm
(`band_geometry.REFERENCE_BAND`); the maps follow the session manifest's convention
(`spherejax.io`: x = column, y = row, pixel centres at integers, from the reference geometry to
the band's).
"""

from __future__ import annotations

import dataclasses

import numpy as np

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


#: The reach of `edge_map`'s local contrast normalisation, pixels (a Gaussian's sigma).
LOCAL_CONTRAST_PX = 8.0


def edge_map(image: np.ndarray) -> np.ndarray:
    """(H, W) edge map of one band (module docstring, step 1): the gradient's magnitude over its
    local mean (a Gaussian of LOCAL_CONTRAST_PX, plus a tenth of the frame's mean so that flat
    noise is not raised to edges), then over the median of the strongest tenth, saturated.

    Why local: a band's edges differ in contrast across the frame (neighbouring patches whose
    spectra part in one band and not in another, the noise growing into the vignetted corners),
    and a fit that weighs each region by its contrast is pulled towards a scale: in register the
    maps' error fell from 0.045 to 0.039 px RMS at most over eight simulated sessions, and from
    0.068 to 0.051 at 2 px of misregistration."""
    gy, gx = np.gradient(image)
    magnitude = np.hypot(gx, gy)
    local = magnitude / (blurred(magnitude, LOCAL_CONTRAST_PX) + 0.1 * np.mean(magnitude))
    strong = local[local >= np.percentile(local, 90)]
    e = local / max(float(np.median(strong)), 1e-12)
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


#: The fine fit's stopping rule: a Gauss-Newton step that moves the frame's corners by less than
#: this (pixels) ends it, as does MAX_ITERATIONS steps.
STEP_TOLERANCE_PX = 1e-4
MAX_ITERATIONS = 50


def _bilinear(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """image (H, W) sampled at (xs, ys) bilinearly, positions clamped into the frame (the edge
    extended, as the pixels near the border carry no weight in the fit)."""
    height, width = image.shape
    xs = np.clip(xs, 0.0, width - 1.0)
    ys = np.clip(ys, 0.0, height - 1.0)
    x0 = np.minimum(np.floor(xs), width - 2).astype(np.intp)
    y0 = np.minimum(np.floor(ys), height - 2).astype(np.intp)
    fx, fy = xs - x0, ys - y0
    flat = image.reshape(-1)
    i = y0 * width + x0
    top = flat[i] * (1 - fx) + flat[i + 1] * fx
    bottom = flat[i + width] * (1 - fx) + flat[i + width + 1] * fx
    return top * (1 - fy) + bottom * fy


def _refine(reference: np.ndarray, band: np.ndarray, weights: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Fine step 3: the similarity map (2 x 3, from `start`) maximising the ECC of `band` sampled
    through it and `reference` over the pixels `weights` selects.

    Gauss-Newton on the standardised difference s(band o map) - s(reference) (its square is
    2 - 2 ECC, Evangelidis & Psarakis 2008: blind to the bands' contrasts and to how much edge a
    map moves in or out of the pixels compared), with the Jacobian from the band's own gradient
    sampled through the map, and each step halved while it does not lower the misfit. Written
    here rather than with optimistix's Levenberg-Marquardt, which took 35-80 steps of a
    Jacobian by forward differentiation through the interpolation (0.2-0.4 s a band and blur,
    30 s a session) where these closed-form steps converge in a few (milliseconds each).

    The map is a similarity, [[a, -b, tx], [b, a, ty]] (scale and rotation, shift): what a
    filter's focus shift, tilt and wedge and the lens's lateral colour make (`band_geometry`);
    the two parameters an affine map adds (anisotropic scale, shear) no filter wheel makes, and
    fitting them doubled the scatter of the maps in register.
    """
    height, width = reference.shape
    selected = weights > 0
    y, x = (coordinate[selected].astype(np.float64) for coordinate in np.mgrid[0:height, 0:width])
    w = weights[selected]
    total = w.sum()
    gy_image, gx_image = np.gradient(band)

    def standardised(values):
        centred = values - np.sum(w * values) / total
        return centred / np.sqrt(np.sum(w * centred**2) / total)

    target = standardised(reference[selected])
    # Parameters about the frame's centre, so that a, b and the shifts are of one scale.
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    u, v = x - cx, y - cy

    def as_matrix(params):
        a, b, tx, ty = params
        return np.array([[a, -b, tx + cx - a * cx + b * cy], [b, a, ty + cy - b * cx - a * cy]])

    def misfit(params):
        m = as_matrix(params)
        xs, ys = m[0, 0] * x + m[0, 1] * y + m[0, 2], m[1, 0] * x + m[1, 1] * y + m[1, 2]
        seen = _bilinear(band, xs, ys)
        return np.sum(w * (standardised(seen) - target) ** 2) / total, xs, ys, seen

    a, b = 0.5 * (start[0, 0] + start[1, 1]), 0.5 * (start[1, 0] - start[0, 1])
    tx = start[0, 2] - cx + a * cx - b * cy
    ty = start[1, 2] - cy + b * cx + a * cy
    params = np.array([a, b, tx, ty])
    reach = np.hypot(cx, cy)  # a unit change of a or b moves the corners this far
    value, xs, ys, seen = misfit(params)
    for _ in range(MAX_ITERATIONS):
        gx, gy = _bilinear(gx_image, xs, ys), _bilinear(gy_image, xs, ys)
        # d(sampled)/d(a, b, tx, ty): x' = a u - b v + tx + cx, y' = b u + a v + ty + cy.
        g = np.stack([gx * u + gy * v, -gx * v + gy * u, gx, gy], axis=1)
        mean = np.sum(w * seen) / total
        sigma = np.sqrt(np.sum(w * (seen - mean) ** 2) / total)
        s = (seen - mean) / sigma
        # The derivative of standardising: centre G, and take out its component along s.
        g_centred = g - np.sum(w[:, None] * g, axis=0) / total
        jacobian = (g_centred - s[:, None] * (np.sum((w * s)[:, None] * g_centred, axis=0) / total)) / sigma
        normal = jacobian.T @ (w[:, None] * jacobian)
        step = -np.linalg.solve(normal + 1e-12 * np.trace(normal) * np.eye(4), jacobian.T @ (w * (s - target)))
        for _ in range(8):  # halve a step that does not lower the misfit
            trial = params + step
            trial_value, trial_xs, trial_ys, trial_seen = misfit(trial)
            if trial_value <= value:
                break
            step = step / 2
        else:
            break
        params, value, xs, ys, seen = trial, trial_value, trial_xs, trial_ys, trial_seen
        if reach * np.abs(step[:2]).max() + np.abs(step[2:]).max() < STEP_TOLERANCE_PX:
            break
    return as_matrix(params)


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


def flat_fielded(frame: np.ndarray, dark: np.ndarray, white: np.ndarray) -> np.ndarray:
    """Eq. 10 as everywhere (`flatfield.flat_field`), float64 (H, W, B); a pixel whose white is not
    above its dark (NaN there) carries no edge: 0."""
    return np.nan_to_num(np.asarray(flat_field(frame, dark, white), np.float64), nan=0.0)


def check_structure(v: np.ndarray) -> None:
    """Raise ValueError naming the first band whose edges are weaker than MIN_EDGE_STRENGTH in the
    flat-fielded capture v (H, W, B): nothing there to register it by."""
    for b in range(v.shape[-1]):
        strength = edge_strength(v[..., b])
        if not strength >= MIN_EDGE_STRENGTH:
            raise ValueError(f"band {b}: its strongest edges change the flat-fielded response by {strength:.2g} a pixel, "
                             f"expected at least {MIN_EDGE_STRENGTH}: a capture with structure across the frame "
                             "(a target chart or a patterned sample)")


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
    v = flat_fielded(frame, dark, white)
    height, width, bands = v.shape
    check_structure(v)
    edges = np.stack([edge_map(v[..., b]) for b in range(bands)])
    weights = np.zeros((height, width))
    weights[BORDER_PX : height - BORDER_PX, BORDER_PX : width - BORDER_PX] = 1.0
    weights *= ~white_structure(white.astype(np.float64) - dark)
    identity = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    transforms = np.broadcast_to(identity, (bands, 2, 3)).copy()
    residual = np.zeros(bands)
    tiles = np.zeros(bands, int)
    pyramid = {sigma: np.stack([blurred(e, sigma) for e in edges]) for sigma in BLUR_SCHEDULE_PX}
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
            ref, moving = pyramid[sigma][reference_band], pyramid[sigma][b]
            forward = _refine(ref, moving, weights, forward)
            backward = _refine(moving, ref, weights, backward)
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
    "check_structure",
    "edge_map",
    "flat_fielded",
    "edge_strength",
    "global_shift",
    "register_bands",
    "tile_shifts",
    "white_structure",
]
