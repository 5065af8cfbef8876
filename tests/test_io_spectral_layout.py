"""`spherejax.io.spectral_layout`: the reflectance EXR's channel names (Fichet, Pacanowski,
Wilkie 2021), checked against colour-science's reader of the layout."""

import numpy as np
import pytest

from spherejax.grid import WAVELENGTHS_NM
from spherejax.io import spectral_layout


def test_names_are_the_layouts_and_read_back():
    names = spectral_layout.reflectance_channel_names(WAVELENGTHS_NM.tolist())
    assert names[:2] == ["T.400nm", "T.410nm"] and names[-1] == "T.700nm" and len(names) == 31
    assert spectral_layout.wavelengths_of_channels(names) == WAVELENGTHS_NM.astype(float).tolist()


def test_fractional_wavelengths_use_a_decimal_comma():
    names = spectral_layout.reflectance_channel_names([412.5, 500.25, 600.0])
    assert names == ["T.412,5nm", "T.500,25nm", "T.600nm"]
    assert spectral_layout.wavelengths_of_channels(names) == [412.5, 500.25, 600.0]


def test_names_colour_science_reads_as_the_same_wavelengths(tmp_path):
    """Whatever we name, colour-science's reader of the layout finds at the same wavelength."""
    import colour
    import OpenImageIO as oiio

    wavelengths = [400.0, 412.5, 700.0]
    path = tmp_path / "t.exr"
    pixels = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    spec = oiio.ImageSpec(3, 2, 3, "float")
    spec.channelnames = spectral_layout.reflectance_channel_names(wavelengths)
    spec.attribute(spectral_layout.LAYOUT_VERSION_ATTRIBUTE, spectral_layout.LAYOUT_VERSION)
    output = oiio.ImageOutput.create(str(path))
    assert output.open(str(path), spec) and output.write_image(pixels) and output.close()
    found, values = colour.io.read_spectral_image_Fichet2021(str(path))["T"]
    np.testing.assert_array_equal(found, wavelengths)
    np.testing.assert_array_equal(values, pixels)


@pytest.mark.parametrize("names, wavelengths", [
    (["400nm", "410nm"], [400.0, 410.0]),                 # spherejax's names before the layout
    (["T.0,4um", "T.5e2nm"], [400.0, 500.0]),            # other SI prefixes and an exponent
    (["T.599584916000000Hz"], [299792458.0 / 599584916000000 * 1e9]),  # a frequency
])
def test_other_spellings_read(names, wavelengths):
    np.testing.assert_allclose(spectral_layout.wavelengths_of_channels(names), wavelengths, rtol=1e-12)


@pytest.mark.parametrize("names", [[], ["R", "G", "B"], ["T.400nm", "L*"], ["S0.400nm"], ["T.nm"], ["T.,nm"]])
def test_anything_else_is_not_a_reflectance_image(names):
    assert spectral_layout.wavelengths_of_channels(names) is None


def test_reflective_channels_leave_out_a_preview_and_keep_their_indices():
    assert spectral_layout.reflective_channels(["B", "G", "R", "T.400nm", "T.410nm"]) == {3: 400.0, 4: 410.0}
    assert spectral_layout.reflective_channels(["410nm", "400nm"]) == {0: 410.0, 1: 400.0}
    assert spectral_layout.reflective_channels(["400nm", "R"]) is None  # older names: all or none
    assert spectral_layout.reflective_channels(["L*", "a*", "b*"]) is None


@pytest.mark.parametrize("name", ["T.0Hz", "T.e5nm", "T.0nm", "T.1e400nm", "T.0,0mm"])
def test_a_name_the_grammar_admits_but_that_gives_no_wavelength_is_none_not_an_error(name):
    """"T.0Hz" raised ZeroDivisionError and "T.e5nm" ValueError out of the readers of outputs."""
    assert spectral_layout.wavelengths_of_channels([name]) is None
    assert spectral_layout.reflective_channels([name, "T.500nm"]) == {1: 500.0}
