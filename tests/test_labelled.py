"""`CorrectionResult.to_xarray()` and `spherejax.labelled`: the outputs as xarray, with the
dimensions, coordinates and values of the arrays they came from."""

import numpy as np
import pytest

import spherejax as sj
from spherejax import labelled
from spherejax.grid import BAND_CENTRES_NM, WAVELENGTHS_NM



@pytest.fixture(scope="module")
def corrected():
    """A result without and one with uncertainties, on the benchmarks' synthetic frames."""
    from benchmarks import reference

    inputs = reference.make_inputs(48)
    calibration = reference.make_calibration(inputs, reference.stage2_coeffs(), reference.wiener_matrix())
    noise = sj.NoiseModel(gain=2.0, read_noise=3.0, dark_frames=8, white_frames=8)
    return sj.correct(inputs["raw"], calibration), sj.correct(inputs["raw"], calibration, noise=noise)


def test_a_result_as_a_dataset(corrected):
    result, _ = corrected
    ds = result.to_xarray(attrs={"illuminant": "D65"})
    height, width = result.quality.shape
    assert dict(ds.sizes) == {"y": height, "x": width, "wavelength": 31, "lab_channel": 3, "band": 16}
    assert ds["reflectance"].dims == ("y", "x", "wavelength") and ds["lab"].dims == ("y", "x", "lab_channel")
    np.testing.assert_array_equal(ds["wavelength"], WAVELENGTHS_NM)
    assert ds["wavelength"].attrs["units"] == "nm"
    np.testing.assert_array_equal(ds["band"], BAND_CENTRES_NM)
    assert list(ds["lab_channel"].values) == ["L*", "a*", "b*"]
    np.testing.assert_array_equal(ds["reflectance"].values, np.asarray(result.reflectance))
    np.testing.assert_array_equal(ds["lab"].values, np.asarray(result.lab))
    np.testing.assert_array_equal(ds["quality"].values, np.asarray(result.quality))
    np.testing.assert_array_equal(ds["p"].values, np.asarray(result.p))
    assert "reflectance_u" not in ds and "v" not in ds  # absent fields are left out
    assert ds.attrs == {"illuminant": "D65"}
    # Selection by wavelength in nm, as a colour scientist would.
    np.testing.assert_array_equal(ds["reflectance"].sel(wavelength=550.0).values, np.asarray(result.reflectance)[..., 15])


def test_uncertainties_and_a_stack(corrected):
    _, with_noise = corrected
    ds = with_noise.to_xarray()
    assert ds["reflectance_u"].dims == ("y", "x", "wavelength")
    assert ds["lab_covariance"].dims == ("y", "x", "lab_channel", "lab_channel_other")
    np.testing.assert_array_equal(ds["lab_u"].values, np.asarray(with_noise.lab_u))
    stacked = labelled.dataset({"reflectance": np.stack([np.asarray(with_noise.reflectance)] * 2)})
    assert stacked["reflectance"].dims == ("image", "y", "x", "wavelength")


def test_bad_arrays_are_named():
    with pytest.raises(ValueError, match="unknown variable 'spectrum'"):
        labelled.dataset({"spectrum": np.zeros((2, 2, 31))})
    with pytest.raises(ValueError, match="reflectance: shape \\(31,\\) has fewer dimensions"):
        labelled.dataset({"reflectance": np.zeros(31)})
