"""Rendering the simulated instrument's camera frames (JAX, jitted: one compilation per image shape).

A scene is a material index map (H, W) int32 over the whole image and its materials (each with
a reflectance (L,) on `simulated_instrument.FINE_WAVELENGTHS_NM`, a first-bounce coupling and a
fluorescence); `_Renderer` turns it into frames in two steps:

- `_Renderer.rates`: the noise-free signal rate of every band, (16, H, W) e-/s up to the flux
  scale, from the multi-bounce sphere of Eqs. 1-9 (the irradiance on the holder depends on the
  holder's area-weighted mean reflectance), β(x) (cos⁴ vignetting times a per-filter linear
  gradient), non-Lambertian first-bounce coupling, fluorescence, and veiling glare (a long-tailed
  PSF applied by FFT);
- `_Renderer.capture`: one averaged 16-band capture, (H, W, 16) uint16 DN, at the exposures
  `_Renderer.calibrate_exposures` chose on the white standard, with the lamp's drift and flicker
  over the capture's band times, shot noise, read noise, dark current, gain, bias and the ADC's
  saturation (`_expose`).

`spherejax.simulate` renders a whole experiment with it; `hw.simcamera` (spherejax_hw) renders
frame by frame, one band at a time, through `_Renderer.rates` and `_expose`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import band_geometry
from .simulated_instrument import InstrumentModel
from .simulated_layout import Material


def glare_kernel_fft(shape: tuple[int, int], core_px) -> jax.Array:
    """rFFT of a normalised long-tailed PSF, 1 / (1 + (r / r0)²)^1.5, r0 = core_px, on the
    zero-padded grid (2H, 2W) of an image of `shape` (H, W). A jax array or tracer core_px
    gives a kernel differentiable in it (`spherejax.twin` fits it)."""
    height, width = 2 * shape[0], 2 * shape[1]
    y = np.fft.fftfreq(height) * height
    x = np.fft.fftfreq(width) * width
    r2 = y[:, None] ** 2 + x[None, :] ** 2
    if isinstance(core_px, (int, float, np.number)):
        # A number: in float64 numpy, as the simulator has always rendered (same frames).
        kernel = (1.0 + r2 / float(core_px) ** 2) ** -1.5
        return jnp.asarray(np.fft.rfft2(kernel / kernel.sum()), dtype=jnp.complex64)
    kernel = (1.0 + jnp.asarray(r2, jnp.asarray(core_px).dtype) / core_px**2) ** -1.5
    return jnp.fft.rfft2(kernel / jnp.sum(kernel))


def glare(image, kernel_fft, stray):
    """(1 - stray) image + stray (PSF * image): veiling glare on images (..., H, W), the PSF's
    rFFT from `glare_kernel_fft`; light spread beyond the frame is lost."""
    height, width = image.shape[-2:]
    padded = jnp.fft.rfft2(image, s=(2 * height, 2 * width))
    spread = jnp.fft.irfft2(padded * kernel_fft, s=(2 * height, 2 * width))[..., :height, :width]
    return (1.0 - stray) * image + stray * spread


def vignette(shape: tuple[int, int], vignetting):
    """(H, W) relative irradiance of a cos⁴ fall-off whose corners lose `vignetting` (0..1):
    (1 + t r²)^-2 with r the distance from the centre over the half diagonal, t chosen so that
    r = 1 gives 1 - vignetting. numpy float64 for a number, jax.numpy (differentiable) for an
    array or tracer (`spherejax.twin` fits it)."""
    height, width = shape
    y, x = np.mgrid[0:height, 0:width].astype(float)
    cy, cx = (height - 1) / 2, (width - 1) / 2
    r2 = (np.hypot(y - cy, x - cx) / np.hypot(cy, cx)) ** 2
    if not isinstance(vignetting, (int, float, np.number)):
        r2 = jnp.asarray(r2, jnp.asarray(vignetting).dtype)
    tan_corner2 = (1.0 - vignetting) ** -0.5 - 1.0
    return (1.0 + tan_corner2 * r2) ** -2


@jax.jit
def _render_rates(material_map, reflectances, couplings, holder_mask, beta, band_weights, wall, alphas, glare_fft, stray, band_samples=None):
    """Noise-free signal rate of every band (e-/s up to one scale), shape (16, H, W).

    material_map (H, W) int32 indexes reflectances (M, L) and couplings (M,); holder_mask
    (H, W) bool; beta (16, H, W); band_weights (16, L); wall (L,); alphas (3,); glare_fft
    the PSF's rFFT on the padded grid; stray the glare fraction; band_samples: (indices,
    weights), each (16, 9, H W), how each band's pixels integrate the scene (the band's geometry,
    `band_geometry.box_weights`), None when the bands are in register.
    """
    alpha_ww, alpha_wsp, alpha_spw = alphas[0], alphas[1], alphas[2]
    counts = jnp.zeros(reflectances.shape[0], reflectances.dtype).at[material_map].add(holder_mask.astype(reflectances.dtype))
    mean_reflectance = counts @ reflectances / jnp.sum(counts)  # ρ̄(λ), area-weighted (Eq. 9)
    k = alpha_ww + alpha_wsp * alpha_spw * mean_reflectance  # Eq. 9
    first = wall  # the first wall bounce's share of the holder irradiance (Eq. 1)
    later = wall * (k * wall) / (1.0 - k * wall)  # Σ_{n>=2} (k ρ_w)^(n-1) ρ_w (Eq. 5-7)
    # Response of each material in each band: the first bounce couples with the material's
    # factor, the diffuse later bounces as for a Lambertian surface.
    spectral = reflectances * (couplings[:, None] * first[None] + later[None])  # (M, L)
    per_material = spectral @ band_weights.T  # (M, 16)
    if band_samples is None:
        scene = jnp.moveaxis(per_material[material_map], -1, 0)  # (16, H, W)
    else:
        # Each band's pixel integrates the scene, constant on each reference pixel, over its
        # footprint: exact overlaps, no interpolation.
        indices, weights = band_samples
        seen = per_material.T[jnp.arange(16)[:, None, None], material_map.reshape(-1)[indices]]  # (16, 9, H W)
        scene = jnp.sum(seen * weights, axis=1).reshape(beta.shape)
    return glare(beta * scene, glare_fft, stray)


@jax.jit
def _expose(rates, exposure, lamp, key, read_noise, dark_current, gain, bias, saturation, frames, noise):
    """Averaged camera frames (H, W, 16) uint16 from rates (16, H, W) (e-/s).

    exposure (16,) s; lamp (16,) relative lamp output during each band's frames; noise: 0 or 1.
    """
    electrons = rates * (exposure * lamp)[:, None, None] + dark_current * exposure[:, None, None]
    key_shot, key_read = jax.random.split(key)
    # Mean of `frames` exposures: shot and read noise both shrink as 1/sqrt(frames).
    shot = jnp.sqrt(jnp.maximum(electrons, 0.0) / frames) * jax.random.normal(key_shot, electrons.shape, electrons.dtype)
    read = read_noise / jnp.sqrt(frames) * jax.random.normal(key_read, electrons.shape, electrons.dtype)
    dn = (electrons + noise * (shot + read)) / gain + bias
    return jnp.clip(jnp.round(dn), 0, saturation).astype(jnp.uint16).transpose(1, 2, 0)


def _band_samples(transforms: np.ndarray, image_shape: tuple[int, int]):
    """`band_geometry.box_weights` as jax arrays (int32 indices, float32 weights), None when every
    band is in register (the frames then are exactly what they were before bands could move)."""
    if np.array_equal(transforms, np.broadcast_to(np.eye(2, 3), transforms.shape)):
        return None
    indices, weights = band_geometry.box_weights(transforms, image_shape)
    return jnp.asarray(indices), jnp.asarray(weights, jnp.float32)


class _Renderer:
    """Renders captures of one instrument at one image size; holds the fixed optics."""

    def __init__(self, instrument: InstrumentModel, image_shape: tuple[int, int], holder_shape, seed: int):
        self.instrument = instrument
        self.image_shape = image_shape
        self.rng = np.random.default_rng(seed)
        self.key = jax.random.PRNGKey(seed)
        holder = np.zeros(image_shape, bool)
        holder[: holder_shape[0], : holder_shape[1]] = True
        self.holder_mask = jnp.asarray(holder)
        self.beta = jnp.asarray(self._beta(), dtype=jnp.float32)
        self.band_weights = jnp.asarray(instrument.band_weights(), dtype=jnp.float32)
        self.wall = jnp.asarray(instrument.wall_reflectance(), dtype=jnp.float32)
        self.alphas = jnp.asarray(instrument.port_fractions(), dtype=jnp.float32)
        self.glare_fft = glare_kernel_fft(image_shape, instrument.stray_light_core_px)
        pixels_per_cm = holder_shape[0] / (instrument.holder_height_m * 100.0)
        self.band_transforms = band_geometry.band_transforms(instrument, image_shape, pixels_per_cm, seed)
        self.band_samples = _band_samples(self.band_transforms, image_shape)
        self.flux_scale = None  # set by calibrate_exposures
        self.exposure = None
        self.clock_s = 0.0

    def _beta(self) -> np.ndarray:
        """β_b(x), (16, H, W): cos⁴ vignetting times a per-filter linear gradient."""
        height, width = self.image_shape
        y, x = np.mgrid[0:height, 0:width].astype(float)
        cy, cx = (height - 1) / 2, (width - 1) / 2
        half_diagonal = np.hypot(cy, cx)
        fall_off = np.asarray(vignette(self.image_shape, self.instrument.vignetting))
        angles = self.rng.uniform(0, 2 * np.pi, 16)
        slopes = self.instrument.filter_gradient * self.rng.uniform(0.5, 1.0, 16)
        along = ((x - cx)[None] * np.cos(angles)[:, None, None] + (y - cy)[None] * np.sin(angles)[:, None, None]) / half_diagonal
        return fall_off[None] * (1.0 + slopes[:, None, None] * along)

    def rates(self, material_map: np.ndarray, materials: list[Material]) -> jax.Array:
        reflectances = np.stack([m.reflectance + m.fluorescence * self.instrument.fluorescence_emission() for m in materials])
        return _render_rates(
            jnp.asarray(material_map, jnp.int32),
            jnp.asarray(reflectances, jnp.float32),
            jnp.asarray([m.coupling for m in materials], jnp.float32),
            self.holder_mask,
            self.beta,
            self.band_weights,
            self.wall,
            self.alphas,
            self.glare_fft,
            jnp.float32(self.instrument.stray_light_fraction),
            self.band_samples,
        )

    def calibrate_exposures(self, white_rates: jax.Array) -> np.ndarray:
        """Exposure per band (s): the protocol's "white standard at ~80 % of full scale"."""
        peak = np.asarray(jnp.max(white_rates, axis=(1, 2)))
        self.flux_scale = float(self.instrument.peak_rate_e_per_s / peak.max())
        fill = self.instrument.exposure_fill * self.instrument.full_well_e
        self.exposure = fill / (peak * self.flux_scale)
        return self.exposure

    def capture(self, rates: jax.Array | None, frames: int) -> tuple[np.ndarray, float]:
        """One averaged 16-band capture; rates None means the shutter is closed (a dark frame).
        Returns the frame (H, W, 16) uint16 and its start time in seconds."""
        inst = self.instrument
        start = self.clock_s
        band_times = start + inst.band_interval_s * np.arange(16)
        self.clock_s = band_times[-1] + inst.band_interval_s
        drift = 1.0 + inst.lamp_drift_per_hour * band_times / 3600.0
        lamp = drift * (1.0 + inst.lamp_fluctuation * self.rng.standard_normal(16))
        self.key, key = jax.random.split(self.key)
        if rates is None:
            rates = jnp.zeros((16, *self.image_shape), jnp.float32)
        frame = _expose(
            rates * self.flux_scale,
            jnp.asarray(self.exposure, jnp.float32),
            jnp.asarray(lamp, jnp.float32),
            key,
            *(np.float32(x) for x in (
                inst.read_noise_e, inst.dark_current_e_per_s, inst.gain_e_per_dn, inst.bias_dn,
                inst.saturation_dn, frames, 1.0 if inst.noise else 0.0,
            )),
        )
        return np.asarray(frame), start
