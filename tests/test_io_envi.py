"""`spherejax.io.envi`: ENVI images read back by Spectral Python (wavelengths, values, the data
ignore value, spherejax's attributes), written atomically, strip by strip."""

import hashlib
import os

import numpy as np
import pytest

from spherejax import io
from spherejax.grid import WAVELENGTHS_NM
from spherejax.io import envi


def write(path, pixels, *, strips=(0,), wavelengths=WAVELENGTHS_NM.tolist(), attributes=None):
    names = [f"{nm}nm" for nm in wavelengths] if wavelengths is not None else [f"c{i}" for i in range(pixels.shape[2])]
    with envi.EnviWriter(path, pixels.shape, description="test", band_names=names, wavelengths_nm=wavelengths,
                         attributes=attributes) as writer:
        bounds = [*strips, len(pixels)]
        for row0, row1 in zip(bounds, bounds[1:]):
            writer.write_rows(row0, pixels[row0:row1])
        return writer.commit()


@pytest.fixture
def pixels():
    rng = np.random.default_rng(0)
    values = rng.uniform(0, 1, (7, 5, 31)).astype(np.float32)
    values[2, 3] = np.nan  # a flagged pixel
    return values


def test_spectral_python_reads_wavelengths_values_and_header(tmp_path, pixels):
    import spectral

    digests = write(tmp_path / "a.reflectance.hdr", pixels, strips=(0, 3, 4),
                    attributes={"spherejax:calibration_checksum": "sha256:abc", "spherejax:illuminant": "D65"})
    image = spectral.open_image(str(tmp_path / "a.reflectance.hdr"))
    assert (image.nrows, image.ncols, image.nbands) == (7, 5, 31)
    np.testing.assert_array_equal(image.bands.centers, WAVELENGTHS_NM.astype(float))
    assert image.metadata["wavelength units"] == "Nanometers" and image.metadata["interleave"] == "bip"
    loaded = image.load()
    ignore = float(image.metadata["data ignore value"])
    assert ignore == envi.IGNORE_VALUE and (np.asarray(loaded[2, 3]) == ignore).all()
    good = ~np.isnan(pixels)
    np.testing.assert_array_equal(np.asarray(loaded)[good], pixels[good])
    assert image.metadata["spherejax calibration checksum"] == "sha256:abc"
    assert sorted(p.name for p in digests) == ["a.reflectance.hdr", "a.reflectance.img"]
    for path, digest in digests.items():
        assert hashlib.sha256(path.read_bytes()).hexdigest() == digest
    assert sorted(os.listdir(tmp_path)) == ["a.reflectance.hdr", "a.reflectance.img"]


def test_the_lazy_reader_gives_nan_back_and_the_attributes(tmp_path, pixels):
    write(tmp_path / "a.reflectance.hdr", pixels, attributes={"spherejax:source": "in/a.tif"})
    lazy, wavelengths, attributes = envi.open_lazy(tmp_path / "a.reflectance.hdr", kind="reflectance", chunk_bytes=2 * 5 * 31 * 4)
    assert lazy.chunks[0] == (2, 2, 2, 1)
    np.testing.assert_array_equal(lazy.compute(), pixels)  # NaN where it was NaN
    assert wavelengths == WAVELENGTHS_NM.astype(float).tolist() and attributes == {"spherejax:source": "in/a.tif"}


def test_the_same_pixels_in_any_strips_give_the_same_bytes(tmp_path, pixels):
    one = write(tmp_path / "one.hdr", pixels)
    many = write(tmp_path / "many.hdr", pixels, strips=(0, 1, 2, 6))
    assert one[tmp_path / "one.img"] == many[tmp_path / "many.img"]


def test_an_unfinished_image_leaves_nothing(tmp_path, pixels):
    with pytest.raises(io.SpherejaxFileError, match="has 3 of its 7 rows"):
        with envi.EnviWriter(tmp_path / "a.hdr", pixels.shape, description="t", band_names=["b"] * 31) as writer:
            writer.write_rows(0, pixels[:3])
            writer.commit()
    with envi.EnviWriter(tmp_path / "b.hdr", pixels.shape, description="t", band_names=["b"] * 31) as writer:
        writer.write_rows(0, pixels[:3])  # left without commit: an error, or a stop request
    assert os.listdir(tmp_path) == []


def test_rows_out_of_order_and_bad_shapes_are_refused(tmp_path, pixels):
    with envi.EnviWriter(tmp_path / "a.hdr", pixels.shape, description="t", band_names=["b"] * 31) as writer:
        with pytest.raises(ValueError, match="expected the next row 0, got 2"):
            writer.write_rows(2, pixels[2:4])
        with pytest.raises(ValueError, match=r"expected \(rows, 5, 31\)"):
            writer.write_rows(0, pixels[:2, :4])
    with pytest.raises(ValueError, match="2 names for 31 channels"):
        envi.EnviWriter(tmp_path / "c.hdr", pixels.shape, description="t", band_names=["a", "b"])


@pytest.mark.parametrize("text", [
    "not an ENVI header\n",                                     # no magic word
    "ENVI\nsamples = 5\nlines = 7\n",                          # no bands, no data type
    "ENVI\nsamples = 5\nlines = 7\nbands = 31\ndata type = 4\ninterleave = bip\nbyte order = 0\n",  # no data file
])
def test_a_header_that_is_not_a_whole_envi_image_is_refused_in_one_line(tmp_path, text):
    (tmp_path / "bad.hdr").write_text(text)
    with pytest.raises(io.SpherejaxFileError, match="bad.hdr: cannot be read") as raised:
        envi.open_lazy(tmp_path / "bad.hdr", kind="reflectance", chunk_bytes=1 << 20)
    assert "\n" not in str(raised.value)


def test_pixels_of_another_type_and_a_reflectance_without_wavelengths_are_refused(tmp_path, pixels):
    write(tmp_path / "plain.hdr", pixels[..., :3], wavelengths=None)
    with pytest.raises(io.SpherejaxFileError, match="plain.hdr: has no wavelength for each band"):
        envi.open_lazy(tmp_path / "plain.hdr", kind="reflectance", chunk_bytes=1 << 20)
    header = (tmp_path / "plain.hdr").read_text().replace("data type = 4", "data type = 5")  # float64
    (tmp_path / "double.hdr").write_text(header)
    (tmp_path / "double.img").write_bytes(np.zeros((7, 5, 3), "<f8").tobytes())
    with pytest.raises(io.SpherejaxFileError, match="double.hdr: holds float64 pixels"):
        envi.open_lazy(tmp_path / "double.hdr", kind="lab", chunk_bytes=1 << 20)
    with pytest.raises(io.SpherejaxFileError, match="plain.hdr: is 7 x 5.*6 x 5"):
        envi.open_lazy(tmp_path / "plain.hdr", kind="lab", chunk_bytes=1 << 20, shape=(6, 5))


def test_a_newline_or_brace_in_a_value_cannot_break_the_header(tmp_path, pixels):
    """A source file named with a newline and braces: the header still reads, one field a line."""
    import spectral

    source = "in/a}\nlines = 1 {b.tif"
    write(tmp_path / "a.hdr", pixels, attributes={"spherejax:source": source})
    image = spectral.open_image(str(tmp_path / "a.hdr"))
    assert (image.nrows, image.ncols, image.nbands) == (7, 5, 31)
    assert image.metadata["spherejax source"] == "in/a) lines = 1 (b.tif"


@pytest.mark.parametrize("field, value, fragment", [
    ("samples", "2000000", "describes 1736000000"), ("lines", "2000000", "describes 1240000000"),
    ("header offset", "-100", "has header offset = -100"), ("header offset", "100000000000", "describes 100000004340"),
    ("data type", "6", "holds complex64 pixels (data type = 6)"), ("bands", "0", "has bands = 0"),
    ("lines", "6", "holds 4340 bytes"),
])
def test_a_damaged_header_is_refused_in_one_line(tmp_path, pixels, field, value, fragment):
    """Sizes, offset or data type that do not describe the data file: Spectral Python mapped the
    file to None and open_corrected raised "AttributeError: 'NoneType' object has no attribute
    'dtype'" (samples or lines 2e6, header offset -100 or 1e11, data type 6)."""
    import re

    import spherejax as sj

    write(tmp_path / "a.reflectance.hdr", pixels)
    header = (tmp_path / "a.reflectance.hdr").read_text()
    damaged, count = re.subn(rf"^{field} = .*$", f"{field} = {value}", header, flags=re.M)
    assert count == 1
    (tmp_path / "a.reflectance.hdr").write_text(damaged)
    with pytest.raises(io.SpherejaxFileError) as raised:
        envi.open_lazy(tmp_path / "a.reflectance.hdr", kind="reflectance", chunk_bytes=1 << 20)
    assert fragment in str(raised.value) and "\n" not in str(raised.value)
    with pytest.raises(io.SpherejaxFileError, match=re.escape(fragment)):
        sj.open_corrected(tmp_path / "a")
