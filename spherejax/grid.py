"""Wavelength grids shared by every module.

The instrument of Zou et al. (2019) has 16 narrow-band filters centred at 400, 420, ..., 700 nm
(FWHM 10 nm); reflectance is reconstructed on the 31-sample grid 400, 410, ..., 700 nm that
colorimetry and the paper's spectral rms use.
"""

import numpy as np

#: Filter centres in nm, shape (16,): the camera's band axis (the last axis of raw and v cubes).
BAND_CENTRES_NM = np.arange(400, 701, 20, dtype=np.int64)

#: Reflectance wavelengths in nm, shape (31,): the last axis of reflectance cubes.
WAVELENGTHS_NM = np.arange(400, 701, 10, dtype=np.int64)

N_BANDS = BAND_CENTRES_NM.size
N_WAVELENGTHS = WAVELENGTHS_NM.size

__all__ = ["BAND_CENTRES_NM", "WAVELENGTHS_NM", "N_BANDS", "N_WAVELENGTHS"]
