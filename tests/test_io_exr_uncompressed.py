"""spherejax.io.exr_uncompressed: uncompressed EXRs written without OpenImageIO must be the bytes
OpenImageIO writes (so any OpenEXR reader reads them, and a file does not depend on the writer),
and keep the atomic writer's guarantees."""

from __future__ import annotations

import hashlib
import os

import numpy as np
import OpenImageIO as oiio
import pytest

from spherejax import io
from spherejax.io import cubes, exr_uncompressed, frames, spectral_layout

REFLECTANCE_NAMES = spectral_layout.reflectance_channel_names(list(range(400, 710, 10)))
ATTRIBUTES = {
    "spectralLayoutVersion": "1.0",
    "spherejax:source": "in/ünïcode name.tif",
    "spherejax:calibration_checksum": "sha256:" + "ab" * 32,
    "spherejax:a_name_longer_than_thirty_one_bytes": "sets OpenEXR's long-names flag",
}


def _through_openimageio(path, pixels, names, attributes, pixel_type):
    """The same file written by OpenImageIO (the writer `open_exr` used before)."""
    spec = cubes._output_spec(path, pixels.shape, np.float16 if pixel_type == "half" else np.float32, names, attributes)
    spec.attribute("compression", "none")
    spec.attribute("DateTime", "")
    writer = frames.AtomicImageWriter(path, spec, "openexr")
    writer.write_rows(0, pixels)
    return writer.commit()


def _pixels(rng, shape):
    pixels = rng.normal(0.4, 2.0, shape).astype(np.float32)
    pixels[1, 2] = np.nan
    pixels[0, 0, 0] = np.inf
    pixels[-1, -1, -1] = 1e-7  # a half-float subnormal
    pixels[-1, 0, 0] = 70000.0  # beyond half's largest: inf
    return pixels


@pytest.mark.parametrize("pixel_type", ["float", "half"])
@pytest.mark.parametrize("names, attributes", [
    (REFLECTANCE_NAMES, ATTRIBUTES),
    (["L*", "a*", "b*"], {"spherejax:illuminant": "D65"}),
    (["zeta", "Alpha", "b", "a"], {}),  # stored sorted by name: the rows' channels reordered
])
def test_the_bytes_are_openimageios(tmp_path, pixel_type, names, attributes):
    pixels = _pixels(np.random.default_rng(len(names)), (11, 9, len(names)))
    writer = io.open_exr(tmp_path / "ours.exr", pixels.shape, channel_names=names, attributes=attributes,
                         compression="none", pixel_type=pixel_type)
    assert isinstance(writer, exr_uncompressed.UncompressedExrWriter)
    with writer:
        for row0, row1 in [(0, 4), (4, 5), (5, 11)]:  # strips of different heights
            writer.write_rows(row0, pixels[row0:row1])
        ours = writer.commit()
    theirs = _through_openimageio(tmp_path / "theirs.exr", pixels, names, attributes, pixel_type)
    data = (tmp_path / "ours.exr").read_bytes()
    assert data == (tmp_path / "theirs.exr").read_bytes()
    assert ours == theirs == hashlib.sha256(data).hexdigest()
    assert sorted(os.listdir(tmp_path)) == ["ours.exr", "theirs.exr"]


def test_openimageio_reads_the_values_back(tmp_path):
    pixels = _pixels(np.random.default_rng(1), (6, 5, 31))
    io.write_exr(tmp_path / "a.exr", pixels, channel_names=REFLECTANCE_NAMES, attributes=ATTRIBUTES, compression="none")
    image = oiio.ImageInput.open(str(tmp_path / "a.exr"))
    try:
        spec = image.spec()
        back = image.read_image(oiio.FLOAT)
    finally:
        image.close()
    assert list(spec.channelnames) == REFLECTANCE_NAMES and spec.get_string_attribute("compression") == "none"
    assert {name: spec.get_string_attribute(name) for name in ATTRIBUTES} == ATTRIBUTES
    np.testing.assert_array_equal(back, pixels)  # NaN where NaN, inf where inf


def test_other_attributes_and_compressions_stay_with_openimageio(tmp_path):
    shape = (3, 4, 3)
    writer = io.open_exr(tmp_path / "a.exr", shape, channel_names=["R", "G", "B"], compression="piz")
    assert isinstance(writer, frames.AtomicImageWriter)
    writer.abort()
    # A name OpenImageIO renames or types: the file stays OpenImageIO's own.
    for attributes in ({"Copyright": "me"}, {"oiio:ColorSpace": "lin_rec709"}, {"spherejax:x y": "z"}):
        assert not exr_uncompressed.takes_attributes(attributes)
        writer = io.open_exr(tmp_path / "b.exr", shape, channel_names=["R", "G", "B"], attributes=attributes, compression="none")
        assert isinstance(writer, frames.AtomicImageWriter)
        writer.abort()
    assert os.listdir(tmp_path) == []


def test_an_unfinished_or_failed_file_leaves_nothing(tmp_path, monkeypatch):
    pixels = _pixels(np.random.default_rng(2), (5, 4, 3))
    with pytest.raises(io.SpherejaxFileError, match="has 2 of its 5 rows"):
        with io.open_exr(tmp_path / "a.exr", pixels.shape, channel_names=["L*", "a*", "b*"], compression="none") as writer:
            writer.write_rows(0, pixels[:2])
            writer.commit()
    with pytest.raises(ValueError, match="expected the next row 0"):
        with io.open_exr(tmp_path / "a.exr", pixels.shape, channel_names=["L*", "a*", "b*"], compression="none") as writer:
            writer.write_rows(1, pixels[1:])

    def no_room(*args):
        raise OSError(28, "No space left on device")

    writer = io.open_exr(tmp_path / "a.exr", pixels.shape, channel_names=["L*", "a*", "b*"], compression="none")
    writer.write_rows(0, pixels)
    monkeypatch.setattr(os, "fsync", no_room)
    with pytest.raises(io.SpherejaxFileError, match=r"a\.exr.*could not be written: No space left on device"):
        writer.commit()
    assert os.listdir(tmp_path) == []


def test_an_existing_file_is_replaced_only_when_complete(tmp_path):
    pixels = _pixels(np.random.default_rng(3), (4, 4, 3))
    (tmp_path / "a.exr").write_bytes(b"earlier")
    with io.open_exr(tmp_path / "a.exr", pixels.shape, channel_names=["L*", "a*", "b*"], compression="none") as writer:
        writer.write_rows(0, pixels[:2])
        assert (tmp_path / "a.exr").read_bytes() == b"earlier"
    assert (tmp_path / "a.exr").read_bytes() == b"earlier"
    assert os.listdir(tmp_path) == ["a.exr"]
