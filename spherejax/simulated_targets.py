"""Reflectance targets seen by the simulated camera: responses with a known system behind them.

The Wiener estimators (`spherejax.estimation`) are validated across material families on
responses that spherejax can make itself: colour-science's measured spectra (`spherejax.spectra`)
rendered through the simulated instrument's camera (`spherejax.simulate.InstrumentModel`: 16
Gaussian filters, the xenon lamp, the CCD's quantum efficiency, all integrated on the 2 nm grid),
with an additive offset (residual dark level and stray light), shot and read noise and frame
averaging, then flat-fielded by the white standard as `flat_field` (Eq. 10) does. Because the
system is known here, so is what an estimator could know at best: the sensitivity on the 31-sample
reflectance grid, the offset and the noise covariance (`TargetSystem`), which the "oracle"
estimator of the tests and of `benchmarks/bench_wiener.py` is built from.

Model, per band b and target r (fine grid λ):
    e_b(r) = E_b (w_b . r) / (w_b . ρ_ws 1)          mean signal electrons, E_b the white's
    o_b    = offset_fraction E_b g_b                 additive offset, g_b a smooth band profile
    x_b    = e_b + o_b + shot + read                 averaged over `frames` exposures
    v_b    = x_b / x_b(white standard)               the flat-fielded response (Eq. 10)
with w_b = filter x QE x lamp x dλ (`InstrumentModel.band_weights`) and E_b the protocol's "white
standard at 80 % of full scale". On the 31-sample grid, v ≈ M r + b with M = W_b^T (31-grid
weights) / (w_b . ρ_ws 1) and b = o_b / E_b: the sensitivity is projected onto the 31 samples
through linear interpolation, the rule by which the 31 samples determine the fine spectrum.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import spectra
from .grid import N_BANDS, WAVELENGTHS_NM
from .simulated_instrument import FINE_WAVELENGTHS_NM, InstrumentModel

#: Default additive offset, as a fraction of the white standard's signal: 0.5 % is a typical
#: residual of dark subtraction plus stray light in a sphere with a dark-corrected camera.
DEFAULT_OFFSET_FRACTION = 0.005


@dataclasses.dataclass(frozen=True)
class TargetSystem:
    """What is true of the simulated camera on the 31-sample grid (400..700 nm step 10).

    sensitivity: M, (16, 31): v = M r + b + noise for a reflectance r sampled at 31 wavelengths.
    offset: b, (16,), in flat-fielded response units.
    read_variance: (16,), the part of a response's noise variance that does not depend on the
      signal; shot_variance_per_response: (16,), the part per unit response, so that the
      variance of v_b is read_variance_b + shot_variance_per_response_b * (M r + b)_b.
    """

    sensitivity: np.ndarray
    offset: np.ndarray
    read_variance: np.ndarray
    shot_variance_per_response: np.ndarray

    def noise_variance(self, reflectances: np.ndarray) -> np.ndarray:
        """Mean response noise variance per band over `reflectances` (n, 31) -> (16,)."""
        mean_response = np.mean(reflectances @ self.sensitivity.T + self.offset, axis=0)
        return self.read_variance + self.shot_variance_per_response * mean_response


def _interpolation_matrix(fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """(len(fine), len(coarse)): linear interpolation from coarse samples to the fine grid, with
    constant extrapolation outside the coarse range (as `spectra` extends measured spectra)."""
    eye = np.eye(coarse.size)
    return np.stack([np.interp(fine, coarse, eye[k]) for k in range(coarse.size)], axis=1)


def _offset_profile() -> np.ndarray:
    """g_b, (16,): stray light and dark residuals weigh most where the signal is weakest (the
    violet end, where lamp, filters and QE are all low), falling smoothly to the red."""
    x = np.linspace(0.0, 1.0, N_BANDS)
    return 1.5 - x


def target_system(instrument: InstrumentModel | None = None, offset_fraction: float = DEFAULT_OFFSET_FRACTION) -> TargetSystem:
    """The true M, b and noise of `render_targets` for `instrument` (default InstrumentModel())."""
    instrument = instrument or InstrumentModel()
    weights = instrument.band_weights()  # (16, L) on FINE_WAVELENGTHS_NM
    white = instrument.white_standard_reflectance * weights.sum(axis=1)  # w_b . ρ_ws 1
    to_fine = _interpolation_matrix(FINE_WAVELENGTHS_NM, WAVELENGTHS_NM.astype(float))
    sensitivity = (weights @ to_fine) / white[:, None]
    offset = offset_fraction * _offset_profile()
    signal_e = instrument.exposure_fill * instrument.full_well_e  # E_b, the same in every band
    frames = instrument.frames_averaged_sample
    read_variance = (instrument.read_noise_e**2 / frames) / signal_e**2
    # Var(x/E) for Poisson electrons x = E v averaged over `frames`: v / (E frames).
    shot = 1.0 / (signal_e * frames)
    return TargetSystem(
        sensitivity=sensitivity,
        offset=offset,
        read_variance=np.full(N_BANDS, read_variance),
        shot_variance_per_response=np.full(N_BANDS, shot),
    )


def render_targets(
    fine_reflectances: np.ndarray,
    *,
    seed: int = 0,
    instrument: InstrumentModel | None = None,
    offset_fraction: float = DEFAULT_OFFSET_FRACTION,
    noise: bool = True,
) -> np.ndarray:
    """Flat-fielded responses (n, 16) of targets whose reflectances are sampled on the fine grid.

    Args:
      fine_reflectances: (n, L) on `simulate.FINE_WAVELENGTHS_NM` (e.g.
        `spectra.reflectance_sets(FINE_WAVELENGTHS_NM)`), so that the camera integrates the
        measured spectrum, not its 31-sample version.
      seed: noise draw.
      instrument: the camera (default InstrumentModel()).
      offset_fraction: the additive offset's size relative to the white's signal.
      noise: False for exact responses (M r + b up to the 31-sample projection).

    Returns:
      v (n, 16), float64.
    """
    instrument = instrument or InstrumentModel()
    fine_reflectances = np.asarray(fine_reflectances, np.float64)
    if fine_reflectances.ndim != 2 or fine_reflectances.shape[1] != FINE_WAVELENGTHS_NM.size:
        raise ValueError(
            f"fine_reflectances: expected shape (n, {FINE_WAVELENGTHS_NM.size}) on "
            f"simulate.FINE_WAVELENGTHS_NM, got {fine_reflectances.shape}"
        )
    rng = np.random.default_rng(seed)
    weights = instrument.band_weights()
    signal_e = instrument.exposure_fill * instrument.full_well_e
    white_e = instrument.white_standard_reflectance * weights.sum(axis=1)
    offset_e = offset_fraction * signal_e * _offset_profile()
    frames = instrument.frames_averaged_sample

    def expose(electrons: np.ndarray, frames: int) -> np.ndarray:
        if not noise:
            return electrons
        shot = rng.normal(size=electrons.shape) * np.sqrt(np.maximum(electrons, 0.0) / frames)
        read = rng.normal(size=electrons.shape) * instrument.read_noise_e / np.sqrt(frames)
        return electrons + shot + read

    electrons = signal_e * (fine_reflectances @ weights.T) / white_e + offset_e
    # The white standard is captured once per session: its noise is common to every target.
    white = expose(np.full((1, N_BANDS), signal_e), instrument.frames_averaged_white)
    return expose(electrons, frames) / white


def family_responses(seed: int = 0, **kwargs) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Material family -> (responses (n, 16), reflectances (n, 31)) rendered by `render_targets`.

    Families (`FAMILIES`): each groups colour-science sets of one kind of material, so that
    holding one out tests an estimator on materials it never saw.
    """
    fine = spectra.reflectance_sets(FINE_WAVELENGTHS_NM)
    coarse = spectra.reflectance_sets()
    out = {}
    for index, (family, prefixes) in enumerate(FAMILIES.items()):
        names = [name for name in coarse if name.startswith(prefixes)]
        R_fine = np.concatenate([fine[name] for name in names])
        R = np.concatenate([coarse[name] for name in names])
        out[family] = (render_targets(R_fine, seed=seed * 101 + index, **kwargs), R)
    return out


#: Material families of the shipped spectra (`spectra.reflectance_sets` name prefixes): printed
#: and painted colour charts; the CIE / NIST test colour samples (Munsell-like paint chips); the
#: TM-30 colour evaluation samples (natural and manufactured objects); the RAW-to-ACES training
#: patches (skin, foliage, fabrics, paints).
FAMILIES: dict[str, tuple[str, ...]] = {
    "ColorChecker": ("ColorChecker",),
    "TCS and CQS": ("TCS", "VS"),
    "TM-30 CES": ("CES",),
    "RAW to ACES": ("RAW to ACES",),
}


__all__ = [
    "DEFAULT_OFFSET_FRACTION",
    "FAMILIES",
    "TargetSystem",
    "family_responses",
    "render_targets",
    "target_system",
]
