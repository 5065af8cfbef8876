"""spherejax.io.calibration_files: calibration files (HDF5, older .npz), round trips, and every
refusal.

Each refusal checks the exception type, that the message is one line starting with the file it
names, the problem (`match=`), and that nothing new or partial is left on disk.
"""

import dataclasses
import datetime
import hashlib
import json
import os
import pathlib
import pickle
import re
import zipfile

import h5py
import hypothesis
import hypothesis.strategies as st
import numpy as np
import pytest

import spherejax as sj
from spherejax import io
from spherejax.io import CalibrationFileError
from tests.helpers import (
    calibration_entries,
    listing,
    refused,
    write_calibration_entries,
)

H, W = 12, 10
BANDS = list(range(400, 701, 20))
B = len(BANDS)

#: The kernel residual's arrays, format version 5 on (`io.calibration_checks.RESIDUAL_ARRAYS`, written out).
RESIDUAL = ("wiener_residual_centre", "wiener_residual_whitening", "wiener_residual_inducing", "wiener_residual_weights")


# --------------------------------------------------------------------------------------- helpers


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def make_calibration(rng, dtype=np.float32, saturation=16383, illuminant="A"):
    patch = np.zeros((H, W), dtype=bool)
    patch[0:2, 8:10] = True
    return sj.Calibration(
        dark=rng.uniform(50, 60, (H, W, B)).astype(dtype),
        white=rng.uniform(9000, 12000, (H, W, B)).astype(dtype),
        patch=patch,
        coeffs=rng.normal(size=(B, 4)).astype(dtype),
        wiener=rng.normal(size=(31, B)).astype(dtype),
        illuminant=illuminant,
        saturation=saturation,
        wiener_offset=rng.normal(scale=0.05, size=31).astype(dtype),
    )


@pytest.fixture
def calibration_path(tmp_path, rng):
    path = tmp_path / "cal.h5"
    io.save_calibration(
        path, make_calibration(rng), instrument_id="sim-sphere-1", band_centres_nm=BANDS
    )
    return path


def header_of(entries) -> dict:
    return json.loads(entries["header"].tobytes().decode("utf-8"))


def rewrite_file(path, entries, header=None, *, recompute_checksum=False, container=None):
    """Write `entries` back to `path` (`write_calibration_entries`: HDF5, or an .npz for a header
    of format version 1 to 3), the header replaced if given."""
    entries = dict(entries)
    if header is not None:
        if recompute_checksum:
            arrays = {k: v for k, v in entries.items() if k != "header"}
            header = {**header, "checksum": io.calibration_files._checksum(header, arrays)}
        entries["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    write_calibration_entries(path, entries, container)


# ----------------------------------------------------------------------------- calibration files


@pytest.mark.parametrize("saturation", [16383, 16000.5, None])
def test_calibration_round_trip(tmp_path, rng, dtype, saturation):
    calibration = make_calibration(rng, dtype, saturation)
    path = tmp_path / "cal.h5"
    metadata = {"stage2_loss": "huber", "training_frames": ["a", "b"], "sigma2": 1e-4}
    written = io.save_calibration(
        path,
        calibration,
        instrument_id="sim-sphere-1",
        band_centres_nm=np.asarray(BANDS),
        metadata=metadata,
    )
    assert listing(tmp_path) == ["cal.h5"]

    loaded, header = io.load_calibration(path, band_centres_nm=BANDS)
    assert header == written
    for name in ("dark", "white", "patch", "coeffs", "wiener", "wiener_offset"):
        original, out = np.asarray(getattr(calibration, name)), np.asarray(getattr(loaded, name))
        assert out.dtype == original.dtype and out.shape == original.shape
        assert out.tobytes() == original.tobytes(), name  # bit for bit
    assert loaded.illuminant == "A" and loaded.observer == calibration.observer
    assert loaded.saturation == saturation and type(loaded.saturation) is type(saturation)

    assert header["format"] == "spherejax-calibration" and header["format_version"] == 7
    assert header["noise_model"] is None  # none given (tests/test_noise_model_files.py: one given)
    assert header["software_version"] == sj.__version__
    assert header["instrument_id"] == "sim-sphere-1" and header["band_centres_nm"] == BANDS
    assert (header["illuminant"], header["saturation"]) == ("A", saturation)
    assert header["metadata"] == metadata
    created = datetime.datetime.fromisoformat(header["created"])
    assert created.utcoffset() == datetime.timedelta(0)
    assert re.fullmatch("sha256:[0-9a-f]{64}", header["checksum"])
    assert header["arrays"]["dark"]["shape"] == [H, W, B]
    assert header["arrays"]["patch"]["dtype"] == "|b1"
    assert header["arrays"]["coeffs"]["dtype"] == np.dtype(dtype).str
    assert header["arrays"]["wiener_offset"]["shape"] == [31]
    assert header["arrays"]["wiener_offset"]["dtype"] == np.dtype(dtype).str
    assert "r0" in header["arrays"]["wiener_offset"]["description"]
    # An affine estimator: a kernel residual of m = 0 inducing points (format version 5 on), no variance arrays.
    assert [header["arrays"][name]["shape"] for name in RESIDUAL] == [[B], [B, B], [0, B], [31, 0]]
    assert loaded.wiener_residual is None
    for name, entry in header["arrays"].items():
        assert re.search(r"Eq\.|Section|E\d", entry["description"]), name

    # Self-describing without spherejax: h5py alone reads the header and the arrays.
    with h5py.File(path, "r") as stored:
        assert json.loads(stored.attrs["header"]) == header
        assert list(stored.attrs) == ["header"]
        assert sorted(stored) == sorted(["coeffs", "dark", "patch", "white", "wiener", "wiener_offset", *RESIDUAL])
        for name, dataset in stored.items():
            assert dataset.attrs["description"] == header["arrays"][name]["description"], name
            if name in RESIDUAL:
                assert not dataset[()].any() and dataset[()].dtype == np.dtype(dtype), name
                continue
            original = np.asarray(getattr(calibration, name))
            assert dataset[()].dtype == original.dtype and dataset[()].tobytes() == original.tobytes(), name
            assert dataset.compression is None, name
            # The frames chunked by whole rows (full width, every band), the rest contiguous.
            chunks = dataset.chunks
            assert (chunks is not None and chunks[1:] == dataset.shape[1:]) == (name in ("dark", "white", "patch")), name


def test_calibration_loads_without_band_check(calibration_path):
    calibration, _ = io.load_calibration(calibration_path)
    assert calibration.bands == B


def test_save_calibration_replaces_atomically(calibration_path, rng, monkeypatch):
    before = calibration_path.read_bytes()

    def fail(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fail)
    match = "could not be written: .*No space left"
    with refused(CalibrationFileError, calibration_path, match, says_expected=False):
        io.save_calibration(
            calibration_path, make_calibration(rng), instrument_id="x", band_centres_nm=BANDS
        )
    assert listing(calibration_path.parent) == ["cal.h5"]
    assert calibration_path.read_bytes() == before


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"calibration": "not one"}, "cannot hold a str .*a spherejax.Calibration"),
        ({"band_centres_nm": BANDS[:-1]}, f"lists {B - 1} bands, the dark frame has shape"),
        ({"band_centres_nm": [float(b) for b in BANDS]}, r"header\.band_centres_nm is \[400\.0"),
        ({"instrument_id": ""}, r'header\.instrument_id is ""'),
        ({"metadata": {"sigma2": float("nan")}}, "the header cannot be stored as JSON"),
    ],
)
def test_save_calibration_refuses(tmp_path, rng, kwargs, match):
    path = tmp_path / "cal.h5"
    arguments = {
        "calibration": make_calibration(rng),
        "instrument_id": "sim-sphere-1",
        "band_centres_nm": BANDS,
        **kwargs,
    }
    with refused(CalibrationFileError, path, match):
        io.save_calibration(path, arguments.pop("calibration"), **arguments)
    assert listing(tmp_path) == []


def test_save_calibration_refuses_patch_weights(tmp_path, rng):
    """A Calibration may hold floating patch weights (for differentiable studies); the file
    format stores a boolean mask only."""
    mask = make_calibration(rng)
    weighted = sj.Calibration(
        dark=mask.dark, white=mask.white, patch=np.asarray(mask.patch, np.float32),
        coeffs=mask.coeffs, wiener=mask.wiener, illuminant=mask.illuminant,
        saturation=mask.saturation,
    )
    path = tmp_path / "cal.h5"
    with refused(CalibrationFileError, path, "array 'patch' has dtype <f4: patch weights cannot be stored"):
        io.save_calibration(path, weighted, instrument_id="sim-sphere-1", band_centres_nm=BANDS)
    assert listing(tmp_path) == []


def test_load_calibration_refuses_patch_weights(calibration_path):
    # A consistent file (header and checksum agree) holding weights instead of a mask.
    entries = calibration_entries(calibration_path)
    entries["patch"] = entries["patch"].astype(np.float32)
    header = header_of(entries)
    header["arrays"]["patch"]["dtype"] = "<f4"
    rewrite_file(calibration_path, entries, header, recompute_checksum=True)
    with refused(CalibrationFileError, calibration_path, r"array 'patch' has dtype <f4.*\(expected a boolean patch mask"):
        io.load_calibration(calibration_path)


def test_load_calibration_missing_file(tmp_path):
    path = tmp_path / "cal.h5"
    with refused(CalibrationFileError, path, "no such file"):
        io.load_calibration(path)


@pytest.mark.parametrize(
    "write",
    [lambda file: file.write(b"dark=...\n"), lambda file: np.save(file, np.zeros(3)), lambda file: file.write(b"\x89HD")],
    ids=["text-line", "npy", "hdf5-signature-cut"],
)
@pytest.mark.parametrize("name", ["cal.h5", "cal.npz", "cal"])
def test_load_calibration_neither_hdf5_nor_npz(tmp_path, write, name):
    path = tmp_path / name
    with open(path, "wb") as file:
        write(file)
    with refused(CalibrationFileError, path, r"is neither HDF5 nor an \.npz \(zip\) archive: it starts with b'"):
        io.load_calibration(path)


def test_load_calibration_empty_file(tmp_path):
    path = tmp_path / "cal.h5"
    path.write_bytes(b"")
    with refused(CalibrationFileError, path, r"is empty \(expected a spherejax calibration file \(HDF5"):
        io.load_calibration(path)


@pytest.mark.parametrize("keep", [0.99, 0.5, 0.01])
def test_load_calibration_truncated(calibration_path, keep):
    data = calibration_path.read_bytes()
    calibration_path.write_bytes(data[: int(len(data) * keep)])
    with refused(CalibrationFileError, calibration_path, r"is truncated: it holds \d+ of the \d+ bytes its HDF5 superblock records"):
        io.load_calibration(calibration_path)


def test_load_calibration_damaged_superblock(calibration_path):
    data = bytearray(calibration_path.read_bytes())
    data[8:40] = b"\xff" * 32  # after the signature: versions, sizes and addresses of the superblock
    calibration_path.write_bytes(bytes(data))
    with refused(CalibrationFileError, calibration_path, "is truncated or corrupted: HDF5 cannot read the superblock at its start"):
        io.load_calibration(calibration_path)


def test_load_calibration_corrupted_bytes(calibration_path):
    data = bytearray(calibration_path.read_bytes())
    middle = len(data) // 3  # inside the stored dark frame: only the checksum tells
    data[middle : middle + 8] = bytes(8)
    calibration_path.write_bytes(bytes(data))
    with refused(CalibrationFileError, calibration_path, "does not match its checksum: tampered or corrupted"):
        io.load_calibration(calibration_path)


def test_load_calibration_tampered_array(calibration_path):
    entries = calibration_entries(calibration_path)
    entries["coeffs"] = entries["coeffs"].copy()
    entries["coeffs"][3, 1] += 0.5
    rewrite_file(calibration_path, entries)  # the old header and checksum
    match = "does not match its checksum: tampered or corrupted"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


def test_load_calibration_tampered_header(calibration_path):
    entries = calibration_entries(calibration_path)
    header = header_of(entries)
    header["illuminant"] = "D65"
    rewrite_file(calibration_path, entries, header)
    with refused(CalibrationFileError, calibration_path, "tampered or corrupted"):
        io.load_calibration(calibration_path)


@pytest.mark.parametrize("missing", ["wiener", "patch", "wiener_offset"])
def test_load_calibration_missing_array(calibration_path, missing):
    entries = calibration_entries(calibration_path)
    del entries[missing]
    rewrite_file(calibration_path, entries)
    with refused(CalibrationFileError, calibration_path, rf"has no array \['{missing}'\]"):
        io.load_calibration(calibration_path)


def test_load_calibration_missing_header(calibration_path):
    entries = calibration_entries(calibration_path)
    del entries["header"]
    rewrite_file(calibration_path, entries)
    with refused(CalibrationFileError, calibration_path, "has no header"):
        io.load_calibration(calibration_path)


def test_load_calibration_header_not_json(calibration_path):
    entries = calibration_entries(calibration_path)
    entries["header"] = np.frombuffer(b"\xff\xfe{", dtype=np.uint8)
    rewrite_file(calibration_path, entries)
    with refused(CalibrationFileError, calibration_path, "has a header that is not UTF-8 JSON"):
        io.load_calibration(calibration_path)


def test_load_calibration_unexpected_entry(calibration_path):
    entries = calibration_entries(calibration_path)
    entries["extra"] = np.zeros(2)
    rewrite_file(calibration_path, entries)
    with refused(CalibrationFileError, calibration_path, r"holds unexpected entries \['extra'\]"):
        io.load_calibration(calibration_path)


def test_load_calibration_zip_member_that_is_not_an_array(tmp_path, rng):
    path = tmp_path / "v3.npz"
    write_older(path, make_calibration(rng), 3)
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("notes.txt", "written by hand")
    with refused(CalibrationFileError, path, r"not \.npy arrays: \['notes\.txt'\]"):
        io.load_calibration(path)


def _group(stored):
    stored.create_group("notes")


def _soft_link(stored):
    stored["notes"] = h5py.SoftLink("/coeffs")


def _external_link(stored):
    stored["notes"] = h5py.ExternalLink("elsewhere.h5", "/dark")


@pytest.mark.parametrize(
    "add, match",
    [(_group, "entry 'notes' is a Group"), (_soft_link, "entry 'notes' is a SoftLink"),
     (_external_link, "entry 'notes' is a ExternalLink")],
    ids=["group", "soft-link", "external-link"],
)
def test_load_calibration_entry_that_is_not_a_dataset(calibration_path, add, match):
    """Only datasets stored in the file: a link (an external one reads another file) or group is refused."""
    with h5py.File(calibration_path, "a") as stored:
        add(stored)
    with refused(CalibrationFileError, calibration_path, rf"{match} \(expected a dataset"):
        io.load_calibration(calibration_path)


def test_load_calibration_compressed_dataset(calibration_path):
    entries = calibration_entries(calibration_path)
    with h5py.File(calibration_path, "a") as stored:
        del stored["white"]
        stored.create_dataset("white", data=entries["white"], chunks=(1, W, B), compression="gzip")
    match = r"dataset 'white' is stored virtual, external or filtered \(compressed\)"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


def test_load_calibration_dataset_with_chunks_never_written(calibration_path):
    """A chunk never written reads as zeros, and such a file can claim any size: refused before any read."""
    with h5py.File(calibration_path, "a") as stored:
        del stored["dark"]
        stored.create_dataset("dark", shape=(H, W, B), dtype="<f4", chunks=(1, W, B))[:2] = 1.0
    match = rf"dataset 'dark' of shape \[{H}, {W}, {B}\] holds {2 * W * B * 4} of its {H * W * B * 4} bytes"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


@pytest.mark.parametrize(
    "value, match",
    [(np.arange(3), r"has a header attribute of ndarray \[0, 1, 2\]"),
     (np.int64(7), "has a header attribute of int64 7")],
    ids=["array", "number"],
)
def test_load_calibration_header_attribute_not_a_string(calibration_path, value, match):
    with h5py.File(calibration_path, "a") as stored:
        stored.attrs["header"] = value
    with refused(CalibrationFileError, calibration_path, rf"{match} \(expected a \"header\" attribute: a string of UTF-8 JSON"):
        io.load_calibration(calibration_path)


def test_load_calibration_header_as_fixed_length_bytes(calibration_path):
    """A header that another writer stored as fixed-length bytes rather than a string reads the same."""
    _, header = io.load_calibration(calibration_path)
    with h5py.File(calibration_path, "a") as stored:
        stored.attrs["header"] = np.bytes_(stored.attrs["header"].encode("utf-8"))
    assert io.load_calibration(calibration_path)[1] == header


def test_load_calibration_dataset_of_the_wrong_dtype(calibration_path):
    entries = calibration_entries(calibration_path)
    entries["wiener"] = entries["wiener"].astype(np.float64)
    rewrite_file(calibration_path, entries)
    match = r"array 'wiener' has shape \[31, 16\] and dtype <f8, the header says \[31, 16\] and <f4"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


def test_load_calibration_version_in_the_other_container(calibration_path, tmp_path):
    """Format versions 4 on are HDF5, versions 1 to 3 an .npz: either in the other is refused."""
    entries = calibration_entries(calibration_path)
    rewrite_file(tmp_path / "v7.npz", entries, container="npz")
    with refused(CalibrationFileError, tmp_path / "v7.npz", r"is an \.npz archive of format version 7 \(expected HDF5 from"):
        io.load_calibration(tmp_path / "v7.npz")
    entries = {k: v for k, v in entries.items() if k not in RESIDUAL}
    header = {**header_of(calibration_entries(calibration_path)), "format_version": 3}
    header["arrays"] = {k: v for k, v in header["arrays"].items() if k not in RESIDUAL}
    rewrite_file(tmp_path / "v3.h5", entries, header, recompute_checksum=True, container="hdf5")
    with refused(CalibrationFileError, tmp_path / "v3.h5", r"is HDF5 of format version 3 \(expected HDF5 from format version 4 on"):
        io.load_calibration(tmp_path / "v3.h5")


def test_load_calibration_wrong_format(calibration_path):
    entries = calibration_entries(calibration_path)
    rewrite_file(calibration_path, entries, {**header_of(entries), "format": "spherejax-session"})
    match = 'is not a spherejax-calibration file: format is "spherejax-session"'
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


def test_load_calibration_newer_version(calibration_path):
    entries = calibration_entries(calibration_path)
    header = {**header_of(entries), "format_version": 8, "new_field": "whatever a newer one adds"}
    rewrite_file(calibration_path, entries, header)
    match = (
        "is spherejax-calibration format version 8, newer than spherejax 0.1.0 reads "
        r"\(expected format version 7 or older; upgrade spherejax"
    )
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


def written_checksum(header: dict, entries: dict) -> str:
    """The checksum as the io module docstring specifies it, written out here (not taken from io)
    so that a change of io's checksum shows: SHA-256 of the canonical header JSON without the
    checksum, then, for dark, white, patch, coeffs, wiener, wiener_offset (none in format
    version 1) and the four arrays of the kernel residual (format version 5 on), the line
    "<name> <dtype.str> <shape>\\n" and the array's bytes in C order."""
    digest = hashlib.sha256(json.dumps(
        {k: v for k, v in header.items() if k != "checksum"},
        sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False,
    ).encode("utf-8"))
    names = ("dark", "white", "patch", "coeffs", "wiener", "wiener_offset", *RESIDUAL)
    version = header["format_version"]
    for name in names[:5] if version == 1 else names[:6] if version < 5 else names:
        array = entries[name]
        digest.update(f"{name} {array.dtype.str} {json.dumps(list(array.shape))}\n".encode("ascii"))
        digest.update(np.ascontiguousarray(array).tobytes())
    return "sha256:" + digest.hexdigest()


def write_older(path, calibration: sj.Calibration, version: int) -> dict:
    """`calibration` written as the writer of format `version` (1 to 3) did: an .npz (np.savez)
    of the arrays and the header, a uint8 array of UTF-8 JSON; no "noise_model" before version
    3, no wiener_offset in version 1; its checksum. Returns the header."""
    header = io.save_calibration(path, calibration, instrument_id="sim-sphere-1", band_centres_nm=BANDS)
    entries = calibration_entries(path)
    header = {k: v for k, v in header.items() if k != "checksum" and (version >= 3 or k != "noise_model")}
    header["format_version"] = version
    dropped = (*RESIDUAL, "wiener_offset") if version == 1 else RESIDUAL  # the kernel residual: version 5 on
    entries = {k: v for k, v in entries.items() if k not in dropped}
    header["arrays"] = {k: v for k, v in header["arrays"].items() if k not in dropped}
    header["checksum"] = written_checksum(header, entries)
    entries["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    with open(path, "wb") as file:  # np.savez(path) would add .npz to another name
        np.savez(file, **entries)
    assert zipfile.is_zipfile(path) and path.read_bytes()[:4] == b"PK\x03\x04"
    return header


def test_calibration_of_format_version_1_opens_with_a_zero_offset(tmp_path, rng, monkeypatch):
    calibration = make_calibration(rng)
    assert np.abs(np.asarray(calibration.wiener_offset)).max() > 0
    path = tmp_path / "old.npz"
    written = write_older(path, calibration, 1)
    assert sorted(calibration_entries(path)) == ["coeffs", "dark", "header", "patch", "white", "wiener"]
    loaded, header = io.load_calibration(path, band_centres_nm=BANDS)
    assert header == written and header["format_version"] == 1
    offset = np.asarray(loaded.wiener_offset)
    assert offset.shape == (31,) and not offset.any()
    for name in ("dark", "white", "patch", "coeffs", "wiener"):
        assert np.asarray(getattr(loaded, name)).tobytes() == np.asarray(getattr(calibration, name)).tobytes()
    # Read by rows (a large file) and cropped to the patch: the same zero offset.
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)
    with io.open_calibration(path) as opened:
        for part in (opened.rows(2, 7), opened.patch_calibration, opened.calibration()):
            assert part.wiener_offset.shape == (31,) and not np.asarray(part.wiener_offset).any()


def test_calibration_offset_survives_rows_and_crops(calibration_path, monkeypatch):
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)
    loaded, _ = io.load_calibration(calibration_path)
    assert np.abs(np.asarray(loaded.wiener_offset)).max() > 0
    with io.open_calibration(calibration_path) as opened:
        for part in (opened.rows(2, 7), opened.patch_calibration):
            assert np.asarray(part.wiener_offset).tobytes() == np.asarray(loaded.wiener_offset).tobytes()


def test_calibration_checksum_covers_the_offset(calibration_path):
    entries = calibration_entries(calibration_path)
    entries["wiener_offset"] = entries["wiener_offset"].copy()
    entries["wiener_offset"][17] += 0.01
    rewrite_file(calibration_path, entries)
    with refused(CalibrationFileError, calibration_path, "does not match its checksum: tampered or corrupted"):
        io.load_calibration(calibration_path)


def test_calibration_version_1_with_an_offset_is_refused(tmp_path, rng):
    """A version 1 file has no offset: one found there is not what its writer wrote."""
    path = tmp_path / "old.npz"
    header = write_older(path, make_calibration(rng), 1)
    entries = calibration_entries(path)
    entries["wiener_offset"] = np.zeros(31, np.float32)
    rewrite_file(path, entries, header)
    match = r"holds unexpected entries \['wiener_offset'\] \(expected only .* \(format version 1\)\)"
    with refused(CalibrationFileError, path, match):
        io.load_calibration(path)


def test_calibration_version_2_without_an_offset_is_refused(calibration_path):
    entries = calibration_entries(calibration_path)
    del entries["wiener_offset"]
    header = header_of(entries)
    del header["arrays"]["wiener_offset"]
    rewrite_file(calibration_path, entries, header)  # refused before the checksum is looked at
    match = r"header\.arrays\.wiener_offset is missing"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


@pytest.mark.parametrize("shape", [(30,), (31, 1)])
def test_calibration_offset_of_the_wrong_shape_is_refused(calibration_path, shape):
    entries = calibration_entries(calibration_path)
    entries["wiener_offset"] = np.zeros(shape, np.float32)
    header = header_of(entries)
    header["arrays"]["wiener_offset"]["shape"] = list(shape)
    header["arrays"]["wiener_offset"]["dtype"] = "<f4"
    rewrite_file(calibration_path, entries, header, recompute_checksum=True)
    match = rf"does not hold a valid calibration: wiener_offset: expected shape \(31,\).*got {re.escape(str(shape))}"
    with refused(CalibrationFileError, calibration_path, match, says_expected=False):
        io.load_calibration(calibration_path)


def test_load_calibration_mistyped_header_field(calibration_path):
    entries = calibration_entries(calibration_path)
    rewrite_file(calibration_path, entries, {**header_of(entries), "saturation": "high"})
    match = r'header\.saturation is "high" \(expected a number > 0 or null'
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


def test_load_calibration_array_disagrees_with_header(calibration_path):
    entries = calibration_entries(calibration_path)
    entries["coeffs"] = entries["coeffs"][:, :3].copy()
    rewrite_file(calibration_path, entries)
    match = rf"array 'coeffs' has shape \[{B}, 3\] .*the header says \[{B}, 4\]"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)


def test_load_calibration_other_bands(calibration_path):
    other = list(range(410, 711, 20))
    match = "was built for bands 400..700 nm step 20 \\(16 bands\\), the session has 410..710 nm"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path, band_centres_nm=other)
    match = r"the session has 400..680 nm step 20 \(15 bands\)"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path, band_centres_nm=BANDS[:-1])


@pytest.mark.parametrize(
    "spoil, match",
    [
        (
            lambda entries, header: entries.update(patch=np.zeros((H, W), bool)),
            "patch: the mask selects no pixel",
        ),
        (lambda entries, header: header.update(illuminant="D50"), "unknown illuminant 'D50'"),
    ],
    ids=["empty-patch", "unknown-illuminant"],
)
def test_load_calibration_invalid_calibration(calibration_path, spoil, match):
    # A consistent file (checksum recomputed) whose contents Calibration itself refuses.
    entries = calibration_entries(calibration_path)
    header = header_of(entries)
    spoil(entries, header)
    rewrite_file(calibration_path, entries, header, recompute_checksum=True)
    # Calibration's own message says what it expected.
    match = f"does not hold a valid calibration: .*{match}"
    with refused(CalibrationFileError, calibration_path, match, says_expected=False):
        io.load_calibration(calibration_path)


# ------------------------------------------------ calibration files: HDF5, by rows, older .npz


def test_calibration_checksum_is_reproducible_from_the_datasets(calibration_path):
    """Other software can verify a file with h5py and hashlib alone (io module docstring)."""
    with h5py.File(calibration_path, "r") as stored:
        header = json.loads(stored.attrs["header"])
        datasets = {name: stored[name][()] for name in stored}
    assert written_checksum(header, datasets) == header["checksum"]


@pytest.fixture(scope="module")
def tall_calibration(tmp_path_factory):
    """(path, calibration) of a file whose frames span 15 chunks: 100 rows of 64 x 16 float64."""
    rng = np.random.default_rng(7)
    patch = np.zeros((100, 64), bool)
    patch[40:45, 10:20] = True
    calibration = sj.Calibration(
        dark=rng.uniform(50, 60, (100, 64, B)), white=rng.uniform(9000, 12000, (100, 64, B)), patch=patch,
        coeffs=rng.normal(size=(B, 4)), wiener=rng.normal(size=(31, B)), wiener_offset=rng.normal(size=31),
    )
    path = tmp_path_factory.mktemp("tall") / "tall.h5"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(io.calibration_hdf5, "_CHUNK_BYTES", 60_000)  # 7 rows of 8 kB: the last chunk partial
        io.save_calibration(path, calibration, instrument_id="sim-sphere-1", band_centres_nm=BANDS)
    with h5py.File(path, "r") as stored:
        assert stored["dark"].chunks == (7, 64, B) and stored["patch"].chunks == (100, 64)
    return path, calibration


@hypothesis.settings(max_examples=40, deadline=None)
@hypothesis.given(rows=st.tuples(st.integers(0, 99), st.integers(1, 100)).filter(lambda r: r[0] < r[1]))
def test_rows_read_lazily_equal_the_whole_arrays_rows(tall_calibration, rows):
    path, calibration = tall_calibration
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)  # dark, white and patch stay on disk
        with io.open_calibration(path) as opened:
            assert isinstance(opened._arrays["dark"], io.calibration_files._StoredArray)
            part = opened.rows(*rows)
    for name in ("dark", "white"):
        whole = np.asarray(getattr(calibration, name))[rows[0]:rows[1]]
        assert np.asarray(getattr(part, name)).tobytes() == whole.tobytes(), name


def test_old_version_3_npz_gives_the_same_calibration(tmp_path, rng, monkeypatch):
    calibration = make_calibration(rng)
    new, old = tmp_path / "new.h5", tmp_path / "old.npz"
    io.save_calibration(new, calibration, instrument_id="sim-sphere-1", band_centres_nm=BANDS)
    written = write_older(old, calibration, 3)
    (from_new, _), (from_old, header) = io.load_calibration(new), io.load_calibration(old, band_centres_nm=BANDS)
    assert header == written and header["format_version"] == 3
    for name in (name for name in io.CALIBRATION_ARRAYS if not name.startswith("wiener_residual")):
        assert np.asarray(getattr(from_old, name)).tobytes() == np.asarray(getattr(from_new, name)).tobytes(), name
    assert from_old.wiener_residual is None and from_new.wiener_residual is None
    assert (from_old.illuminant, from_old.observer, from_old.saturation) == (from_new.illuminant, from_new.observer, from_new.saturation)
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)  # an .npz is read whole all the same
    with io.open_calibration(old) as opened:
        assert opened._file is None
        assert np.asarray(opened.rows(3, 5).dark).tobytes() == np.asarray(calibration.dark)[3:5].tobytes()


@pytest.mark.parametrize("in_memory", [True, False], ids=["in-memory", "by-rows"])
def test_open_calibration_pickles(calibration_path, monkeypatch, in_memory):
    """An open file pickles to another process (a dask worker): the one read by rows is opened
    again there (an HDF5 file, like a descriptor, does not travel) and still reads once the
    original is closed."""
    if not in_memory:
        monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)
    loaded, _ = io.load_calibration(calibration_path)
    with io.open_calibration(calibration_path) as opened:
        copied = pickle.loads(pickle.dumps(opened))
    with copied:
        assert copied.header == opened.header
        assert np.asarray(copied.rows(2, 6).white).tobytes() == np.asarray(loaded.white)[2:6].tobytes()


def test_a_calibration_file_changed_before_it_is_unpickled_is_refused(calibration_path, rng, monkeypatch):
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)
    with io.open_calibration(calibration_path) as opened:
        state = pickle.dumps(opened)
    io.save_calibration(calibration_path, make_calibration(rng), instrument_id="sim-sphere-1", band_centres_nm=BANDS)
    with refused(CalibrationFileError, calibration_path, "changed since it was opened: another checksum"):
        pickle.loads(state)


def test_save_calibration_closes_the_hdf5_file_before_the_rename(tmp_path, rng, monkeypatch):
    """h5py writes the temporary file, and has closed it (every byte handed over) before it is
    fsynced and renamed into place."""
    events = []
    real_close, real_fsync, real_replace = h5py.File.close, os.fsync, os.replace

    def close(self):
        if self.id.valid:
            events.append(("close", pathlib.Path(self.filename).name))
        real_close(self)

    def fsync(descriptor):
        events.append(("fsync",))
        real_fsync(descriptor)

    def replace(source, destination):
        events.append(("rename", pathlib.Path(source).name))
        real_replace(source, destination)

    monkeypatch.setattr(h5py.File, "close", close)
    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    io.save_calibration(tmp_path / "cal.h5", make_calibration(rng), instrument_id="sim-sphere-1", band_centres_nm=BANDS)
    assert [event[0] for event in events] == ["close", "fsync", "rename", "fsync"]
    assert io.is_temp_sibling(events[2][1], "cal.h5")


def test_a_kernel_residual_round_trips_and_bad_shapes_are_refused(tmp_path, rng):
    """Format version 5 stores the estimator's kernel residual (E8): read back bit for bit, in
    the whole calibration and in its rows; shapes that do not fit the bands or one m are refused
    in one line naming the array."""
    from spherejax.estimation import KernelResidual

    calibration = make_calibration(rng)
    residual = KernelResidual(*(np.asarray(x, np.float32) for x in (
        rng.normal(size=B), rng.normal(size=(B, B)), rng.normal(size=(5, B)), rng.normal(size=(31, 5)))))
    kernel = dataclasses.replace(calibration, wiener_residual=residual)
    path = tmp_path / "kernel.h5"
    header = io.save_calibration(path, kernel, instrument_id="sim-sphere-1", band_centres_nm=BANDS)
    assert header["arrays"]["wiener_residual_inducing"]["shape"] == [5, B]
    loaded, _ = io.load_calibration(path)
    with io.open_calibration(path) as opened:
        rows = opened.rows(2, 4)
    for got in (loaded.wiener_residual, rows.wiener_residual):
        for name in ("centre", "whitening", "inducing", "weights"):
            assert np.asarray(getattr(got, name)).tobytes() == np.asarray(getattr(residual, name)).tobytes(), name
    entries = calibration_entries(path)
    entries["wiener_residual_weights"] = entries["wiener_residual_weights"][:, :4]
    header = header_of(entries)
    header["arrays"]["wiener_residual_weights"]["shape"] = [31, 4]  # as the header says: a residual of two m
    rewrite_file(path, entries, header, recompute_checksum=True)
    match = r"array 'wiener_residual_weights' has shape \[31, 4\] \(expected a kernel residual of the 16 bands"
    with refused(CalibrationFileError, path, match):
        io.load_calibration(path)


def test_a_centre_without_inducing_points_is_refused(calibration_path):
    """m = 0 is an affine estimator: a non-zero centre (or whitening) there would be read as
    nothing, so the file is refused rather than silently taken for affine."""
    entries = calibration_entries(calibration_path)
    entries["wiener_residual_centre"] = entries["wiener_residual_centre"] + 1
    rewrite_file(calibration_path, entries, header_of(entries), recompute_checksum=True)
    match = r"array 'wiener_residual_centre' is not zero with no inducing point \(m = 0\)"
    with refused(CalibrationFileError, calibration_path, match):
        io.load_calibration(calibration_path)
