"""Conventions over the whole public surface (in the spirit of dm_pix's api_test)."""

import inspect

import numpy as np
import pytest

import spherejax as sj

PUBLIC_FUNCTIONS = [
    name for name in sj.__all__ if inspect.isfunction(getattr(sj, name))
]

# docs/design.md's public API: acceptance checks call these names with these leading parameters.
DESIGN_SIGNATURES = {
    "reflectance_to_xyz": ["refl", "illuminant"],
    "xyz_to_lab": ["xyz", "white_xyz"],
    "reflectance_to_lab": ["refl", "illuminant"],
    "delta_e_2000": ["lab1", "lab2"],
    "flat_field": ["raw", "dark", "white"],
    "white_patch_ratio": ["raw", "dark", "white", "patch"],
    "stage1": ["v", "p"],
    "stage2": ["v", "p", "coeffs"],
    "fit_stage2": ["v", "p", "target", "loss"],
    "fit_wiener": ["responses", "reflectances"],
    "wiener": ["v", "W"],
    "correct": ["raw", "calibration"],
    "plan": ["calibration", "shape"],
    "measure": ["raw", "calibration", "mask", "noise"],
    "patch_ratio": ["raw", "calibration"],
    "patch_ratio_u": ["raw", "calibration", "noise"],
    "open_corrected": ["path"],
}


def test_all_names_exist():
    for name in sj.__all__:
        assert hasattr(sj, name), name


@pytest.mark.parametrize("name", sorted(DESIGN_SIGNATURES))
def test_design_signatures(name):
    parameters = list(inspect.signature(getattr(sj, name)).parameters)
    assert parameters[: len(DESIGN_SIGNATURES[name])] == DESIGN_SIGNATURES[name]


def test_defaults_named_in_design():
    assert inspect.signature(sj.reflectance_to_xyz).parameters["illuminant"].default == "D65"
    assert inspect.signature(sj.fit_stage2).parameters["loss"].default == "l2"
    calibration_fields = inspect.signature(sj.Calibration).parameters
    for field in ("dark", "white", "patch", "coeffs", "wiener", "illuminant"):
        assert field in calibration_fields
    assert calibration_fields["illuminant"].default == "D65"


@pytest.mark.parametrize("name", PUBLIC_FUNCTIONS)
def test_documented(name):
    doc = inspect.getdoc(getattr(sj, name))
    assert doc and len(doc.splitlines()) >= 2, f"{name} needs a docstring with shapes"


@pytest.mark.parametrize("name", PUBLIC_FUNCTIONS)
def test_options_after_arrays_are_keyword_only_or_design_named(name):
    """Options beyond those docs/design.md lists positionally are keyword-only, so call sites read."""
    signature = inspect.signature(getattr(sj, name))
    allowed_positional = set(DESIGN_SIGNATURES.get(name, [])) | {
        # Non-DESIGN functions: their positional parameters are arrays or the same illuminant.
        "illuminant", "responses", "reflectances", "noise_variances", "noise_variance",
        "sensitivity", "lab", "reference", "bands", "dtype", "reflectance", "present",
        # wiener_from_system's arrays of the system and the reflectance statistics (E6-E7).
        "offset", "reflectance_mean", "reflectance_covariance",
    }
    for parameter in signature.parameters.values():
        if parameter.kind is parameter.POSITIONAL_OR_KEYWORD:
            assert parameter.name in allowed_positional, f"{name}({parameter.name}) should be keyword-only"


def test_bands_and_wavelengths():
    np.testing.assert_array_equal(sj.BAND_CENTRES_NM, np.arange(400, 701, 20))
    np.testing.assert_array_equal(sj.WAVELENGTHS_NM, np.arange(400, 701, 10))
