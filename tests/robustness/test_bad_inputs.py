"""The catalogue of bad inputs (README, "Reliability"): every command and the Python API, each case
refused with one line that names the input and the problem, a non-zero exit status, no traceback,
nothing new or partial on disk and earlier outputs untouched.

A case prepares its files in a fresh folder, runs the command line (in-process, or the real entry
point in a child process where the case needs a file-size limit), and compares a snapshot of the
whole folder (every path, its bytes and modification time) before and after. `correct` goes on
past a bad input (it logs it and exits 1) and records it in OUT's manifest: there the manifest is
the one thing allowed to change, and an earlier batch's outputs in OUT must not.

Read-only folders use the immutable attribute (`chattr +i`), which stops root too (the tests run
as root on CI); a full disk is a file-size limit (RLIMIT_FSIZE), under which writes fail with
EFBIG ("File too large") as they would with ENOSPC.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import pathlib
import shutil
import struct
import subprocess
import sys
from collections.abc import Callable

import numpy as np
import pytest

import spherejax as sj
from hw import profile as hw_profile
from spherejax import archive, cli, io
from tests.helpers import no_compilation_cache_writes
from tests.hw.test_acquire import write_profile
from tests.test_archive import NAMES, frame
from tests.test_io import write_with_oiio

# --------------------------------------------------------------------------------------------
# Helpers


@dataclasses.dataclass
class Folder:
    """The case's folder and the shared inputs it may copy."""

    tmp: pathlib.Path
    workspace: pathlib.Path  # session/ and cal.npz (tests/test_cli.py)
    cube_cal: pathlib.Path  # a calibration for 40 x 48 x 16 cubes (tests/test_archive.py)

    def session(self) -> pathlib.Path:
        """A private copy of the simulated session, to damage."""
        target = self.tmp / "session"
        if not target.exists():
            shutil.copytree(self.workspace / "session", target)
        return target

    def calibration(self) -> pathlib.Path:
        target = self.tmp / "cal.npz"
        if not target.exists():
            shutil.copyfile(self.workspace / "cal.npz", target)
        return target

    def edit_manifest(self, change) -> pathlib.Path:
        path = self.session() / "manifest.json"
        manifest = json.loads(path.read_text())
        change(manifest)
        path.write_text(json.dumps(manifest))
        return path

    def replace_frame(self, name: str, array: np.ndarray) -> pathlib.Path:
        path = self.session() / "frames" / name
        path.unlink()
        io.write_frame(path, np.ascontiguousarray(array))
        return path

    def frame_of(self, name: str) -> np.ndarray:
        return io.read_frame(self.session() / "frames" / name)

    def cube(self, name: str = "in/a.tif", array: np.ndarray | None = None, names=NAMES) -> pathlib.Path:
        path = self.tmp / name
        path.parent.mkdir(parents=True, exist_ok=True)
        io.write_frame(path, frame(np.random.default_rng(3)) if array is None else array, channel_names=names)
        return path


def snapshot(folder: pathlib.Path) -> dict[str, tuple]:
    """Every path under `folder` -> (kind, sha256 or link target, mtime); links not followed."""
    out = {}
    for path in sorted(folder.rglob("*")):
        key = path.relative_to(folder).as_posix()
        if path.is_symlink():
            out[key] = ("link", os.readlink(path), None)
        elif path.is_dir():
            out[key] = ("dir", None, None)
        else:
            out[key] = ("file", hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns)
    return out


@contextlib.contextmanager
def read_only(folder: pathlib.Path):
    """`folder` cannot be written, even by root, for the duration (chattr +i; chmod when not root)."""
    if os.geteuid() == 0:
        subprocess.run(["chattr", "+i", str(folder)], check=True, capture_output=True)
        try:
            yield
        finally:
            subprocess.run(["chattr", "-i", str(folder)], check=True, capture_output=True)
    else:
        mode = folder.stat().st_mode
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(mode)


def huge_tiff(path: pathlib.Path, width: int = 200_000, height: int = 150_000) -> pathlib.Path:
    """A small valid 16-band TIFF whose header then claims width x height pixels."""
    io.write_frame(path, frame(np.random.default_rng(4)), channel_names=NAMES)
    data = bytearray(path.read_bytes())
    assert data[:4] == b"II*\x00", "little-endian classic TIFF expected"
    (ifd,) = struct.unpack_from("<I", data, 4)
    (count,) = struct.unpack_from("<H", data, ifd)
    for index in range(count):
        entry = ifd + 2 + 12 * index
        tag, _ = struct.unpack_from("<HH", data, entry)
        if tag in (256, 257):  # ImageWidth, ImageLength: as LONG values
            struct.pack_into("<HHII", data, entry, tag, 4, 1, width if tag == 256 else height)
    path.write_bytes(bytes(data))
    return path


def write_any_tiff(path: pathlib.Path, array: np.ndarray) -> pathlib.Path:
    """A TIFF of any dtype OpenImageIO writes, in place of `path` (io.write_frame writes uint16 only)."""
    path.unlink(missing_ok=True)
    write_with_oiio(path, [array])
    return path


def truncate(path: pathlib.Path, fraction: float = 0.5) -> pathlib.Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


# --------------------------------------------------------------------------------------------
# The catalogue


@dataclasses.dataclass(frozen=True)
class Case:
    """One bad input. `prepare` makes the files and returns (argv, the input the message names)."""

    id: str
    command: str
    prepare: Callable[[Folder], tuple[list[str], str]]
    problem: str  # a fragment of the message that says what is wrong
    file_size_limit: int | None = None  # bytes: run the real entry point with RLIMIT_FSIZE
    read_only: str | None = None  # a folder under tmp made read-only during the run
    batch: bool = False  # a `correct` batch over a bad input: logged, exit 1, the rest goes on


def _session_case(id, change, problem, command="calibrate"):
    """calibrate (or evaluate) on a session damaged by `change(folder) -> the path to name`."""

    def prepare(f: Folder):
        named = change(f)
        session = f.session()
        if command == "calibrate":
            return ["calibrate", str(session), "-o", str(f.tmp / "new.npz")], str(named)
        return ["evaluate", str(session), "-c", str(f.calibration()), "--out", str(f.tmp / "evaluation")], str(named)

    return Case(id, command, prepare, problem)


def _evaluate_with_calibration(id, make_calibration, problem):
    def prepare(f: Folder):
        path = make_calibration(f)
        return ["evaluate", str(f.session()), "-c", str(path), "--out", str(f.tmp / "evaluation")], str(path)

    return Case(id, "evaluate", prepare, problem)


def _correct_case(id, make_input, problem, **kwargs):
    """correct -c CAL INPUT -o OUT with --resume over an earlier batch of one good cube."""

    def prepare(f: Folder):
        path = make_input(f)
        return ["correct", "-c", str(f.cube_cal), str(f.tmp / "in"), "-o", str(f.tmp / "out"), "--resume"], str(
            path.relative_to(f.tmp) if path.is_relative_to(f.tmp) else path
        )

    return Case(id, "correct", prepare, problem, batch=True, **kwargs)


def _acquire_case(id, make_profile, problem, **kwargs):
    def prepare(f: Folder):
        path = make_profile(f)
        return ["acquire", "--profile", str(path), "-o", str(f.tmp / "acquired"), "--emulate", "--yes"], str(path)

    return Case(id, "acquire", prepare, problem, **kwargs)


def _calibration_bytes(f: Folder) -> dict[str, np.ndarray]:
    with np.load(f.workspace / "cal.npz", allow_pickle=False) as stored:
        return {name: stored[name] for name in stored.files}


def _tampered_calibration(f: Folder) -> pathlib.Path:
    arrays = _calibration_bytes(f)
    arrays["coeffs"] = arrays["coeffs"].copy()
    arrays["coeffs"][0, 0] += 1e-3
    np.savez(f.tmp / "tampered.npz", **arrays)
    return f.tmp / "tampered.npz"


def _newer_calibration(f: Folder) -> pathlib.Path:
    arrays = _calibration_bytes(f)
    header = json.loads(bytes(arrays["header"]).decode())
    header["format_version"] = 99
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez(f.tmp / "newer.npz", **arrays)
    return f.tmp / "newer.npz"


def _other_bands_calibration(f: Folder) -> pathlib.Path:
    calibration, _ = io.load_calibration(f.workspace / "cal.npz")
    io.save_calibration(f.tmp / "other.npz", calibration, instrument_id="x", band_centres_nm=list(range(410, 711, 20)))
    return f.tmp / "other.npz"


def _write(name: str, content: bytes | str):
    def make(f: Folder) -> pathlib.Path:
        path = f.tmp / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, str):
            path.write_text(content)
        else:
            path.write_bytes(content)
        return path

    return make


def _profile(edit: Callable[[str], str]):
    def make(f: Folder) -> pathlib.Path:
        path = write_profile(f.tmp, samples=("train-bg00-g0",))
        path.write_text(edit(path.read_text()))
        return path

    return make


def _frames(f: Folder, name: str) -> pathlib.Path:
    return f.session() / "frames" / name


CATALOGUE: list[Case] = [
    # ---- simulate
    Case("simulate-into-non-empty-folder",
         "simulate", lambda f: (_write("out/keep.txt", "mine")(f) and ["simulate", str(f.tmp / "out")], str(f.tmp / "out")),
         "not an empty folder"),
    Case("simulate-onto-a-file",
         "simulate", lambda f: (_write("out", "a file")(f) and ["simulate", str(f.tmp / "out")], str(f.tmp / "out")),
         "not an empty folder"),
    Case("simulate-into-read-only-folder",
         "simulate", lambda f: ((f.tmp / "locked").mkdir() or ["simulate", str(f.tmp / "locked" / "s")], str(f.tmp / "locked" / "s")),
         "Operation not permitted", read_only="locked"),
    Case("simulate-full-disk",
         "simulate", lambda f: (["simulate", str(f.tmp / "s")], str(f.tmp / "s")),
         "could not be written", file_size_limit=256 * 1024),
    # ---- calibrate: sessions
    Case("session-missing", "calibrate", lambda f: (["calibrate", str(f.tmp / "absent"), "-o", str(f.tmp / "c.npz")],
                                                    str(f.tmp / "absent")), "no such"),
    _session_case("manifest-missing", lambda f: (f.session() / "manifest.json").unlink() or f.session() / "manifest.json", "manifest.json"),
    _session_case("manifest-not-json", lambda f: _write("session/manifest.json", "{ not json")(f.session() and f), "JSON"),
    _session_case("manifest-empty", lambda f: _write("session/manifest.json", b"")(f.session() and f), "JSON"),
    _session_case("manifest-binary", lambda f: _write("session/manifest.json", bytes(range(256)))(f.session() and f), "manifest"),
    _session_case("manifest-no-bands", lambda f: f.edit_manifest(lambda m: m.pop("band_centres_nm")), "band_centres_nm"),
    _session_case("manifest-no-frames", lambda f: f.edit_manifest(lambda m: m.pop("frames")), "frames"),
    _session_case("manifest-frames-not-a-list", lambda f: f.edit_manifest(lambda m: m.__setitem__("frames", 7)), "frames"),
    _session_case("manifest-patch-empty", lambda f: f.edit_manifest(lambda m: m.__setitem__("white_patch", [8, 8, 250, 260])), "white_patch"),
    _session_case("manifest-patch-outside", lambda f: f.edit_manifest(lambda m: m.__setitem__("white_patch", [8, 32, 300, 400])), "white_patch"),
    _session_case("manifest-huge-image-shape", lambda f: f.edit_manifest(lambda m: m.__setitem__("image_shape", [10**9, 10**9]))
                  and _frames(f, "dark.tif"), "1000000000"),
    _session_case("manifest-frame-path-escapes", lambda f: f.edit_manifest(
        lambda m: m["frames"][0].__setitem__("file", "../../../etc/passwd")), "inside the folder"),
    _session_case("frame-missing", lambda f: _frames(f, "train-bg01-g0.tif").unlink() or _frames(f, "train-bg01-g0.tif"), "train-bg01-g0.tif"),
    _session_case("frame-not-an-image", lambda f: _write("session/frames/dark.tif", "not a TIFF")(f.session() and f), "dark.tif"),
    _session_case("frame-empty-file", lambda f: _write("session/frames/dark.tif", b"")(f.session() and f), "dark.tif"),
    _session_case("frame-truncated", lambda f: truncate(_frames(f, "white.tif"), 0.3), "white.tif"),
    _session_case("frame-huge-header", lambda f: huge_tiff(_frames(f, "white.tif")), "white.tif"),
    _session_case("frame-wrong-size", lambda f: f.replace_frame("train-bg00-g0.tif", f.frame_of("train-bg00-g0.tif")[:-4]), "train-bg00-g0.tif"),
    _session_case("frame-wrong-band-count", lambda f: f.replace_frame("white.tif", f.frame_of("white.tif")[..., :15]), "white.tif"),
    _session_case("frame-wrong-dtype", lambda f: write_any_tiff(_frames(f, "white.tif"), f.frame_of("white.tif").astype(np.int32)), "uint16"),
    _session_case("white-equals-dark", lambda f: f.replace_frame("white.tif", f.frame_of("dark.tif")), "white standard"),
    _session_case("white-below-dark", lambda f: f.replace_frame("white.tif", np.zeros_like(f.frame_of("dark.tif"))), "white standard"),
    _session_case("white-all-nan", lambda f: write_any_tiff(_frames(f, "white.tif"), np.full(f.frame_of("white.tif").shape, np.nan, np.float32)), "uint16"),
    _session_case("white-saturated", lambda f: f.replace_frame("white.tif", np.full_like(f.frame_of("white.tif"), 65535)), "white standard"),
    _session_case("samples-all-zero", lambda f: [
        f.replace_frame(m["file"].split("/")[-1], np.zeros_like(f.frame_of("white.tif")))
        for m in json.loads((f.session() / "manifest.json").read_text())["frames"] if m["role"] == "sample"
    ][0], "white-patch ratio"),
    _session_case("targets-all-zero", lambda f: [
        f.replace_frame(m["file"].split("/")[-1], np.zeros_like(f.frame_of("white.tif")))
        for m in json.loads((f.session() / "manifest.json").read_text())["frames"] if m["role"] == "target"
    ] and f.session() / "manifest.json", "target regions"),
    # ---- calibrate: the output
    Case("calibrate-into-read-only-folder", "calibrate",
         lambda f: ((f.tmp / "locked").mkdir() or ["calibrate", str(f.session()), "-o", str(f.tmp / "locked" / "c.npz")],
                    str(f.tmp / "locked" / "c.npz")), "Operation not permitted", read_only="locked"),
    Case("calibrate-full-disk", "calibrate",
         lambda f: (["calibrate", str(f.session()), "-o", str(f.tmp / "c.npz")], str(f.tmp / "c.npz")),
         "File too large", file_size_limit=64 * 1024),
    Case("calibrate-onto-a-folder", "calibrate",
         lambda f: ((f.tmp / "c.npz").mkdir() or ["calibrate", str(f.session()), "-o", str(f.tmp / "c.npz")], str(f.tmp / "c.npz")),
         "Is a directory"),
    # ---- evaluate: calibration files
    _evaluate_with_calibration("calibration-missing", lambda f: f.tmp / "none.npz", "no such"),
    _evaluate_with_calibration("calibration-empty", _write("empty.npz", b""), "npz"),
    _evaluate_with_calibration("calibration-not-npz", _write("text.npz", "hello"), "npz"),
    _evaluate_with_calibration("calibration-truncated", lambda f: truncate(f.calibration(), 0.5), "npz"),
    _evaluate_with_calibration("calibration-tampered", _tampered_calibration, "checksum"),
    _evaluate_with_calibration("calibration-newer-version", _newer_calibration, "99"),
    _evaluate_with_calibration("calibration-other-bands", _other_bands_calibration, "bands"),
    Case("evaluate-into-read-only-folder", "evaluate",
         lambda f: ((f.tmp / "locked").mkdir() or ["evaluate", str(f.session()), "-c", str(f.calibration()),
                                                   "--out", str(f.tmp / "locked" / "e")], str(f.tmp / "locked" / "e")),
         "Operation not permitted", read_only="locked"),
    # ---- correct: inputs (each fails alone; an earlier batch's outputs stay as they were)
    _correct_case("cube-not-an-image", _write("in/text.tif", "not an image"), "not a readable image"),
    _correct_case("cube-empty-file", _write("in/empty.tif", b""), "in/empty.tif"),
    _correct_case("cube-truncated", lambda f: truncate(f.cube("in/cut.tif")), "corrupted"),
    _correct_case("cube-huge-header", lambda f: huge_tiff(f.tmp / "in" / "huge.tif"), "200000"),
    _correct_case("cube-wrong-band-count", lambda f: f.cube("in/b15.tif", frame(np.random.default_rng(5), (40, 48, 15)), NAMES[:15]), "15 channels"),
    _correct_case("cube-wrong-size", lambda f: f.cube("in/size.tif", frame(np.random.default_rng(5), (40, 50, 16))), "40 x 50"),
    _correct_case("cube-wrong-dtype", lambda f: write_any_tiff(f.tmp / "in" / "int8.tif", np.zeros((40, 48, 16), np.int8)), "in/int8.tif"),
    _correct_case("output-through-a-link-out-of-out", lambda f: (
        (f.tmp / "elsewhere").mkdir() or (f.tmp / "out" / "in" / "esc").symlink_to(f.tmp / "elsewhere")
        or f.cube("in/esc/y.tif")), "would be written outside OUT"),
    Case("calibration-missing-for-correct", "correct", lambda f: (
        f.cube("in/a.tif") and ["correct", "-c", str(f.tmp / "none.npz"), str(f.tmp / "in"), "-o", str(f.tmp / "out2")],
        str(f.tmp / "none.npz")), "no such"),
    # ---- acquire: profiles
    _acquire_case("profile-missing", lambda f: f.tmp / "none.toml", "no such"),
    _acquire_case("profile-empty", _write("empty.toml", ""), "instrument"),
    _acquire_case("profile-not-toml", _write("bad.toml", "[instrument\nid = "), "TOML"),
    _acquire_case("profile-binary", _write("bin.toml", bytes(range(256)) * 4), "bin.toml"),
    _acquire_case("profile-no-camera", _profile(lambda t: t.replace('[camera]\nbackend = "sim"\n', "")), "camera"),
    _acquire_case("profile-band-on-unknown-wheel", _profile(lambda t: t.replace('400 = ["a", 1]', '400 = ["z", 1]')), "z"),
    _acquire_case("profile-slot-out-of-range", _profile(lambda t: t.replace('400 = ["a", 1]', '400 = ["a", 99]')), "99"),
    _acquire_case("profile-negative-frames", _profile(lambda t: t.replace("frames_averaged = 2", "frames_averaged = -3")), "frames_averaged"),
    Case("acquire-into-read-only-folder", "acquire",
         lambda f: ((f.tmp / "locked").mkdir() or ["acquire", "--profile", str(write_profile(f.tmp, samples=("train-bg00-g0",))),
                                                   "-o", str(f.tmp / "locked" / "s"), "--emulate", "--yes"],
                    str(f.tmp / "locked" / "s")), "Operation not permitted", read_only="locked"),
]


def _baseline_batch(f: Folder) -> None:
    """An earlier batch in OUT: one good cube, corrected, which later runs must not touch."""
    f.cube("in/good.tif")
    assert cli.main(["-q", "correct", "-c", str(f.cube_cal), str(f.tmp / "in"), "-o", str(f.tmp / "out")]) == 0


def _run_child(argv: list[str], limit: int) -> tuple[int, str]:
    """The real entry point under a file-size limit, set by a tiny launcher that then execs it
    (not preexec_fn: forking this multithreaded JAX process is unsafe, and JAX warns)."""
    launcher = (
        "import os, resource, sys; "
        f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit})); "
        "os.execv(sys.executable, [sys.executable, '-m', 'spherejax.cli', '-q', *sys.argv[1:]])"
    )
    # Under the limit a write of the shared compilation cache would be cut short: read it only.
    env = no_compilation_cache_writes({**os.environ, "JAX_PLATFORMS": "cpu"})
    result = subprocess.run([sys.executable, "-c", launcher, *argv], capture_output=True, text=True, env=env, timeout=600)
    return result.returncode, result.stderr


def parameters(cases: list[Case], slow: set[str]) -> list:
    """`cases` as parameters named by their ids, those in `slow` (over about 10 s on a 2-core
    machine: a whole calibrate, evaluate or simulate) marked so."""
    assert slow <= {case.id for case in cases}, slow
    return [pytest.param(case, id=case.id, marks=[pytest.mark.slow] if case.id in slow else []) for case in cases]


@pytest.mark.parametrize("case", parameters(CATALOGUE, slow={"simulate-full-disk", "calibrate-full-disk",
                                                             "evaluate-into-read-only-folder"}))
def test_bad_input(case: Case, workspace, cal, tmp_path, capsys):
    f = Folder(tmp_path / "case", workspace, tmp_path / "cube-cal.npz")
    f.tmp.mkdir()
    shutil.copyfile(cal, f.cube_cal)
    if case.batch:
        _baseline_batch(f)
    argv, named = case.prepare(f)
    capsys.readouterr()
    before = snapshot(tmp_path)

    with read_only(f.tmp / case.read_only) if case.read_only else contextlib.nullcontext():
        if case.file_size_limit:
            status, err = _run_child(argv, case.file_size_limit)
        else:
            status = cli.main(["-q", *argv])
            err = capsys.readouterr().err
    after = snapshot(tmp_path)

    assert status != 0, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    if case.batch:
        # Logged once as it happens and once in the summary, one line each, exit status 1.
        assert status == 1
        mentions = [line for line in lines if named in line]
        assert mentions and all(case.problem in line for line in mentions), err
        # The earlier batch's outputs are untouched; the manifest, the one file allowed to
        # change, records the failure; nothing else is new.
        changed = {key for key in set(before) | set(after) if before.get(key) != after.get(key)}
        manifest = f"case/out/{archive.MANIFEST_NAME}"
        assert changed <= {manifest}, sorted(changed)
        if manifest in changed:
            records = archive.read_manifest(f.tmp / "out")
            assert any(r["status"] == "failed" for r in records.values())
    else:
        assert status == cli.EXIT_BAD_INPUT, err
        assert len(lines) == 1 and lines[0].startswith("spherejax: error: "), err
        assert named in lines[0] or pathlib.Path(named).name in lines[0], (named, lines[0])
        assert case.problem in lines[0], (case.problem, lines[0])
        assert after == before, sorted(set(before) ^ set(after))


def test_catalogue_size():
    """The issue asks for at least 40 cases across simulate, calibrate, correct, evaluate,
    acquire and the Python API (below)."""
    assert len(CATALOGUE) + len(API_CASES) >= 40
    assert {case.command for case in CATALOGUE} == {"simulate", "calibrate", "evaluate", "correct", "acquire"}


# --------------------------------------------------------------------------------------------
# The Python API: ValueError (or its subclass SpherejaxFileError) with one line naming the argument


def _api_calibration(**changes):
    rng = np.random.default_rng(0)
    fields = dict(dark=np.zeros((8, 9, 16), np.float32), white=np.full((8, 9, 16), 100.0, np.float32),
                  patch=np.pad(np.ones((2, 2), bool), ((0, 6), (0, 7))), coeffs=np.asarray(sj.identity_coeffs(16)),
                  wiener=rng.uniform(0, 0.1, (31, 16)).astype(np.float32), saturation=16383.0)
    fields.update(changes)
    return sj.Calibration(**fields)


API_CASES = {
    "calibration-white-shape": (lambda tmp: _api_calibration(white=np.ones((8, 9, 15))), "white"),
    "calibration-coeffs-shape": (lambda tmp: _api_calibration(coeffs=np.ones((16, 3))), "coeffs"),
    "calibration-wiener-shape": (lambda tmp: _api_calibration(wiener=np.ones((30, 16))), "wiener"),
    "calibration-empty-patch": (lambda tmp: _api_calibration(patch=np.zeros((8, 9), bool)), "patch"),
    "calibration-unknown-illuminant": (lambda tmp: _api_calibration(illuminant="D50x"), "D50x"),
    "calibration-negative-saturation": (lambda tmp: _api_calibration(saturation=-1.0), "saturation"),
    "correct-wrong-bands": (lambda tmp: sj.correct(np.zeros((8, 9, 15), np.uint16), _api_calibration()), "raw"),
    "correct-wrong-size": (lambda tmp: sj.correct(np.zeros((9, 9, 16), np.uint16), _api_calibration()), "raw"),
    "correct-complex-dtype": (lambda tmp: sj.correct(np.zeros((8, 9, 16), np.complex64), _api_calibration()), "raw"),
    "correct-p-wrong-length": (lambda tmp: sj.correct(np.zeros((8, 9, 16), np.uint16), _api_calibration(), p=np.ones(3)), "p"),
    "delta-e-wrong-axis": (lambda tmp: sj.delta_e_2000(np.zeros((5, 4)), np.zeros((5, 3))), "lab1"),
    "read-frame-huge-header": (lambda tmp: io.read_frame(huge_tiff(tmp / "huge.tif")), "huge.tif"),
    "read-frame-not-an-image": (lambda tmp: io.read_frame(_write("x.exr", "text")(Folder(tmp, tmp, tmp))), "x.exr"),
    "load-calibration-random-bytes": (lambda tmp: io.load_calibration(_write("r.npz", os.urandom(4096))(Folder(tmp, tmp, tmp))), "r.npz"),
    "load-session-missing": (lambda tmp: io.load_session(tmp / "nowhere"), "nowhere"),
    "load-profile-not-toml": (lambda tmp: hw_profile.load_profile(_write("p.toml", "= =")(Folder(tmp, tmp, tmp))), "p.toml"),
}


@pytest.mark.parametrize("name", list(API_CASES))
def test_api_bad_input(name, tmp_path):
    make, fragment = API_CASES[name]
    before = snapshot(tmp_path)
    with pytest.raises(ValueError) as raised:
        make(tmp_path)
    message = str(raised.value)
    assert "\n" not in message and fragment in message, message
    created = set(snapshot(tmp_path)) - set(before)
    # Only the case's own input file may be new; nothing is written by the call.
    assert len(created) <= 1, created


# --------------------------------------------------------------------------------------------
# Frames that are all NaN, all zero or saturated are not refused by `correct`: they come out
# with every pixel flagged and NaN, never as numbers.


@pytest.mark.parametrize("fill", ["nan", "zero", "saturated"])
def test_degenerate_frames_come_out_flagged_not_as_numbers(fill):
    calibration = _api_calibration()
    raw = {"nan": np.full((8, 9, 16), np.nan, np.float32), "zero": np.zeros((8, 9, 16), np.float32),
           "saturated": np.full((8, 9, 16), 16383, np.uint16)}[fill]
    result = sj.correct(raw, calibration)
    quality = np.asarray(result.quality)
    if fill == "zero":
        # Zero counts, dark 0: v = 0 everywhere and the patch signal is 0, so p is not finite.
        assert (quality & sj.QUALITY_PATCH_UNUSABLE).all()
    else:
        expected = sj.QUALITY_NONFINITE if fill == "nan" else sj.QUALITY_SATURATED
        assert (quality & expected).all()
    assert np.isnan(np.asarray(result.reflectance)).all() and np.isnan(np.asarray(result.lab)).all()
