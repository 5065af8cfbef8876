"""Synthetic target families closer to real ones: shade cards, brighteners, gloss and texture.

The Kubelka-Munk families of `spherejax.kubelka_munk` are mixing sets: recipes of 1 to 3 of six
dyes drawn at random, rendered through the simulated camera, with the reference seeing exactly
what the camera sees. Real targets of one material differ in four ways, each a family kind here
(`FAMILY_KINDS`), so that estimator designs are decided on all of them:

  "km_mixing"      the existing families, unchanged (`kubelka_munk.km_family_responses`; one of
                   its four, `KM_DEFAULT_FAMILY` unless `family=` names another).
  "shade_card"     one substrate (bleached cotton) and a dye range of 13 dyes: 12 spanning the
                   hue circle (`SHADE_CARD_RING`) and a black. Recipes are laid out as a shade card
                   is: hues spread around the circle (two neighbouring dyes of the ring in
                   proportion), depths from pale to deep, a third dye (the black or the hue's
                   complement) dulling some of them, plus greys, near-neutrals and whites
                   (`shade_card_recipes`). Camera and reference see the same surface (SCE).
  "fluorescent"    the shade card on a brightened substrate (`BRIGHTENER`, a stilbene-type
                   fluorescent whitening agent in every target). The camera sees the reflectance
                   plus the fluorescence the sphere's xenon light excites; the reference
                   spectrophotometer reports the total radiance factor under D65. The two
                   illuminants' ultraviolet differs, so camera and reference see different
                   fluorescence; dyes absorb in the excitation and emission bands, so the
                   brightener's effect fades in deep shades (Eqs. F1-F5).
  "gloss_texture"  the shade card with surface reflection and texture (`SURFACE`): each target's
                   surface reflection k1 and its finish, from matte to satin (the fraction g of
                   the surface reflection in the specular direction), a cavity fraction f of pile
                   and weave whose inter-reflections deepen colour (Eq. S1), a reference measured
                   specular included (SCI, d/8) beside the camera's d/0 view, which misses the
                   specular part (Eq. S3), and a per-target texture noise in the camera's region
                   mean (Eq. S4).
  "mixed_real"     everything together: the shade card, the brightener on the paler targets
                   (whites and pastels, `BRIGHTENER_MAX_DEPTH`, as dyers use it), gloss and
                   texture.

Every kind but "km_mixing" also gives the reference reflectances a spectrophotometer's noise
(`REFERENCE_NOISE`); the camera's noise is the simulator's (`simulated_targets.render_targets`)
for region means over `patch_pixels` pixels (as `kubelka_munk.km_family_responses` renders them:
the instrument's frame counts times `patch_pixels`; 1225 = the paper's 35 x 35 px regions).
Held out (the best affine estimator of fit_wiener on seed 0, tested on seed 1, n = 200 each,
1225 px), spectral rms: km_mixing 0.00087, shade_card 0.0018, fluorescent 0.0022, gloss_texture
0.0024, mixed_real 0.0037 (every candidate estimator on every kind: benchmarks/bench_wiener.py).
Against the noise-free reference the shade card's is 0.0010: the spectrophotometer's noise is most
of what it adds; the part of the surface reflection the camera cannot see, (1 - f) g k1 (about
2 % reflectance, varying by 0.2 % between targets), much of gloss_texture's.

Fluorescence (the brightener), Kubelka-Munk two-flux with a source, S the same at every
wavelength (K/S in units of S), per target, excitation μ, emission λ:
  (F1) σ = sqrt(a (a + 2)), a = K/S, R_∞ = 1 + a - σ                      decay rate of the flux
  (F2) i(μ) = (1 - k1) E_p(μ) / (1 - k2 R_∞(μ))                           diffuse flux entering
  (F3) absorbed by the brightener per unit depth: Φ a_b(μ) (1 + R_∞(μ)) i(μ) exp(-σ_μ z), Φ the
       quantum yield, a_b its K/S
  (F4) η(λ, μ) = (1 + R_∞(λ)) σ_μ / (2 (σ_λ + σ_μ))                       the fraction of light
       emitted with that depth profile that leaves the layer upward: the two-flux equations with
       a source q exp(-σ_μ z) split equally up and down, no downward flux at the top, solved in
       closed form (η = 1 where nothing absorbs at λ, 0 where everything does)
  (F5) β_L(λ) = (1 - k2) / (1 - k2 R_∞(λ)) f(λ) / E_p(λ) Σ_μ Δμ Φ a_b(μ) (1 + R_∞(μ)) i(μ) η(λ, μ) / σ_μ
       the luminescent radiance factor, f the emission spectrum (photons per nm, unit area), E_p
       the illuminant in photons; the total radiance factor is β_T = R_m + β_L (Donaldson 1954).
  The leading factor of (F5) is Saunderson's for light leaving from inside: the internally
  reflected part k2 goes back down and returns R_∞ of itself, and so on. The extended
  Kubelka-Munk treatment of brighteners is that of Shakespeare & Shakespeare (2003) and Coppel et
  al. (2011); (F4) is the closed form of its two-flux equations for an opaque layer, derived here
  and checked in tests/test_target_families.py against a numerical solution of them.

Surface and texture, per target (R the body's reflectance outside the surface, Saunderson's
Eq. (4) of `kubelka_munk` without k1, β_L added where the target fluoresces):
  (S1) R_cav(R) = R (1 - a) / (1 - a R)          a cavity's reflectance: light leaving a wall
       hits another wall with probability a, escapes with 1 - a (the geometric series of
       inter-reflections; Koenderink & van Doorn 1983); a = 1 - sin(θ) for a V-groove of
       half-opening θ (2-D view factor), `SurfaceFinish.cavity_self_view`
  (S2) R_SCI = (1 - f) (R + k1) + f R_cav(R + k1)                     the reference, d/8 SCI
  (S3) R_cam = (1 - f) (R + (1 - g) k1) + f R_cav(R + k1)              the camera, d/0: it misses
       the specular part g k1 of the flat tops' surface reflection (its specular direction is
       the dark detector port: `kubelka_munk.SPECULAR_INCLUDED`), while the cavity walls, tilted
       every way, send their surface reflection diffusely; so R_SCI - R_cam = (1 - f) g k1
  (S4) f_cam = f (1 + ε c sqrt(cell / patch_pixels)), ε ~ N(0, 1)     the camera's region mean
       sees patch_pixels / cell weave cells of relative cavity contrast c; the reference's
       aperture averages thousands

References:
  R. Donaldson, "Spectrophotometry of fluorescent pigments", Br. J. Appl. Phys. 5, 210-214 (1954).
  T. Shakespeare, J. Shakespeare, "A fluorescent extension to the Kubelka-Munk model", Color Res.
    Appl. 28, 4-14 (2003).
  L. G. Coppel, M. Andersson, P. Edström, J. Kinnunen, "Limitations in the efficiency of
    fluorescent whitening agents in uncoated paper", Nord. Pulp Pap. Res. J. 26, 319-328 (2011),
    doi:10.3183/npprj-2011-26-03-p319-328.
  H. Zollinger, "Color Chemistry", 3rd ed., Wiley-VCH (2003): dye classes and their absorption.
  A. Siegrist, C. Eckhardt, J. Kaschig, E. Schmidt, "Optical Brighteners", Ullmann's Encyclopedia
    of Industrial Chemistry, Wiley-VCH (2003).
  J. J. Koenderink, A. J. van Doorn, "Geometrical modes as a general method to treat diffuse
    interreflections in radiometry", J. Opt. Soc. Am. 73, 843-850 (1983).
  J. L. Saunderson, J. Opt. Soc. Am. 32, 727-736 (1942); R. S. Berns, "Billmeyer and Saltzman's
    Principles of Color Technology", 4th ed., Wiley (2019): SCI and SCE geometries, colorant
    mixing, instrument precision.
  ASTM E2214, "Standard Practice for Specifying and Verifying the Performance of Color-Measuring
    Instruments": repeatability and reproducibility of spectrophotometers.
"""

from __future__ import annotations

import dataclasses

import colour
import numpy as np

from .kubelka_munk import (
    K1_N_1_5,
    MATERIAL_FAMILIES,
    AbsorptionBand,
    Dye,
    absorption_bands_ks,
    km_family_responses,
    on_reflectance_grid,
    reflectance_from_ks,
    saunderson,
)
from .simulate import FINE_WAVELENGTHS_NM, InstrumentModel
from .simulated_targets import render_targets

#: The family kinds `target_family` makes (module docstring).
FAMILY_KINDS = ("km_mixing", "shade_card", "fluorescent", "gloss_texture", "mixed_real")

#: The Kubelka-Munk family "km_mixing" returns unless `family=` names another of
#: `kubelka_munk.MATERIAL_FAMILIES`: reactive dyes on cotton, the substrate of the shade cards.
KM_DEFAULT_FAMILY = "cotton reactive"

#: Excitation wavelengths of the brightener, nm: 300 nm (where D65 and a xenon lamp through a
#: sphere's glass-free port still emit; stilbene brighteners absorb from ~300 nm) to 428 nm (the
#: tail of their band into the violet), 2 nm steps as the simulator's grid.
EXCITATION_WAVELENGTHS_NM = np.arange(300.0, 429.0, 2.0)


def _band(peak_nm: float, fwhm_nm: float, strength: float) -> AbsorptionBand:
    return AbsorptionBand(peak_nm, fwhm_nm, strength)


# --- the shade card's material ------------------------------------------------------------------

#: The shade cards' substrate, k1 and k2: `kubelka_munk`'s bleached cotton (~0.80 at 400 nm, ~0.88
#: at 700 nm), normal-incidence Fresnel k1 for n = 1.5 and k2 = 0.6 (as its cotton family).
SHADE_CARD_SUBSTRATE = MATERIAL_FAMILIES["cotton reactive"].substrate
SHADE_CARD_K1 = K1_N_1_5
SHADE_CARD_K2 = 0.6

#: Twelve reactive dyes in hue order around the circle (CIELAB hue angle under D65 falling from
#: one to the next at 1 % owf, tests/test_target_families.py checks it), unit K/S per 1 % owf as
#: `kubelka_munk`'s dyes: bands Gaussian in wavenumber at the absorption maxima of their classes
#: (greenish yellow ~400 nm, yellow 420-430, golden yellow and orange 460-490, scarlet and red
#: 500-515, rubine ~530, violet ~570, navy broad near 600, royal blue ~620 with its red shoulder,
#: copper phthalocyanine turquoise with its 626/670 nm Q bands and its near-UV B band, a green with
#: a blue and a red band, as green reactive dyes are (a yellow and a blue chromophore linked)),
#: strengths 2-4 at the main peak: pale tints at 0.01 % owf, deep shades at 4 %
#: (`SHADE_CARD_DEPTH_RANGE`). Each dye also absorbs in the near ultraviolet, as the aromatic
#: systems of azo, anthraquinone and phthalocyanine dyes do (bands at 320-420 nm, Zollinger 2003):
#: where its visible bands leave the ultraviolet clear, a band at 330 nm of a quarter to a half of
#: the main one; so deep shades take the light a brightener needs (F3). Synthesised, not measured
#: (as `kubelka_munk`'s).
SHADE_CARD_RING = (
    Dye("greenish yellow", (_band(402, 70, 2.6), _band(350, 50, 0.8))),
    Dye("yellow", (_band(425, 85, 2.8), _band(365, 60, 0.8))),
    Dye("golden yellow", (_band(462, 90, 2.6), _band(380, 60, 0.5))),
    Dye("orange", (_band(488, 85, 2.6), _band(400, 60, 0.4))),
    Dye("scarlet", (_band(502, 75, 3.0), _band(540, 40, 0.5), _band(330, 50, 1.0))),
    Dye("red", (_band(515, 75, 3.0), _band(545, 40, 0.8), _band(390, 70, 0.3), _band(330, 50, 0.8))),
    Dye("rubine", (_band(530, 70, 2.8), _band(562, 40, 1.0), _band(335, 50, 1.0))),
    Dye("violet", (_band(572, 80, 2.6), _band(535, 50, 0.8), _band(410, 60, 0.4))),
    Dye("navy", (_band(595, 130, 2.4), _band(545, 70, 0.9), _band(420, 80, 0.3), _band(330, 50, 1.0))),
    Dye("royal blue", (_band(618, 90, 3.0), _band(662, 60, 1.6), _band(330, 50, 1.2))),
    Dye("turquoise (Cu phthalocyanine)", (_band(626, 55, 4.0), _band(670, 45, 3.0), _band(350, 50, 1.5))),
    Dye("green", (_band(430, 70, 1.8), _band(650, 70, 2.2))),
)

#: The range's black: broad absorption across the visible (a bis-azo black is a navy chromophore
#: with brown and violet side bands), for greys and for dulling.
SHADE_CARD_BLACK = Dye("black", (_band(600, 150, 2.4), _band(480, 110, 1.8), _band(400, 80, 1.0), _band(330, 60, 1.2)))

#: The dye range: the ring, then the black (recipes (n, 13) in this order).
SHADE_CARD_DYES = (*SHADE_CARD_RING, SHADE_CARD_BLACK)

#: Depth of shade, the total dye in a recipe, % owf: 0.01 (a pale tint, 1/100 standard depth) to
#: 4 % (deep shades; reactive navies and blacks go to 6-8 %), log-uniform as shade cards step
#: through depths by factors.
SHADE_CARD_DEPTH_RANGE = (0.01, 4.0)


# --- the brightener -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Brightener:
    """A fluorescent whitening agent: absorption (K/S per 1 % owf, Eq. (6) of `kubelka_munk`),
    emission band (Gaussian in wavenumber: peak and FWHM in nm) and quantum yield Φ (F3)."""

    absorption: tuple[AbsorptionBand, ...]
    emission_peak_nm: float
    emission_fwhm_nm: float
    quantum_yield: float

    def unit_ks(self, wavelengths_nm: np.ndarray) -> np.ndarray:
        """(L,) K/S per 1 % owf at `wavelengths_nm`."""
        return absorption_bands_ks(wavelengths_nm, self.absorption)

    def emission(self, wavelengths_nm: np.ndarray) -> np.ndarray:
        """(L,) f(λ), photons per nm, sum(f dλ) = 1 on the 2 nm grid; zero below 396 nm, where a
        band excited at 300-428 nm emits nothing (Stokes shift)."""
        wavelengths_nm = np.asarray(wavelengths_nm, np.float64)
        offset = (1.0 / wavelengths_nm - 1.0 / self.emission_peak_nm) * self.emission_peak_nm**2 / self.emission_fwhm_nm
        shape = np.where(wavelengths_nm >= 396.0, np.exp(-4.0 * np.log(2.0) * offset**2), 0.0)
        return shape / (shape.sum() * 2.0)


#: A stilbene-type brightener (a 4,4'-bis(triazinylamino)stilbene-2,2'-disulfonate, the class of
#: most textile and paper brighteners; Siegrist et al. 2003): absorption peak at 350 nm (their
#: maxima lie at 340-360 nm, the band spanning ~300-400 nm), FWHM 35 nm, so that it leaves the
#: visible nearly clear (K/S 0.04 at 400 nm at the loading below: more tail into the violet is
#: what greens whites at high loadings, Coppel et al. 2011); emission peak 440 nm (reported
#: 430-440 nm on cellulose; the simulator's `InstrumentModel.fluorescence_peak_nm` is 440), FWHM
#: 60 nm (emission spans ~400-500 nm). Strength 15 K/S per 1 % owf: at `BRIGHTENER_CONCENTRATION`
#: = 0.2 % owf (textile loadings are about 0.05-0.5 % owf) the brightened cotton's K/S at 350 nm
#: is 3: it takes most of the ultraviolet. Φ = 0.6: stilbene brighteners fluoresce efficiently
#: when bound to the fibre (values from ~0.3 to ~0.9 are reported across the class and its
#: environments; Siegrist et al. 2003). With these values a brightened white's total radiance
#: factor under D65 peaks at 1.06 near 430 nm, within the 1.05-1.15 of brightened papers and
#: cottons (tests/test_target_families.py checks it); under the sphere's light at 1.12.
BRIGHTENER = Brightener(absorption=(_band(350, 35, 15.0),), emission_peak_nm=440.0,
                        emission_fwhm_nm=60.0, quantum_yield=0.6)
BRIGHTENER_CONCENTRATION = 0.2

#: In "mixed_real" the brightener is in whites and pastels only (recipes of at most this total
#: dye, % owf): dyers add it to pale shades, where it brightens, not to deep ones, where the dyes
#: absorb its light (F4).
BRIGHTENER_MAX_DEPTH = 0.1


# --- surface, texture, reference ----------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SurfaceFinish:
    """The ranges from which each target's surface is drawn (uniformly), Eqs. S1-S4.

    A family is one material: its targets share one fabric and finish, and differ in surface only
    as dyeing changes it, so the defaults are narrow spreads about the middle of the ranges that
    materials span (given per field below). Drawn per target across those whole ranges, the
    surface the camera cannot see (R_SCI - R_SCE, 0.7-3.7 % reflectance) was most of every
    estimator's error and hid every difference between them (measured: affine and kernel 0.0074
    held out on gloss_texture); `SurfaceFinish(k1_range=(0.040, 0.053), gloss_range=(0.2, 0.8),
    cavity_fraction_range=(0.05, 0.35))` makes that mixture of finishes.

    k1_range: surface reflection, 0.040-0.053: normal-incidence Fresnel for n = 1.50-1.60
      (cellulose 1.53-1.55; finishes and softeners shift it; polyester reaches 1.64).
    gloss_range: g, the part of k1 in the specular direction: 0.2 (matte: rough fibre surfaces
      scatter most of it) to 0.8 (satin: calendered or long-float weaves), which makes R_SCI -
      R_SCE of 0.8-4 % reflectance, the range textile SCI-SCE differences span (Berns 2019).
    cavity_fraction_range: f, the area fraction of pile and weave interstices: 0.05 (a tight
      plain weave) to 0.35 (a pile or a loose knit).
    cavity_self_view: a of Eq. S1, 0.5: a V-groove of half-opening 30° (a = 1 - sin 30°).
    texture_contrast: c of Eq. S4, 0.5: the cavity fraction of one weave cell differs from the
      mean by about half of it (yarn spacing and shadowing vary along a fabric).
    cell_pixels: pixels per weave cell, 16: a 0.4 mm repeat at ~0.1 mm per pixel (a 100 mm holder
      over ~1000 px).
    """

    k1_range: tuple[float, float] = (0.045, 0.048)
    gloss_range: tuple[float, float] = (0.45, 0.55)
    cavity_fraction_range: tuple[float, float] = (0.15, 0.25)
    cavity_self_view: float = 0.5
    texture_contrast: float = 0.5
    cell_pixels: float = 16.0


SURFACE = SurfaceFinish()


@dataclasses.dataclass(frozen=True)
class ReferenceNoise:
    """The reference spectrophotometer's noise, in reflectance (0..1): 0.1-0.3 % in all, as the
    repeatability of a d/8 instrument on textiles is quoted (ASTM E2214 sets out how it is
    specified; Berns 2019 on instrument precision), most of it smooth across the spectrum.

    per_wavelength: 0.0005, independent at each of the 31 wavelengths: the diode array's own
      short-term noise (a benchtop instrument repeats to ~0.05 % on a white tile).
    relative_per_target: 0.002, and offset_per_target: 0.001: a gain and an offset common to a
      target's spectrum, from re-presenting it (pile direction, pressure, the area under the
      aperture) and the instrument's drift between targets.
    """

    per_wavelength: float = 0.0005
    relative_per_target: float = 0.002
    offset_per_target: float = 0.001


REFERENCE_NOISE = ReferenceNoise()

#: Per kind: does the reference include the specular component (SCI, d/8), does the camera see
#: gloss and texture, where is the brightener ("all", "pale", None).
_KIND_SETTINGS = {
    "shade_card": {"sci": False, "surface": False, "brightener": None},
    "fluorescent": {"sci": False, "surface": False, "brightener": "all"},
    "gloss_texture": {"sci": True, "surface": True, "brightener": None},
    "mixed_real": {"sci": True, "surface": True, "brightener": "pale"},
}


# --- recipes ------------------------------------------------------------------------------------


def _stratified(m: int, rng: np.random.Generator) -> np.ndarray:
    """(m,) in [0, 1), one in each of m equal strata, in random order: a shade card's even steps."""
    return (rng.permutation(m) + rng.random(m)) / max(m, 1)


def shade_card_recipes(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 13) recipes (% owf, in `SHADE_CARD_DYES` order), laid out as a shade card is.

    3 % whites (no dye), 15 % greys and near-neutrals (the black at a depth, with a tint of one
    ring dye at up to a fifth of it in 60 % of them), the rest chromatic: a hue position stratified
    around the ring (two neighbouring dyes in proportion, one alone within 15 % of a ring dye)
    and, independently stratified, a depth log-uniform over `SHADE_CARD_DEPTH_RANGE`; 35 % of
    them dulled by a third dye (the black or the ring's opposite dye) at 5-40 % of the depth.
    So every recipe uses 0 to 3 dyes, and hues, depths and chroma cover the card evenly.
    """
    ring = len(SHADE_CARD_RING)
    black = ring
    recipes = np.zeros((n, len(SHADE_CARD_DYES)))
    n_white = round(0.03 * n)
    n_grey = round(0.15 * n)
    n_hue = n - n_white - n_grey
    log_low, log_high = np.log(SHADE_CARD_DEPTH_RANGE)

    hue = _stratified(n_hue, rng) * ring
    depth = np.exp(log_low + _stratified(n_hue, rng) * (log_high - log_low))
    first = np.floor(hue).astype(int) % ring
    second = (first + 1) % ring
    share = hue - np.floor(hue)
    share = np.where(share < 0.15, 0.0, np.where(share > 0.85, 1.0, share))
    dulled = rng.random(n_hue) < 0.35
    dulling = np.where(dulled, rng.uniform(0.05, 0.4, n_hue), 0.0)
    dullant = np.where(rng.random(n_hue) < 0.5, black, (first + ring // 2) % ring)
    rows = np.arange(n_hue)
    np.add.at(recipes, (rows, first), (1.0 - dulling) * (1.0 - share) * depth)
    np.add.at(recipes, (rows, second), (1.0 - dulling) * share * depth)
    np.add.at(recipes, (rows, dullant), dulling * depth)

    grey_rows = n_hue + np.arange(n_grey)
    grey_depth = np.exp(log_low + _stratified(n_grey, rng) * (log_high - log_low))
    recipes[grey_rows, black] = grey_depth
    tinted = rng.random(n_grey) < 0.6
    tint = rng.integers(0, ring, n_grey)
    np.add.at(recipes, (grey_rows, tint), np.where(tinted, rng.uniform(0.0, 0.2, n_grey), 0.0) * grey_depth)
    return recipes[rng.permutation(n)]


# --- fluorescence, F1-F5 ------------------------------------------------------------------------


def _flux_terms(ks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(σ, R_∞) of Eq. F1 for K/S values a (any shape), in units of S."""
    ks = np.asarray(ks, np.float64)
    return np.sqrt(ks * (ks + 2.0)), reflectance_from_ks(ks)


def escape_fraction(ks_emission: np.ndarray, decay_excitation: np.ndarray) -> np.ndarray:
    """η of Eq. F4: the fraction of light emitted in an opaque Kubelka-Munk layer with depth
    profile exp(-σ_μ z) that leaves it upward (before the surface, F5 adds that).

    Args:
      ks_emission: K/S at the emission wavelength (...), in units of S.
      decay_excitation: σ_μ > 0 of the source's depth profile (...), in units of S; broadcast.

    Returns:
      η in [0, 1] (...): 1 where nothing absorbs at λ, falling to 0 as K/S at λ grows.
    """
    sigma, reflectance = _flux_terms(ks_emission)
    return (1.0 + reflectance) * decay_excitation / (2.0 * (sigma + decay_excitation))


def luminescent_radiance_factor(
    ks_excitation: np.ndarray,
    brightener_ks_excitation: np.ndarray,
    ks_emission: np.ndarray,
    photon_irradiance_excitation: np.ndarray,
    photon_irradiance_emission: np.ndarray,
    emission: np.ndarray,
    *,
    quantum_yield: float,
    k1,
    k2: float,
    step_nm: float = 2.0,
) -> np.ndarray:
    """β_L (n, L) of Eq. F5, the radiance factor the brightener's fluorescence adds.

    Args:
      ks_excitation: (n, X) the layer's total K/S at the excitation wavelengths (brightener
        included); brightener_ks_excitation: (n, X) the brightener's part of it.
      ks_emission: (n, L) the layer's total K/S at the emission wavelengths.
      photon_irradiance_excitation: (X,), photon_irradiance_emission: (L,): the illuminant in
        photons per nm (energy times λ), in one unit (β_L is a ratio).
      emission: (L,) f, photons per nm, sum(f) * 2 nm = 1 (`Brightener.emission`).
      quantum_yield: Φ; k1: surface reflection, a float or (n,); k2: internal surface reflection.
      step_nm: the excitation grid's spacing.

    Returns:
      (n, L) β_L >= 0 (0 where the brightener is absent).
    """
    k1 = np.asarray(k1, np.float64).reshape(-1, 1) if np.ndim(k1) else float(k1)
    sigma_mu, reflectance_mu = _flux_terms(ks_excitation)  # (n, X)
    entering = (1.0 - k1) * photon_irradiance_excitation / (1.0 - k2 * reflectance_mu)  # F2
    safe_sigma = np.where(sigma_mu > 0.0, sigma_mu, 1.0)  # no brightener absorbs where σ is 0
    absorbed = quantum_yield * brightener_ks_excitation * (1.0 + reflectance_mu) * entering / safe_sigma  # F3, integrated over z
    eta = escape_fraction(ks_emission[:, :, None], safe_sigma[:, None, :])  # (n, L, X)
    emitted = step_nm * np.einsum("nlx,nx->nl", eta, absorbed)
    _, reflectance_lambda = _flux_terms(ks_emission)
    leaving = (1.0 - k2) / (1.0 - k2 * reflectance_lambda)
    return leaving * emitted * emission / photon_irradiance_emission


def d65_photon_irradiance(wavelengths_nm: np.ndarray) -> np.ndarray:
    """CIE D65 (colour-science's `SDS_ILLUMINANTS['D65']`, 300-780 nm) in photons per nm at
    `wavelengths_nm` (its relative power times λ, linearly interpolated from 5 nm)."""
    d65 = colour.SDS_ILLUMINANTS["D65"]
    wavelengths_nm = np.asarray(wavelengths_nm, np.float64)
    return np.interp(wavelengths_nm, d65.wavelengths, d65.values) * wavelengths_nm


def sphere_photon_irradiance(wavelengths_nm: np.ndarray, instrument: InstrumentModel | None = None) -> np.ndarray:
    """Relative photon irradiance on the sphere's holder at `wavelengths_nm` (300-720 nm).

    The lamp (`InstrumentModel.lamp_spectrum`, on 380-720 nm) times the sphere's gain
    ρ_w / (1 - α_ww ρ_w) (simulate's Eqs. 6-9, the holder's share of k, ~1 % of the wall's, left
    out), times λ for photons. Below 380 nm the lamp is its continuum, Planck's law at
    `lamp_colour_temperature_k` matched at 380 nm (xenon's lines lie at 450-500 nm), and the wall
    keeps its 380 nm value (the simulator's wall is flat below 400 nm). The sphere raises the red
    (ρ_w 0.99) more than the violet (0.95) by a factor ~2.5, so its light excites a brightener less,
    relative to the emission band, than D65 does.
    """
    instrument = instrument or InstrumentModel()
    wavelengths_nm = np.asarray(wavelengths_nm, np.float64)

    def planck(nm):
        metres = nm * 1e-9
        return 1.0 / (metres**5 * np.expm1(1.438777e-2 / (metres * instrument.lamp_colour_temperature_k)))

    lamp_fine = instrument.lamp_spectrum()
    below = planck(wavelengths_nm) * lamp_fine[0] / planck(FINE_WAVELENGTHS_NM[0])
    lamp = np.where(wavelengths_nm >= FINE_WAVELENGTHS_NM[0], np.interp(wavelengths_nm, FINE_WAVELENGTHS_NM, lamp_fine), below)
    wall = np.interp(wavelengths_nm, FINE_WAVELENGTHS_NM, instrument.wall_reflectance())
    alpha_ww = instrument.port_fractions()[0]
    return lamp * wall / (1.0 - alpha_ww * wall) * wavelengths_nm


# --- surface and texture, S1-S4 -----------------------------------------------------------------


def cavity_reflectance(reflectance: np.ndarray, self_view: float) -> np.ndarray:
    """R_cav of Eq. S1: R (1 - a) / (1 - a R), a cavity of walls of reflectance R, any shape."""
    reflectance = np.asarray(reflectance, np.float64)
    return reflectance * (1.0 - self_view) / (1.0 - self_view * reflectance)


def surface_view(body, k1, gloss, cavity_fraction, self_view: float, *, specular_included: bool) -> np.ndarray:
    """The reflectance an instrument measures of a textured, glossy target, Eqs. S2-S3.

    Args:
      body: (n, L) the body's radiance factor outside the surface, without k1 (Saunderson SCE,
        plus β_L where it fluoresces).
      k1, gloss (g), cavity_fraction (f): (n,) or floats. self_view: a of Eq. S1.
      specular_included: True for the reference's SCI (S2), False for the camera's d/0 (S3).

    Returns:
      (n, L). g = 1, f = 0 gives `body` without k1 (SCE, the camera of `kubelka_munk`).
    """
    k1, gloss, cavity_fraction = (np.asarray(x, np.float64).reshape(-1, 1) if np.ndim(x) else float(x)
                                  for x in (k1, gloss, cavity_fraction))
    flat = body + (k1 if specular_included else (1.0 - gloss) * k1)
    return (1.0 - cavity_fraction) * flat + cavity_fraction * cavity_reflectance(body + k1, self_view)


# --- families -----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class TargetSet:
    """One draw of a family kind before the instruments' noise, on `FINE_WAVELENGTHS_NM` (L = 171).

    recipes: (n, 13) % owf in `SHADE_CARD_DYES` order; brightener: (n,) % owf.
    k1, gloss, cavity_fraction: (n,) Eqs. S2-S3 (k1 = `SHADE_CARD_K1`, g = 1, f = 0 where the
      kind has no surface effects: the camera and the SCE reference then see `body_camera`).
    body_camera, body_reference: (n, L) the body's radiance factor (Saunderson SCE, Eq. (4) of
      `kubelka_munk`) plus β_L (F5) under the sphere's light and under D65.
    specular_included: whether the reference is SCI (S2) or, as the camera, SCE.
    cavity_self_view: a of Eq. S1.
    """

    kind: str
    recipes: np.ndarray
    brightener: np.ndarray
    k1: np.ndarray
    gloss: np.ndarray
    cavity_fraction: np.ndarray
    body_camera: np.ndarray
    body_reference: np.ndarray
    specular_included: bool
    cavity_self_view: float

    def camera(self, cavity_fraction=None) -> np.ndarray:
        """(n, L) what the camera sees, Eq. S3; `cavity_fraction` (n,): the region's f (S4)."""
        f = self.cavity_fraction if cavity_fraction is None else cavity_fraction
        return surface_view(self.body_camera, self.k1, self.gloss, f, self.cavity_self_view, specular_included=False)

    def reference(self) -> np.ndarray:
        """(n, L) what the reference spectrophotometer reports, noise-free: Eq. S2 or S3."""
        return surface_view(self.body_reference, self.k1, self.gloss, self.cavity_fraction, self.cavity_self_view,
                            specular_included=self.specular_included)


def _layer_ks(recipes: np.ndarray, brightener: np.ndarray, wavelengths_nm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(total K/S, the brightener's part), each (n, L), of shade-card recipes (n, 13) and
    brightener concentrations (n,) at `wavelengths_nm`, Eq. (3) of `kubelka_munk`."""
    dyes = np.stack([dye.unit_ks(wavelengths_nm) for dye in SHADE_CARD_DYES])
    own = np.asarray(brightener, np.float64)[:, None] * BRIGHTENER.unit_ks(wavelengths_nm)
    return SHADE_CARD_SUBSTRATE.ks(wavelengths_nm) + np.asarray(recipes, np.float64) @ dyes + own, own


def brightener_fluorescence(recipes, brightener, k1, photon_irradiance) -> np.ndarray:
    """β_L (n, L) on `FINE_WAVELENGTHS_NM` of shade-card recipes, Eq. F5.

    Args:
      recipes: (n, 13) % owf (`SHADE_CARD_DYES`); brightener: (n,) `BRIGHTENER` in % owf.
      k1: surface reflection, float or (n,).
      photon_irradiance: the illuminant, a function of wavelengths (nm) -> photons per nm
        (`d65_photon_irradiance`, `sphere_photon_irradiance`).
    """
    ks_excitation, brightener_ks = _layer_ks(recipes, brightener, EXCITATION_WAVELENGTHS_NM)
    ks_emission, _ = _layer_ks(recipes, brightener, FINE_WAVELENGTHS_NM)
    return luminescent_radiance_factor(
        ks_excitation, brightener_ks, ks_emission, photon_irradiance(EXCITATION_WAVELENGTHS_NM),
        photon_irradiance(FINE_WAVELENGTHS_NM), BRIGHTENER.emission(FINE_WAVELENGTHS_NM),
        quantum_yield=BRIGHTENER.quantum_yield, k1=k1, k2=SHADE_CARD_K2)


def _streams(kind: str, seed: int) -> list[np.random.Generator]:
    """Independent generators for (recipes and surfaces, camera noise, texture and reference
    noise) of one kind, all fixed by `seed`."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence([seed, FAMILY_KINDS.index(kind)]).spawn(3)]


def sample_targets(kind: str, n: int, seed: int = 0, *, instrument: InstrumentModel | None = None,
                   surface: SurfaceFinish = SURFACE) -> TargetSet:
    """n targets of a family kind other than "km_mixing" (module docstring), noise-free.

    Args:
      kind: one of `FAMILY_KINDS[1:]`. n: targets, >= 1. seed: the draw (same seed, same targets).
      instrument: the camera whose light excites the brightener (default InstrumentModel()).
      surface: the ranges of the targets' surfaces, for the kinds with gloss and texture.
    """
    kind = _check_kind(kind, FAMILY_KINDS[1:])
    n = _check_count(n, "n")
    settings = _KIND_SETTINGS[kind]
    rng = _streams(kind, seed)[0]
    recipes = shade_card_recipes(n, rng)
    depth = recipes.sum(axis=1)
    brightener = {"all": np.full(n, BRIGHTENER_CONCENTRATION),
                  "pale": np.where(depth <= BRIGHTENER_MAX_DEPTH, BRIGHTENER_CONCENTRATION, 0.0),
                  None: np.zeros(n)}[settings["brightener"]]
    if settings["surface"]:
        k1, gloss, cavity = (rng.uniform(*bounds, n) for bounds in
                             (surface.k1_range, surface.gloss_range, surface.cavity_fraction_range))
    else:
        k1, gloss, cavity = np.full(n, SHADE_CARD_K1), np.ones(n), np.zeros(n)

    body = saunderson(reflectance_from_ks(_layer_ks(recipes, brightener, FINE_WAVELENGTHS_NM)[0]), k1[:, None],
                      SHADE_CARD_K2, specular_included=False)
    body_camera, body_reference = body, body
    if np.any(brightener > 0.0):
        body_camera = body + brightener_fluorescence(recipes, brightener, k1, lambda wl: sphere_photon_irradiance(wl, instrument))
        body_reference = body + brightener_fluorescence(recipes, brightener, k1, d65_photon_irradiance)
    return TargetSet(kind, recipes, brightener, k1, gloss, cavity, body_camera, body_reference, settings["sci"],
                     surface.cavity_self_view)


def _check_kind(kind, kinds=FAMILY_KINDS) -> str:
    if not isinstance(kind, str) or kind not in kinds:
        raise ValueError(f"kind: expected one of {kinds}, got {kind!r}")
    return kind


def _check_count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
    return int(value)


def target_family(
    kind: str,
    n: int = 200,
    seed: int = 0,
    *,
    patch_pixels: int = 1225,
    noise: bool = True,
    family: str = KM_DEFAULT_FAMILY,
    instrument: InstrumentModel | None = None,
    surface: SurfaceFinish = SURFACE,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera responses and reference reflectances of n targets of one family kind.

    Targets and samples of one family are two calls with different seeds: the material (dyes,
    substrate, brightener, surface ranges) is the kind's, the recipes, surfaces and noise the
    seed's.

    Args:
      kind: one of `FAMILY_KINDS`.
      n: targets, an integer >= 1.
      seed: the draw.
      patch_pixels: responses are region means over this many pixels (1225 = 35 x 35, the
        paper's regions): the instrument's frame counts times this (`kubelka_munk.
        km_family_responses`), and the texture noise of Eq. S4 over these pixels.
      noise: False: exact responses (`render_targets`), no texture or reference noise.
      family: for "km_mixing", which of `kubelka_munk.MATERIAL_FAMILIES` (default
        `KM_DEFAULT_FAMILY`); the draw is `km_family_responses(seed, n, noise, patch_pixels)`'s.
      instrument: the camera (default InstrumentModel()), before its frames are scaled.
      surface: the ranges of the targets' surfaces and the texture noise (Eqs. S1-S4).

    Returns:
      responses (n, 16) float64, flat-fielded region means; reflectances (n, 31) float64 at
      `grid.WAVELENGTHS_NM`, the reference's (with `REFERENCE_NOISE` if noise, except for
      "km_mixing", whose reference is exact as in `kubelka_munk`).

    Raises:
      ValueError: one line, for an unknown kind or family, n or patch_pixels not an integer >= 1.
    """
    kind = _check_kind(kind)
    n = _check_count(n, "n")
    patch_pixels = _check_count(patch_pixels, "patch_pixels")
    if kind == "km_mixing":
        if family not in MATERIAL_FAMILIES:
            raise ValueError(f"family: expected one of {tuple(MATERIAL_FAMILIES)}, got {family!r}")
        extra = {} if instrument is None else {"instrument": instrument}
        responses, reflectances, _ = km_family_responses(seed, n, noise, patch_pixels, **extra)[family]
        return np.asarray(responses, np.float64), np.asarray(reflectances, np.float64)
    instrument = instrument or InstrumentModel()
    targets = sample_targets(kind, n, seed, instrument=instrument, surface=surface)
    _, camera_rng, other_rng = _streams(kind, seed)
    region_cavity = targets.cavity_fraction
    if noise and _KIND_SETTINGS[kind]["surface"]:  # Eq. S4
        spread = surface.texture_contrast * np.sqrt(surface.cell_pixels / patch_pixels)
        region_cavity = np.clip(region_cavity * (1.0 + spread * other_rng.standard_normal(n)), 0.0, 1.0)
    region_mean = dataclasses.replace(
        instrument,
        frames_averaged_sample=instrument.frames_averaged_sample * patch_pixels,
        frames_averaged_white=instrument.frames_averaged_white * patch_pixels,
    )
    responses = render_targets(targets.camera(region_cavity), seed=int(camera_rng.integers(2**31)), noise=noise,
                               instrument=region_mean)
    reflectances = on_reflectance_grid(targets.reference())
    if noise:
        gain = 1.0 + REFERENCE_NOISE.relative_per_target * other_rng.standard_normal((n, 1))
        offset = REFERENCE_NOISE.offset_per_target * other_rng.standard_normal((n, 1))
        reflectances = reflectances * gain + offset + REFERENCE_NOISE.per_wavelength * other_rng.standard_normal(reflectances.shape)
    return np.asarray(responses, np.float64), np.asarray(reflectances, np.float64)


def family_kinds_responses(seed: int = 0, n: int = 200, *, patch_pixels: int = 1225, noise: bool = True,
                           **kwargs) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{kind: (responses (n, 16), reflectances (n, 31))} for every kind of `FAMILY_KINDS`, each
    `target_family(kind, n, seed, patch_pixels=..., noise=..., **kwargs)`."""
    return {kind: target_family(kind, n, seed, patch_pixels=patch_pixels, noise=noise, **kwargs) for kind in FAMILY_KINDS}


__all__ = [
    "BRIGHTENER",
    "BRIGHTENER_CONCENTRATION",
    "BRIGHTENER_MAX_DEPTH",
    "EXCITATION_WAVELENGTHS_NM",
    "FAMILY_KINDS",
    "KM_DEFAULT_FAMILY",
    "REFERENCE_NOISE",
    "SHADE_CARD_BLACK",
    "SHADE_CARD_DEPTH_RANGE",
    "SHADE_CARD_DYES",
    "SHADE_CARD_K1",
    "SHADE_CARD_K2",
    "SHADE_CARD_RING",
    "SHADE_CARD_SUBSTRATE",
    "SURFACE",
    "Brightener",
    "ReferenceNoise",
    "SurfaceFinish",
    "TargetSet",
    "brightener_fluorescence",
    "cavity_reflectance",
    "d65_photon_irradiance",
    "escape_fraction",
    "family_kinds_responses",
    "luminescent_radiance_factor",
    "sample_targets",
    "shade_card_recipes",
    "sphere_photon_irradiance",
    "surface_view",
    "target_family",
]
