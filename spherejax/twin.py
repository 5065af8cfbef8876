"""The digital twin: the simulator's physical parameters (`simulated_instrument.InstrumentModel`)
fitted to a session's frames, so that `spherejax simulate --instrument` renders that instrument.

Three statistics of a session, each with the part of the simulator's model that explains it:

1. Noise (full_well_e, read_noise_e). Per band, the variance of the dark frame's and the white
   frame's pixels about their neighbours (second differences, which cancel the smooth flat field,
   clipped at 5 robust sigmas, which leaves edges out): an average of n frames of a pixel with e
   electrons has  var_DN = e / (n g) + σ_r² / (n g²) + 1/12  (shot, read noise, the ADC's
   rounding), g = full_well_e / saturation e- per DN. The dark frame gives σ_r² / g², the white
   frame's bands (at their different levels) give 1 / g: one least-squares line, closed form
   (not an iterative fit: the model is linear in σ_r² / g² and 1 / g).
2. The white frame's shape (vignetting, filter_gradient, stray_light_fraction,
   stray_light_core_px). The white standard on the holder (its certificate in the session's
   metadata), the mount and the white patch in the strip beside it, rendered through the
   simulator's own optics (`simulated_rendering.vignette`, a linear filter gradient per band,
   `glare`) and fitted to the dark-subtracted white frame (2 x 2 pixel means, relative
   residuals) by BFGS (optimistix) through the differentiable model (`fit_white_frame` says how
   the per-band coefficients are solved inside the loss). Glare shows where the
   standard meets the dark strip and the frame's edge, vignetting as a radial fall-off.
3. The sphere (wall_reflectance_400nm, wall_reflectance_700nm, lamp_fluctuation). Across the
   sample and target captures, the white patch ratio p (Eqs. 14-15; the glare the fitted optics put
   on the patch taken out) against the holder's mean reflectance ρ̄ (Stage I's estimate):
   Eq. 9 gives  p = c_b (1 - k_s ρ_w) / (1 - k_r ρ_w),  k = α_ww + α_wsp α_spw ρ̄, with the
   port fractions α of the sphere's geometry and ρ_w(λ) the simulator's wall curve through its
   400 and 700 nm values; least squares on log p (Levenberg-Marquardt, optimistix), c_b the
   white frame's lamp level per band. What the model leaves is the lamp's frame-to-frame
   flicker: its rms is lamp_fluctuation.

Everything else (the sphere's geometry, the filters, the lamp spectrum, the camera's bit depth,
the materials) keeps the base instrument's values (`fit_twin(base=...)`, the default
`InstrumentModel()`). What the simulator does not model is not fitted: a real camera's
photo-response non-uniformity (fixed pattern) adds to the white frame's variance, and statistic 1
then overstates the shot noise and understates the gain; for such a camera give `calibrate` the
gain of a photon-transfer measurement (--gain) rather than the twin's. Nor does statistic 2
model the bands' maps (`band_geometry`): it draws the white frame's edges (holder, white patch,
mount) alike in every band, so a session whose bands are out of register, as a filter wheel's
are, inflates the glare it finds (stray light 0.045 read as 0.064 at the simulator's default
maps of 0.2-0.5 px; leaving the edges' pixels out loses the glare's core instead). Simulate the
sessions it is checked on in register (`spherejax simulate --band-misregistration 0`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .estimation.small_solve import spd_solve
from .evaluate import DEFAULT_WHITE_REFLECTANCE
from .grid import WAVELENGTHS_NM
from .simulated_instrument import FINE_WAVELENGTHS_NM, InstrumentModel
from .simulated_rendering import glare, glare_kernel_fft, vignette

#: The InstrumentModel fields `fit_twin` fits, in the order it reports them.
FITTED_PARAMETERS = (
    "full_well_e", "read_noise_e", "vignetting", "filter_gradient", "stray_light_fraction", "stray_light_core_px",
    "wall_reflectance_400nm", "wall_reflectance_700nm", "lamp_fluctuation",
)

_HIGHEST = jax.lax.Precision.HIGHEST
_MAD_TO_SIGMA = 1.482602218505602
_EDGE_PX = 16  # pixels left out along the holder's edges in the noise statistic


@dataclasses.dataclass(frozen=True)
class TwinFit:
    """What `fit_twin` found: the instrument (the base with FITTED_PARAMETERS replaced), the fitted
    values, and per statistic how well the model explains it (`report`: JSON-ready)."""

    instrument: InstrumentModel
    fitted: dict
    report: dict


# ---- 1. noise --------------------------------------------------------------------------------


def _noise_variance(image: np.ndarray) -> float:
    """Variance of one pixel's noise in `image` (h, w), from second differences along rows
    (var = 6 sigma^2 for independent noise): their variance within 5 robust sigmas (median
    absolute deviation) of their median, so that an edge in the frame does not count. Not the
    MAD itself: of integer frames it takes a few values only (a dark frame of 2 DN noise read
    10 % high)."""
    d = (image[:, 2:] - 2.0 * image[:, 1:-1] + image[:, :-2]).ravel()
    centre = np.median(d)
    spread = _MAD_TO_SIGMA * max(np.median(np.abs(d - centre)), 0.5)
    kept = d[np.abs(d - centre) < 5.0 * spread]
    return float(np.var(kept) / 6.0)


def fit_noise(dark: np.ndarray, white: np.ndarray, holder, frames_dark: int, frames_white: int, saturation: float) -> dict:
    """{"full_well_e", "read_noise_e", "gain_e_per_dn", "dark_variance" (B,), "white_variance"
    (B,), "white_level" (B,)} from the dark and white frames (H, W, B) in DN, statistic 1."""
    r0, r1, c0, c1 = holder
    edge = _EDGE_PX if min(r1 - r0, c1 - c0) > 4 * _EDGE_PX else 0
    inner = (slice(r0 + edge, r1 - edge), slice(c0 + edge, c1 - edge))
    bands = dark.shape[-1]
    dark_var = np.array([_noise_variance(dark[..., b].astype(float)) for b in range(bands)])
    white_var = np.array([_noise_variance(white[inner][..., b].astype(float)) for b in range(bands)])
    level = np.array([np.mean(white[inner][..., b].astype(float) - dark[inner][..., b]) for b in range(bands)])
    rounding = 1.0 / 12.0
    read_over_gain2 = frames_dark * max(float(np.mean(dark_var)) - rounding, 0.0)  # σ_r² / g²
    # frames_white (var_w - 1/12) - σ_r²/g² = level / g: a line through the origin.
    y = frames_white * (white_var - rounding) - read_over_gain2
    inverse_gain = float(np.dot(level, y) / np.dot(level, level))
    # Shot noise at least twice the ADC's rounding in the brightest band (4 x its variance): any
    # camera's white frame at tens of percent of full scale has tens of counts of it.
    if not (np.isfinite(inverse_gain) and inverse_gain > 0.0 and np.all(level > 0) and np.max(white_var) > 4.0 * rounding):
        raise ValueError(f"the white frame's noise does not grow with its level (shot noise {inverse_gain:.3g} DN per DN "
                         "of signal): expected a camera's frames, with their noise (a simulated session without noise "
                         "has none to fit)")
    gain = 1.0 / inverse_gain
    return {
        "gain_e_per_dn": gain, "full_well_e": gain * float(saturation), "read_noise_e": float(np.sqrt(read_over_gain2) * gain),
        "dark_variance": dark_var.tolist(), "white_variance": white_var.tolist(), "white_level": level.tolist(),
    }


# ---- 2. the white frame's shape ----------------------------------------------------------------


def _bin2(x):
    """2 x 2 pixel means of (..., H, W) (H, W even)."""
    *lead, h, w = x.shape
    return x.reshape(*lead, h // 2, 2, w // 2, 2).mean(axis=(-3, -1))


def _squash(raw, low, high):
    return low + (high - low) * jax.nn.sigmoid(raw)


def _unsquash(value, low, high):
    t = (value - low) / (high - low)
    return float(np.log(t / (1.0 - t)))


# Ranges the fit searches (the simulator's defaults well inside): fractions and pixels.
_VIGNETTING = (0.0, 0.8)
_STRAY = (0.0, 0.3)
_CORE_PX = (0.5, 60.0)


def _white_scene(image_shape, holder, white_patch):
    """Masks (H, W) of the holder, the white patch, and the rest of the strip (the mount)."""
    rows, cols = np.mgrid[0:image_shape[0], 0:image_shape[1]]

    def inside(rect):
        r0, r1, c0, c1 = rect
        return (rows >= r0) & (rows < r1) & (cols >= c0) & (cols < c1)

    holder_mask, patch_mask = inside(holder), inside(white_patch)
    return holder_mask, patch_mask, ~holder_mask & ~patch_mask


def fit_white_frame(white: np.ndarray, dark: np.ndarray, holder, white_patch, base: InstrumentModel | None = None) -> dict:
    """{"vignetting", "filter_gradient", "stray_light_fraction", "stray_light_core_px",
    "relative_rms", "steps", "converged"} from the dark-subtracted white frame (H, W, B),
    statistic 2.

    The rendered white frame of band b is  a_b glare(V (1 + g_b . x) S_b)  with V the vignetting,
    g_b the band's filter gradient, S_b the scene (standard, white patch, mount): linear, for
    given vignetting and glare, in the 9 images glare(V {1, x, y} {holder, patch, mount}), which
    do not depend on the band. So each band's 9 coefficients are a weighted least-squares
    solution (relative residuals) inside the loss, and BFGS (optimistix) searches the 3
    nonlinear parameters only (the 9 coefficients of a band hold its scale, gradient and the
    patch's and mount's reflectances, their products left free).
    """
    image = np.moveaxis(white.astype(np.float64) - dark.astype(np.float64), -1, 0)  # (B, H, W)
    bands, height, width = image.shape
    height2, width2 = height - height % 2, width - width % 2
    masks = [m[:height2, :width2] for m in _white_scene((height, width), holder, white_patch)]
    data = _bin2(image[:, :height2, :width2]).reshape(bands, -1)  # (B, P)
    y, x = np.mgrid[0:height2, 0:width2].astype(float)
    half_diagonal = np.hypot((height2 - 1) / 2, (width2 - 1) / 2)
    along = [np.ones_like(x), (x - (width2 - 1) / 2) / half_diagonal, (y - (height2 - 1) / 2) / half_diagonal]
    products_np = np.stack([a * m for a in along for m in masks])  # (9, H, W)
    weights_np = 1.0 / np.maximum(data, 1e-6 * data.max())  # relative residuals

    def fitted(raw):
        v, stray, core = (_squash(raw[i], *bounds) for i, bounds in enumerate((_VIGNETTING, _STRAY, _CORE_PX)))
        basis = _bin2(glare(vignette((height2, width2), v)[None] * products, glare_kernel_fft((height2, width2), core), stray))
        basis = basis.reshape(len(products), -1)  # (9, P)

        def one_band(d, w):
            A = (basis * w[None, :]).T  # rows: pixels, relative
            coefficients = _normal_solve(A, d * w)
            return coefficients, jnp.matmul(coefficients, basis, precision=_HIGHEST)

        return jax.vmap(one_band)(data_j, weights)

    def loss(raw, _):
        _, model = fitted(raw)
        return jnp.mean((model / data_j - 1.0) ** 2)

    # float64: the 9 x 9 normal equations of a band lose the fit's last digits in float32, and
    # BFGS then stalls on a noisy loss.
    with jax.enable_x64(True):
        products, weights, data_j = (jnp.asarray(a, jnp.float64) for a in (products_np, weights_np, data))
        start = jnp.asarray([_unsquash(0.2, *_VIGNETTING), _unsquash(0.02, *_STRAY), _unsquash(5.0, *_CORE_PX)])
        solution = optx.minimise(loss, optx.BFGS(rtol=1e-8, atol=1e-12), start, max_steps=200, throw=False)
        raw = solution.value
        coefficients, _ = fitted(raw)
        coefficients = np.asarray(coefficients)
        rms = float(np.sqrt(loss(raw, None)))
        vignetting, stray, core = (float(_squash(raw[i], *bounds)) for i, bounds in enumerate((_VIGNETTING, _STRAY, _CORE_PX)))
    holder_index = 0  # products: {1, x, y} x {holder, patch, mount}: the holder's are 0, 3, 6
    slopes = np.hypot(coefficients[:, 3 + holder_index], coefficients[:, 6 + holder_index]) / coefficients[:, holder_index]
    return {
        "vignetting": vignetting,
        # The simulator draws each band's slope from filter_gradient x U(0.5, 1): mean 0.75.
        "filter_gradient": float(np.mean(slopes) / 0.75),
        "stray_light_fraction": stray,
        "stray_light_core_px": core,
        "relative_rms": rms,
        "steps": int(solution.stats["num_steps"]),
        "converged": bool(solution.result == optx.RESULTS.successful),
    }


def _normal_solve(A, b):
    """Least-squares x of A x = b (A (P, k), k small) by the normal equations and a Cholesky in
    jax.numpy (`estimation.small_solve`: no batched LAPACK call under the vmap over bands)."""
    return spd_solve(jnp.matmul(A.T, A, precision=_HIGHEST), jnp.matmul(A.T, b, precision=_HIGHEST))


# ---- 3. the sphere and the lamp -------------------------------------------------------------------


def _band_means(spectrum_fine: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(B,) band-weighted means of a spectrum on FINE_WAVELENGTHS_NM, weights (B, L)."""
    return weights @ spectrum_fine / weights.sum(axis=1)


def _wall_bands(rho_400, rho_700, shape_bands):
    """The simulator's wall curve (`InstrumentModel.wall_reflectance`) in each band."""
    return rho_400 + (rho_700 - rho_400) * shape_bands


def fit_sphere(ratios: np.ndarray, holder_means: np.ndarray, standard_bands: np.ndarray, base: InstrumentModel) -> dict:
    """{"wall_reflectance_400nm", "wall_reflectance_700nm", "lamp_fluctuation", ...} from the
    white patch ratios p (F, B) of F captures and their holders' mean reflectance (F, B),
    statistic 3."""
    alpha_ww, alpha_wsp, alpha_spw = base.port_fractions()
    weights = base.band_weights()
    # The wall curve's shape in each band: (ρ_w - ρ_400) / (ρ_700 - ρ_400) is fixed by the model.
    unit = dataclasses.replace(base, wall_reflectance_400nm=0.0, wall_reflectance_700nm=1.0).wall_reflectance()
    shape_np = _band_means(unit, weights)

    def residuals(raw, _):
        wall = _wall_bands(_squash(raw["w400"], 0.5, 1.0), _squash(raw["w700"], 0.5, 1.0), shape_bands)
        predicted = raw["log_c"][None, :] + jnp.log(1.0 - k_s * wall[None, :]) - jnp.log(1.0 - k_r * wall)[None, :]
        return predicted - log_p

    with jax.enable_x64(True):  # the captures' ratios differ in their fourth digit
        shape_bands = jnp.asarray(shape_np)
        log_p = jnp.asarray(np.log(ratios))
        k_s = alpha_ww + alpha_wsp * alpha_spw * jnp.asarray(holder_means)
        k_r = alpha_ww + alpha_wsp * alpha_spw * jnp.asarray(standard_bands)
        start = {"w400": jnp.float64(_unsquash(0.95, 0.5, 1.0)), "w700": jnp.float64(_unsquash(0.98, 0.5, 1.0)),
                 "log_c": jnp.zeros(ratios.shape[1])}
        solution = optx.least_squares(residuals, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12), start, max_steps=400, throw=False)
        raw = solution.value
        left = np.asarray(residuals(raw, None))
        w400, w700 = float(_squash(raw["w400"], 0.5, 1.0)), float(_squash(raw["w700"], 0.5, 1.0))
    count, parameters = left.size, 2 + ratios.shape[1]
    return {
        "wall_reflectance_400nm": w400,
        "wall_reflectance_700nm": w700,
        "lamp_fluctuation": float(np.sqrt(np.sum(left**2) / max(count - parameters, 1))),
        "captures": int(ratios.shape[0]),
        "converged": bool(solution.result == optx.RESULTS.successful),
    }


def _patch_glare(frame_bhw: np.ndarray, patch_mask: np.ndarray, stray: float, kernel) -> np.ndarray:
    """(B,) mean over the white patch of the glare the fitted optics add there, from the frame
    itself (first order: the glare of the glare is left in); kernel: the fitted PSF's
    `glare_kernel_fft`, made once for every frame."""
    spread = np.asarray(glare(jnp.asarray(frame_bhw, jnp.float32), kernel, 1.0))
    return stray * (spread[:, patch_mask] - frame_bhw[:, patch_mask]).mean(axis=1)


# ---- the whole fit -----------------------------------------------------------------------------


#: Captures the sphere's statistic needs at the least (the white patch against backgrounds).
MIN_CAPTURES = 4


def check_session(session, base: InstrumentModel | None = None) -> dict:
    """Raise ValueError, one line naming the manifest, unless `fit_twin` can fit `session`: the
    white standard's certificate, where the metadata has one ("white_standard_reflectance", 31
    values in (0, 1]; without it `evaluate`'s DEFAULT_WHITE_REFLECTANCE), the base instrument's
    band count, MIN_CAPTURES sample or target captures, frames with noise (the last, statistic 1,
    is `fit_noise`'s; it is returned)."""
    base = base or InstrumentModel()
    _check_session_record(session, base)
    # Its refusal too before any long work (the command line's progress line starts after it).
    return _session_noise(session, base, session.dark().astype(np.float64), session.white().astype(np.float64))


def _check_session_record(session, base: InstrumentModel) -> None:
    """`check_session`'s checks of what the manifest records (no frame read)."""
    certificate = session.metadata.get("white_standard_reflectance")
    values = certificate if isinstance(certificate, list) else []
    usable = (len(values) == len(WAVELENGTHS_NM)
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 < v <= 1.0 for v in values))
    if certificate is not None and not usable:
        raise ValueError(f"{session.manifest_path}: metadata \"white_standard_reflectance\" is {certificate!r} (expected the "
                         f"white standard's {len(WAVELENGTHS_NM)} reflectances at 400..700 nm, each in (0, 1])")
    if session.bands != len(base.filters()):
        raise ValueError(f"{session.manifest_path}: has {session.bands} bands (expected the simulator's {len(base.filters())})")
    captures = [f for f in session.frames if f.role in ("sample", "target")]
    if len(captures) < MIN_CAPTURES:
        raise ValueError(f"{session.manifest_path}: has {len(captures)} sample or target captures (expected at least "
                         f"{MIN_CAPTURES}: the white patch against backgrounds of different brightness)")


def _session_noise(session, base: InstrumentModel, dark: np.ndarray, white: np.ndarray) -> dict:
    """Statistic 1 (`fit_noise`) of the session's dark and white frames (H, W, B) float64; its
    refusal names the manifest."""
    dark_info, white_info = session.frames_with("dark")[0], session.frames_with("white")[0]
    try:
        return fit_noise(dark, white, session.holder,
                         int(dark_info.metadata.get("frames_averaged", base.frames_averaged_dark)),
                         int(white_info.metadata.get("frames_averaged", base.frames_averaged_white)), session.saturation)
    except ValueError as error:
        raise ValueError(f"{session.manifest_path}: {error}") from None


def fit_twin(session, base: InstrumentModel | None = None) -> TwinFit:
    """The simulator's instrument fitted to `session` (a `spherejax.io.Session`): statistics 1-3
    of the module docstring. The session needs its dark and white frames and sample or target
    captures on backgrounds of different brightness (`check_session`); the white standard's
    certificate (metadata "white_standard_reflectance", 31 values at 400..700 nm) where it has
    one, else `evaluate.DEFAULT_WHITE_REFLECTANCE` (the report says which)."""
    base = base or InstrumentModel()
    _check_session_record(session, base)
    dark, white = session.dark().astype(np.float64), session.white().astype(np.float64)
    noise = _session_noise(session, base, dark, white)
    certificate = session.metadata.get("white_standard_reflectance")
    if certificate is None:  # as `spherejax evaluate` takes it
        certificate = np.full(len(WAVELENGTHS_NM), DEFAULT_WHITE_REFLECTANCE)
    weights = base.band_weights()
    standard_bands = _band_means(np.interp(FINE_WAVELENGTHS_NM, WAVELENGTHS_NM, np.asarray(certificate, float)), weights)
    white_info = session.frames_with("white")[0]
    optics = fit_white_frame(white, dark, session.holder, session.white_patch, base)

    captures = [f for f in session.frames if f.role in ("sample", "target")]
    patch_mask = session.white_patch_mask()
    holder_mask = session.holder_mask()
    white_bhw = np.moveaxis(white - dark, -1, 0) / white_info.exposure_s[:, None, None]
    stray, kernel = optics["stray_light_fraction"], glare_kernel_fft(white_bhw.shape[-2:], float(optics["stray_light_core_px"]))
    white_patch = white_bhw[:, patch_mask].mean(axis=1) - _patch_glare(white_bhw, patch_mask, stray, kernel)
    flat = np.where(white_bhw > 0, white_bhw, np.nan)
    ratios, means = [], []
    for info in captures:
        frame = np.moveaxis(session.read(info).astype(np.float64) - dark, -1, 0) / info.exposure_s[:, None, None]
        patch = frame[:, patch_mask].mean(axis=1) - _patch_glare(frame, patch_mask, stray, kernel)
        p = white_patch / patch
        ratios.append(p)
        means.append(np.nanmean(frame[:, holder_mask] / flat[:, holder_mask], axis=1) * p * standard_bands)
    sphere = fit_sphere(np.array(ratios), np.array(means), standard_bands, base)

    fitted = {
        "full_well_e": noise["full_well_e"], "read_noise_e": noise["read_noise_e"],
        **{name: optics[name] for name in ("vignetting", "filter_gradient", "stray_light_fraction", "stray_light_core_px")},
        **{name: sphere[name] for name in ("wall_reflectance_400nm", "wall_reflectance_700nm", "lamp_fluctuation")},
    }
    instrument = dataclasses.replace(base, **fitted)
    report = {
        "white_standard": "certificate" if "white_standard_reflectance" in session.metadata else f"default {DEFAULT_WHITE_REFLECTANCE}",
        "noise": {k: noise[k] for k in ("gain_e_per_dn", "full_well_e", "read_noise_e")},
        "white_frame": optics,
        "sphere": sphere,
    }
    return TwinFit(instrument, fitted, report)


__all__ = ["FITTED_PARAMETERS", "MIN_CAPTURES", "TwinFit", "check_session", "fit_noise", "fit_sphere", "fit_twin", "fit_white_frame"]
