"""Library messages in spherejax's words: what OpenImageIO (libtiff, OpenEXR, libpng), h5py (HDF5) and pyserial say about a damaged
file or a bad port reaches the user as one line that names the file, says what is wrong in plain
words and what was expected, never as the library's jargon ("Read error at scanline 4294967295",
"EXR_ERR_READ_IO", "Unable to synchronously open file", "[Errno 2]"). And a `correct` batch whose
inputs hold nothing to correct is refused (exit 2) before OUT is created.

Each damaged input is checked through the command line (`spherejax.cli.main` in this process, or
the real entry point where the exit status itself matters), with the catalogue's promises
(tests/robustness/catalogue.py: one line, exit status, nothing new or partial on disk); sweeps
over many cut points and damaged bytes check every message the libraries give through the
Python API, which the command line prints as it is.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import struct
import subprocess
import sys

import h5py
import numpy as np
import pytest
from spherejax_hw import acquire as hw_acquire
from spherejax_hw.emulators import EmulatedPort, FilterWheelEmulator
from spherejax_hw.errors import PortError
from spherejax_hw.filterwheel import FilterWheel

import spherejax
from spherejax import archive, cli, io
from tests.batch_support import NAMES, B, H, W, frame, outputs_of
from tests.helpers import no_compilation_cache_writes
from tests.hw.support import pty_resources, write_profile
from tests.robustness.catalogue import (
    Folder,
    check_case,
    correct_case,
    snapshot,
    truncate,
)

#: Words of the libraries that must never reach the user: the row counter at -1 read as
#: unsigned, OpenEXR's error codes and prefixes, HDF5's internals, Python's errno and codec forms.
JARGON = (
    "4294967295", "scanline", "EXR_ERR", "EXR Error", "synchronously", "sblock", "stored_eof", "eof =",
    "[Errno", "Could not open file", "PNG read error", "TIFFRead", "codec can't", "Traceback",
    "could not find a format reader", "(25, ",
)


def assert_plain(line: str, named, expected: str | None = "(expected ") -> None:
    """One line that names `named`, says what was expected and holds no library jargon."""
    assert "\n" not in line, line
    assert str(named) in line, (named, line)
    if expected is not None:
        assert expected in line, line
    leaked = [word for word in JARGON if word in line]
    assert not leaked, (leaked, line)


def assert_error_line(err: str, named, problem: str) -> str:
    """stderr is exactly one "spherejax: error: " line, plain (`assert_plain`), with `problem`."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("spherejax: error: "), err
    assert_plain(lines[0], named)
    assert problem in lines[0], (problem, lines[0])
    return lines[0]


def _kind_of(error: io.SpherejaxFileError) -> str:
    """What kind of refusal a message is: its problem up to the first colon ("is truncated")."""
    return error.problem.split(":")[0]


# ------------------------------------------------------------------------------ damaged inputs


def _tiff(f: Folder, name: str = "in/cut.tif") -> pathlib.Path:
    return f.cube(name)


def _cut_at(name: str, keep):
    """A good cube TIFF (or EXR) cut to `keep(data)` bytes."""

    def make(f: Folder) -> pathlib.Path:
        path = _exr(f, name) if name.endswith(".exr") else _tiff(f, name)
        data = path.read_bytes()
        path.write_bytes(data[: keep(data)])
        return path

    return make


def _exr(f: Folder, name: str = "in/cut.exr") -> pathlib.Path:
    path = f.tmp / name
    path.parent.mkdir(parents=True, exist_ok=True)
    io.write_exr(path, frame(np.random.default_rng(3)).astype(np.float32), channel_names=NAMES)
    return path


def _overwrite(name: str, where, fill: bytes):
    """A good cube with `fill` written over its bytes from offset `where(data)`."""

    def make(f: Folder) -> pathlib.Path:
        path = _exr(f, name) if name.endswith(".exr") else _tiff(f, name)
        data = bytearray(path.read_bytes())
        start = where(bytes(data))
        data[start : start + len(fill)] = fill
        path.write_bytes(bytes(data))
        return path

    return make


def _first_directory(data: bytes) -> int:
    """The offset of a little-endian classic TIFF's first directory (its IFD)."""
    assert data[:4] == b"II*\x00"
    return struct.unpack_from("<I", data, 4)[0]


def _garbage_after_cut(f: Folder) -> pathlib.Path:
    """A cube cut in half and padded back to its size with garbage: a copy gone wrong."""
    path = _tiff(f, "in/padded.tif")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] + bytes(range(256)) * 40)
    return path


def _band_files_one_cut(f: Folder) -> pathlib.Path:
    """A folder of 16 band files, one of them cut short."""
    cube = frame(np.random.default_rng(6))
    folder = f.tmp / "in" / "bands"
    folder.mkdir(parents=True)
    for band, name in enumerate(NAMES):
        io.write_frame(folder / f"s_{name}.tif", np.ascontiguousarray(cube[..., band : band + 1]))
    cut = folder / f"s_{NAMES[5]}.tif"
    truncate(cut, 0.6)
    return cut


#: (case, fragment of the reason, words the "expected" must hold)
BATCH_CASES = [
    (correct_case("tiff-cut-in-its-header", _cut_at("in/h.tif", lambda d: 5), "fewer than the 8 of a TIFF header"),
     "(expected a cube"),
    (correct_case("tiff-cut-in-its-directory", _cut_at("in/d.tif", lambda d: 100), "its TIFF directory"),
     "(expected a cube"),
    # The cut cases' fragments hold for every OpenImageIO release in range: 3.2 adds what libtiff
    # says ("a strip of their pixel data stops after N of its M bytes"), 3.1 says nothing.
    (correct_case("tiff-cut-mid-strip", _cut_at("in/m.tif", lambda d: len(d) // 2),
                  "is truncated or corrupted: rows"), f"(expected a complete 16-bit TIFF of {H} x {W} pixels and {B} channels)"),
    (correct_case("tiff-cut-in-its-last-strip", _cut_at("in/l.tif", lambda d: len(d) - 50),
                  "is truncated or corrupted: rows"), "(expected a complete 16-bit TIFF"),
    (correct_case("tiff-garbage-after-a-cut", _garbage_after_cut, "is truncated or corrupted: rows"),
     "(expected a complete 16-bit TIFF"),
    (correct_case("tiff-garbage-in-the-pixels", _overwrite("in/p.tif", lambda d: int(len(d) * 0.85), b"\xa5" * 64),
                  "cannot be decoded"), "(expected a complete 16-bit TIFF"),
    (correct_case("tiff-garbage-signature", _overwrite("in/s.tif", lambda d: 0, b"\x00" * 8),
                  "is not a readable image: it does not start as a TIFF does"), "(expected a cube"),
    (correct_case("tiff-garbage-directory", _overwrite("in/i.tif", lambda d: _first_directory(d) + 2, b"\xff" * 60),
                  "its TIFF directory"), "(expected a cube"),
    (correct_case("tiff-empty", _cut_at("in/e.tif", lambda d: 0), "is empty"), "(expected a cube"),
    (correct_case("band-file-cut", _band_files_one_cut, "is truncated or corrupted"),
     f"(expected a complete 16-bit TIFF of {H} x {W} pixels and 1 channel)"),
    (correct_case("exr-cut-in-its-header", _cut_at("in/h.exr", lambda d: 100), "its OpenEXR header"),
     "(expected a cube"),
    (correct_case("exr-cut-mid-pixels", _cut_at("in/m.exr", lambda d: len(d) // 2), "are missing or cannot be decoded"),
     f"(expected a complete OpenEXR of {H} x {W} pixels and {B} channels)"),
    (correct_case("exr-cut-at-its-end", _cut_at("in/l.exr", lambda d: len(d) - 30), "are missing or cannot be decoded"),
     "(expected a complete OpenEXR"),
    (correct_case("exr-garbage-signature", _overwrite("in/s.exr", lambda d: 0, b"\x00" * 8),
                  "does not start with the OpenEXR signature"), "(expected a cube"),
    (correct_case("exr-garbage-header", _overwrite("in/g.exr", lambda d: 64, b"\xff" * 16),
                  "its OpenEXR header is invalid"), "(expected a cube"),
]


@pytest.mark.parametrize("case, expected", [pytest.param(case, expected, id=case.id) for case, expected in BATCH_CASES])
def test_a_damaged_input_fails_in_plain_words(case, expected, workspace, cal, tmp_path, capsys):
    """`correct` names the damaged input and what is wrong with it, goes on, records the failure
    and leaves nothing of it in OUT (check_case); the reason is plain and says what was expected."""
    lines = check_case(case, workspace, cal, tmp_path, capsys)
    failed = [line for line in lines if line.startswith("spherejax: failed ")]
    assert len(failed) == 1 == len(lines), lines
    assert_plain(failed[0], "case/in/", expected)


def test_a_truncated_cube_given_to_measure_is_one_error_line(cal, tmp_path, capsys):
    """The commands that read a cube whole (measure) print the same words as `correct` does."""
    f = Folder(tmp_path, tmp_path, cal)
    cube = _cut_at("cut.tif", lambda d: len(d) // 2)(f)
    before = snapshot(tmp_path)
    status = cli.main(["-q", "measure", str(cube), "-c", str(cal), "--region", "a=8,16,8,16", "-o", str(tmp_path / "m")])
    err = capsys.readouterr().err
    assert status == cli.EXIT_BAD_INPUT
    assert_error_line(err, cube, "is truncated or corrupted: rows 0 to 39 of its 40 cannot be read")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("suffix", [".tif", ".exr"])
def test_every_cut_and_damaged_byte_gives_a_plain_message(suffix, tmp_path):
    """Cut at every point of a cube file, or with bytes damaged at many offsets: what the reader
    says is one line naming the file, in plain words, with what was expected."""
    f = Folder(tmp_path, tmp_path, tmp_path)
    good = (_exr if suffix == ".exr" else _tiff)(f, "good" + suffix)
    data = good.read_bytes()
    rng = np.random.default_rng(11)
    variants = [data[:n] for n in np.linspace(0, len(data) - 1, 48).astype(int)]
    for offset in [*range(0, 2048, 64), *rng.integers(0, len(data), 24)]:
        damaged = bytearray(data)
        damaged[offset : offset + 16] = rng.bytes(16)
        variants.append(bytes(damaged))
    path = tmp_path / ("x" + suffix)
    refused = set()
    for variant in variants:
        path.write_bytes(variant)
        try:
            io.read_cube(path, expected_shape=(H, W, B), band_centres_nm=[int(n[:-2]) for n in NAMES])
        except io.SpherejaxFileError as error:
            assert_plain(str(error), path)
            refused.add(_kind_of(error))
    # Cut short or damaged, not only "not an image": the words say which.
    assert {"is empty", "is truncated or corrupted"} <= refused, refused


_FULL_DISK_SCRIPT = """
import resource, sys, pathlib
import numpy as np
from spherejax import io
folder = pathlib.Path(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
pixels = np.random.default_rng(0).random((200, 200, 16))
writes = {
    "a.exr": lambda path: io.write_exr(path, pixels.astype(np.float32), channel_names=[f"c{i}" for i in range(16)]),
    "a.tif": lambda path: io.write_frame(path, (pixels * 60000).astype(np.uint16)),
    # OpenImageIO's PNG writer reported success on a cut file (the preview was left cut short)
    "a.png": lambda path: io.write_png(path, (pixels[..., :3] * 255).astype(np.uint8), channel_names=["R", "G", "B"]),
}
for name, write in writes.items():
    try:
        write(folder / name)
        print("written", name)
    except io.SpherejaxFileError as error:
        print(error)
"""


def test_a_write_the_file_size_limit_stops_says_so(tmp_path):
    """OpenEXR's and libtiff's words for a write that failed ("Failed OpenEXR write: Failed to
    write pixel data to image file "/x/.a.exr.1a6a887e87ab.tmp"", "TIFFWriteScanline failed
    writing line y=32,z=0") name the temporary file and not the cause: the message says why, and
    nothing is left."""
    env = no_compilation_cache_writes({**os.environ, "JAX_PLATFORMS": "cpu"})
    result = subprocess.run([sys.executable, "-c", _FULL_DISK_SCRIPT, str(tmp_path)], capture_output=True, text=True,
                            env=env, timeout=600, check=False)
    lines = result.stdout.splitlines()
    assert result.returncode == 0 and len(lines) == 3, (result.stdout, result.stderr)
    for name, line in zip(("a.exr", "a.tif", "a.png"), lines):
        assert line == (f"{tmp_path / name}: could not be written: it reached 20000 bytes, the largest file this "
                        "process may write (ulimit -f)"), line
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------ calibrations


def _hdf5_without_spherejax(path: pathlib.Path) -> pathlib.Path:
    with h5py.File(path, "w") as stored:
        stored.create_group("measurements")
        stored["spectra"] = np.zeros((3, 31))
        stored.attrs["instrument"] = "another program"
    return path


CALIBRATION_CASES = {
    "truncated-to-its-superblock": (lambda p: truncate(p, 0.004), "is truncated: it holds"),
    "truncated-in-half": (lambda p: truncate(p, 0.5), "bytes its HDF5 superblock records"),
    "truncated-by-ten-bytes": (lambda p: p.write_bytes(p.read_bytes()[:-10]) and p, "is truncated: it holds"),
    "garbage-superblock": (lambda p: p.write_bytes(p.read_bytes()[:8] + b"\xff" * 32 + p.read_bytes()[40:]) and p,
                           "is truncated or corrupted: HDF5 cannot read the superblock"),
    "not-hdf5": (lambda p: p.write_text("dark = 0\nwhite = 1\n") and p, "is neither HDF5 nor an .npz"),
    "hdf5-of-another-program": (_hdf5_without_spherejax, "is an HDF5 file but not a spherejax calibration"),
}


@pytest.mark.parametrize("name", list(CALIBRATION_CASES))
def test_a_damaged_calibration_is_one_plain_error_line(name, cal, tmp_path, capsys):
    damage, problem = CALIBRATION_CASES[name]
    f = Folder(tmp_path, tmp_path, cal)
    f.cube("in/a.tif")
    calibration = tmp_path / "cal.h5"
    shutil.copyfile(cal, calibration)
    damage(calibration)
    before = snapshot(tmp_path)
    status = cli.main(["-q", "correct", "-c", str(calibration), str(tmp_path / "in"), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == cli.EXIT_BAD_INPUT
    line = assert_error_line(err, calibration, problem)
    assert line.startswith(f"spherejax: error: {calibration}: ")
    assert snapshot(tmp_path) == before  # no OUT, no lock


def test_every_damaged_calibration_byte_gives_a_plain_message(cal, tmp_path):
    """Bytes damaged across the HDF5 metadata (superblock, object headers, heaps, B-trees) and
    the file cut at many points: every refusal is plain, names the file and what was expected."""
    data = cal.read_bytes()
    path = tmp_path / "cal.h5"
    rng = np.random.default_rng(5)
    variants = [data[:n] for n in np.linspace(8, len(data) - 1, 12).astype(int)]
    for offset in [*range(8, 4096, 48), *rng.integers(4096, len(data), 8)]:
        damaged = bytearray(data)
        damaged[offset : offset + 16] = rng.bytes(16)
        variants.append(bytes(damaged))
    problems = set()
    for variant in variants:
        path.write_bytes(variant)
        try:
            io.open_calibration(path).close()
        except io.CalibrationFileError as error:
            assert_plain(str(error), path)
            problems.add(_kind_of(error))
    assert {"is truncated", "is truncated or corrupted"} <= problems, problems


# ------------------------------------------------------------------------------ outputs read back


@pytest.fixture
def corrected(cal, tmp_path):
    """OUT of a batch of one cube (EXR and ENVI), for damaging its outputs."""
    f = Folder(tmp_path, tmp_path, cal)
    f.cube("in/a.tif")
    for form in ("exr", "envi"):
        assert cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(tmp_path / form),
                         "--format", form]) == 0
    return tmp_path


def test_a_truncated_reflectance_exr_opens_with_a_plain_error(corrected):
    exr = corrected / "exr" / "in" / "a.reflectance.exr"
    truncate(exr, 0.5)
    dataset = spherejax.open_corrected(corrected / "exr" / "in" / "a")  # the header is whole: opens lazily
    with pytest.raises(io.SpherejaxFileError) as raised:
        dataset["reflectance"].load()
    assert_plain(str(raised.value), exr, f"(expected a complete OpenEXR of {H} x {W} pixels and 31 channels)")
    assert "are missing or cannot be decoded" in str(raised.value)


@pytest.mark.parametrize("keep, problem", [(20, "ends inside its IHDR chunk"), (0, "is empty"),
                                           (None, "does not start with the PNG signature")])
def test_a_damaged_quality_png_opens_with_a_plain_error(corrected, keep, problem):
    quality = corrected / "exr" / "in" / "a.quality.png"
    data = quality.read_bytes()
    quality.write_bytes(data[:keep] if keep is not None else b"GIF89a" + data[6:])
    with pytest.raises(io.SpherejaxFileError) as raised:
        spherejax.open_corrected(corrected / "exr" / "in" / "a")
    assert_plain(str(raised.value), quality)
    assert problem in str(raised.value)


def test_an_envi_image_shorter_than_its_header_says_is_refused(corrected):
    data = corrected / "envi" / "in" / "a.reflectance.img"
    size = data.stat().st_size
    truncate(data, 0.5)
    with pytest.raises(io.SpherejaxFileError) as raised:
        spherejax.open_corrected(corrected / "envi" / "in" / "a")
    message = str(raised.value)
    assert_plain(message, data)
    assert f"holds {size // 2} bytes where its header" in message and f"describes {size}" in message


# ------------------------------------------------------------------------------ an empty batch


def test_an_empty_batch_is_refused_before_out_exists(cal, tmp_path, capsys):
    """Inputs that hold no cube: exit 2, one line naming them and what was searched for, and
    neither OUT nor its lock is created."""
    (tmp_path / "empty").mkdir()
    notes = tmp_path / "notes"
    (notes / "deeper").mkdir(parents=True)
    (notes / "readme.txt").write_text("no cube here")
    (notes / "deeper" / "a.tif.bak").write_text("nor here")
    (notes / ".hidden").mkdir()
    (notes / ".hidden" / "x.tif").write_bytes(b"a hidden folder is not searched")
    before = snapshot(tmp_path)
    status = cli.main(["correct", "-c", str(cal), str(tmp_path / "empty"), str(notes), "-o", str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert status == cli.EXIT_BAD_INPUT == 2 and captured.out == ""
    line = assert_error_line(captured.err, notes, "no cube found: searched them and every folder below")
    assert line.startswith(f"spherejax: error: {tmp_path / 'empty'}, {notes}: no cube found")
    for searched in ("*.tif", "*.tiff", "*.exr", "band files", "sessions", "hidden names and OUT left out"):
        assert searched in line, searched
    assert "(expected at least one cube, set of band files or session with frames to correct)" in line
    assert snapshot(tmp_path) == before
    assert not (tmp_path / "out").exists()


def test_an_empty_batch_raises_in_the_python_api_too(cal, tmp_path):
    (tmp_path / "empty").mkdir()
    out = tmp_path / "out"
    with pytest.raises(archive.NoInputError) as raised:
        archive.run_batch([tmp_path / "empty"], out, cal)
    assert isinstance(raised.value, archive.BatchError) and isinstance(raised.value, ValueError)
    assert str(raised.value).startswith(f"{tmp_path / 'empty'}: no cube found: searched it and every folder below")
    assert not out.exists()


def test_an_empty_batch_into_an_earlier_out_leaves_it_alone(cal, tmp_path, capsys):
    f = Folder(tmp_path, tmp_path, cal)
    f.cube("in/a.tif")
    out = tmp_path / "out"
    assert cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)]) == 0
    (tmp_path / "later").mkdir()
    before = snapshot(tmp_path)
    capsys.readouterr()
    status = cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "later"), "-o", str(out), "--resume"])
    assert status == cli.EXIT_BAD_INPUT
    assert_error_line(capsys.readouterr().err, tmp_path / "later", "no cube found")
    assert snapshot(tmp_path) == before
    assert not (out / archive.LOCK_NAME).exists()


def test_a_resumed_batch_whose_inputs_are_all_done_is_not_empty(cal, tmp_path, capsys):
    """Every input already done is a batch that skips them: exit 0, as before."""
    f = Folder(tmp_path, tmp_path, cal)
    f.cube("in/a.tif")
    out = tmp_path / "out"
    assert cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)]) == 0
    whole = outputs_of(out)
    capsys.readouterr()
    status = cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out), "--resume"])
    captured = capsys.readouterr()
    assert status == 0 and captured.err == ""
    assert captured.out.strip() == "0 corrected, 1 skipped (already done), 0 failed"
    assert outputs_of(out) == whole

    # A cut quality PNG is no library error on resume: its SHA-256 is not the one the manifest
    # records, so it is not provably spherejax's (docs/reliability.md, section 3): one plain line
    # naming it, the file left as it is; once its owner moves it, the input is redone.
    truncate(out / "in" / "a.quality.png", 0.5)
    cut = (out / "in" / "a.quality.png").read_bytes()
    status = cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out), "--resume"])
    captured = capsys.readouterr()
    assert status == 2 and "a.quality.png" in captured.err and len(captured.err.strip().splitlines()) == 1
    assert "Traceback" not in captured.err and "libpng" not in captured.err.lower()
    assert (out / "in" / "a.quality.png").read_bytes() == cut
    (out / "in" / "a.quality.png").unlink()
    status = cli.main(["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out), "--resume"])
    captured = capsys.readouterr()
    assert status == 0 and captured.err == ""
    assert captured.out.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    assert outputs_of(out) == whole


def test_an_empty_batch_exits_2_from_the_real_entry_point(cal, tmp_path):
    (tmp_path / "empty").mkdir()
    env = no_compilation_cache_writes({**os.environ, "JAX_PLATFORMS": "cpu"})
    result = subprocess.run(
        [sys.executable, "-m", "spherejax.cli", "correct", "-c", str(cal), str(tmp_path / "empty"), "-o", str(tmp_path / "out")],
        capture_output=True, text=True, env=env, timeout=600, check=False,
    )
    assert result.returncode == 2 and result.stdout == ""
    assert_error_line(result.stderr, tmp_path / "empty", "no cube found")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


def test_an_input_removed_after_discovery_fails_in_plain_words(cal, tmp_path):
    """An input gone between discovery and its correction: the reason names it, no "[Errno 2]"."""
    f = Folder(tmp_path, tmp_path, cal)
    cube = f.cube("in/a.tif")
    [spec] = archive.discover_inputs([cube], tmp_path / "out")
    cube.unlink()
    (tmp_path / "out").mkdir()
    result = archive.correct_input(spec, tmp_path / "out", cal)
    assert result.status == "failed"
    assert_plain(result.reason, cube)
    assert "no such file (removed or renamed since the batch found it)" in result.reason
    assert list((tmp_path / "out").iterdir()) == []


# ------------------------------------------------------------------------------ serial ports


def _profile_with_port(tmp_path: pathlib.Path, port: str) -> pathlib.Path:
    profile = write_profile(tmp_path, samples=("train-bg00-g0",))
    profile.write_text(profile.read_text().replace("/dev/ttyUSB0", port))
    return profile


@pytest.mark.parametrize("kind, problem", [
    ("missing", "there is no such device"),
    ("regular-file", "it is a regular file, not a serial port"),
    ("folder", "it is a folder, not a serial device"),
])
def test_a_port_that_is_no_serial_port_is_one_plain_error_line(kind, problem, tmp_path, capsys):
    port = tmp_path / "ttyUSB0"
    if kind == "regular-file":
        port.write_text("not a device")
    elif kind == "folder":
        port.mkdir()
    profile = _profile_with_port(tmp_path, str(port))
    before = snapshot(tmp_path)
    status = cli.main(["-q", "acquire", "--profile", str(profile), "-o", str(tmp_path / "session"), "--yes"])
    err = capsys.readouterr().err
    assert status == cli.EXIT_BAD_INPUT
    line = assert_error_line(err, port, f"cannot open port: {problem}")
    assert "(expected a serial port: a terminal device such as /dev/ttyUSB0" in line
    assert "wheel 'a' ([wheels.a])" in line  # which device of the profile it is
    assert snapshot(tmp_path) == before


def test_a_port_that_vanishes_mid_run_stops_the_acquisition_in_plain_words(tmp_path, capsys, monkeypatch):
    """A wheel unplugged during the white standard's bands: one line naming its port and what
    happened, the bands taken so far kept for --resume, no session written."""
    real_connect = hw_acquire.connect
    vanished = {}

    def connect(*args, **kwargs):
        instrument = real_connect(*args, **kwargs)
        port = instrument.emulated["wheels"]["b"]
        real_average, calls = instrument.camera.average, [0]

        def average(n):
            calls[0] += 1
            if calls[0] == 25:
                vanished["path"] = port.path
                port.vanish()
            return real_average(n)

        instrument.camera.average = average
        return instrument

    monkeypatch.setattr(hw_acquire, "connect", connect)
    profile = write_profile(tmp_path, samples=("train-bg00-g0",))
    out = tmp_path / "session"
    status = cli.main(["-q", "acquire", "--profile", str(profile), "-o", str(out), "--emulate", "--yes"])
    err = capsys.readouterr().err
    # The operator's prompts, answered by --yes, then the one line that says why it stopped.
    lines = [line for line in err.splitlines() if line.strip() and not line.endswith("assumed done (--yes)")]
    assert status == 1 and len(lines) == 1, err
    assert lines[0].startswith("spherejax: acquisition stopped: ")
    assert_plain(lines[0], vanished["path"])
    assert "port failed: the device is gone: unplugged or switched off" in lines[0]
    assert "--resume" in lines[0] and not out.exists()


def test_pyserial_failures_are_port_errors_in_plain_words(tmp_path, no_leaks):
    """The driver itself: opening a path that is none, and a port gone mid-session."""
    regular = tmp_path / "tty"
    regular.write_bytes(b"")
    with pytest.raises(PortError) as raised:
        FilterWheel(str(regular)).connect()
    assert_plain(str(raised.value), regular)
    assert "cannot open port: it is a regular file, not a serial port" in str(raised.value)
    with pytest.raises(PortError) as raised:
        FilterWheel("nosuchscheme://x").connect()
    assert "cannot open port: it is neither a device path nor a URL pyserial knows" in str(raised.value)
    with EmulatedPort(FilterWheelEmulator()) as port:
        with FilterWheel(port.path, timeout_s=0.5, move_timeout_s=1.0) as wheel:
            port.vanish()
            with pytest.raises(PortError) as raised:
                wheel.move_to(2)
    assert_plain(str(raised.value), port.path, "(expected a device that stays connected)")
    assert "port failed: the device is gone" in str(raised.value)


@pytest.fixture
def no_leaks():
    before = pty_resources()
    yield
    assert pty_resources() == before


# ------------------------------------------------------------------------------ quality masks


def _quality_png(path: pathlib.Path) -> bytes:
    bits = (np.arange(40 * 48) % 32).astype(np.uint8).reshape(40, 48)
    io.write_quality_png(path, bits)
    return path.read_bytes()


def _damaged_text_chunk(data: bytes) -> bytes:
    at = data.index(b"tEXt") + 8  # inside the first text chunk's data: its CRC no longer matches
    return data[:at] + bytes([data[at] ^ 0x20]) + data[at + 1:]


@pytest.mark.parametrize("damage, problem", [
    (lambda data: data[: len(data) // 2], "is truncated: its pixel data stops before its last row"),
    (_damaged_text_chunk, "is corrupted: its tEXt chunk fails its CRC check"),
    (lambda data: b"GIF89a" + data[6:], "is not a PNG file"),
])
def test_a_damaged_quality_png_is_said_plainly(tmp_path, damage, problem):
    """Pillow's words ("image file is truncated (0 bytes not processed)", "broken PNG file (bad
    header checksum in b'tEXt')") came through as they were."""
    path = tmp_path / "a.quality.png"
    path.write_bytes(damage(_quality_png(path)))
    with pytest.raises(io.SpherejaxFileError) as refused:
        io.read_quality_png(path)
    assert_plain(str(refused.value), path)
    assert problem in str(refused.value) and "Pillow" not in str(refused.value)


# ------------------------------------------------------------------- the words of each release


@pytest.mark.parametrize("message, rows, problem", [
    # OpenImageIO 3.2 (libtiff's words through it)
    ("Read error at scanline 4294967295; got 16460 bytes, expected 45643", (2, 8),
     "is truncated or corrupted: rows 2 to 7 of its 40 cannot be read: a strip of their pixel data stops after "
     "16460 of its 45643 bytes"),
    ("Decoding error at scanline 39, incorrect data check", (0, 40),
     "is corrupted: the compressed pixel data of rows 0 to 39 of its 40 cannot be decoded (zlib: incorrect data check)"),
    ("Some scanline chunks were missing or corrupted", (0, 40),
     "is truncated or corrupted: the pixel data of rows 0 to 39 of its 40 are missing or cannot be decoded"),
    # OpenImageIO 3.1: nothing for a cut TIFF strip; OpenEXR's "query scanline" for cut pixels
    ("", (2, 8), "is truncated or corrupted: rows 2 to 7 of its 40 cannot be decoded"),
    ("Failed OpenEXR read: Unable to query scanline information", (0, 40),
     "is truncated or corrupted: the pixel data of rows 0 to 39 of its 40 are missing or cannot be decoded"),
])
def test_each_releases_words_for_unreadable_pixels(tmp_path, message, rows, problem):
    """Both OpenImageIO releases in range (3.1 in the oldest set, 3.2 in the newest) are
    translated, whichever one the tests run with."""
    path = tmp_path / "a.tif"
    path.write_bytes(b"x" * 1000)
    said = io.library_messages.image_read_problem(path, message, *rows, 40, "tiff")
    assert said.startswith(problem), said
    assert not [word for word in JARGON if word in said], said


@pytest.mark.parametrize("message, problem", [
    ("EXR Error (/x/a.exr): EXR_ERR_READ_IO End of file attempting to read header",
     "is truncated or corrupted: it ends inside its OpenEXR header (it holds 100 bytes)"),
    ("OpenEXR exception: Unable to open '/x/a.exr' for read",
     "is truncated or corrupted: its OpenEXR header cannot be read (it holds 100 bytes)"),
    ("is not an OpenEXR file", "is not a readable image: it does not start with the OpenEXR signature"),
    ("OpenEXR exception: Invalid or missing attribute when attempting to open for read",
     "is truncated or corrupted: its OpenEXR header is invalid (OpenEXR: Invalid or missing attribute"),
])
def test_each_releases_words_for_an_unreadable_exr_header(tmp_path, message, problem):
    path = tmp_path / "a.exr"
    path.write_bytes(b"x" * 100)
    said = io.library_messages.image_open_problem(path, message)
    assert said.startswith(problem), said
    assert "/x/a.exr" not in said and "EXR_ERR" not in said
