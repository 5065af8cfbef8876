"""Band maps in calibration files (format version 7): stored under "band_transforms" as an array
and in the header with how they were estimated, read back bit for bit by every reader (h5py
too), crops and rows in their own coordinates; a version 6 file (no maps) opens as before, and
maps of the wrong shape, out of range or in a version 6 file are refused in one line."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

import spherejax as sj
from spherejax import band_resampling, io, stripwise
from spherejax.io import CalibrationFileError
from tests.helpers import calibration_entries, write_calibration_entries

H, W, B = 30, 40, 16
BANDS = list(range(400, 701, 20))


def maps(rng):
    out = np.zeros((B, 2, 3))
    out[:, 0, 0] = out[:, 1, 1] = 1.0 + rng.uniform(-5e-4, 5e-4, B)
    out[:, :, 2] = rng.uniform(-1.5, 1.5, (B, 2))
    return out


def calibration(rng, transforms=None):
    patch = np.zeros((H, W), bool)
    patch[12:18, 15:25] = True
    return sj.Calibration(
        dark=rng.uniform(90, 110, (H, W, B)).astype(np.float32),
        white=rng.uniform(9000, 11000, (H, W, B)).astype(np.float32), patch=patch,
        coeffs=sj.identity_coeffs(B), wiener=(rng.uniform(0, 1, (31, B)) / B).astype(np.float32),
        saturation=16383.0, band_transforms=transforms,
    )


RECORD = {"frame": "targets", "reference_band": 8, "reference_band_nm": 560, "residual_px": [0.1] * B}


@pytest.fixture
def saved(tmp_path):
    rng = np.random.default_rng(0)
    transforms = maps(rng)
    cal = calibration(rng, transforms)
    path = tmp_path / "cal.h5"
    io.save_calibration(path, cal, instrument_id="sphere", band_centres_nm=BANDS, band_registration=RECORD)
    return path, cal, transforms


def test_maps_are_stored_under_band_transforms_with_how_they_were_estimated(saved):
    path, cal, transforms = saved
    with h5py.File(path, "r") as stored:  # a reader that is not spherejax
        np.testing.assert_array_equal(stored["band_transforms"][()], np.asarray(cal.band_transforms))
        header = json.loads(stored.attrs["header"])
    assert header["format_version"] == 7
    record = header["band_registration"]
    assert {k: record[k] for k in RECORD} == RECORD
    np.testing.assert_array_equal(np.asarray(record["band_transforms"]), np.asarray(cal.band_transforms))
    loaded, _ = io.load_calibration(path)
    np.testing.assert_array_equal(np.asarray(loaded.band_transforms), np.asarray(cal.band_transforms))
    raw = np.random.default_rng(1).integers(2000, 9000, (H, W, B)).astype(np.uint16)
    np.testing.assert_array_equal(np.asarray(sj.correct(raw, loaded).reflectance), np.asarray(sj.correct(raw, cal).reflectance))


@pytest.mark.parametrize("in_memory", [True, False])
def test_strips_give_the_whole_frames_numbers(saved, tmp_path, monkeypatch, in_memory):
    """Strips read with the rows their registered pixels come from and p from the patch grown by
    the maps' reach, of a calibration held in memory and of one too large to hold
    (IN_MEMORY_BYTES made small, read by rows)."""
    path, cal, transforms = saved
    raw = np.random.default_rng(2).integers(2000, 9000, (H, W, B)).astype(np.uint16)
    whole = sj.correct(raw, cal)
    io.write_frame(tmp_path / "raw.tif", raw)
    if not in_memory:
        monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 1)
    with io.open_calibration(path) as opened, io.open_cube(tmp_path / "raw.tif", expected_shape=raw.shape) as cube:
        assert opened.in_memory == in_memory
        assert opened.patch_read_box == band_resampling.read_box(opened.patch_box, transforms, (H, W))
        strips = dict(stripwise.correct_strips(cube, opened, rows_per_strip=8))
    reflectance = np.concatenate([strips[r]["reflectance"] for r in sorted(strips)])
    quality = np.concatenate([strips[r]["quality"] for r in sorted(strips)])
    np.testing.assert_array_equal(quality, np.asarray(whole.quality))
    np.testing.assert_allclose(reflectance, np.asarray(whole.reflectance), rtol=1e-5, atol=1e-6)


def test_a_version_6_file_opens_as_before(saved, tmp_path):
    """A file without maps, of the format version before them, opens with none and corrects as a
    calibration without maps does."""
    path, cal, _ = saved
    entries = calibration_entries(path)
    del entries["band_transforms"]
    header = json.loads(entries["header"].tobytes())
    header["format_version"] = 6
    del header["band_registration"]
    del header["arrays"]["band_transforms"]
    arrays = {k: v for k, v in entries.items() if k != "header"}
    header["checksum"] = io.calibration_files._checksum(header, arrays)
    entries["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    old = tmp_path / "v6.h5"
    write_calibration_entries(old, entries)
    loaded, _ = io.load_calibration(old)
    assert loaded.band_transforms is None


def rewritten(path, tmp_path, change):
    entries = calibration_entries(path)
    header = json.loads(entries["header"].tobytes())
    change(entries, header)
    arrays = {k: v for k, v in entries.items() if k != "header"}
    header["arrays"]["band_transforms"]["shape"] = list(entries["band_transforms"].shape)
    header["checksum"] = io.calibration_files._checksum(header, arrays)
    entries["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    out = tmp_path / "changed.h5"
    write_calibration_entries(out, entries)
    return out


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda e, h: e.update(band_transforms=e["band_transforms"][:, :, :2].copy()),
         r"array 'band_transforms' has shape \[16, 2, 2\] \(expected one 2 x 3 affine map per band: \[16, 2, 3\]\)"),
        (lambda e, h: e["band_transforms"].__setitem__((3, 0, 2), 400.0),
         r"band_transforms: a band is displaced by 4\d\d px in the frame, expected at most 50 px"),
        (lambda e, h: h.update(format_version=6),
         r"header has unknown fields \['band_registration'\]"),
        (lambda e, h: (h.update(format_version=6), h.pop("band_registration")),
         r"header\.arrays has unknown fields \['band_transforms'\]"),
    ],
)
def test_bad_maps_in_a_file_are_refused_in_one_line(saved, tmp_path, change, message):
    path, _, _ = saved
    bad = rewritten(path, tmp_path, change)
    with pytest.raises(CalibrationFileError, match=message) as raised:
        io.load_calibration(bad)
    assert "\n" not in str(raised.value) and str(bad) in str(raised.value)


def test_a_calibration_without_maps_stores_none(tmp_path):
    cal = calibration(np.random.default_rng(3))
    path = tmp_path / "plain.h5"
    header = io.save_calibration(path, cal, instrument_id="sphere", band_centres_nm=BANDS)
    assert "band_registration" not in header
    with h5py.File(path, "r") as stored:
        assert "band_transforms" not in stored
    assert io.load_calibration(path)[0].band_transforms is None
