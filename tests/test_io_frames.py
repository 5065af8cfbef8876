"""spherejax.io.frames: camera frames (16-bit TIFF), round trips, and every refusal.

Each refusal checks the exception type, that the message is one line starting with the file it
names, the problem (`match=`), and that nothing new or partial is left on disk.
"""

import os

import numpy as np
import pytest

from spherejax import io
from spherejax.io import SpherejaxFileError
from tests.helpers import listing, refused, write_with_oiio

H, W = 12, 10
BANDS = list(range(400, 701, 20))
B = len(BANDS)


# --------------------------------------------------------------------------------------- helpers


def counts(rng, shape=(H, W, B)) -> np.ndarray:
    return rng.integers(0, 65536, shape, dtype=np.uint16)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


# ---------------------------------------------------------------------------------------- frames


@pytest.mark.parametrize("channels", [1, 3, 4, 16])
def test_frame_round_trip(tmp_path, rng, channels):
    array = counts(rng, (H, W, channels))
    array[0, 0] = 65535  # full scale survives
    array[..., min(3, channels - 1)] = 0  # a zero fourth channel is not taken for alpha
    names = [f"{400 + 20 * i}nm" for i in range(channels)]
    path = tmp_path / "frame.tif"
    io.write_frame(path, array, channel_names=names, attributes={"role": "dark", "Artist": "lab"})
    out = io.read_frame(path, expected_shape=(H, W, channels))
    assert out.dtype == np.uint16 and out.shape == (H, W, channels)
    np.testing.assert_array_equal(out, array)
    assert io.frame_spec(path) == (H, W, channels)
    assert io.read_frame_metadata(path) == {
        "channel_names": names,
        "attributes": {"role": "dark", "Artist": "lab"},
    }
    assert listing(tmp_path) == ["frame.tif"]


def test_write_frame_replaces_an_existing_file(tmp_path, rng):
    path = tmp_path / "frame.tif"
    io.write_frame(path, counts(rng))
    second = counts(rng, (H, W, 2))
    io.write_frame(path, second)
    np.testing.assert_array_equal(io.read_frame(path), second)
    assert listing(tmp_path) == ["frame.tif"]


@pytest.mark.parametrize(
    "array",
    [
        np.zeros((H, W), np.uint16),
        np.zeros((H, W, B), np.float32),
        np.zeros((H, W, B), np.int32),
        np.zeros((0, W, B), np.uint16),
    ],
    ids=["2d", "float32", "int32", "empty"],
)
def test_write_frame_refuses_arrays(tmp_path, array):
    path = tmp_path / "frame.tif"
    with refused(SpherejaxFileError, path, "cannot hold an array of shape"):
        io.write_frame(path, array)
    assert listing(tmp_path) == []


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"channel_names": ["400nm"]}, "channel_names is"),
        ({"attributes": {"exposure": 0.1}}, "attribute \"exposure\" is 0.1"),
        ({"attributes": {"ImageDescription": "x"}}, "is reserved"),
    ],
)
def test_write_frame_refuses_names_and_attributes(tmp_path, rng, kwargs, match):
    path = tmp_path / "frame.tif"
    with refused(SpherejaxFileError, path, match):
        io.write_frame(path, counts(rng, (H, W, 2)), **kwargs)
    assert listing(tmp_path) == []


def test_write_frame_failure_leaves_the_old_file_and_no_temporary(tmp_path, rng, monkeypatch):
    path = tmp_path / "frame.tif"
    old = counts(rng)
    io.write_frame(path, old)

    def fail(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fail)
    match = "could not be written: .*No space left"
    with refused(SpherejaxFileError, path, match, says_expected=False):
        io.write_frame(path, counts(rng))
    assert listing(tmp_path) == ["frame.tif"]
    np.testing.assert_array_equal(io.read_frame(path), old)


def test_write_frame_into_a_missing_folder(tmp_path, rng):
    path = tmp_path / "missing" / "frame.tif"
    with refused(SpherejaxFileError, path, "cannot be written: no such folder"):
        io.write_frame(path, counts(rng))
    assert listing(tmp_path) == []


def test_read_frame_missing_file(tmp_path):
    path = tmp_path / "nope.tif"
    with refused(SpherejaxFileError, path, "no such file"):
        io.read_frame(path)
    with refused(SpherejaxFileError, path, "no such file"):
        io.frame_spec(path)


def test_read_frame_text_file_named_tif(tmp_path):
    path = tmp_path / "notes.tif"
    path.write_text("exposure 10 ms, lamp warm\n")
    with refused(SpherejaxFileError, path, "is not a readable image: .*(TIFF|magic)"):
        io.read_frame(path)


def test_read_frame_truncated_tiff(tmp_path, rng):
    path = tmp_path / "frame.tif"
    io.write_frame(path, counts(rng))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with refused(SpherejaxFileError, path, "is truncated or corrupted|is not a readable image"):
        io.read_frame(path)


def test_read_frame_corrupt_pixel_data_and_header_only_spec(tmp_path, rng):
    path = tmp_path / "frame.tif"
    io.write_frame(path, counts(rng))
    data = bytearray(path.read_bytes())
    middle = len(data) // 2  # past the header, inside the deflate stream
    data[middle : middle + 64] = bytes(range(64))
    path.write_bytes(bytes(data))
    # The header is intact, and frame_spec reads nothing else.
    assert io.frame_spec(path) == (H, W, B)
    with refused(SpherejaxFileError, path, "is (truncated or )?corrupted: rows 0 to 11 of its 12 cannot be decoded"):
        io.read_frame(path)


def test_read_frame_wrong_size(tmp_path, rng):
    path = tmp_path / "frame.tif"
    io.write_frame(path, counts(rng, (H, W + 1, B)))
    with refused(SpherejaxFileError, path, f"is {H} x {W + 1} pixels .*{H} x {W} pixels"):
        io.read_frame(path, expected_shape=(H, W, B))


def test_read_frame_wrong_channel_count(tmp_path, rng):
    path = tmp_path / "frame.tif"
    io.write_frame(path, counts(rng, (H, W, 3)))
    with refused(SpherejaxFileError, path, f"has 3 channels .*{B} channels"):
        io.read_frame(path, expected_shape=(H, W, B))


def test_read_frame_refuses_8_bit(tmp_path):
    path = tmp_path / "frame.tif"
    write_with_oiio(path, [np.zeros((H, W, 3), np.uint8)])
    with refused(SpherejaxFileError, path, "has uint8 samples of 8 bits .*16-bit"):
        io.read_frame(path)


def test_read_frame_refuses_several_pages(tmp_path):
    path = tmp_path / "frame.tif"
    write_with_oiio(path, [np.zeros((H, W, 1), np.uint16), np.ones((H, W, 1), np.uint16)])
    with refused(SpherejaxFileError, path, "more than one image"):
        io.frame_spec(path)
