"""`spherejax.open_corrected`: a batch's outputs as an xarray Dataset, lazily, in row chunks;
both reflectance namings (the spectral layout, and the older "400nm"), and one-line refusals."""

import warnings

import numpy as np
import OpenImageIO as oiio
import pytest

import spherejax
from spherejax import cli, io
from spherejax.grid import WAVELENGTHS_NM
from spherejax.io import corrected

from .batch_support import NAMES, frame


def channel_names(path) -> list[str]:
    image = oiio.ImageInput.open(str(path))
    names = list(image.spec().channelnames)
    image.close()
    return names


@pytest.fixture(scope="module")
def batch(cal, tmp_path_factory):
    """One input corrected by the command line: (OUT/a, the raw frame, correct()'s result)."""
    folder = tmp_path_factory.mktemp("corrected")
    raw = frame(np.random.default_rng(3))
    io.write_frame(folder / "a.tif", raw, channel_names=NAMES)
    assert cli.main(["-q", "correct", "-c", str(cal), str(folder / "a.tif"), "-o", str(folder / "out")]) == 0
    calibration, header = io.load_calibration(cal)
    return folder / "out" / "a", spherejax.correct(raw, calibration), header


@pytest.mark.parametrize("given", ["a.reflectance.exr", "a", "a.lab.exr", "a.quality.png"])
def test_a_batch_output_opens_as_a_dataset(batch, given):
    stem, expected, header = batch
    ds = spherejax.open_corrected(stem.with_name(given))
    assert ds["reflectance"].dims == ("y", "x", "wavelength")
    np.testing.assert_array_equal(ds["wavelength"], WAVELENGTHS_NM.astype(float))
    assert ds["wavelength"].attrs["units"] == "nm"
    np.testing.assert_array_equal(ds["reflectance"].values, np.asarray(expected.reflectance))
    np.testing.assert_array_equal(ds["lab"].values, np.asarray(expected.lab))
    np.testing.assert_array_equal(ds["quality"].values, np.asarray(expected.quality))
    assert ds.attrs["spherejax:calibration_checksum"] == header["checksum"]
    assert ds.attrs["spectralLayoutVersion"] == "1.0"


def test_reading_is_lazy_and_by_rows(batch, monkeypatch):
    """Small chunks: a selection of a few rows reads only the chunks that hold them."""
    stem, expected, _ = batch
    monkeypatch.setattr(corrected, "CHUNK_BYTES", 8 * 48 * 31 * 4)  # eight rows a chunk
    calls = []
    real = corrected._read_rows

    def counting(path, row0, row1, order):
        calls.append((path.rsplit(".", 2)[-2], row0, row1))
        return real(path, row0, row1, order)

    monkeypatch.setattr(corrected, "_read_rows", counting)
    ds = spherejax.open_corrected(stem)
    assert calls == []  # opening reads no pixel
    assert ds["reflectance"].chunks[0] == (8, 8, 8, 8, 8)
    window = ds["reflectance"].isel(y=slice(10, 14)).values
    assert calls == [("reflectance", 8, 16)]
    np.testing.assert_array_equal(window, np.asarray(expected.reflectance)[10:14])


def test_older_names_still_open(batch, tmp_path):
    """A reflectance EXR of "400nm".."700nm" channels (written before the spectral layout), in
    a channel order other than wavelength order."""
    stem, expected, _ = batch
    reflectance = np.asarray(expected.reflectance)
    order = np.random.default_rng(0).permutation(31)
    spec = oiio.ImageSpec(reflectance.shape[1], reflectance.shape[0], 31, "float")
    spec.channelnames = [f"{WAVELENGTHS_NM[i]}nm" for i in order]
    output = oiio.ImageOutput.create(str(tmp_path / "old.reflectance.exr"))
    assert output.open(str(tmp_path / "old.reflectance.exr"), spec)
    assert output.write_image(np.ascontiguousarray(reflectance[..., order])) and output.close()
    ds = spherejax.open_corrected(tmp_path / "old.reflectance.exr")
    np.testing.assert_array_equal(ds["wavelength"], WAVELENGTHS_NM.astype(float))
    np.testing.assert_array_equal(ds["reflectance"].values, reflectance)
    assert "lab" not in ds and "quality" not in ds  # no siblings: reflectance alone


def test_refusals_name_the_file(batch, tmp_path):
    stem, _, _ = batch
    with pytest.raises(io.SpherejaxFileError, match="nothing.*no reflectance file"):
        spherejax.open_corrected(tmp_path / "nothing")
    lab_only = tmp_path / "x.reflectance.exr"
    io.write_exr(lab_only, np.zeros((4, 5, 3), np.float32), channel_names=["L*", "a*", "b*"])
    with pytest.raises(io.SpherejaxFileError, match=r"x.reflectance.exr: has channels \['L\*'"):
        spherejax.open_corrected(lab_only)
    broken = tmp_path / "y.reflectance.exr"
    broken.write_bytes(b"not an image")
    with pytest.raises(io.SpherejaxFileError, match="y.reflectance.exr: is not a readable image"):
        spherejax.open_corrected(broken)


def test_a_spectral_image_of_another_name_opens(batch, tmp_path):
    """A reflectance in the spectral layout that spherejax did not name (colour-science wrote it),
    and an ENVI image under its own name."""
    import colour

    stem, expected, _ = batch
    reflectance = np.asarray(expected.reflectance)[:4, :6]
    components = {"T": (WAVELENGTHS_NM.astype(float), np.nan_to_num(reflectance))}
    specification = colour.io.Specification_Fichet2021(is_emissive=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", colour.utilities.ColourRuntimeWarning)  # its sRGB preview's shape notice
        colour.io.write_spectral_image_Fichet2021(components, str(tmp_path / "scan.exr"), "float32", specification)
    assert {"R", "G", "B"} <= set(channel_names(tmp_path / "scan.exr"))  # colour's RGB preview, as the layout allows
    ds = spherejax.open_corrected(tmp_path / "scan.exr")
    np.testing.assert_array_equal(ds["wavelength"], WAVELENGTHS_NM.astype(float))
    np.testing.assert_array_equal(ds["reflectance"].values, np.nan_to_num(reflectance))
    assert set(ds.data_vars) == {"reflectance"}

    from spherejax.io import envi

    with envi.EnviWriter(tmp_path / "scan2.hdr", reflectance.shape, description="t", band_names=["b"] * 31,
                         wavelengths_nm=WAVELENGTHS_NM.tolist()) as writer:
        writer.write_rows(0, reflectance)
        writer.commit()
    for given in ("scan2.hdr", "scan2.img"):
        np.testing.assert_array_equal(spherejax.open_corrected(tmp_path / given)["reflectance"].values, reflectance)
