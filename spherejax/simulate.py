"""A physical integrating-sphere multispectral imager, and the paper's experiment on it.

Nobody here has the instrument of Zou et al. (2019), so this module renders the camera frames such
an instrument would record, from first principles, with the phenomena the paper corrects and the
ones it cannot correct exactly:

- the multi-bounce sphere of Eqs. 1-9: the holder's area-weighted mean reflectance sets
  k(λ) = α_ww + α_wsp α_spw ρ̄(λ) (Eq. 9), and the irradiance on the holder is the sum of all wall
  bounces, ρ_w Φ_0 Σ_n (k ρ_w)^(n-1) = ρ_w Φ_0 / (1 - k ρ_w) (Eq. 6-7); port fractions follow
  from the sphere's geometry (Section 5);
- spatial non-uniformity β(x): cos⁴-like vignetting times a per-filter linear gradient;
- a xenon lamp: a 6000 K near-continuum with the xenon line cluster at 450-500 nm, slow drift,
  and frame-to-frame fluctuation of each band image;
- what Stage I cannot remove: veiling glare (a long-tailed point spread carrying a few percent of
  the flux), non-Lambertian samples (the first wall bounce, which reaches the holder from a narrow
  range of directions, couples into the camera differently from the diffuse later bounces, by a
  factor that depends on the material), and optional fluorescence near 440 nm in backgrounds;
- the camera: 16 Gaussian filters (FWHM 10 nm) integrated on a 2 nm grid with a CCD quantum
  efficiency, shot noise, read noise, dark current, frame averaging, a 14-bit ADC and saturation.

All reflectances are measured spectra shipped with colour-science (`spherejax.spectra`).
Rendering is JAX (jitted; one compilation per image shape); layout and bookkeeping are numpy.

`simulate_experiment` builds the paper's experiment (Section 4-5): grey patches on uniform
backgrounds at several positions (training), coloured patches on patterned backgrounds (test),
a 144-target chart of known reflectance (Wiener training), the reference white patch beside the
holder in every frame, 35 x 35 pixel averaging regions. `session_contents` gives it as a
session's contents, which `spherejax.io.write_simulated_session` writes to disk.
"""

from __future__ import annotations

import dataclasses
import datetime
import zlib

import jax
import jax.numpy as jnp
import numpy as np

from . import spectra
from .grid import BAND_CENTRES_NM, WAVELENGTHS_NM

#: Spectral integration grid, nm: 2 nm steps, wide enough for the 400 and 700 nm filters' tails.
FINE_WAVELENGTHS_NM = np.arange(380.0, 721.0, 2.0)
_FINE_AT_31 = np.searchsorted(FINE_WAVELENGTHS_NM, WAVELENGTHS_NM.astype(float))


@dataclasses.dataclass(frozen=True)
class InstrumentModel:
    """Physical parameters of the simulated instrument. Each default, and why:

    sphere_diameter_m: 0.50, entrance_port_diameter_m: 0.06, detector_port_diameter_m: 0.05,
      holder_height_m: 0.08, holder_width_m: 0.10 -- the paper's sphere (Section 5); they give
      its stated port fraction of 1.63 %.
    wall_reflectance_400nm: 0.95, wall_reflectance_700nm: 0.99 -- PTFE / BaSO4 coatings lose a
      few percent in the violet and approach 0.99 in the red (docs/design.md: 0.95-0.99).
    lamp_colour_temperature_k: 6000 -- xenon short arcs emit a near-continuum close to 6000 K.
    lamp_line_strength: 0.15 -- the Xe I line cluster at 450-500 nm rises ~15 % above it.
    lamp_drift_per_hour: -0.005 -- a warmed-up arc still drifts by tenths of a percent per hour.
    lamp_fluctuation: 0.015 -- frame-to-frame arc flicker of 1-2 % (docs/design.md).
    stray_light_fraction: 0.03 -- veiling glare of lens + filter + window, a few % of the flux.
    stray_light_core_px: 8.0 -- the glare PSF's core radius; its tail falls as r^-3 (long-tailed).
    non_lambertian_spread: 0.25 -- first-bounce coupling 1 ± up to 25 % by material: woven and
      pile textiles at 0° viewing differ that much between oblique and diffuse illumination.
    vignetting: 0.25 -- relative fall-off in the corners of a 50 mm lens at this field (cos⁴ law).
    filter_gradient: 0.03 -- interference filters shift with angle: up to ±3 % across the field.
    filter_fwhm_nm: 10.0, filter_peak_transmission: 0.5 -- the paper's filters; typical peak.
    qe_peak: 0.77, qe_peak_nm: 560, qe_width_nm: 150 -- Sony ICX695 CCD (QImaging QI695).
    full_well_e: 17000, read_noise_e: 6, dark_current_e_per_s: 0.01, bias_dn: 100, adc_bits: 14
      -- the same sensor, cooled, 14-bit, with the usual ADC offset.
    exposure_fill: 0.8 -- docs/instrument.md's protocol: the white standard at ~80 % of full scale.
    peak_rate_e_per_s: 4e5 -- electrons per second at the brightest band's brightest pixel
      (sets the exposure times, tens of ms, of a 150 W lamp through 10 nm filters).
    white_standard_reflectance: 0.985 -- a PTFE (Spectralon-like) board.
    white_patch_reflectance: 0.97 -- a ceramic white tile, like the sphere wall (Section 3).
    mount_reflectance: 0.05 -- the black mount around the white patch, beside the holder.
    fluorescence_peak_nm: 440, fluorescence_width_nm: 15 -- whitening agents emit at 430-450 nm
      (Fig. 6 of the paper shows the peak near 440 nm).
    fluorescence_strength: 0.12 -- apparent reflectance they add at the peak, under xenon UV.
    frames_averaged_dark: 16, frames_averaged_white: 8, frames_averaged_sample: 4 -- averaging
      of docs/instrument.md's protocol (10-25 for darks).
    band_interval_s: 3.0 -- wheel move (~2.5 s) plus exposures, per band.
    """

    sphere_diameter_m: float = 0.50
    entrance_port_diameter_m: float = 0.06
    detector_port_diameter_m: float = 0.05
    holder_height_m: float = 0.08
    holder_width_m: float = 0.10
    wall_reflectance_400nm: float = 0.95
    wall_reflectance_700nm: float = 0.99
    lamp_colour_temperature_k: float = 6000.0
    lamp_line_strength: float = 0.15
    lamp_drift_per_hour: float = -0.005
    lamp_fluctuation: float = 0.015
    stray_light_fraction: float = 0.03
    stray_light_core_px: float = 8.0
    non_lambertian_spread: float = 0.25
    vignetting: float = 0.25
    filter_gradient: float = 0.03
    filter_fwhm_nm: float = 10.0
    filter_peak_transmission: float = 0.5
    qe_peak: float = 0.77
    qe_peak_nm: float = 560.0
    qe_width_nm: float = 150.0
    full_well_e: float = 17000.0
    read_noise_e: float = 6.0
    dark_current_e_per_s: float = 0.01
    bias_dn: float = 100.0
    adc_bits: int = 14
    exposure_fill: float = 0.8
    peak_rate_e_per_s: float = 4.0e5
    white_standard_reflectance: float = 0.985
    white_patch_reflectance: float = 0.97
    mount_reflectance: float = 0.05
    fluorescence_peak_nm: float = 440.0
    fluorescence_width_nm: float = 15.0
    fluorescence_strength: float = 0.12
    frames_averaged_dark: int = 16
    frames_averaged_white: int = 8
    frames_averaged_sample: int = 4
    band_interval_s: float = 3.0
    noise: bool = True

    def lambertian(self) -> "InstrumentModel":
        """The same instrument with glare, non-Lambertian coupling and fluorescence switched off:
        the world Stage I was derived for (Section 3)."""
        return dataclasses.replace(
            self, stray_light_fraction=0.0, non_lambertian_spread=0.0, fluorescence_strength=0.0
        )

    # --- derived quantities -------------------------------------------------------------------

    def port_fractions(self) -> tuple[float, float, float]:
        """(α_ww, α_wsp, α_spw) of Eqs. 2-3 from the geometry.

        In a sphere, light leaving any diffuse wall point lands on a region in proportion to the
        region's area (the sphere's defining property). From the wall: the holder gets its area
        fraction, the wall gets the rest less the ports. From the flat holder: everything but
        the two ports is wall (it cannot see itself).
        """
        area = np.pi * self.sphere_diameter_m**2
        ports = np.pi / 4.0 * (self.entrance_port_diameter_m**2 + self.detector_port_diameter_m**2)
        holder = self.holder_height_m * self.holder_width_m
        alpha_w_sp = holder / area
        alpha_w_w = 1.0 - (ports + holder) / area
        alpha_sp_w = 1.0 - ports / area
        return alpha_w_w, alpha_w_sp, alpha_sp_w

    def wall_reflectance(self) -> np.ndarray:
        """ρ_w(λ) on FINE_WAVELENGTHS_NM: rising from the violet value to the red one."""
        x = np.clip((FINE_WAVELENGTHS_NM - 400.0) / 300.0, 0.0, 1.0)
        shape = 1.0 - np.exp(-4.0 * x)  # coatings lose reflectance mostly below ~480 nm
        shape /= shape[-1]
        return self.wall_reflectance_400nm + (self.wall_reflectance_700nm - self.wall_reflectance_400nm) * np.clip(shape, 0, 1)

    def lamp_spectrum(self) -> np.ndarray:
        """Relative xenon spectral power on FINE_WAVELENGTHS_NM, max 1."""
        wl_m = FINE_WAVELENGTHS_NM * 1e-9
        planck = 1.0 / (wl_m**5 * (np.exp(1.438777e-2 / (wl_m * self.lamp_colour_temperature_k)) - 1.0))
        lines = sum(
            np.exp(-0.5 * ((FINE_WAVELENGTHS_NM - centre) / 3.0) ** 2) for centre in (450.1, 462.4, 467.1, 473.4, 480.7)
        )
        spectrum = planck / planck.max() * (1.0 + self.lamp_line_strength * lines / lines.max())
        return spectrum / spectrum.max()

    def filters(self) -> np.ndarray:
        """Filter transmissions (16, L) on FINE_WAVELENGTHS_NM."""
        sigma = self.filter_fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
        centres = BAND_CENTRES_NM[:, None].astype(float)
        return self.filter_peak_transmission * np.exp(-0.5 * ((FINE_WAVELENGTHS_NM[None] - centres) / sigma) ** 2)

    def quantum_efficiency(self) -> np.ndarray:
        return self.qe_peak * np.exp(-0.5 * ((FINE_WAVELENGTHS_NM - self.qe_peak_nm) / self.qe_width_nm) ** 2)

    def band_weights(self) -> np.ndarray:
        """(16, L): filter x QE x lamp x dλ, the spectral weight of each band's response."""
        step = np.gradient(FINE_WAVELENGTHS_NM)
        return self.filters() * self.quantum_efficiency() * self.lamp_spectrum() * step

    def fluorescence_emission(self) -> np.ndarray:
        """(L,) apparent reflectance added by whitening agents at full strength."""
        return self.fluorescence_strength * np.exp(
            -0.5 * ((FINE_WAVELENGTHS_NM - self.fluorescence_peak_nm) / self.fluorescence_width_nm) ** 2
        )

    @property
    def saturation_dn(self) -> int:
        return 2**self.adc_bits - 1

    @property
    def gain_e_per_dn(self) -> float:
        return self.full_well_e / self.saturation_dn


@dataclasses.dataclass(frozen=True)
class ExperimentDesign:
    """Layout of the simulated experiment (Zou et al. Sections 4-5), in pixels.

    pixels_per_cm: 24 -- the 10 x 8 cm holder images to 240 x 192 px (the paper's camera has far
      more pixels; this keeps a session near 70 MB).
    patch_px: 42 -- small patches of 1.75 cm: the paper's 0.5 cm patch is what its camera saw as
      more than 35 x 35 px; here the patch must hold the 35 x 35 px averaging region with a
      margin against glare at its edges.
    region_px: 35 -- the paper's averaging region.
    white_patch_px: 24, strip_px: 32 -- the reference white patch on a black mount beside the
      holder, in every frame (Fig. 2).
    training_patches: 9, training_backgrounds: 10 -- Section 4's n_p and n_b.
    patches_per_capture: 3 -- three small patches at a time, rotating through three positions
      from background to background ("at different positions").
    test_patches: 6, test_backgrounds: 6 -- coloured patches on patterned backgrounds (Fig. 4).
    targets: 144, target_px: 16, target_region_px: 10 -- a 12 x 12 chart of known reflectances.
    fluorescent_training_backgrounds: 2, fluorescent_test_backgrounds: 1 -- the brightest
      backgrounds carry whitening agents, as white-ish textiles do.
    """

    pixels_per_cm: float = 24.0
    patch_px: int = 42
    region_px: int = 35
    white_patch_px: int = 24
    strip_px: int = 32
    training_patches: int = 9
    training_backgrounds: int = 10
    patches_per_capture: int = 3
    test_patches: int = 6
    test_backgrounds: int = 6
    targets: int = 144
    target_px: int = 16
    target_region_px: int = 10
    fluorescent_training_backgrounds: int = 2
    fluorescent_test_backgrounds: int = 1

    def holder_shape(self, instrument: InstrumentModel) -> tuple[int, int]:
        return (
            int(round(instrument.holder_height_m * 100 * self.pixels_per_cm)),
            int(round(instrument.holder_width_m * 100 * self.pixels_per_cm)),
        )

    def image_shape(self, instrument: InstrumentModel) -> tuple[int, int]:
        height, width = self.holder_shape(instrument)
        return height, width + self.strip_px

    def white_patch(self, instrument: InstrumentModel) -> tuple[int, int, int, int]:
        _, width = self.holder_shape(instrument)
        c0 = width + (self.strip_px - self.white_patch_px) // 2
        return 8, 8 + self.white_patch_px, c0, c0 + self.white_patch_px


# ---------------------------------------------------------------------------------------------
# Materials


@dataclasses.dataclass(frozen=True)
class Material:
    """A surface on the holder: its name, source, reflectance on FINE_WAVELENGTHS_NM (L,), its
    first-bounce coupling (1 = Lambertian) and its fluorescence (0..1 of full strength)."""

    name: str
    source: str
    reflectance: np.ndarray
    coupling: float = 1.0
    fluorescence: float = 0.0

    def at_31(self) -> np.ndarray:
        """The spectrophotometer's view: reflectance at 400..700 nm step 10 (no fluorescence)."""
        return self.reflectance[_FINE_AT_31]


def _stable_unit(name: str, seed: int) -> float:
    """A number in [-1, 1) fixed by a material's name and the seed (same material, same value)."""
    return np.random.default_rng([zlib.crc32(name.encode()), seed]).uniform(-1.0, 1.0)


def _material(name, source, reflectance, instrument, seed, lambertian=False, fluorescence=0.0):
    coupling = 1.0 if lambertian else 1.0 + instrument.non_lambertian_spread * _stable_unit(name, seed)
    return Material(name, source, np.asarray(reflectance, float), coupling, fluorescence)


def _flat(value: float) -> np.ndarray:
    return np.full(FINE_WAVELENGTHS_NM.shape, value)


class _Library:
    """The measured spectra the experiment draws from, split so that no spectrum is used twice."""

    def __init__(self):
        self.sets = spectra.reflectance_sets(FINE_WAVELENGTHS_NM)
        self.names = spectra.reflectance_names(FINE_WAVELENGTHS_NM)

    def take(self, set_name: str, predicate=lambda name: True) -> list[tuple[str, np.ndarray]]:
        return [(n, r) for n, r in zip(self.names[set_name], self.sets[set_name]) if predicate(n)]


def _spread_by_brightness(items, count):
    """`count` items spread evenly from darkest to brightest (mean reflectance)."""
    order = sorted(items, key=lambda item: float(np.mean(item[1])))
    picks = np.round(np.linspace(0, len(order) - 1, count)).astype(int)
    return [order[i] for i in picks]


# ---------------------------------------------------------------------------------------------
# Rendering (JAX)


def _glare_kernel_fft(shape: tuple[int, int], core_px: float) -> jax.Array:
    """rFFT of a normalised long-tailed PSF, 1 / (1 + (r / r0)²)^1.5, on the zero-padded grid."""
    height, width = 2 * shape[0], 2 * shape[1]
    y = np.fft.fftfreq(height) * height
    x = np.fft.fftfreq(width) * width
    r2 = y[:, None] ** 2 + x[None, :] ** 2
    kernel = (1.0 + r2 / core_px**2) ** -1.5
    kernel /= kernel.sum()
    return jnp.asarray(np.fft.rfft2(kernel), dtype=jnp.complex64)


@jax.jit
def _render_rates(material_map, reflectances, couplings, holder_mask, beta, band_weights, wall, alphas, glare_fft, stray):
    """Noise-free signal rate of every band (e-/s up to one scale), shape (16, H, W).

    material_map (H, W) int32 indexes reflectances (M, L) and couplings (M,); holder_mask
    (H, W) bool; beta (16, H, W); band_weights (16, L); wall (L,); alphas (3,); glare_fft
    the PSF's rFFT on the padded grid; stray the glare fraction.
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
    image = beta * jnp.moveaxis(per_material[material_map], -1, 0)  # (16, H, W)
    height, width = image.shape[-2:]
    padded = jnp.fft.rfft2(image, s=(2 * height, 2 * width))
    glare = jnp.fft.irfft2(padded * glare_fft, s=(2 * height, 2 * width))[:, :height, :width]
    return (1.0 - stray) * image + stray * glare


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
        self.glare_fft = _glare_kernel_fft(image_shape, instrument.stray_light_core_px)
        self.flux_scale = None  # set by calibrate_exposures
        self.exposure = None
        self.clock_s = 0.0

    def _beta(self) -> np.ndarray:
        """β_b(x), (16, H, W): cos⁴ vignetting times a per-filter linear gradient."""
        height, width = self.image_shape
        y, x = np.mgrid[0:height, 0:width].astype(float)
        cy, cx = (height - 1) / 2, (width - 1) / 2
        half_diagonal = np.hypot(cy, cx)
        r = np.hypot(y - cy, x - cx) / half_diagonal
        # cos⁴ law with the field angle chosen so the corners fall by `vignetting`.
        tan_corner2 = (1.0 - self.instrument.vignetting) ** -0.5 - 1.0
        vignette = (1.0 + tan_corner2 * r**2) ** -2
        angles = self.rng.uniform(0, 2 * np.pi, 16)
        slopes = self.instrument.filter_gradient * self.rng.uniform(0.5, 1.0, 16)
        along = ((x - cx)[None] * np.cos(angles)[:, None, None] + (y - cy)[None] * np.sin(angles)[:, None, None]) / half_diagonal
        return vignette[None] * (1.0 + slopes[:, None, None] * along)

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


# ---------------------------------------------------------------------------------------------
# The experiment


@dataclasses.dataclass
class SimulatedFrame:
    """One capture: what the session manifest records and the pixels."""

    id: str
    role: str
    pixels: np.ndarray  # (H, W, 16) uint16
    start_s: float
    set: str | None = None
    background: str | None = None
    regions: list[dict] = dataclasses.field(default_factory=list)
    metadata: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class SimulatedExperiment:
    """Everything a simulated session holds (`session_contents`): frames plus the layout and the
    parameters."""

    instrument: InstrumentModel
    design: ExperimentDesign
    seed: int
    image_shape: tuple[int, int]
    holder: tuple[int, int, int, int]
    white_patch: tuple[int, int, int, int]
    exposure_s: np.ndarray
    frames: list[SimulatedFrame]
    materials: dict[str, Material]


def _centred_region(r0, c0, size, region):
    offset = (size - region) // 2
    return [r0 + offset, r0 + offset + region, c0 + offset, c0 + offset + region]


def _patch_slots(holder_shape, patch_px, count):
    """`count` positions (row, col) of small patches on the holder, spread over the field."""
    height, width = holder_shape
    rows = np.linspace(0.22, 0.78, count) * height - patch_px / 2
    cols = np.linspace(0.2, 0.8, count) * width - patch_px / 2
    # Alternate rows so the positions cover the field's corners and centre.
    rows = np.concatenate([rows[::2], rows[1::2]])
    return [(int(r), int(c)) for r, c in zip(rows, cols)]


def _pattern(kind: int, holder_shape, n_materials: int, rng) -> np.ndarray:
    """Index map (H, W) of a patterned background made of `n_materials` stripes or checks."""
    height, width = holder_shape
    y, x = np.mgrid[0:height, 0:width]
    period = int(rng.integers(28, 64))
    if kind % 4 == 0:
        cells = x // period
    elif kind % 4 == 1:
        cells = y // period
    elif kind % 4 == 2:
        cells = (x // period) + (y // period)
    else:
        cells = (x + y) // period
    return (cells % n_materials).astype(np.int32)


@dataclasses.dataclass(frozen=True)
class Scene:
    """What lies on the holder for one capture: a material index map over the holder and its
    material table, plus the session-manifest fields (regions in image pixels)."""

    name: str
    role: str  # "white", "sample" or "target"
    holder_map: np.ndarray  # (holder H, holder W) int32, indices into `table`
    table: tuple  # Material, ...
    regions: tuple = ()  # {"name", "patch", "region": [r0, r1, c0, c1], "reflectance": 31}
    set: str | None = None
    background: str | None = None


@dataclasses.dataclass
class ExperimentLayout:
    """The paper's experiment before rendering: materials and where everything lies.

    `scenes` holds the sample and target captures in capture order; `white` the white standard.
    `sensor_map` adds what surrounds the holder in every frame (the black mount and the white
    reference patch).
    """

    instrument: InstrumentModel
    design: ExperimentDesign
    seed: int
    image_shape: tuple[int, int]
    holder_shape: tuple[int, int]
    white_patch: tuple[int, int, int, int]
    standard: Material
    white_tile: Material
    mount: Material
    white: Scene
    scenes: dict[str, Scene]
    materials: dict[str, Material]

    def sensor_map(self, scene: Scene) -> tuple[np.ndarray, list[Material]]:
        """`sensor_map` of a scene of this experiment."""
        return sensor_map(scene, self.image_shape, self.white_patch, self.mount, self.white_tile)


def sensor_map(scene: Scene, image_shape, white_patch, mount: Material, white_tile: Material) -> tuple[np.ndarray, list[Material]]:
    """(material index map (H, W) over the whole image, material table) of a scene: the
    holder's content at the top left plus the strip beside it, black mount with the white
    reference patch at `white_patch` (r0, r1, c0, c1)."""
    table = list(scene.table) + [mount, white_tile]
    full = np.full(tuple(image_shape), len(table) - 2, np.int32)
    height, width = scene.holder_map.shape
    full[:height, :width] = scene.holder_map
    r0, r1, c0, c1 = white_patch
    full[r0:r1, c0:c1] = len(table) - 1
    return full, table


def fixed_materials(instrument: InstrumentModel, seed: int) -> tuple[Material, Material, Material]:
    """(white standard, white reference tile, black mount): in every experiment."""
    standard = _material("white standard", "PTFE board", _flat(instrument.white_standard_reflectance), instrument, seed, lambertian=True)
    white_tile = _material("white patch", "ceramic tile", _flat(instrument.white_patch_reflectance), instrument, seed, lambertian=True)
    mount = _material("mount", "black anodised", _flat(instrument.mount_reflectance), instrument, seed, lambertian=True)
    return standard, white_tile, mount


def experiment_layout(seed: int = 0, instrument: InstrumentModel | None = None, design: ExperimentDesign | None = None) -> ExperimentLayout:
    """The materials and scenes of the paper's experiment (Section 4), without rendering:
    9 grey patches on 10 uniform backgrounds (training), coloured patches on patterned
    backgrounds (test), a chart of colour targets. Deterministic for a seed, instrument, design.
    `simulate_experiment` renders it; `hw.simcamera` renders it frame by frame."""
    instrument = instrument or InstrumentModel()
    design = design or ExperimentDesign()
    library = _Library()
    holder_shape = design.holder_shape(instrument)

    def material(name, source, reflectance, lambertian=False, fluorescence=0.0):
        return _material(name, source, reflectance, instrument, seed, lambertian, fluorescence)

    standard, white_tile, mount = fixed_materials(instrument, seed)

    # Greys for training: the neutral rows of the ColorCheckers, spread light to dark.
    neutrals = []
    for set_name in ("ColorChecker: BabelColor Average", "ColorChecker: ColorChecker N Ohta", "ColorChecker: ISO 17321-1"):
        neutrals += [(f"{set_name} / {n}", r) for n, r in library.take(set_name, lambda n: n.startswith(("white", "neutral", "black")))]
    greys = [material(n, "colour-science", r) for n, r in _spread_by_brightness(neutrals, design.training_patches)]

    # Backgrounds: TM-30 CES spectra, uniform for training and in patterns for test, disjoint.
    ces = library.take("CES (TM-30)")
    training_picks = _spread_by_brightness(ces, design.training_backgrounds)  # darkest first
    training_names = {n for n, _ in training_picks}
    fluorescent = {n for n, _ in training_picks[-design.fluorescent_training_backgrounds :]} if design.fluorescent_training_backgrounds else set()
    backgrounds = [
        material(f"CES / {n}", "colour-science", r, fluorescence=1.0 if n in fluorescent else 0.0)
        for n, r in training_picks
    ]
    remaining = [item for item in ces if item[0] not in training_names]
    remaining += [(f"CQS 9.0 / {n}", r) for n, r in library.take("VS: NIST CQS 9.0")]

    # Coloured test patches: chromatic ColorChecker patches (BabelColor), spread in hue.
    chromatic = library.take("ColorChecker: BabelColor Average", lambda n: not n.startswith(("white", "neutral", "black")))
    chosen = [chromatic[int(i)] for i in np.round(np.linspace(0, len(chromatic) - 1, design.test_patches))]
    test_patches = [material(f"BabelColor / {n}", "colour-science", r) for n, r in chosen]

    # Targets: the RAW to ACES training patches, spread over the set.
    aces = library.take("RAW to ACES training")
    target_idx = np.round(np.linspace(0, len(aces) - 1, design.targets)).astype(int)
    targets = [material(f"ACES / {aces[i][0]}", "colour-science", aces[i][1]) for i in target_idx]
    chart_surround = greys[len(greys) // 2]

    materials = {m.name: m for m in [standard, white_tile, mount, *greys, *backgrounds, *test_patches, *targets]}
    scenes: dict[str, Scene] = {}
    slots = _patch_slots(holder_shape, design.patch_px, design.patches_per_capture)

    def patch_scene(frame_id, set_name, background_name, holder_map, table, patches, shift):
        """Place `patches` on a background at rotated slots."""
        holder_map = holder_map.copy()
        table = list(table)
        regions = []
        for k, patch in enumerate(patches):
            r, c = slots[(k + shift) % len(slots)]
            table.append(patch)
            holder_map[r : r + design.patch_px, c : c + design.patch_px] = len(table) - 1
            regions.append({
                "name": patch.name, "patch": patch.name,
                "region": _centred_region(r, c, design.patch_px, design.region_px),
                "reflectance": patch.at_31().tolist(),
            })
        scenes[frame_id] = Scene(frame_id, "sample", holder_map, tuple(table), tuple(regions), set_name, background_name)

    groups = [greys[i : i + design.patches_per_capture] for i in range(0, len(greys), design.patches_per_capture)]
    for j, background in enumerate(backgrounds):
        for g, group in enumerate(groups):
            patch_scene(
                f"train-bg{j:02d}-g{g}", "training", background.name,
                np.zeros(holder_shape, np.int32), [background], group, shift=j + g,
            )

    test_groups = [test_patches[i : i + design.patches_per_capture] for i in range(0, len(test_patches), design.patches_per_capture)]
    pattern_rng = np.random.default_rng([seed, 7])
    test_fluorescent = design.fluorescent_test_backgrounds
    for j in range(design.test_backgrounds):
        n_materials = 2 + j % 3
        picks = [remaining[int(i)] for i in pattern_rng.choice(len(remaining), n_materials, replace=False)]
        table = [
            material(n if n.startswith("CQS") else f"CES / {n}", "colour-science", r,
                     fluorescence=1.0 if (j < test_fluorescent and k == 0) else 0.0)
            for k, (n, r) in enumerate(picks)
        ]
        for m in table:
            materials[m.name] = m
        holder_map = _pattern(j, holder_shape, n_materials, pattern_rng)
        name = "pattern-" + "+".join(m.name.split(" / ")[-1] for m in table)
        for g, group in enumerate(test_groups):
            patch_scene(f"test-bg{j:02d}-g{g}", "test", name, holder_map, table, group, shift=j + g)

    # The target chart: 12 x 12 targets on a mid-grey surround, centred on the holder.
    per_row = int(np.ceil(np.sqrt(design.targets)))
    chart = np.zeros(holder_shape, np.int32)
    table = [chart_surround]
    regions = []
    top = (holder_shape[0] - per_row * design.target_px) // 2
    left = (holder_shape[1] - per_row * design.target_px) // 2
    for k, target in enumerate(targets):
        r = top + (k // per_row) * design.target_px
        c = left + (k % per_row) * design.target_px
        table.append(target)
        chart[r : r + design.target_px, c : c + design.target_px] = len(table) - 1
        regions.append({
            "name": f"t{k:03d}", "patch": target.name,
            "region": _centred_region(r, c, design.target_px, design.target_region_px),
            "reflectance": target.at_31().tolist(),
        })
    scenes["targets"] = Scene("targets", "target", chart, tuple(table), tuple(regions))

    return ExperimentLayout(
        instrument=instrument, design=design, seed=seed, image_shape=design.image_shape(instrument),
        holder_shape=holder_shape, white_patch=design.white_patch(instrument), standard=standard,
        white_tile=white_tile, mount=mount,
        white=Scene("white", "white", np.zeros(holder_shape, np.int32), (standard,)),
        scenes=scenes, materials=materials,
    )


def simulate_experiment(seed: int = 0, instrument: InstrumentModel | None = None, design: ExperimentDesign | None = None) -> SimulatedExperiment:
    """Render the paper's experiment (`experiment_layout`): dark, white standard, training, test
    and target captures.

    Deterministic for a given seed, instrument and design.
    """
    layout = experiment_layout(seed, instrument, design)
    instrument, design = layout.instrument, layout.design
    renderer = _Renderer(instrument, layout.image_shape, layout.holder_shape, seed)

    # White standard, then exposures, then the dark frame at those exposures.
    white_rates = renderer.rates(*layout.sensor_map(layout.white))
    exposure = renderer.calibrate_exposures(white_rates)
    frames: list[SimulatedFrame] = []
    dark_pixels, t = renderer.capture(None, instrument.frames_averaged_dark)
    frames.append(SimulatedFrame("dark", "dark", dark_pixels, t))
    white_pixels, t = renderer.capture(white_rates, instrument.frames_averaged_white)
    frames.append(SimulatedFrame("white", "white", white_pixels, t))
    for scene in layout.scenes.values():
        pixels, start = renderer.capture(renderer.rates(*layout.sensor_map(scene)), instrument.frames_averaged_sample)
        frames.append(SimulatedFrame(scene.name, scene.role, pixels, start, scene.set, scene.background, list(scene.regions)))

    return SimulatedExperiment(
        instrument=instrument, design=design, seed=seed, image_shape=layout.image_shape,
        holder=(0, layout.holder_shape[0], 0, layout.holder_shape[1]), white_patch=layout.white_patch,
        exposure_s=exposure, frames=frames, materials=layout.materials,
    )


def session_contents(experiment: SimulatedExperiment) -> dict:
    """What a session folder of `experiment` holds, as the keyword arguments of
    `spherejax.io.write_session` (instrument id, bands, shape, saturation, white patch, holder,
    frames (manifest entry, (H, W, B) uint16 pixels), metadata). Writing them is the files
    layer's (`spherejax.io.write_simulated_session`, `spherejax simulate`): this module computes.
    """
    start = datetime.datetime(2026, 1, 1, 9, 0, 0, tzinfo=datetime.timezone.utc)
    frames = []
    for frame in experiment.frames:
        info = {
            "id": frame.id,
            "role": frame.role,
            "exposure_s": [float(e) for e in experiment.exposure_s],
            "timestamp": (start + datetime.timedelta(seconds=frame.start_s)).isoformat(),
            "metadata": dict(frame.metadata, frames_averaged={
                "dark": experiment.instrument.frames_averaged_dark,
                "white": experiment.instrument.frames_averaged_white,
            }.get(frame.role, experiment.instrument.frames_averaged_sample)),
        }
        if frame.role == "sample":
            info["set"] = frame.set
            info["background"] = frame.background
        if frame.regions:
            info["regions"] = frame.regions
        frames.append((info, frame.pixels))
    metadata = {
        # The white board's certificate: what a lab would copy into its session (the Markov
        # baseline needs R_W).
        "white_standard_reflectance": experiment.materials["white standard"].at_31().tolist(),
        "simulator": {
            "seed": experiment.seed,
            "instrument": dataclasses.asdict(experiment.instrument),
            "design": dataclasses.asdict(experiment.design),
            "materials": {
                m.name: {"source": m.source, "coupling": m.coupling, "fluorescence": m.fluorescence}
                for m in experiment.materials.values()
            },
        }
    }
    if experiment.instrument.noise:
        # The camera's true noise, for calibrate's noise model (`spherejax.uncertainty`); with
        # the model's noise switched off the frames have none, and no camera record claims any.
        gain = float(experiment.instrument.gain_e_per_dn)
        metadata["camera"] = {"gain_e_per_count": gain, "read_noise_counts": float(experiment.instrument.read_noise_e) / gain}
    return dict(
        instrument_id="sim-sphere-1",
        band_centres_nm=[int(b) for b in BAND_CENTRES_NM],
        image_shape=list(experiment.image_shape),
        saturation=experiment.instrument.saturation_dn,
        white_patch=list(experiment.white_patch),
        holder=list(experiment.holder),
        frames=frames,
        metadata=metadata,
    )


__all__ = [
    "FINE_WAVELENGTHS_NM",
    "InstrumentModel",
    "ExperimentDesign",
    "Material",
    "SimulatedFrame",
    "SimulatedExperiment",
    "Scene",
    "ExperimentLayout",
    "experiment_layout",
    "fixed_materials",
    "sensor_map",
    "simulate_experiment",
    "session_contents",
]
