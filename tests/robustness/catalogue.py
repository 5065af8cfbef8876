"""The machinery of the bad-input catalogues (test_bad_inputs.py,
test_odd_inputs_and_environments.py): a case's folder and its shared inputs, snapshots of a
folder, read-only folders, cases for each command, and `check_case`, which runs one and checks the
catalogue's promises (test_bad_inputs.py's docstring says what they are)."""

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

from spherejax import archive, cli, io
from tests.batch_support import NAMES, frame
from tests.helpers import no_compilation_cache_writes, write_with_oiio
from tests.hw.support import write_profile


@dataclasses.dataclass
class Folder:
    """The case's folder and the shared inputs it may copy."""

    tmp: pathlib.Path
    workspace: pathlib.Path  # session/ and cal.h5 (tests/test_cli.py)
    cube_cal: pathlib.Path  # a calibration for 40 x 48 x 16 cubes (tests/batch_support.py)

    def session(self) -> pathlib.Path:
        """A private copy of the simulated session, to damage."""
        target = self.tmp / "session"
        if not target.exists():
            shutil.copytree(self.workspace / "session", target)
        return target

    def calibration(self) -> pathlib.Path:
        target = self.tmp / "cal.h5"
        if not target.exists():
            shutil.copyfile(self.workspace / "cal.h5", target)
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


def session_case(id, change, problem, command="calibrate"):
    """calibrate (or evaluate) on a session damaged by `change(folder) -> the path to name`."""

    def prepare(f: Folder):
        named = change(f)
        session = f.session()
        if command == "calibrate":
            return ["calibrate", str(session), "-o", str(f.tmp / "new.h5")], str(named)
        return ["evaluate", str(session), "-c", str(f.calibration()), "--out", str(f.tmp / "evaluation")], str(named)

    return Case(id, command, prepare, problem)


def evaluate_with_calibration(id, make_calibration, problem):
    def prepare(f: Folder):
        path = make_calibration(f)
        return ["evaluate", str(f.session()), "-c", str(path), "--out", str(f.tmp / "evaluation")], str(path)

    return Case(id, "evaluate", prepare, problem)


def correct_case(id, make_input, problem, **kwargs):
    """correct -c CAL INPUT -o OUT with --resume over an earlier batch of one good cube."""

    def prepare(f: Folder):
        path = make_input(f)
        return ["correct", "-c", str(f.cube_cal), str(f.tmp / "in"), "-o", str(f.tmp / "out"), "--resume"], str(
            path.relative_to(f.tmp) if path.is_relative_to(f.tmp) else path
        )

    return Case(id, "correct", prepare, problem, batch=True, **kwargs)


def acquire_case(id, make_profile, problem, **kwargs):
    def prepare(f: Folder):
        path = make_profile(f)
        return ["acquire", "--profile", str(path), "-o", str(f.tmp / "acquired"), "--emulate", "--yes"], str(path)

    return Case(id, "acquire", prepare, problem, **kwargs)


def write_file(name: str, content: bytes | str):
    def make(f: Folder) -> pathlib.Path:
        path = f.tmp / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, str):
            path.write_text(content)
        else:
            path.write_bytes(content)
        return path

    return make


def edited_profile(edit: Callable[[str], str]):
    def make(f: Folder) -> pathlib.Path:
        path = write_profile(f.tmp, samples=("train-bg00-g0",))
        path.write_text(edit(path.read_text()))
        return path

    return make


def baseline_batch(f: Folder) -> None:
    """An earlier batch in OUT: one good cube, corrected, which later runs must not touch."""
    f.cube("in/good.tif")
    assert cli.main(["-q", "correct", "-c", str(f.cube_cal), str(f.tmp / "in"), "-o", str(f.tmp / "out")]) == 0


def run_child(argv: list[str], limit: int) -> tuple[int, str]:
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


def check_case(case: Case, workspace, cal, tmp_path, capsys) -> list[str]:
    """Run one case in a fresh folder under tmp_path and check what the module docstring says:
    one line naming the input and the problem, the exit status, no traceback, nothing new or
    partial on disk (for a `correct` batch: only OUT's manifest changed, recording the failure).
    workspace, cal: the fixtures of tests/conftest.py; capsys: pytest's. Returns the non-empty
    lines of stderr, for further checks of their words."""
    f = Folder(tmp_path / "case", workspace, tmp_path / "cube-cal.h5")
    f.tmp.mkdir()
    shutil.copyfile(cal, f.cube_cal)
    if case.batch:
        baseline_batch(f)
    argv, named = case.prepare(f)
    capsys.readouterr()
    before = snapshot(tmp_path)

    with read_only(f.tmp / case.read_only) if case.read_only else contextlib.nullcontext():
        if case.file_size_limit:
            status, err = run_child(argv, case.file_size_limit)
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
    return lines


def assert_refused(status: int, err: str, named, *fragments: str) -> str:
    """Exit status 2, one line naming `named` (the output) with every fragment, no traceback."""
    assert status == cli.EXIT_BAD_INPUT, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"spherejax: error: {named}: "), err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def run_quietly(argv, capsys) -> tuple[int, str, str]:
    """`spherejax -q ARGV` in this process: (exit status, stdout, stderr)."""
    status = cli.main(["-q", *map(str, argv)])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def refused_unchanged(root: pathlib.Path, argv, capsys, named, *fragments: str) -> str:
    """Run `argv` (`run_quietly`): exit status 2, one line naming `named` with every fragment, no
    traceback, nothing on stdout, and everything under `root` as it was; return the line."""
    before = snapshot(root)
    status, out, err = run_quietly(argv, capsys)
    line = assert_refused(status, err, named, *fragments)
    assert out == ""
    assert snapshot(root) == before, sorted(set(snapshot(root).items()) ^ set(before.items()))
    return line
