"""Cube channels that cannot be mapped to bands unambiguously.

OpenEXR keeps a file's channels sorted by name, not in the order they were written. A cube whose
channels are named c0..c15 or B1..B16 reads back as c0, c1, c10..c15, c2..c9, which taken in
order corrects scrambled (reflectance off by up to 0.34); a cube written with "400nm" twice holds
"channel1" in place of the second (OpenImageIO's rename), scrambled the same way. Such layouts are
refused in one line naming the file and the channel names found; the layouts that do name every
band's wavelength ("400nm", "400 nm", the spectral layout's "T.400nm") are read in band order,
whatever their order in the file.
"""

from __future__ import annotations

import json
import re

import numpy as np
import OpenImageIO as oiio
import pytest

from spherejax import archive, cli, io
from tests.batch_support import BANDS, NAMES, frame, manifest_records, read_exr

C_NAMES = [f"c{i}" for i in range(16)]
B_NAMES = [f"B{i + 1}" for i in range(16)]
REPEATED_400 = [NAMES[0], NAMES[0], *NAMES[2:]]  # 420nm's channel mislabelled "400nm"
SHAPE = (40, 48, 16)  # the `cal` fixture's frames


def _write_exr(path, array, names, *, description=None):
    """`array` (H, W, C) as a float32 OpenEXR with channels `names`, written in that order."""
    height, width, channels = array.shape
    spec = oiio.ImageSpec(width, height, channels, oiio.FLOAT)
    spec.channelnames = tuple(names)
    if description is not None:
        spec.attribute("ImageDescription", description)
    output = oiio.ImageOutput.create(str(path))
    assert output.open(str(path), spec), oiio.geterror()
    assert output.write_image(np.ascontiguousarray(array, np.float32)), output.geterror()
    output.close()
    return path


def _stored_names(path) -> list[str]:
    image = oiio.ImageInput.open(str(path))
    names = list(image.spec().channelnames)
    image.close()
    return names


def _refusals(path, shape=SHAPE, bands=BANDS) -> list[str]:
    """The messages of open_cube and read_cube on `path`, with and without the calibration's
    bands; each must be a SpherejaxFileError of one line naming the file."""
    messages = []
    for band_centres in (bands, None):
        for reader in (io.open_cube, io.read_cube):
            with pytest.raises(io.SpherejaxFileError) as raised:
                reader(path, expected_shape=shape, band_centres_nm=band_centres)
            message = str(raised.value)
            assert "\n" not in message and message.startswith(f"{path}: "), message
            assert raised.value.expected, message
            messages.append(message)
    return messages


def _outputs(out) -> list[str]:
    """The corrected outputs under OUT (relative paths): every file but the manifest and
    spherejax's hidden bookkeeping (lock, claims)."""
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*")
                  if p.is_file() and p.name != archive.MANIFEST_NAME and not p.name.startswith("."))


def _names_every(message: str, names) -> bool:
    return all(re.search(rf"(?<![\w.]){re.escape(name)}(?!\w)", message) for name in names)


@pytest.mark.parametrize("names", [C_NAMES, B_NAMES, ["T.0Hz", "T.e5nm", *NAMES[2:]]],
                         ids=["c0-c15", "B1-B16", "layout-names-without-a-wavelength"])
def test_exr_channels_not_named_by_wavelength_are_refused(tmp_path, names):
    """Guards against reading an OpenEXR whose channel names do not all carry a wavelength in
    the file's (sorted by name) order, which is not the order they were written in: refused,
    naming the file and every channel found, with or without the calibration's bands. Names of
    the spectral layout's form whose number is no wavelength ("T.0Hz": a division by zero,
    "T.e5nm": no number) count as carrying none, and raise nothing else."""
    path = _write_exr(tmp_path / "cube.exr", frame(np.random.default_rng(1)), names)
    assert _stored_names(path) != names  # the writer's order is lost: what this is about
    for message in _refusals(path):
        assert _names_every(message, names), message
        assert "OpenEXR" in message and "sorted by name" in message, message


def test_exr_with_a_repeated_wavelength_is_refused(tmp_path):
    """Guards against a cube written with "400nm" twice: OpenImageIO writes the second as
    "channel1", and the file was read with it as the last band. Refused, naming the channels."""
    path = _write_exr(tmp_path / "cube.exr", frame(np.random.default_rng(2)), REPEATED_400)
    stored = _stored_names(path)
    assert "channel1" in stored and stored.count("400nm") == 1  # what OpenImageIO makes of it
    for message in _refusals(path):
        assert _names_every(message, stored), message
        assert 'OpenImageIO writes "channelN" in place of a repeated' in message, message


def test_exr_description_naming_other_channels_is_not_trusted(tmp_path):
    """Guards against a TIFF's channel-name JSON (write_frame's ImageDescription, which a
    converter such as oiiotool carries over) being taken for an OpenEXR's channel names: the
    names in the JSON are in written order, the channels in the file sorted by name."""
    description = json.dumps({"channel_names": NAMES, "attributes": {}})
    path = _write_exr(tmp_path / "cube.exr", frame(np.random.default_rng(3)), C_NAMES, description=description)
    for message in _refusals(path):
        assert _names_every(message, C_NAMES), message


def test_tiff_with_a_repeated_wavelength_is_refused(tmp_path):
    """Guards against a frame whose channel names give one wavelength twice: which of the two is
    which band cannot be told (it was read as stored without the calibration's bands, and
    refused only as "other bands" with them)."""
    path = tmp_path / "cube.tif"
    io.write_frame(path, frame(np.random.default_rng(4)), channel_names=REPEATED_400)
    for message in _refusals(path):
        assert "giving 400 nm twice (400nm, 400nm)" in message, message


def test_exr_wavelengths_other_than_the_calibrations_are_refused(tmp_path):
    """Guards against channels named in the spectral layout ("T.405nm") being read as stored
    whatever their wavelengths: they must be the calibration's bands."""
    names = [f"T.{nm + 5}nm" for nm in BANDS]
    path = _write_exr(tmp_path / "cube.exr", frame(np.random.default_rng(5)), names)
    with pytest.raises(io.SpherejaxFileError) as raised:
        io.open_cube(path, expected_shape=SHAPE, band_centres_nm=BANDS)
    message = str(raised.value)
    assert message.startswith(f"{path}: has bands 405..705 nm step 20 (16 bands)"), message
    assert "expected the calibration's bands, 400..700 nm step 20 (16 bands)" in message, message


def test_wavelength_named_layouts_read_in_band_order(tmp_path):
    """Guards the layouts that do map to bands: channels named "<nm>nm", "<nm> nm" or
    "T.<nm>nm", stored in any order (here, names whose sorted order is not the wavelengths'),
    are read in band order with or without the calibration's bands; a single-channel OpenEXR
    and a TIFF's channels in its stored order need no wavelengths."""
    bands = [850, 900, 950, 1000, 1050, 1100]
    cube = np.random.default_rng(6).uniform(0, 1, (4, 5, len(bands))).astype(np.float32)
    order = [3, 0, 5, 1, 4, 2]  # the order the channels are written in
    for style in ("{}nm", "{} nm", "T.{}nm"):
        path = _write_exr(tmp_path / "cube.exr", cube[..., order], [style.format(bands[i]) for i in order])
        for band_centres in (bands, None):
            read = io.read_cube(path, expected_shape=cube.shape, band_centres_nm=band_centres)
            np.testing.assert_array_equal(read, cube, err_msg=f"{style} {band_centres}")
            with io.open_cube(path, expected_shape=cube.shape, band_centres_nm=band_centres) as opened:
                np.testing.assert_array_equal(opened.read_rows(1, 3), cube[1:3], err_msg=f"{style} {band_centres}")
    one = _write_exr(tmp_path / "one.exr", cube[..., :1], ["Y"])
    np.testing.assert_array_equal(io.read_cube(one, expected_shape=(4, 5, 1)), cube[..., :1])
    counts = frame(np.random.default_rng(7))
    io.write_frame(tmp_path / "plain.tif", counts, channel_names=C_NAMES)  # TIFF keeps the order
    np.testing.assert_array_equal(io.read_cube(tmp_path / "plain.tif", expected_shape=SHAPE, band_centres_nm=BANDS), counts)


@pytest.mark.parametrize("names", [C_NAMES, B_NAMES, REPEATED_400], ids=["c0-c15", "B1-B16", "400nm-twice"])
def test_correct_reports_the_cube_failed_and_writes_nothing(cal, tmp_path, capsys, names):
    """Guards `spherejax correct -c CAL cube.exr -o OUT`: the cube is a failed input whose one
    line names it and its channels, exit status 1, and OUT holds no output of it."""
    path = _write_exr(tmp_path / "cube.exr", frame(np.random.default_rng(8)), names)
    status = cli.main(["-q", "correct", "-c", str(cal), str(path), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 1, err
    assert "Traceback" not in err, err
    [line] = [line for line in err.splitlines() if "cube.exr" in line]
    assert line.startswith(f"spherejax: failed cube.exr: {path}: has 16 channels "), line
    assert _names_every(line, _stored_names(path)), line
    assert _outputs(tmp_path / "out") == []
    [record] = manifest_records(tmp_path / "out")
    assert record["status"] == "failed" and "sorted by name" in record["reason"], record


def test_correct_corrects_the_well_named_cube_beside_the_refused_one(cal, tmp_path, capsys):
    """Guards the batch around a refused cube: in one folder, a cube named c0..c15 fails while
    a cube whose channels are "T.<nm>nm" (written in reverse) gives the outputs of the same
    counts as a plain 16-bit TIFF; exit status 1."""
    raw = frame(np.random.default_rng(9))
    (tmp_path / "in").mkdir()
    _write_exr(tmp_path / "in" / "bad.exr", raw, C_NAMES)
    _write_exr(tmp_path / "in" / "good.exr", raw[..., ::-1], [f"T.{nm}nm" for nm in BANDS[::-1]])
    (tmp_path / "ref").mkdir()
    io.write_frame(tmp_path / "ref" / "good.tif", raw, channel_names=NAMES)
    assert cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "ref"), "-o", str(tmp_path / "ref-out")]) == 0
    status = cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 1, err
    [line] = [line for line in err.splitlines() if "bad.exr" in line]
    assert _names_every(line, C_NAMES), line
    assert _outputs(tmp_path / "out") == sorted(f"in/good.{kind}" for kind in archive.OUTPUT_KINDS)
    for kind in archive.OUTPUT_KINDS:
        if kind.endswith("exr"):
            got = read_exr(tmp_path / "out" / "in" / f"good.{kind}")[0]
            want = read_exr(tmp_path / "ref-out" / "ref" / f"good.{kind}")[0]
            np.testing.assert_array_equal(got, want, err_msg=kind)
