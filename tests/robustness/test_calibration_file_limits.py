"""Limits before work (docs/reliability.md, section 1): a calibration
file's declared sizes are checked against what the file really stores before anything long is
done with it, and verifying a calibration stops when asked to.

A 48 kB HDF5 calibration declaring 100000 x 100000 x 16 frames, allocated and never written (a
sparse file of 1.3 TB), would keep `spherejax correct` checksumming for over ten minutes, and a
stop request is honoured only at the safe points of `spherejax.interrupt`. So such a file is
refused with one line before any of its data is read, and the verification reads in bounded
blocks, each a safe point.
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
import signal
import struct

import h5py
import numpy as np
import pytest

import spherejax
from spherejax import cli, interrupt, io
from tests.batch_support import NAMES, frame, make_calibration
from tests.helpers import calibration_entries

SPARSE_SHAPE = (100_000, 100_000, 16)
DECLARED = "100000 x 100000 x 16"
EXPECTED = "(expected a calibration written whole by spherejax calibrate)"


class _StillRunning(BaseException):
    """`_within`'s alarm: a BaseException, so that no `except Exception` on the way (nor the
    command line's `except OSError`) takes it for a refusal of the file."""


@contextlib.contextmanager
def _within(seconds: float):
    """Fail, rather than run for hours, when the block outlives `seconds`: before this round the
    files of these tests were checksummed block after block until the end of their declared
    terabytes (SIGALRM is no stop request: `interrupt.stop_requests` takes SIGINT and SIGTERM).
    The alarm repeats every 0.2 s: raised where Python cannot pass it on (a weakref callback),
    an exception is printed as ignored and the work goes on."""

    def expire(signum, frame):
        raise _StillRunning

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds, 0.2)
    try:
        yield
    except _StillRunning:
        pytest.fail(f"still running after {seconds} s: the file's declared size was not checked before the work")
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _declaring(cal: pathlib.Path, path: pathlib.Path, shape, make_frame) -> pathlib.Path:
    """`cal` rewritten at `path`: its header declaring dark and white frames of `shape` (the
    checksum left as it was: only reading every declared byte could tell it no longer matches),
    its other arrays as they were, written first, then white and dark by `make_frame(stored,
    name)`, last in the file."""
    entries = calibration_entries(cal)
    header = json.loads(entries.pop("header").tobytes())
    for name in ("dark", "white"):
        header["arrays"][name]["shape"] = list(shape)
    with h5py.File(path, "w") as stored:
        stored.attrs.create("header", json.dumps(header), dtype=h5py.string_dtype("utf-8"))
        for name, array in entries.items():
            if name not in ("dark", "white"):
                stored.create_dataset(name, data=array)
        for name in ("white", "dark"):
            make_frame(stored, name, entries[name])
    return path


def _allocated_never_written(shape, chunks=None):
    """A frame maker for `_declaring`: float32 of `shape`, its storage allocated when the dataset
    is created (early allocation, no fill value written) and never written. HDF5 counts it as
    stored (its storage size is the whole frame); the file only grows, by a hole."""

    def make(stored, name, _):
        plist = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        if chunks is None:
            plist.set_layout(h5py.h5d.CONTIGUOUS)
        else:
            plist.set_chunk(chunks)
        plist.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
        plist.set_fill_time(h5py.h5d.FILL_TIME_NEVER)
        space = h5py.h5s.create_simple(shape)
        h5py.h5d.create(stored.id, name.encode(), h5py.h5t.IEEE_F32LE, space, dcpl=plist)

    return make


def _cube(path: pathlib.Path) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    io.write_frame(path, frame(np.random.default_rng(8)), channel_names=NAMES)
    return path


def _correct(calibration: pathlib.Path, tmp_path: pathlib.Path, capsys) -> tuple[int, list[str], pathlib.Path]:
    """`spherejax correct -c CALIBRATION cube.tif -o OUT` in this process: (exit status, the lines
    on stderr, OUT)."""
    out = tmp_path / "out"
    cube = _cube(tmp_path / "in" / "cube.tif")
    status = cli.main(["correct", "-c", str(calibration), str(cube), "-o", str(out)])
    return status, capsys.readouterr().err.splitlines(), out


# ------------------------------------------------------------- declared, never written (8)


@pytest.mark.parametrize(
    "chunks", [None, (1, SPARSE_SHAPE[1], SPARSE_SHAPE[2])], ids=["contiguous", "chunked-by-rows"]
)
def test_a_calibration_declaring_frames_never_written_is_refused_before_any_read(cal, tmp_path, chunks):
    """1.28 TB declared, a few kB (contiguous) or MB (the chunk index) stored."""
    path = _declaring(cal, tmp_path / "sparse.h5", SPARSE_SHAPE, _allocated_never_written(SPARSE_SHAPE, chunks))
    stat = os.stat(path)
    assert stat.st_size > 10**12 and stat.st_blocks * 512 < 64 << 20  # what the test is about: a sparse file
    with _within(30), pytest.raises(io.CalibrationFileError) as refused:
        io.open_calibration(path)
    message = str(refused.value)
    assert message.startswith(f"{path}: dataset 'dark' declares {DECLARED} values (640000000000 bytes) "
                              "but the file stores only "), message
    assert "allocated but never written (holes of a sparse file)" in message
    assert message.endswith(EXPECTED) and "\n" not in message


def test_correct_refuses_a_calibration_declaring_frames_never_written(cal, tmp_path, capsys):
    """Through the command line, where checksumming it would take over ten minutes: one line
    naming the file, a failure status, and OUT never created."""
    path = _declaring(cal, tmp_path / "sparse.h5", SPARSE_SHAPE, _allocated_never_written(SPARSE_SHAPE))
    with _within(60):
        status, err, out = _correct(path, tmp_path, capsys)
    assert status not in (0, 130, 143)
    [line] = err
    assert line.startswith(f"spherejax: error: {path}: dataset 'dark' declares {DECLARED} values "), line
    assert line.endswith(EXPECTED)
    assert not out.exists()


# ---------------------------------------------------------------- past the file's end (9)


def _cut_short(cal: pathlib.Path, path: pathlib.Path) -> pathlib.Path:
    """`cal` rewritten with dark last in the file, in chunks of 8 rows, then cut in the middle of
    its third chunk. HDF5 refuses a file shorter than its superblock's end-of-file address says
    (and a contiguous dataset past it), so the address is cut too, as a damaged or hand-made
    file may have it: then only spherejax's own check stands between the reads and the end."""
    entries = calibration_entries(cal)
    rows, width, bands = entries["dark"].shape

    def make(stored, name, array):
        stored.create_dataset(name, data=array, chunks=(8, width, bands))

    _declaring(cal, path, (rows, width, bands), make)
    with h5py.File(path, "r") as stored:
        cut = stored["dark"].id.get_chunk_info(2).byte_offset + 1000
    with open(path, "r+b") as file:
        superblock = file.read(16)
        # Version 0 (h5py's default), 8-byte addresses: the end-of-file address at byte 40.
        assert superblock[8] == 0 and superblock[13] == 8, superblock
        file.truncate(cut)
        file.seek(40)
        file.write(struct.pack("<Q", cut))
    with h5py.File(path, "r") as stored:
        assert stored["dark"].id.get_storage_size() == rows * width * bands * 4  # HDF5 sees no loss
    return path


def test_a_calibration_whose_data_run_past_its_end_is_refused_before_any_read(cal, tmp_path):
    """Unchecked, such a file is refused only by the read that reaches the end ("addr overflow"),
    after every byte before it was read, in words that name no dataset."""
    path = _cut_short(cal, tmp_path / "cut.h5")
    with pytest.raises(io.CalibrationFileError) as refused:
        io.open_calibration(path)
    message = str(refused.value)
    size = path.stat().st_size
    assert message.startswith(f"{path}: dataset 'dark' declares 40 x 48 x 16 values (122880 bytes) "
                              "but the file stores only "), message
    assert f"past the file's end at byte {size}: the file was cut short" in message
    assert message.endswith(EXPECTED) and "\n" not in message


def test_correct_refuses_a_calibration_cut_short(cal, tmp_path, capsys):
    path = _cut_short(cal, tmp_path / "cut.h5")
    status, err, out = _correct(path, tmp_path, capsys)
    assert status not in (0, 130, 143)
    [line] = err
    assert line.startswith(f"spherejax: error: {path}: dataset 'dark' declares 40 x 48 x 16 values "), line
    assert "past the file's end" in line and line.endswith(EXPECTED)
    assert not out.exists()


# ------------------------------------------------------------- what must still be taken


def test_zeros_a_file_system_stores_as_holes_are_still_data(tmp_path):
    """Not every hole is a forgery: a file system may keep runs of zeros as holes (ZFS with
    compression, `cp --sparse=always`), and an all-zero dark frame is a calibration. Such a copy
    (a small frame: its holes cost nothing to read) opens as the original does."""
    rng = np.random.default_rng(9)
    h, w, b = 64, 64, 16
    patch = np.zeros((h, w), bool)
    patch[4:12, 4:12] = True
    calibration = spherejax.Calibration(
        dark=np.zeros((h, w, b), np.float32), white=rng.uniform(9000, 11000, (h, w, b)).astype(np.float32),
        patch=patch, coeffs=np.asarray(spherejax.identity_coeffs(b)),
        wiener=rng.uniform(0, 1 / b, (31, b)).astype(np.float32),
    )
    original = tmp_path / "cal.h5"
    bands = spherejax.BAND_CENTRES_NM.astype(int).tolist()
    io.save_calibration(original, calibration, instrument_id="sphere-1", band_centres_nm=bands)
    copy = tmp_path / "sparse-copy.h5"
    data, block = original.read_bytes(), 4096
    with open(copy, "wb") as file:  # as cp --sparse=always: every all-zero block a hole
        for start in range(0, len(data), block):
            piece = data[start:start + block]
            if piece.count(0) == len(piece) and start + block < len(data):
                file.seek(len(piece), os.SEEK_CUR)
            else:
                file.write(piece)
    fd = os.open(copy, os.O_RDONLY)
    try:
        first_hole = os.lseek(fd, 0, os.SEEK_HOLE)
    finally:
        os.close(fd)
    if first_hole >= len(data):
        pytest.skip("this file system stores no holes")
    with io.open_calibration(copy) as opened, io.open_calibration(original) as expected:
        assert opened.header == expected.header
        np.testing.assert_array_equal(opened.calibration().dark, 0.0)


def test_a_frame_in_more_chunks_than_any_calibration_is_refused_before_they_are_listed(cal, tmp_path):
    """HDF5's implicit chunk index stores nothing per chunk, so a small file can declare 10^10
    chunks; counting or listing them (its storage size, the check for holes) would take hours.
    More chunks than `save_calibration` ever writes are refused first."""
    many = (1 << 20) + 1
    shape = (many, 1, 16)

    def make(stored, name, _):
        stored.create_dataset(name, shape=shape, dtype="<f4", chunks=(1, 1, 16))

    path = _declaring(cal, tmp_path / "chunks.h5", shape, make)
    with pytest.raises(io.CalibrationFileError) as refused:
        io.open_calibration(path)
    assert str(refused.value).startswith(
        f"{path}: dataset 'dark' of shape [{many}, 1, 16] is stored in {many} chunks of shape [1, 1, 16] "
        f"(expected at most {1 << 20} chunks"
    ), str(refused.value)


# ------------------------------------------------------------ stopping the verification


def test_a_stop_request_stops_the_verification(cal):
    """SIGTERM received (inside `interrupt.stop_requests`, as `spherejax correct` runs) before or
    while a calibration is verified: the verification stops at its next block, raising
    `interrupt.Interrupted`, instead of reading the whole file first."""
    with interrupt.stop_requests():
        os.kill(os.getpid(), signal.SIGTERM)
        assert interrupt.requested() == signal.SIGTERM
        with pytest.raises(interrupt.Interrupted) as stopped:
            io.open_calibration(cal)
    assert stopped.value.exit_status == 143


def _large_calibration(path: pathlib.Path) -> pathlib.Path:
    """A valid calibration of 512 x 640 x 16 float32 frames: 20 MiB each, so that reading and
    hashing either takes two blocks of the 16 MiB the verification reads at a time."""
    rng = np.random.default_rng(10)
    h, w, b = 512, 640, 16
    patch = np.zeros((h, w), bool)
    patch[8:40, 8:40] = True
    calibration = spherejax.Calibration(
        dark=rng.uniform(90, 110, (h, w, b)).astype(np.float32),
        white=rng.uniform(9000, 11000, (h, w, b)).astype(np.float32), patch=patch,
        coeffs=np.asarray(spherejax.identity_coeffs(b)), wiener=rng.uniform(0, 1 / b, (31, b)).astype(np.float32),
    )
    bands = spherejax.BAND_CENTRES_NM.astype(int).tolist()
    io.save_calibration(path, calibration, instrument_id="sphere-1", band_centres_nm=bands)
    return path


def test_sigterm_while_correct_verifies_the_calibration_stops_it_within_a_block(tmp_path, capsys, monkeypatch):
    """SIGTERM arriving while `spherejax correct` reads the calibration to verify it: the run stops
    with the exit status 143 and its one "interrupted" line after at most one more block, before
    OUT is created. (It went on reading every array, then created OUT and stopped there.) The
    signal is sent from inside the first read of the file, so that it lands mid-verification
    whatever the machine's speed."""
    path = _large_calibration(tmp_path / "large.h5")
    reads = []
    read_direct = h5py.Dataset.read_direct
    unhandled = signal.getsignal(signal.SIGTERM)

    def reading(self, *args, **kwargs):
        reads.append(self.name)
        # Only once `correct` has turned SIGTERM into a stop request: never kill the test.
        if len(reads) == 1 and signal.getsignal(signal.SIGTERM) is not unhandled:
            os.kill(os.getpid(), signal.SIGTERM)
        return read_direct(self, *args, **kwargs)

    monkeypatch.setattr(h5py.Dataset, "read_direct", reading)
    with _within(60):
        status, err, out = _correct(path, tmp_path, capsys)
    assert status == 143, err
    [line] = err
    assert line.startswith("spherejax: interrupted"), line
    assert len(reads) <= 2, reads  # the read the signal came in, and at most the one under way
    assert not out.exists()


@pytest.mark.parametrize("damage", ["dark_nan", "white_at_dark"])
def test_a_calibration_whose_patch_has_no_usable_pixel_is_refused_when_saved_and_opened(tmp_path, damage, monkeypatch):
    """Non-finite dark or white frames across the white patch made every image's patch ratio
    NaN and every pixel flagged, yet the file was saved, opened and `correct` said "done"."""
    rng = np.random.default_rng(0)
    calibration, bands, instrument = make_calibration(rng)
    dark, white = np.array(calibration.dark), np.array(calibration.white)
    patch = np.asarray(calibration.patch, bool)
    if damage == "dark_nan":
        dark[patch, 3] = np.nan
    else:
        white[patch, 3] = dark[patch, 3]
    broken = spherejax.Calibration(dark=dark, white=white, patch=calibration.patch, coeffs=calibration.coeffs,
                            wiener=calibration.wiener, wiener_offset=calibration.wiener_offset,
                            saturation=calibration.saturation)
    path = tmp_path / "cal.h5"
    with pytest.raises(io.CalibrationFileError, match=r"no pixel of the white patch has white - dark finite and > 0 "
                                                       r"in band\(s\) \[3\]"):
        io.save_calibration(path, broken, instrument_id=instrument, band_centres_nm=bands)
    assert not path.exists()
    # Written by something else (this check switched off), it is refused when opened too.
    good = tmp_path / "good.h5"
    io.save_calibration(good, calibration, instrument_id=instrument, band_centres_nm=bands)
    from spherejax.io import calibration_files

    with monkeypatch.context() as patched:
        patched.setattr(calibration_files, "_require_usable_patch", lambda *args: None)
        io.save_calibration(path, broken, instrument_id=instrument, band_centres_nm=bands)
    with pytest.raises(io.CalibrationFileError, match="no pixel of the white patch"):
        io.open_calibration(path)
    io.open_calibration(good).close()
