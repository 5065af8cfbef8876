"""Reliability of `spherejax correct` against what the file system does to it: symbolic-link
loops, one input named several ways, and FIFOs, sockets and devices among the inputs.

Each bad input must give one clear line and never hang. (SIGINT / SIGTERM in the middle of a run,
and SIGKILL, are tested with each command: tests/test_archive.py and tests/hw/test_acquire.py.)
"""

from __future__ import annotations

import os
import pathlib
import socket
import subprocess
import sys

import numpy as np
import pytest

from spherejax import io
from tests.batch_support import KINDS, NAMES, frame, manifest_records, outputs_of, run

ENV = {**os.environ, "JAX_PLATFORMS": "cpu"}


@pytest.fixture
def rng():
    return np.random.default_rng(3)


def _cube(path: pathlib.Path, rng) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    io.write_frame(path, frame(rng), channel_names=NAMES)


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("spherejax: warning: ")]


def _correct(cal, inputs, out, capsys):
    return run(["correct", "-c", str(cal), *map(str, inputs), "-o", str(out)], capsys)


# ------------------------------------------------------------------------- links and repeats


def test_a_link_to_the_parent_folder_is_not_followed(cal, tmp_path, rng, capsys):
    """`in/self -> ..` was followed about 40 levels deep: a.tif corrected 41 times, into
    OUT/in/self/in/self/..., exit 0."""
    _cube(tmp_path / "in" / "a.tif", rng)
    (tmp_path / "in" / "self").symlink_to("..")
    out = tmp_path / "out"
    status, stdout, err = _correct(cal, [tmp_path / "in"], out, capsys)
    assert status == 0, err
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    assert sorted(outputs_of(out)) == sorted(f"in/a.{kind}" for kind in KINDS)
    [warning] = _warnings(err)
    assert f"{tmp_path / 'in' / 'self'}: leads to {tmp_path}, which holds {tmp_path / 'in'}" in warning
    assert "not followed" in warning
    assert "Traceback" not in err


def test_a_link_to_the_folder_itself_is_searched_once(cal, tmp_path, rng, capsys):
    _cube(tmp_path / "in" / "a.tif", rng)
    (tmp_path / "in" / "here").symlink_to(".")
    out = tmp_path / "out"
    status, stdout, err = _correct(cal, [tmp_path / "in"], out, capsys)
    assert status == 0, err
    assert sorted(outputs_of(out)) == sorted(f"in/a.{kind}" for kind in KINDS)
    [warning] = _warnings(err)
    assert f"{tmp_path / 'in' / 'here'}: is {tmp_path / 'in'} again, searched already" in warning


def _session(folder: pathlib.Path, rng) -> None:
    stamp = "2026-01-01T00:00:00"
    frames = [
        ({"id": "dark", "role": "dark", "exposure_s": [1.0] * len(NAMES), "timestamp": stamp}, frame(rng)),
        ({"id": "white", "role": "white", "exposure_s": [1.0] * len(NAMES), "timestamp": stamp}, frame(rng)),
        ({"id": "s1", "role": "sample", "exposure_s": [1.0] * len(NAMES), "timestamp": stamp,
          "set": "test", "background": "bg"}, frame(rng)),
    ]
    io.write_session(folder, instrument_id="sphere-1", band_centres_nm=[int(n[:-2]) for n in NAMES],
                     image_shape=[40, 48], saturation=16383, white_patch=[2, 8, 2, 8], holder=[10, 30, 10, 40],
                     frames=frames)


def test_a_link_to_a_parent_holding_a_session_is_not_followed(cal, tmp_path, rng, capsys):
    """The report's case: a link to a parent holding a session gave 1,760 outputs of 43 captures."""
    archive_folder = tmp_path / "archive"
    _session(archive_folder / "sess", rng)
    _cube(archive_folder / "batch" / "a.tif", rng)
    (archive_folder / "batch" / "up").symlink_to("..")
    out = tmp_path / "out"
    status, stdout, err = _correct(cal, [archive_folder / "batch"], out, capsys)
    assert status == 0, err
    assert sorted(outputs_of(out)) == sorted(f"batch/a.{kind}" for kind in KINDS)
    assert len(_warnings(err)) == 1 and "batch/up: leads to" in err
    # The session is corrected when it is asked for, once, however it is reached.
    out2 = tmp_path / "out2"
    status, stdout, err = _correct(cal, [archive_folder / "sess", archive_folder / "batch"], out2, capsys)
    assert status == 0, err
    assert sorted(outputs_of(out2)) == sorted([f"batch/a.{kind}" for kind in KINDS] + [f"sess/frames/s1.{kind}" for kind in KINDS])


def test_the_same_file_given_twice_is_corrected_once(cal, tmp_path, rng, capsys):
    _cube(tmp_path / "in" / "a.tif", rng)
    out = tmp_path / "out"
    status, stdout, err = _correct(cal, [tmp_path / "in" / "a.tif", tmp_path / "in" / "a.tif"], out, capsys)
    assert status == 0, err
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    assert [r["name"] for r in manifest_records(out)] == ["a"]
    [warning] = _warnings(err)
    assert warning == "spherejax: warning: a.tif: is a.tif again (the same file, given twice); skipped: corrected once, as a.tif"


def test_the_same_file_through_a_link_and_directly_is_corrected_once(cal, tmp_path, rng, capsys):
    """The link sorts first; the file is corrected under its real name, the link's is skipped."""
    _cube(tmp_path / "in" / "a.tif", rng)
    (tmp_path / "in" / "0latest.tif").symlink_to("a.tif")
    out = tmp_path / "out"
    status, stdout, err = _correct(cal, [tmp_path / "in"], out, capsys)
    assert status == 0, err
    assert sorted(outputs_of(out)) == sorted(f"in/a.{kind}" for kind in KINDS)
    assert [r["name"] for r in manifest_records(out)] == ["in/a"]
    [warning] = _warnings(err)
    assert warning.startswith("spherejax: warning: in/0latest.tif: is in/a.tif again (the same file, given twice)")
    # The file given again on the command line, beside its folder: still once.
    out2 = tmp_path / "out2"
    status, stdout, err = _correct(cal, [tmp_path / "in", tmp_path / "in" / "0latest.tif"], out2, capsys)
    assert status == 0, err
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    assert len(_warnings(err)) == 2


# ------------------------------------------------------------------------------ special files


def test_fifos_sockets_and_devices_are_refused_without_being_opened(cal, tmp_path, rng):
    """Each is refused by what it is, given or found in a folder; a FIFO was "no such file or
    folder". Run as a subprocess with a timeout: opening a FIFO for reading would block."""
    folder = tmp_path / "in"
    _cube(folder / "a.tif", rng)
    os.mkfifo(folder / "pipe.tif")  # found in a folder, named like a cube
    os.mkfifo(folder / "notes.fifo")  # found in a folder, named like no cube: ignored
    os.mkfifo(tmp_path / "given.tif")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(tmp_path / "s.sock"))
    out = tmp_path / "out"
    try:
        command = [sys.executable, "-m", "spherejax.cli", "-q", "correct", "-c", str(cal), str(folder),
                   str(tmp_path / "given.tif"), str(tmp_path / "s.sock"), "/dev/zero", "/dev/null", "-o", str(out)]
        done = subprocess.run(command, env=ENV, capture_output=True, text=True, timeout=120)
    finally:
        server.close()
    assert done.returncode == 1, done.stderr
    assert done.stdout.strip() == "1 corrected, 0 skipped (already done), 5 failed"
    expected = {
        f"{folder / 'pipe.tif'}: is a FIFO (expected a cube file or a folder)",
        f"{tmp_path / 'given.tif'}: is a FIFO (expected a cube file or a folder)",
        f"{tmp_path / 's.sock'}: is a socket (expected a cube file or a folder)",
        "/dev/zero: is a character device (expected a cube file or a folder)",
        "/dev/null: is a character device (expected a cube file or a folder)",
    }
    lines = done.stderr.strip().splitlines()
    assert len(lines) == len(expected) and "Traceback" not in done.stderr, done.stderr
    for message in expected:
        assert sum(line.startswith("spherejax: failed ") and line.endswith(message) for line in lines) == 1, (message, lines)
    assert sorted(outputs_of(out)) == sorted(f"{folder.relative_to('/').as_posix()}/a.{kind}" for kind in KINDS)


def test_a_fifo_in_a_files_place_after_discovery_is_refused_at_once(tmp_path):
    """The first read of an input (its checksum) opens it without waiting for a writer."""
    os.mkfifo(tmp_path / "a.tif")
    code = (
        "import sys; from spherejax import archive, io\n"
        "spec = archive.InputSpec(name='a', source='a.tif', files=(sys.argv[1],))\n"
        "try:\n    archive.input_checksum(spec)\nexcept io.SpherejaxFileError as error:\n    print(error)\n"
    )
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "a.tif")], env=ENV, capture_output=True,
                          text=True, timeout=60)
    assert done.stdout.strip() == f"{tmp_path / 'a.tif'}: is a FIFO (expected a cube file)", done.stderr
