"""Dyed-material families made as real ones are: Kubelka-Munk mixtures of a few dyes on a substrate.

The simulated families of `spherejax.simulated_targets` are colour-science's measured spectra,
which an estimator sees as points in reflectance space with no structure tying them together. Dyed
materials have one: K/S, not reflectance, is linear in the dye concentrations. A family here is a
substrate and a range of D = 6 dyes of one class, as a dyehouse's or a mill's dye range is (a real
set of a couple of hundred dyed samples of one material is made from such a range, not from three
dyes); each recipe uses 1 to `max_dyes_per_recipe` = 3 of them. Each choice of three dyes spans a
curved 3-dimensional piece of reflectance space, so a family lies on a union of such pieces (20 of
them, meeting along their 2- and 1-dye edges) in the image of the 6-dimensional dye space: curved,
as no linear map from camera responses can follow, while the responses themselves stay linear in
reflectance. With three dyes (a trichromat, recipes of 1 to 3 of them) the manifold is so
low-dimensional that a 16-band affine map follows it to 1e-4-5e-4 (noiseless, held out) and a
nonlinear estimator has little left to learn; with six, the affine map misses by ~5e-4-1e-3 and a
nonlinear regression on its residuals removes a third to two thirds of that
(tests/test_kubelka_munk.py measures it). This module makes such families for validating
reflectance estimators; `km_family_responses` renders them through the simulated camera as region
means (see there: a target's response is the mean over a patch of pixels, so its noise is far
below a pixel's).

Model (single-constant Kubelka-Munk theory for opaque layers, with Saunderson's correction):

  (1) K/S = (1 - R_inf)^2 / (2 R_inf)                               Kubelka & Munk (1931)
  (2) R_inf = 1 + K/S - sqrt((K/S)^2 + 2 K/S)                       the inverse of (1)
          = 1 / (1 + K/S + sqrt((K/S)^2 + 2 K/S))                   the same, free of cancellation
  (3) K/S(λ) = (K/S)_substrate(λ) + sum_i c_i (k/s)_i(λ)            single-constant additivity
                                                                    (Allen 1980; Berns 2019)
  (4) R_m = k1' + (1 - k1)(1 - k2) R_inf / (1 - k2 R_inf)           Saunderson (1942)
  (5) R_inf = (R_m - k1') / ((1 - k1)(1 - k2) + k2 (R_m - k1'))     the exact inverse of (4)

R_inf is the internal reflectance of a layer thick enough that the backing does not show; K and S
the absorption and scattering coefficients; c_i >= 0 the concentration of dye i (% on weight of
fibre, owf) and (k/s)_i its unit K/S (per 1 % owf); the substrate's K/S is that of the undyed
material. Equation (3) is the single-constant form: the dyes absorb, the substrate alone scatters
(S does not depend on c), which holds for dyes on textiles and paper (Allen 1980).

Saunderson's correction (4) relates R_inf, inside the material, to the reflectance R_m measured
outside it: k1 is the fraction of the incident light reflected at the surface before entering
(Fresnel, normal incidence: ((n - 1)/(n + 1))^2 = 0.04 for n = 1.5), k2 the fraction of the
diffuse light inside reflected back at the surface (0.4-0.6 for n ≈ 1.5). By reciprocity the
sphere's d:0° geometry (docs/instrument.md: diffuse illumination, 0° viewing) behaves as 0°:d,
so k1 is the normal-incidence value. k1' = k1 when the measurement includes the specular
component (SCI) and k1' = 0 when it excludes it (SCE). spherejax's instrument views the sample
along its normal, and the specular direction of the normal points back into the detector port,
which reflects no light: its measurement excludes the specular component, so SCE is the default
here (`SPECULAR_INCLUDED = False`); every function that applies (4) takes `specular_included`.

Dye absorption. Each dye's unit K/S is a sum of absorption bands, Gaussian in wavenumber (the
shape of an electronic absorption band broadened by vibrations, which gives the band a longer tail
to the red in wavelength), given by peak wavelength, full width at half maximum in nm at the peak,
and strength (unit K/S at the peak):
  (6) (k/s)(λ) = sum_j a_j exp(-4 ln2 ((1/λ - 1/λ_j) λ_j^2 / w_j)^2)
The bands are synthesised, not measured: their positions follow the absorption maxima of the dye
classes named (yellow 400-460 nm, orange 470-500 nm, red 480-520 nm, rubine, magenta and violet
520-560 nm, navy 575-620 nm, blue and cyan 580-670 nm, the anthraquinone blues' doublet, the
copper phthalocyanines' Q-band pair and their B band in the near UV), with secondary bands
(vibronic shoulders, unwanted blue absorption) where those classes have them, and strengths of
about 2-3.5 unit K/S at the main peak (per 1 % owf), so that a family's range spans pale tints
(K/S ≈ 0.02-0.07 at the peak) to deep shades (K/S ≈ 5-15). Each family has six dyes of its class:
a yellow, an orange and a red; a rubine, magenta or violet (cotton: a third blue instead); and two
of navy, bright blue and turquoise, each family's at its own positions and with its own band
shapes (`MATERIAL_FAMILIES`); no dye name is shared between families.
Substrates absorb a little, most in the blue (yellowness):
  (7) (K/S)_substrate(λ) = b + a exp(-(λ - 400 nm) / τ)
with b, a and τ set so that the undyed material measures as its kind does (bleached cotton ~0.80
at 400 nm and ~0.88 at 700 nm, scoured wool ~0.45 rising to ~0.76, polyester ~0.79 to ~0.84,
bleached paper ~0.83 to ~0.91).

Everything is on the simulator's fine grid `simulate.FINE_WAVELENGTHS_NM` (380..720 nm step 2,
L = 171), so that `simulated_targets.render_targets` integrates the spectra through the camera;
`on_reflectance_grid` takes the 31 samples at `grid.WAVELENGTHS_NM` (the fine grid contains them:
the model is evaluated pointwise, so these are exact, not interpolated). Targets and samples of
one family are two draws of `sample_family` (or `km_family_responses`) with different seeds.

References:
  P. Kubelka, F. Munk, "Ein Beitrag zur Optik der Farbanstriche", Z. Tech. Phys. 12, 593-601 (1931).
  J. L. Saunderson, "Calculation of the color of pigmented plastics", J. Opt. Soc. Am. 32, 727-736 (1942).
  E. Allen, "Colorant Formulation and Shading", in F. Grum, C. J. Bartleson (eds.), Optical
    Radiation Measurements, Vol. 2: Color Measurement, Academic Press (1980).
  R. S. Berns, "Billmeyer and Saltzman's Principles of Color Technology", 4th ed., Wiley (2019),
    the chapter on colorant mixing (Kubelka-Munk theory, Saunderson's correction).
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping

import numpy as np

from .grid import WAVELENGTHS_NM
from .simulated_instrument import FINE_WAVELENGTHS_NM, InstrumentModel
from .simulated_targets import render_targets

#: spherejax's d:0° sphere excludes the specular component (module docstring): Eq. (4) with k1' = 0.
SPECULAR_INCLUDED = False

#: Surface reflection k1 at normal incidence for refractive index n = 1.5 (Fresnel), Eq. (4).
K1_N_1_5 = 0.04

#: Indices of `grid.WAVELENGTHS_NM` (400..700 nm step 10) in `FINE_WAVELENGTHS_NM` (380..720 step 2).
_REFLECTANCE_GRID_INDEX = np.searchsorted(FINE_WAVELENGTHS_NM, WAVELENGTHS_NM.astype(float))
if not np.array_equal(FINE_WAVELENGTHS_NM[_REFLECTANCE_GRID_INDEX], WAVELENGTHS_NM):  # exact samples, never interpolated
    raise ImportError("simulate.FINE_WAVELENGTHS_NM must contain every wavelength of grid.WAVELENGTHS_NM")


# --- the equations ------------------------------------------------------------------------------


def ks_from_reflectance(reflectance_inf: np.ndarray) -> np.ndarray:
    """K/S of an opaque layer from its internal reflectance R_inf, Eq. (1): (1 - R)^2 / (2 R).

    Args:
      reflectance_inf: R_inf in (0, 1], any shape, dimensionless.

    Returns:
      K/S >= 0, the same shape, dimensionless (0 for R_inf = 1, +inf for R_inf = 0).
    """
    reflectance_inf = np.asarray(reflectance_inf, np.float64)
    return (1.0 - reflectance_inf) ** 2 / (2.0 * reflectance_inf)


def reflectance_from_ks(ks: np.ndarray) -> np.ndarray:
    """Internal reflectance R_inf of an opaque layer from its K/S, Eq. (2).

    Evaluated as 1 / (1 + K/S + sqrt((K/S)^2 + 2 K/S)), which equals 1 + K/S - sqrt((K/S)^2 + 2 K/S)
    but keeps full relative precision for deep shades (large K/S), where the difference of the
    textbook form cancels.

    Args:
      ks: K/S >= 0, any shape, dimensionless.

    Returns:
      R_inf in (0, 1], the same shape, decreasing in K/S (1 at K/S = 0).
    """
    ks = np.asarray(ks, np.float64)
    return 1.0 / (1.0 + ks + np.sqrt(ks * ks + 2.0 * ks))


def layer_over_background(reflectance_inf: np.ndarray, scattering_power, reflectance_background: np.ndarray) -> np.ndarray:
    """Reflectance of a layer of finite thickness over a background, Kubelka (1948) Eq. (7):

      R = (1 - R_g (a - b coth(b S X))) / (a - R_g + b coth(b S X)),
      a = (1 / R_inf + R_inf) / 2,  b = (1 / R_inf - R_inf) / 2,

    with R_inf the layer's reflectance when thick enough that the background does not show
    (what a spectrophotometer reads of a specimen folded to opacity, AATCC EP6 / ISO 105-J01),
    S X its scattering power (scattering coefficient times thickness, dimensionless) and R_g the
    background's reflectance. R -> R_inf as S X -> inf; R -> R_g as S X -> 0. b coth(b S X) is
    evaluated as b / tanh(b S X), which tends to 1 / (S X) for a non-absorbing layer (b -> 0).

    Args:
      reflectance_inf: R_inf in (0, 1], any shape (clipped to [1e-4, 1 - 1e-9]).
      scattering_power: S X > 0, broadcastable (a number for a layer whose S does not depend on
        wavelength: fibres far larger than the wavelength scatter alike across the visible).
      reflectance_background: R_g in [0, 1], broadcastable.

    Returns:
      R, the broadcast shape, between R_inf and R_g.
    """
    r_inf = np.clip(np.asarray(reflectance_inf, np.float64), 1e-4, 1.0 - 1e-9)
    sx = np.asarray(scattering_power, np.float64)
    r_g = np.asarray(reflectance_background, np.float64)
    a = 0.5 * (1.0 / r_inf + r_inf)
    b = 0.5 * (1.0 / r_inf - r_inf)
    b_coth = b / np.tanh(b * sx)
    return (1.0 - r_g * (a - b_coth)) / (a - r_g + b_coth)


def saunderson(
    reflectance_inf: np.ndarray, k1: float, k2: float, *, specular_included: bool = SPECULAR_INCLUDED
) -> np.ndarray:
    """Measured reflectance R_m from the internal reflectance R_inf, Saunderson's correction, Eq. (4).

    Args:
      reflectance_inf: R_inf in [0, 1], any shape.
      k1: surface reflection of the incident light (0.04 for n = 1.5 at normal incidence).
      k2: internal reflection of diffuse light at the surface (0.4-0.6).
      specular_included: True adds the surface reflection k1 to R_m (SCI); False (SCE, the
        default: spherejax's d:0° sphere) leaves it out.

    Returns:
      R_m, the same shape: in [0, 1 - k1] (SCE) or [k1, 1] (SCI). k1 = k2 = 0 is the identity.
    """
    reflectance_inf = np.asarray(reflectance_inf, np.float64)
    surface = k1 if specular_included else 0.0
    return surface + (1.0 - k1) * (1.0 - k2) * reflectance_inf / (1.0 - k2 * reflectance_inf)


def inverse_saunderson(
    reflectance_measured: np.ndarray, k1: float, k2: float, *, specular_included: bool = SPECULAR_INCLUDED
) -> np.ndarray:
    """Internal reflectance R_inf from the measured R_m, the exact inverse of Eq. (4), Eq. (5).

    Args and geometry as `saunderson`; reflectance_measured: R_m, any shape.

    Returns:
      R_inf, the same shape.
    """
    reflectance_measured = np.asarray(reflectance_measured, np.float64)
    body = reflectance_measured - (k1 if specular_included else 0.0)
    return body / ((1.0 - k1) * (1.0 - k2) + k2 * body)


def mixture_ks(substrate_ks: np.ndarray, dye_ks: np.ndarray, concentrations: np.ndarray) -> np.ndarray:
    """K/S of dyes on a substrate, single-constant Kubelka-Munk, Eq. (3).

    Args:
      substrate_ks: (L,) K/S of the undyed substrate.
      dye_ks: (D, L) unit K/S of each dye (per unit concentration).
      concentrations: (..., D) concentrations c_i >= 0 (the unit of `dye_ks`, e.g. % owf).

    Returns:
      (..., L) K/S of the dyed material.
    """
    concentrations = np.asarray(concentrations, np.float64)
    return np.asarray(substrate_ks, np.float64) + concentrations @ np.asarray(dye_ks, np.float64)


def absorption_bands_ks(wavelengths_nm: np.ndarray, bands: tuple[AbsorptionBand, ...]) -> np.ndarray:
    """Sum of absorption bands Gaussian in wavenumber, Eq. (6).

    Args:
      wavelengths_nm: (L,) in nm.
      bands: each band's peak (nm), full width at half maximum at the peak (nm) and strength.

    Returns:
      (L,) K/S (per unit concentration for a dye's unit bands).
    """
    wavelengths_nm = np.asarray(wavelengths_nm, np.float64)
    total = np.zeros_like(wavelengths_nm)
    for band in bands:
        # A width of w nm at λ_j spans w / λ_j^2 in wavenumber (first order): d(1/λ) = -dλ / λ^2.
        offset = (1.0 / wavelengths_nm - 1.0 / band.peak_nm) * band.peak_nm**2 / band.fwhm_nm
        total += band.strength * np.exp(-4.0 * np.log(2.0) * offset**2)
    return total


def on_reflectance_grid(fine: np.ndarray) -> np.ndarray:
    """(..., 31) samples at `grid.WAVELENGTHS_NM` of spectra (..., L) on `FINE_WAVELENGTHS_NM`."""
    fine = np.asarray(fine)
    if fine.shape[-1] != FINE_WAVELENGTHS_NM.size:
        raise ValueError(f"expected spectra on simulate.FINE_WAVELENGTHS_NM (..., {FINE_WAVELENGTHS_NM.size}), got {fine.shape}")
    return fine[..., _REFLECTANCE_GRID_INDEX]


# --- dyes, substrates, families -----------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class AbsorptionBand:
    """One absorption band of Eq. (6): peak wavelength (nm), FWHM (nm) and strength (K/S at the peak)."""

    peak_nm: float
    fwhm_nm: float
    strength: float


@dataclasses.dataclass(frozen=True)
class Dye:
    """A dye: its name (the dye class it is modelled on) and the bands of its unit K/S (per 1 unit)."""

    name: str
    bands: tuple[AbsorptionBand, ...]

    def unit_ks(self, wavelengths_nm: np.ndarray = FINE_WAVELENGTHS_NM) -> np.ndarray:
        """(L,) unit K/S at `wavelengths_nm`, Eq. (6)."""
        return absorption_bands_ks(wavelengths_nm, self.bands)


@dataclasses.dataclass(frozen=True)
class Substrate:
    """An undyed material whose K/S is Eq. (7): base + blue exp(-(λ - 400 nm) / blue_decay_nm)."""

    name: str
    base_ks: float
    blue_ks: float
    blue_decay_nm: float

    def ks(self, wavelengths_nm: np.ndarray = FINE_WAVELENGTHS_NM) -> np.ndarray:
        """(L,) K/S at `wavelengths_nm`, Eq. (7)."""
        wavelengths_nm = np.asarray(wavelengths_nm, np.float64)
        return self.base_ks + self.blue_ks * np.exp(-(wavelengths_nm - 400.0) / self.blue_decay_nm)


@dataclasses.dataclass(frozen=True, eq=False)
class MaterialFamily:
    """A family of dyed materials: one substrate, its dye set, its surface and its recipe range.

    name: the family's name (a key of `MATERIAL_FAMILIES`).
    substrate: the undyed material; dyes: its D dyes, its dye range (D = 6 in every shipped family).
    k1, k2: Saunderson's surface reflections, Eq. (4).
    concentration_range: (lowest, highest) concentration of a dye in a recipe, in `concentration_unit`.
    concentration_unit: the unit of the concentrations and of the dyes' unit K/S.
    max_dyes_per_recipe: the most dyes one recipe uses, 1..D (default 3, as shade recipes are
      mostly one to three dyes of the range): `sample_recipes` draws each recipe's dye count
      uniformly from 1..max_dyes_per_recipe and the dyes as a random subset of the D, so a family
      is a union of curved pieces of that dimension, one per subset (module docstring).
    substrate_ks: (L,) and dye_ks: (D, L), read-only, on `FINE_WAVELENGTHS_NM` (derived).
    """

    name: str
    substrate: Substrate
    dyes: tuple[Dye, ...]
    k1: float
    k2: float
    concentration_range: tuple[float, float]
    concentration_unit: str = "% owf"
    max_dyes_per_recipe: int = 3
    substrate_ks: np.ndarray = dataclasses.field(init=False, repr=False)
    dye_ks: np.ndarray = dataclasses.field(init=False, repr=False)

    def __post_init__(self):
        low, high = self.concentration_range
        if not 0.0 < low < high:
            raise ValueError(f"{self.name}: concentration_range must satisfy 0 < low < high, got {self.concentration_range}")
        if not (0.0 <= self.k1 < 1.0 and 0.0 <= self.k2 < 1.0):
            raise ValueError(f"{self.name}: k1 and k2 must lie in [0, 1), got {self.k1}, {self.k2}")
        max_dyes = self.max_dyes_per_recipe
        if isinstance(max_dyes, bool) or not isinstance(max_dyes, (int, np.integer)) or not 1 <= max_dyes <= len(self.dyes):
            raise ValueError(
                f"{self.name}: max_dyes_per_recipe must be an integer in 1..{len(self.dyes)} (the number of dyes), "
                f"got {self.max_dyes_per_recipe!r}"
            )
        substrate_ks = self.substrate.ks()
        dye_ks = np.stack([dye.unit_ks() for dye in self.dyes])
        substrate_ks.setflags(write=False)
        dye_ks.setflags(write=False)
        object.__setattr__(self, "substrate_ks", substrate_ks)
        object.__setattr__(self, "dye_ks", dye_ks)

    @property
    def dye_names(self) -> tuple[str, ...]:
        return tuple(dye.name for dye in self.dyes)

    def reflectance(self, concentrations: np.ndarray, *, specular_included: bool = SPECULAR_INCLUDED) -> np.ndarray:
        """Measured reflectance (..., L) on `FINE_WAVELENGTHS_NM` of recipes (..., D): Eqs. (3), (2), (4)."""
        internal = reflectance_from_ks(mixture_ks(self.substrate_ks, self.dye_ks, concentrations))
        return saunderson(internal, self.k1, self.k2, specular_included=specular_included)

    def ks_from_measured(self, reflectance_measured: np.ndarray, *, specular_included: bool = SPECULAR_INCLUDED) -> np.ndarray:
        """K/S (..., L) from measured reflectances (..., L): Eqs. (5), (1), as colorant formulation does."""
        internal = inverse_saunderson(reflectance_measured, self.k1, self.k2, specular_included=specular_included)
        return ks_from_reflectance(internal)


def _band(peak_nm: float, fwhm_nm: float, strength: float) -> AbsorptionBand:
    return AbsorptionBand(peak_nm, fwhm_nm, strength)


# Strengths are unit K/S (per 1 % owf) at the band peak: at the top of each family's range the
# main bands reach K/S ≈ 5-15 (R_m ≈ 0.01-0.05, a deep shade), at the bottom ≈ 0.02-0.07 (a pale
# tint). Six dyes per family, the three of a trichromat and three more of the same class.
_FAMILIES = (
    MaterialFamily(
        # Bifunctional reactive dyes on bleached cotton, which measures ~0.80 at 400 nm and ~0.88 at
        # 700 nm: the yellow / red / navy trichromat of exhaust dyeing, an azo orange, a bright
        # anthraquinone blue (592 nm with its red shoulder) and a copper phthalocyanine turquoise
        # (Q bands 626/668 nm, the shorter one the stronger as aggregated on the fibre; B band).
        name="cotton reactive",
        substrate=Substrate("bleached cotton", base_ks=0.0006, blue_ks=0.0024, blue_decay_nm=50.0),
        dyes=(
            Dye("reactive yellow", (_band(420, 90, 2.6), _band(360, 60, 1.0))),
            Dye("reactive orange", (_band(492, 85, 2.6), _band(390, 60, 0.5))),
            Dye("reactive red", (_band(505, 80, 3.0), _band(540, 40, 0.7), _band(390, 70, 0.3))),
            Dye("reactive navy", (_band(600, 120, 2.2), _band(560, 70, 0.9), _band(420, 80, 0.3))),
            Dye("reactive blue (anthraquinone)", (_band(592, 60, 2.4), _band(628, 50, 1.4))),
            Dye("reactive turquoise (Cu phthalocyanine)", (_band(626, 50, 2.4), _band(668, 40, 1.6), _band(350, 50, 1.2))),
        ),
        k1=K1_N_1_5,
        k2=0.6,
        concentration_range=(0.01, 5.0),
    ),
    MaterialFamily(
        # Levelling acid dyes on scoured wool, yellowish (~0.45 at 400 nm rising to ~0.75): a
        # pyrazolone yellow, an azo orange, an azo red with its vibronic shoulder, a magenta with
        # one, an anthraquinone blue with its 595/635 doublet and a broad navy (the blue-black
        # component of a navy or black mixture).
        name="wool acid",
        substrate=Substrate("scoured wool", base_ks=0.005, blue_ks=0.065, blue_decay_nm=40.0),
        dyes=(
            Dye("acid yellow", (_band(415, 70, 3.0), _band(370, 50, 0.6))),
            Dye("acid orange", (_band(485, 95, 3.0), _band(420, 60, 0.6))),
            Dye("acid red", (_band(500, 60, 2.8), _band(532, 40, 1.0))),
            Dye("acid magenta", (_band(548, 60, 3.4), _band(510, 45, 1.0))),
            Dye("acid blue (anthraquinone)", (_band(595, 55, 2.2), _band(635, 55, 2.0))),
            Dye("acid navy", (_band(610, 140, 2.4), _band(560, 80, 0.8))),
        ),
        k1=K1_N_1_5,
        k2=0.6,
        concentration_range=(0.01, 3.0),
    ),
    MaterialFamily(
        # Disperse dyes on polyester (n ≈ 1.64: k1 = ((n - 1)/(n + 1))^2 ≈ 0.059), white (~0.82):
        # a yellow, azo orange and red, an anthraquinone rubine (522/556 nm pair), an anthraquinone
        # blue (610/652 nm) and an azo navy (broad, ~600 nm, with a violet shoulder).
        name="polyester disperse",
        substrate=Substrate("polyester", base_ks=0.0012, blue_ks=0.0015, blue_decay_nm=30.0),
        dyes=(
            Dye("disperse yellow", (_band(450, 80, 3.2),)),
            Dye("disperse orange", (_band(482, 85, 2.8),)),
            Dye("disperse red", (_band(505, 90, 2.8), _band(390, 50, 0.3))),
            Dye("disperse rubine", (_band(522, 60, 2.4), _band(556, 55, 2.0), _band(390, 60, 0.4))),
            Dye("disperse blue (anthraquinone)", (_band(610, 60, 2.4), _band(652, 60, 2.2), _band(440, 80, 0.2))),
            Dye("disperse navy", (_band(598, 110, 2.6), _band(545, 60, 0.8))),
        ),
        k1=0.059,
        k2=0.6,
        concentration_range=(0.02, 4.0),
    ),
    MaterialFamily(
        # Bleached-pulp paper dyed in the stock with direct dyes (an opaque sheet, as Eq. (2)
        # assumes), broad-banded as these large, aggregating molecules are: a greenish yellow, an
        # orange, a red, a violet with blue side absorption, a dull blue and a copper
        # phthalocyanine turquoise (Q-band pair 615/665 nm, B band near 345 nm). A calendered
        # sheet reflects less of its internal diffuse light (k2 = 0.45).
        name="paper direct",
        substrate=Substrate("bleached paper", base_ks=0.0004, blue_ks=0.003, blue_decay_nm=25.0),
        dyes=(
            Dye("direct yellow", (_band(405, 85, 2.8),)),
            Dye("direct orange", (_band(478, 110, 2.6),)),
            Dye("direct red", (_band(512, 105, 2.8), _band(400, 60, 0.3))),
            Dye("direct violet", (_band(555, 90, 2.4), _band(520, 50, 0.8), _band(400, 60, 0.5))),
            Dye("direct blue", (_band(600, 130, 2.6), _band(420, 70, 0.2))),
            Dye("direct turquoise (Cu phthalocyanine)", (_band(615, 45, 2.0), _band(665, 50, 3.0), _band(345, 50, 1.5))),
        ),
        k1=K1_N_1_5,
        k2=0.45,
        concentration_range=(0.01, 2.0),
    ),
)

#: Family name -> MaterialFamily, read-only: different substrates and different dye sets.
MATERIAL_FAMILIES: Mapping[str, MaterialFamily] = types.MappingProxyType({family.name: family for family in _FAMILIES})


# --- sampling -----------------------------------------------------------------------------------


def sample_recipes(family: MaterialFamily, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, D) recipes: each uses 1..`family.max_dyes_per_recipe` of the family's D dyes (equally
    likely counts, a random subset of the D: 1 to 3 of 6 in the shipped families), each used dye
    at a concentration log-uniform over `family.concentration_range` (so pale tints and deep shades
    are equally common per decade, as in a dyehouse's shade range), the others 0."""
    dyes = len(family.dyes)
    low, high = family.concentration_range
    counts = rng.integers(1, family.max_dyes_per_recipe + 1, size=n)
    # A random subset of `count` dyes: the `count` smallest of D uniform keys.
    ranks = np.argsort(np.argsort(rng.random((n, dyes)), axis=1), axis=1)
    used = ranks < counts[:, None]
    amounts = np.exp(rng.uniform(np.log(low), np.log(high), size=(n, dyes)))
    return np.where(used, amounts, 0.0)


def sample_family(
    family: MaterialFamily | str, n: int, seed: int = 0, *, specular_included: bool = SPECULAR_INCLUDED
) -> tuple[np.ndarray, np.ndarray]:
    """n random recipes of one family and their measured reflectances.

    Args:
      family: a MaterialFamily or a key of `MATERIAL_FAMILIES`.
      n: number of recipes.
      seed: the draw; the same seed gives the same recipes. Targets and samples of one family are
        two draws with different seeds.
      specular_included: the measurement geometry of Eq. (4) (default SCE).

    Returns:
      concentrations (n, D) in `family.concentration_unit`, and measured reflectances (n, L) on
      `FINE_WAVELENGTHS_NM` (`on_reflectance_grid` gives their 31 samples).
    """
    family = MATERIAL_FAMILIES[family] if isinstance(family, str) else family
    concentrations = sample_recipes(family, n, np.random.default_rng(seed))
    return concentrations, family.reflectance(concentrations, specular_included=specular_included)


def km_family_responses(
    seed: int = 0, n: int = 120, noise: bool = True, patch_pixels: int = 400, **render_kwargs
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Family name -> (responses (n, 16), reflectances (n, 31), concentrations (n, D)) of every
    family in `MATERIAL_FAMILIES`, rendered through the simulated camera.

    Targets are patch means, not single pixels. `render_targets`'s noise is a pixel's: shot and
    read noise averaged over the instrument's `frames_averaged_sample` frames (the white standard's
    over `frames_averaged_white`), about 0.003 in response at 4 frames. In calibration a colour
    target's or a sample's response is the mean over a region of pixels (the paper measures its
    targets as region means), and the noise of independent pixels averages down as 1/sqrt(pixels)
    in that mean, as more frames would. A response here is therefore rendered with an instrument
    whose `frames_averaged_sample` and `frames_averaged_white` are both `patch_pixels` times the
    given one's: the flat field (Eq. 10) divides pixel by pixel by the white standard's image, so
    the white's per-pixel noise averages over the region too (to first order the mean of the
    ratios is the ratio of the means). This matters to what an estimator can learn: at a pixel's
    noise a family's nonlinear structure (module docstring) is buried (a nonlinear regression
    gains 2-4 % on the affine map), at a 20 x 20 px mean's it shows (it gains a third to over
    a half).

    Args:
      seed: the draw of recipes and of the camera's noise; targets and samples of the same
        families are two calls with different seeds.
      n: recipes per family.
      noise: False for exact responses (`simulated_targets.render_targets`).
      patch_pixels: responses are means over this many pixels of each target: 400 (default) = a
        20 x 20 px region; 1 gives single-pixel responses. An integer >= 1, else ValueError.
      render_kwargs: passed on to `render_targets` (instrument: default `InstrumentModel()`,
        whose frame counts are scaled by `patch_pixels` as above; offset_fraction).

    Returns:
      As above: responses are flat-fielded (`render_targets`) patch means, reflectances the 31
      samples at `grid.WAVELENGTHS_NM` of the fine spectra the camera integrated.
    """
    if isinstance(patch_pixels, bool) or not isinstance(patch_pixels, (int, np.integer)) or patch_pixels < 1:
        raise ValueError(
            f"patch_pixels must be an integer >= 1 (the pixels averaged per target, 400 = 20 x 20 px), got {patch_pixels!r}"
        )
    instrument = render_kwargs.pop("instrument", None) or InstrumentModel()
    render_kwargs["instrument"] = dataclasses.replace(
        instrument,
        frames_averaged_sample=instrument.frames_averaged_sample * int(patch_pixels),
        frames_averaged_white=instrument.frames_averaged_white * int(patch_pixels),
    )
    out = {}
    for index, (name, family) in enumerate(MATERIAL_FAMILIES.items()):
        # Independent streams for each family's recipes and noise, all fixed by `seed`.
        recipe_seed, noise_seed = np.random.SeedSequence([seed, index]).generate_state(2)
        concentrations, fine = sample_family(family, n, seed=int(recipe_seed))
        responses = render_targets(fine, seed=int(noise_seed), noise=noise, **render_kwargs)
        out[name] = (responses, on_reflectance_grid(fine), concentrations)
    return out


__all__ = [
    "K1_N_1_5",
    "MATERIAL_FAMILIES",
    "SPECULAR_INCLUDED",
    "AbsorptionBand",
    "Dye",
    "MaterialFamily",
    "Substrate",
    "absorption_bands_ks",
    "inverse_saunderson",
    "km_family_responses",
    "ks_from_reflectance",
    "layer_over_background",
    "mixture_ks",
    "on_reflectance_grid",
    "reflectance_from_ks",
    "sample_family",
    "sample_recipes",
    "saunderson",
]
