"""spherejax's outputs as labelled arrays (xarray): one naming for `CorrectionResult.to_xarray()`
and for files opened with `spherejax.open_corrected`.

Dimensions and coordinates:

    y, x           pixel row and column (integer coordinates 0..H-1, 0..W-1)
    wavelength     nm, 400..700 step 10 (float; units "nm")
    band           nm, the camera's band centres (p and the intermediate responses)
    lab_channel    "L*", "a*", "b*"; lab_covariance also has lab_channel_other (same labels)
    image          the leading dimension of a stack of images (more leading ones: image_1, ...)

Data variables (those present):

    reflectance    (..., y, x, wavelength)   reflectance factor, NaN where quality != 0
    lab            (..., y, x, lab_channel)  CIELAB under the calibration's illuminant
    quality        (..., y, x)               uint8 bit mask (spherejax.QUALITY_*), 0 = good
    reflectance_u, lab_u, lab_covariance     standard uncertainties and Lab's covariance
    p              (..., band)               white-patch ratio (Eq. 15)
    v, v_stage1, v_stage2                    intermediate responses (..., y, x, band)

xarray is imported when a function here is called, so `import spherejax` does not need it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from .grid import BAND_CENTRES_NM, WAVELENGTHS_NM

LAB_LABELS = ("L*", "a*", "b*")

#: The trailing dimensions of each variable (leading ones are named by `_leading`).
TRAILING_DIMS = {
    "reflectance": ("y", "x", "wavelength"),
    "reflectance_u": ("y", "x", "wavelength"),
    "lab": ("y", "x", "lab_channel"),
    "lab_u": ("y", "x", "lab_channel"),
    "lab_covariance": ("y", "x", "lab_channel", "lab_channel_other"),
    "quality": ("y", "x"),
    "p": ("band",),
    "p_u": ("band",),
    "v": ("y", "x", "band"),
    "v_stage1": ("y", "x", "band"),
    "v_stage2": ("y", "x", "band"),
}

_DESCRIPTIONS = {
    "reflectance": "reflectance factor (dimensionless), NaN where quality != 0",
    "reflectance_u": "standard uncertainty of reflectance",
    "lab": "CIELAB L*, a*, b*",
    "lab_u": "standard uncertainties of L*, a*, b*",
    "lab_covariance": "covariance of L*, a*, b*",
    "quality": "quality bit mask (spherejax.QUALITY_*), 0 = good",
    "p": "white-patch ratio (Zou et al. 2019, Eq. 15)",
    "p_u": "standard uncertainty of p",
    "v": "flat-fielded response (Eq. 10)",
    "v_stage1": "Stage I response (Eq. 17)",
    "v_stage2": "Stage II response (Eq. 23)",
}


def _leading(count: int) -> tuple[str, ...]:
    return tuple("image" if i == 0 else f"image_{i}" for i in range(count))


def coordinates(sizes: Mapping[str, int], *, wavelengths_nm: Sequence[float] | None = None,
                band_centres_nm: Sequence[float] | None = None) -> dict:
    """The coordinates of the dimensions in `sizes` (name -> length); wavelengths and band
    centres default to spherejax's grids when their lengths match."""
    import xarray as xr

    coords = {}
    for name, size in sizes.items():
        if name in ("y", "x"):
            coords[name] = np.arange(size)
        elif name == "wavelength":
            values = WAVELENGTHS_NM if wavelengths_nm is None else wavelengths_nm
            coords[name] = xr.Variable(name, np.asarray(values, dtype=np.float64), {"units": "nm"})
        elif name == "band" and (band_centres_nm is not None or size == len(BAND_CENTRES_NM)):
            values = BAND_CENTRES_NM if band_centres_nm is None else band_centres_nm
            coords[name] = xr.Variable(name, np.asarray(values, dtype=np.float64), {"units": "nm", "long_name": "band centre"})
        elif name in ("lab_channel", "lab_channel_other"):
            coords[name] = list(LAB_LABELS)
    return coords


def dataset(arrays: Mapping[str, object], *, attrs: Mapping | None = None,
            wavelengths_nm: Sequence[float] | None = None, band_centres_nm: Sequence[float] | None = None):
    """An `xarray.Dataset` of spherejax's outputs (names in the module docstring).

    Args:
      arrays: variable name -> array (numpy, JAX or dask), each with the trailing dimensions of
        `TRAILING_DIMS[name]` after any leading ones; None values are left out.
      attrs: the dataset's attributes (for example a file's header).
      wavelengths_nm, band_centres_nm: coordinates where they are not spherejax's grids.

    Raises:
      ValueError: an unknown name, or an array of fewer dimensions than its variable has.
    """
    import xarray as xr

    variables, sizes = {}, {}
    for name, array in arrays.items():
        if array is None:
            continue
        if name not in TRAILING_DIMS:
            raise ValueError(f"arrays: unknown variable {name!r}; expected some of {sorted(TRAILING_DIMS)}")
        if not hasattr(array, "dask"):  # dask arrays stay lazy; anything else becomes numpy
            array = np.asarray(array)
        trailing = TRAILING_DIMS[name]
        if array.ndim < len(trailing):
            raise ValueError(f"{name}: shape {tuple(array.shape)} has fewer dimensions than {trailing}")
        dims = (*_leading(array.ndim - len(trailing)), *trailing)
        sizes.update(zip(dims, array.shape))
        variables[name] = xr.Variable(dims, array, {"description": _DESCRIPTIONS[name]})
    coords = coordinates(sizes, wavelengths_nm=wavelengths_nm, band_centres_nm=band_centres_nm)
    return xr.Dataset(variables, coords=coords, attrs=dict(attrs or {}))


__all__ = ["LAB_LABELS", "TRAILING_DIMS", "coordinates", "dataset"]
