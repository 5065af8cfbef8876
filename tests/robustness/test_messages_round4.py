"""Messages when the environment, not an input, is what is wrong (docs/reliability.md, section 1):
closed or non-interactive stdin, closed, full or abandoned stdout, a working folder deleted under
the shell, output folders that cannot be written, and a locale that is not UTF-8.

Each must end in one line naming what is wrong (or, for a reader of stdout that went away, the
exit status Unix tools give, 141), never a traceback, and never after the work when it could be
found before it. The stream cases run the real entry point in a child process, since they are
about the process's own descriptors; the rest run in-process where they can.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

from spherejax import archive, cli, io
from spherejax.cli import streams
from spherejax.io.library_messages import library_path
from tests.batch_support import NAMES, frame
from tests.hw.support import write_profile
from tests.robustness.catalogue import read_only, snapshot

ENV = {**os.environ, "JAX_PLATFORMS": "cpu"}
#: A locale that is not UTF-8, with Python's UTF-8 mode and its locale coercion both off: file
#: names and arguments then reach Python as ASCII with lone surrogates for the other bytes.
C_LOCALE = {**ENV, "LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
SPHEREJAX = [sys.executable, "-m", "spherejax.cli"]


def _run(args, *, env=ENV, cwd=None, shell_redirect: str = "", stdin=None) -> subprocess.CompletedProcess:
    """The real entry point with `args`; `shell_redirect` (">&-", "> /dev/full", "<&-") applied
    by a shell that then execs it."""
    if shell_redirect:
        command = ["bash", "-c", f'exec "$@" {shell_redirect}', "spherejax", *SPHEREJAX, *map(str, args)]
    else:
        command = [*SPHEREJAX, *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, env=env, cwd=cwd, timeout=600, stdin=stdin)


def _one_error_line(err: str) -> str:
    """The one error line of `err` (measure's note that the calibration has no noise model aside)."""
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("spherejax: note: ")]
    assert len(lines) == 1 and lines[0].startswith("spherejax: error: "), err
    return lines[0]


def _cube(path: pathlib.Path) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    io.write_frame(path, frame(np.random.default_rng(3)), channel_names=NAMES)
    return path


# --------------------------------------------------------------------------------------------
# stdin: a prompt that has no terminal to answer it


@pytest.mark.parametrize("stdin", ["closed", "dev-null"])
def test_acquire_without_yes_and_no_terminal_on_stdin_refuses_in_one_line(stdin, tmp_path):
    """A closed stdin (`<&-`) raised AttributeError on None.isatty(); /dev/null is the same case
    seen another way. Either: one line saying a terminal or --yes is needed, exit 2, nothing made."""
    profile = write_profile(tmp_path, samples=("train-bg00-g0",))
    before = snapshot(tmp_path)
    args = ["acquire", "--profile", profile, "-o", tmp_path / "acquired", "--emulate"]
    if stdin == "closed":
        result = subprocess.run(["bash", "-c", 'exec "$@" <&-', "spherejax", *SPHEREJAX, *map(str, args)],
                                capture_output=True, text=True, env=ENV, timeout=600)
    else:
        result = _run(args, stdin=subprocess.DEVNULL)
    assert result.returncode == 2, result.stderr
    line = _one_error_line(result.stderr)
    assert "terminal" in line and "--yes" in line, line
    assert snapshot(tmp_path) == before


def test_an_operator_prompt_with_stdin_none_or_at_its_end_is_an_acquisition_error(monkeypatch):
    """Through the API (no command line to open /dev/null on a closed stdin): sys.stdin None is
    'no terminal', and a terminal that ends while the prompt waits stops the run in words."""
    from spherejax_hw import acquire

    monkeypatch.setattr(sys, "stdin", None)
    with pytest.raises(acquire.AcquisitionError, match="terminal"):
        acquire.Operator(yes=False).check_can_prompt()

    def ended(prompt):
        raise EOFError

    with pytest.raises(acquire.AcquisitionError, match="standard input ended while waiting"):
        acquire.Operator(yes=False, input_fn=ended).ask("place the white standard")


# --------------------------------------------------------------------------------------------
# stdout: full, closed, or a reader that went away


def test_version_into_a_full_device_fails_in_one_line():
    """`--version > /dev/full` exited 0: the line was lost and nobody said so."""
    result = _run(["--version"], shell_redirect="> /dev/full")
    assert result.returncode == 2, result.stderr
    line = _one_error_line(result.stderr)
    assert "standard output" in line and "No space left on device" in line, line


def test_version_into_a_closed_stdout_fails_in_one_line():
    result = subprocess.run(["bash", "-c", 'exec "$@" >&-', "spherejax", *SPHEREJAX, "--version"],
                            capture_output=True, text=True, env=ENV, timeout=600)
    assert result.returncode == 2, result.stderr
    line = _one_error_line(result.stderr)
    assert "standard output" in line and "closed" in line, line


def test_version_into_a_pipe_nobody_reads_exits_141_silently():
    process = subprocess.Popen([*SPHEREJAX, "--version"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV)
    process.stdout.close()  # the reader is gone before the line is written
    with process.stderr:
        err = process.stderr.read().decode()
    assert process.wait(timeout=600) == streams.EXIT_BROKEN_PIPE, err
    assert err == "", err


def test_correct_into_a_pipe_nobody_reads_records_the_batch_then_exits_141(cal, tmp_path):
    """`correct ... | true` did all the work, then printed "[Errno 32] Broken pipe" and exited 2.
    Now the batch is finished and recorded, and the exit status is a Unix tool's (141), with no
    message: the reader chose to stop reading."""
    _cube(tmp_path / "in" / "a.tif")
    _cube(tmp_path / "in" / "b.tif")
    out = tmp_path / "out"
    process = subprocess.Popen([*SPHEREJAX, "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV)
    process.stdout.close()
    with process.stderr:
        err = process.stderr.read().decode()
    assert process.wait(timeout=600) == streams.EXIT_BROKEN_PIPE, err
    assert "Broken pipe" not in err and "Traceback" not in err and "error" not in err, err
    records = archive.read_manifest(out)
    assert sorted(records) == ["in/a", "in/b"] and all(r["status"] == "done" for r in records.values()), records


def test_measure_into_a_full_device_writes_its_files_then_fails_in_one_line(cal, tmp_path):
    """A variant at another command: the measurement's files are written (the work is done and
    kept), and the lost table is said in one line, exit 2."""
    cube = _cube(tmp_path / "a.tif")
    result = _run(["measure", "-c", cal, cube, "--region", "r=0,10,0,10", "-o", tmp_path / "m"],
                  shell_redirect="> /dev/full")
    assert result.returncode == 2, result.stderr
    line = _one_error_line(result.stderr)
    assert "standard output" in line and "No space left on device" in line, line
    assert (tmp_path / "m.csv").is_file() and (tmp_path / "m.json").is_file()


def test_the_guard_keeps_the_first_failure_and_drops_later_writes():
    """The stream a command writes through never raises; the first failure decides the status."""

    class Full:
        def write(self, text):
            raise OSError(28, "No space left on device")

        def flush(self):
            pass

    guarded = streams._GuardedStream(Full(), "<stdout>")
    assert guarded.write("abc") == 3 and guarded.write("def") == 3
    assert guarded.failure.errno == 28
    messages = streams._GuardedStream(__import__("io").StringIO(), "<stderr>")
    assert streams.Guard(guarded, messages).exit_status(0) == 2
    assert "No space left on device" in messages._stream.getvalue()
    assert streams.Guard(guarded, messages).exit_status(1) == 1  # a failed command keeps its status
    broken = streams._GuardedStream(Full(), "<stdout>")
    broken.failure = BrokenPipeError(32, "Broken pipe")
    assert streams.Guard(broken, messages).exit_status(0) == 141


# --------------------------------------------------------------------------------------------
# A working folder deleted under the shell


@pytest.mark.parametrize("command", [["calibrate", "session", "-o", "c.h5"],
                                     ["measure", "-c", "cal.h5", "a.tif", "--region", "r=0,1,0,1"]])
def test_a_deleted_working_folder_is_named_in_one_line(command, tmp_path):
    """os.getcwd() fails in a folder removed while the shell stood in it: every relative path
    failed as "[Errno 2] No such file or directory" naming nothing."""
    gone = tmp_path / "gone"
    gone.mkdir()
    script = f'cd {gone} && rmdir {gone} && exec "$@"'
    result = subprocess.run(["bash", "-c", script, "spherejax", *SPHEREJAX, *command],
                            capture_output=True, text=True, env=ENV, timeout=600)
    assert result.returncode == 2, result.stderr
    line = _one_error_line(result.stderr)
    assert "working folder" in line and str(gone) in line and "no longer exists" in line, line


# --------------------------------------------------------------------------------------------
# Output folders that cannot be written: refused before any work


def _no_work(monkeypatch):
    """Every command's first piece of real work raises: a refusal must come before it."""
    from spherejax import calibrate, evaluate, measurement, study

    def started(*args, **kwargs):
        raise AssertionError("the work started before the output folder was checked")

    monkeypatch.setattr(evaluate, "evaluate_session", started)
    monkeypatch.setattr(calibrate, "calibrate_session", started)
    monkeypatch.setattr(study, "study_session", started)
    monkeypatch.setattr(io, "write_simulated_session", started)
    monkeypatch.setattr(io, "read_cube", started)
    monkeypatch.setattr(measurement, "measure", started)


@pytest.mark.parametrize("command", ["evaluate", "study", "calibrate", "simulate", "demo", "measure", "measure-cgats"])
def test_an_output_folder_that_cannot_be_written_is_refused_before_any_work(
        command, workspace, cal, tmp_path, capsys, monkeypatch):
    """`evaluate` into a read-only folder failed after 30 s of work. Every writing command tries
    its output folder first (immutable, so that root is stopped too) and names it in one line."""
    locked = tmp_path / "locked"
    locked.mkdir()
    cube = _cube(tmp_path / "a.tif")
    session, calibration = workspace / "session", workspace / "cal.h5"
    argv, named = {
        "evaluate": (["evaluate", session, "-c", calibration, "-o", locked / "e"], locked / "e"),
        "study": (["study", session, "-c", calibration, "-o", locked / "s"], locked / "s"),
        "calibrate": (["calibrate", session, "-o", locked / "c.h5"], locked / "c.h5"),
        "simulate": (["simulate", "-o", locked / "session"], locked / "session"),
        "demo": (["demo", "-o", locked / "demo"], locked / "demo"),
        "measure": (["measure", "-c", cal, cube, "--region", "r=0,10,0,10", "-o", locked / "m"], locked / "m.csv"),
        "measure-cgats": (["measure", "-c", cal, cube, "--region", "r=0,10,0,10", "-o", tmp_path / "m",
                           "--cgats", locked / "m.txt"], locked / "m.txt"),
    }[command]
    _no_work(monkeypatch)
    before = snapshot(tmp_path)
    with read_only(locked):
        status = cli.main(["-q", *map(str, argv)])
    err = capsys.readouterr().err
    assert status == 2, err
    line = _one_error_line(err)
    assert str(named) in line and "cannot be" in line and "Operation not permitted" in line, line
    assert snapshot(tmp_path) == before


def test_a_writable_output_folder_is_tried_and_left_as_it_was(tmp_path):
    from spherejax.cli.shared import check_writable

    (tmp_path / "out").mkdir()
    check_writable(tmp_path / "out", "-o DIR", folder=True)
    check_writable(tmp_path / "new" / "deeper" / "x.h5", "-o CAL", folder=False)  # the nearest folder that exists
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and not any((tmp_path / "out").iterdir())


# --------------------------------------------------------------------------------------------
# A locale that is not UTF-8


def test_library_path_is_the_utf8_of_the_names_bytes(tmp_path):
    """OpenImageIO's binding encodes a str as UTF-8; a name decoded under LC_ALL=C holds lone
    surrogates it refused ("incompatible function arguments"). The same bytes, read as UTF-8,
    open the file; bytes that are not UTF-8 are refused naming the file."""
    escaped = str(tmp_path / "r\udcc3\udcb4t.tif")  # "rôt.tif" as os.fsdecode gives it under LC_ALL=C
    assert library_path(escaped) == str(tmp_path / "rôt.tif")
    _cube(tmp_path / "rôt.tif")
    assert io.read_frame(escaped).shape == frame(np.random.default_rng(3)).shape  # through OpenImageIO
    latin1 = os.fsdecode(bytes(tmp_path / "caf") + b"\xe9.tif")
    with pytest.raises(io.SpherejaxFileError, match="has a name that is not UTF-8") as refused:
        library_path(latin1)
    assert refused.value.path == latin1


def test_correct_and_measure_take_utf8_names_under_the_c_locale(cal, tmp_path):
    """Under LC_ALL=C (PYTHONUTF8=0), `correct` failed "rôt.tif" with OpenImageIO's
    "incompatible function arguments", and `measure` with a traceback; a region named "rôt" was
    said to hold "a control character", and the table's "±" could not be printed."""
    cube = _cube(tmp_path / "in" / "rôt.tif")
    _cube(tmp_path / "in" / "b.tif")
    result = _run(["correct", "-c", cal, tmp_path / "in", "-o", tmp_path / "out"], env=C_LOCALE)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert (tmp_path / "out" / "in" / "rôt.reflectance.exr").is_file()
    assert all(r["status"] == "done" for r in archive.read_manifest(tmp_path / "out").values())

    result = _run(["measure", "-c", cal, cube, "--region", "rôt=0,10,0,10", "--reference", "rôt",
                   "-o", tmp_path / "m"], env=C_LOCALE)
    assert result.returncode == 0, result.stderr
    assert [line for line in result.stderr.splitlines() if not line.startswith("spherejax: note: ")] == []
    assert "L*" in result.stdout  # the table, "±" and all, in a locale that has no "±"
    assert (tmp_path / "m.csv").read_text(encoding="utf-8").splitlines()[1].startswith("rôt,")


def test_a_batch_with_utf8_names_resumes_under_the_c_locale(cal, tmp_path):
    """Under LC_ALL=C the manifest records "rôt.tif" by the lone surrogates Python decodes its
    bytes to; the record check refused them (pydantic's strings cannot hold them), so `--resume`
    never trusted the record and corrected the input again."""
    _cube(tmp_path / "in" / "rôt.tif")
    _cube(tmp_path / "in" / "b.tif")
    argv = ["correct", "-c", cal, tmp_path / "in", "-o", tmp_path / "out"]
    assert _run(argv, env=C_LOCALE).returncode == 0
    before = snapshot(tmp_path / "out")
    result = _run([*argv, "--resume"], env=C_LOCALE)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    assert result.stdout.strip() == "0 corrected, 2 skipped (already done), 0 failed"
    assert snapshot(tmp_path / "out") == before


@pytest.mark.parametrize("region, problem", [(b"r\xf4t=0,10,0,10", "is not UTF-8 text"),
                                             (b"r\tt=0,10,0,10", "control character")])
def test_a_region_name_is_refused_for_what_is_wrong_with_it_under_the_c_locale(region, problem, cal, tmp_path):
    cube = _cube(tmp_path / "a.tif")
    command = [*SPHEREJAX, "measure", "-c", str(cal), str(cube), "--region", region, "-o", str(tmp_path / "m")]
    result = subprocess.run(command, capture_output=True, text=True, env=C_LOCALE, timeout=600)
    assert result.returncode == 2, result.stderr
    line = _one_error_line(result.stderr)
    assert "--region" in line and problem in line, line
    assert not (tmp_path / "m.csv").exists()


def test_the_streams_write_names_as_their_bytes_and_other_characters_as_escapes():
    assert "r\udcc3\udcb4t ±".encode("ascii", streams.ERROR_HANDLER) == b"r\xc3\xb4t \\xb1"



def test_a_session_with_utf8_names_calibrates_under_the_c_locale(workspace, tmp_path):
    """Variants at another command and other paths: a session folder "séance" whose manifest
    names a frame "frames/blänc.tif" (UTF-8 text, which LC_ALL=C cannot encode as a path), read
    through OpenImageIO, and a calibration written by h5py whose header records the session's
    path (it failed: "'utf-8' codec can't encode characters ...: surrogates not allowed")."""
    import json

    session = tmp_path / "séance"
    shutil.copytree(workspace / "session", session)
    manifest = json.loads((session / "manifest.json").read_text())
    white = next(frame for frame in manifest["frames"] if frame["role"] == "white")
    (session / white["file"]).rename(session / "frames" / "blänc.tif")
    white["file"] = "frames/blänc.tif"
    (session / "manifest.json").write_text(json.dumps(manifest, ensure_ascii=False), encoding="utf-8")
    result = _run(["-q", "calibrate", session, "-o", session / "câl.h5"], env=C_LOCALE)
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    calibration_file = io.open_calibration(session / "câl.h5")
    try:
        assert calibration_file.header["metadata"]["session"] == str(session)
    finally:
        calibration_file.close()
