"""The simulated instrument's physics (`InstrumentModel`): the integrating sphere, the xenon lamp,
the filters and the CCD camera, as parameters with the values of Zou et al. (2019)'s instrument
and the quantities the renderer derives from them.

- the sphere (Section 5, Eqs. 2-3): port fractions (α_ww, α_wsp, α_spw) from its diameter, its
  ports and the holder; wall reflectance ρ_w(λ) rising from the violet to the red;
- the lamp: a 6000 K near-continuum with the xenon line cluster at 450-500 nm, relative, max 1;
- the camera: 16 Gaussian filters (FWHM 10 nm) at `grid.BAND_CENTRES_NM`, a CCD quantum
  efficiency, and (16, L) band weights filter x QE x lamp x dλ; gain e-/DN and saturation DN;
- fluorescence: the apparent reflectance whitening agents add near 440 nm.

Spectra are on FINE_WAVELENGTHS_NM (L = 171 samples, 380..720 nm step 2), numpy; lengths m,
wavelengths nm, times s, charges e-. What lies on the holder is `spherejax.simulated_layout`'s,
how frames are rendered from both `spherejax.simulated_rendering`'s.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .grid import BAND_CENTRES_NM

#: Spectral integration grid, nm: 2 nm steps, wide enough for the 400 and 700 nm filters' tails.
FINE_WAVELENGTHS_NM = np.arange(380.0, 721.0, 2.0)


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
    non_lambertian_spread: 0.002 -- first-bounce coupling 1 ± up to 0.2 % by material: a textile
      BRDF (`textile_brdf`: rough diffuse plus sheen, over its parameters' published ranges)
      under the light the paper's sphere sends to the holder (`sphere_radiosity.incident_light`)
      couples the first reflection's light within 0.2 % of the later reflections'
      (tests/test_textile_brdf.py). It was 0.25, a guess from gonioreflectometry under
      directional light, until that was computed; the sphere's light is too diffuse for more.
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
    filter_thickness_mm: 3.0, filter_thickness_tolerance_mm: 0.1, filter_refractive_index: 1.5 --
      mounted 25 mm interference filters are a few millimetres of glass (fused silica 1.46,
      borosilicate 1.52), made to a tenth of a millimetre or so; no two in a wheel are alike.
    filter_tilt_deg: 0.5 -- how far a filter may sit tilted in its bore of the wheel (each is
      drawn within ±this per seed); a tilted plate displaces the image (`band_geometry`).
    filter_wedge_arcsec: 30 -- the parallelism catalogue bandpass filters are specified to.
    filter_to_sensor_mm: 15 -- a wheel between a C-mount lens and the sensor lies within the
      mount's 17.526 mm flange distance.
    image_distance_mm: 55, magnification: 0.109 -- a 50 mm lens at the paper's field: the QI695's
      12.5 mm sensor (2750 px of 4.54 µm) across ~11.5 cm (the holder and the white patch beside
      it); v = f (1 + m) for a thin lens.
    lens_lateral_colour_per_nm: 2e-6 -- the magnification's change per nm of wavelength, 0.06 %
      across 400-700 nm: a few micrometres at the field's edge, a corrected lens's lateral colour.
    band_misregistration_px: None -- the bands' maps as the filter and lens parameters above make
      them (`band_geometry.physical_transforms`): 0.2-0.5 frame pixels at most over the frame at
      24 px/cm (2-5 of the QI695's; seeds 0-3), the realistic default now that `calibrate`
      registers the bands. A number rescales the maps to that largest displacement of any band
      from the reference band (560 nm), in frame pixels (`spherejax simulate --band-misregistration
      PX`); 0 renders the bands in register.
    sample_layer_scattering_power: 0 -- the Kubelka scattering power S X (scattering coefficient
      times thickness) of the small patches and chart targets as single layers over what lies
      beneath them (`kubelka_munk.layer_over_background`); 0 lays them opaque, as the paper's
      Table 4 implies. A single woven layer is far from opaque: colour measurement folds a
      textile until it is (AATCC EP6; ISO 105-J01), and "two to four layers" suffice for most
      woven and knitted fabrics (Datacolor's measurement practice note), which for a mid-tone
      (R_inf 0.3, opaque to 0.002 at S X 2.25) puts one layer at S X 0.6-1.1. Yet at S X 3
      (seed 0) Stage II leaves 1.55 ΔE00 on the training patches where the paper's leaves 0.37:
      what shows through depends on the patch's own K/S and the stripe beneath, which the
      polynomial in v and p cannot follow (docs/results.md's ablation). So the paper's patches
      behaved as opaque ones (backed, or thick), and so do the default's. For studies of thin
      specimens.
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
    non_lambertian_spread: float = 0.002
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
    filter_thickness_mm: float = 3.0
    filter_thickness_tolerance_mm: float = 0.1
    filter_refractive_index: float = 1.5
    filter_tilt_deg: float = 0.5
    filter_wedge_arcsec: float = 30.0
    filter_to_sensor_mm: float = 15.0
    image_distance_mm: float = 55.0
    magnification: float = 0.109
    lens_lateral_colour_per_nm: float = 2e-6
    band_misregistration_px: float | None = None
    sample_layer_scattering_power: float = 0.0
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


__all__ = ["FINE_WAVELENGTHS_NM", "InstrumentModel"]
