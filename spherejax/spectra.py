"""Measured reflectance spectra shipped with colour-science, on spherejax's 31-sample grid.

The simulator, the tests and the benchmarks draw targets, patches and backgrounds from here, so
no reflectance is invented. Sets (colour-science 0.4.x):

- ColorChecker: "ColorChecker N Ohta", "BabelColor Average", "ISO 17321-1" (24 patches each), and
  "PMC" (30 patches), from `colour.SDS_COLOURCHECKERS` (aliases dropped);
- TCS: the CIE 13.3-1995 (14) and CIE 2024 (15) test colour samples (`colour.quality.SDS_TCS`);
- VS: the 15 NIST CQS 7.4 and 9.0 test samples (`colour.quality.SDS_VS`);
- CES: the 99 colour evaluation samples of IES TM-30-18 / CIE 224:2017;
- RAW to ACES: the 190 training patches of AMPAS rawtoaces.

Only spectra that cover 400-700 nm are kept; values at 400, 410, ..., 700 nm (or another grid)
are taken with colour-science's own interpolation (exact at measured wavelengths).
"""

from __future__ import annotations

import functools
import warnings

import numpy as np

from .grid import WAVELENGTHS_NM

# colour-science registers some datasets twice, under a long and a short name.
_COLOURCHECKER_ALIASES = {"babel_average", "cc_ohta"}


def _sample(sd, wavelengths: tuple[float, ...]) -> np.ndarray | None:
    """Reflectance of one colour-science SpectralDistribution at `wavelengths`, or None if it does
    not cover 400-700 nm. Outside its measured range (e.g. 380-400 nm for the PMC set) the value
    is colour-science's constant extrapolation."""
    if sd.shape.start > WAVELENGTHS_NM[0] or sd.shape.end < WAVELENGTHS_NM[-1]:
        return None
    grid = np.asarray(wavelengths)
    inside = (grid >= sd.shape.start) & (grid <= sd.shape.end)
    values = np.empty(grid.shape, dtype=np.float64)
    values[inside] = sd[grid[inside]]
    values[grid < sd.shape.start] = sd.values[0]
    values[grid > sd.shape.end] = sd.values[-1]
    return values


@functools.lru_cache(maxsize=None)
def _load(wavelengths: tuple[float, ...]) -> dict[str, np.ndarray]:
    import colour
    from colour.characterisation import read_training_data_rawtoaces_v1
    from colour.quality import SDS_TCS, SDS_VS
    from colour.quality.cfi2017 import load_TCS_CIE2017

    sets: dict[str, list[np.ndarray]] = {}
    labels: dict[str, list[str]] = {}

    def add(name, sds):
        for sd in sds:
            values = _sample(sd, wavelengths)
            if values is not None:
                sets.setdefault(name, []).append(values)
                labels.setdefault(name, []).append(str(sd.name))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # colour-science's interpolation / alignment notices
        for name, checker in colour.SDS_COLOURCHECKERS.items():
            if name not in _COLOURCHECKER_ALIASES:
                add(f"ColorChecker: {name}", checker.values())
        for name, samples in SDS_TCS.items():
            add(f"TCS: {name}", samples.values())
        for name, samples in SDS_VS.items():
            add(f"VS: {name}", samples.values())
        ces = load_TCS_CIE2017(colour.SpectralShape(380, 780, 5))
        add("CES (TM-30)", colour.colorimetry.sds_and_msds_to_sds(ces))
        add("RAW to ACES training", colour.colorimetry.sds_and_msds_to_sds(read_training_data_rawtoaces_v1()))
    out = {}
    for name, rows in sets.items():
        array = np.stack(rows)
        array.setflags(write=False)
        out[name] = array
    _LABELS[wavelengths] = {name: tuple(names) for name, names in labels.items()}
    return out


_LABELS: dict[tuple[float, ...], dict[str, tuple[str, ...]]] = {}


def _grid(wavelengths) -> tuple[float, ...]:
    grid = WAVELENGTHS_NM if wavelengths is None else np.asarray(wavelengths, dtype=np.float64)
    return tuple(float(w) for w in grid)


def reflectance_sets(wavelengths=None) -> dict[str, np.ndarray]:
    """Every shipped reflectance set, name -> read-only float64 array (n, L).

    Args:
      wavelengths: sampling grid in nm, shape (L,); default `grid.WAVELENGTHS_NM` (31 samples).
        A finer grid (e.g. 380..720 nm step 2 for the simulator) uses colour-science's
        interpolation inside each measured range and constant extrapolation outside it.
    """
    return dict(_load(_grid(wavelengths)))


def reflectance_names(wavelengths=None) -> dict[str, tuple[str, ...]]:
    """The patch names of `reflectance_sets(wavelengths)`, in the same order."""
    grid = _grid(wavelengths)
    _load(grid)
    return dict(_LABELS[grid])


def all_reflectances(wavelengths=None) -> np.ndarray:
    """All shipped reflectances stacked, float64 (N, L), in the order of `reflectance_sets`."""
    return np.concatenate(list(_load(_grid(wavelengths)).values()))


__all__ = ["reflectance_sets", "reflectance_names", "all_reflectances"]
