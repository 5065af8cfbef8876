"""`spherejax correct` proves every file it replaces or removes its own, one file at a time, and
creates nothing before its inputs are found and OUT is known to lie apart from them.

- A file at an output's name is spherejax's only when its bytes are bytes spherejax recorded
  putting at that very name: the SHA-256 a record of OUT's manifest lists for it, or one a run
  wrote into its lock file just before renaming the file into place (its made records). An EXR
  copied from another batch whose source matches proves nothing about the user's preview.png
  beside it; a recorded name now holding the user's bytes is the user's; a name a killed run
  claimed but never wrote is not its own.
- OUT may not be an input, lie inside one or hold one (a folder given, a session's folder, an
  input file), however the paths are spelled: refused in one line before anything is created.
- A path given that leads to nothing refuses the batch before OUT, its manifest or its lock
  exist, so that the corrected command is a new batch, not a `--resume`.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest

from spherejax import archive, cli, io
from spherejax.archive import batch as batch_module
from spherejax.archive import lock as lock_module
from tests.batch_support import NAMES, frame, manifest_records, outputs_of, run
from tests.helpers import no_compilation_cache_writes
from tests.robustness.catalogue import snapshot


def _correct(cal, inputs, out, *extra):
    return ["correct", "-c", str(cal), *map(str, inputs), "-o", str(out), *extra]


def _inputs(tmp_path, names=("a",), seed=3):
    """tmp_path/in holding a 16-band cube per name."""
    folder = tmp_path / "in"
    folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    for name in names:
        io.write_frame(folder / f"{name}.tif", frame(rng), channel_names=NAMES)
    return folder


def _refused(status, stdout, err) -> str:
    """The one error line of a batch refused with exit status 2."""
    assert status == cli.EXIT_BAD_INPUT and stdout == "", (status, stdout, err)
    assert "Traceback" not in err
    line, = err.strip().splitlines()
    assert line.startswith("spherejax: error: ")
    return line


IN_THE_WAY = "is in the way of an output"


def _but_lock(folder):
    """`snapshot` of a folder without OUT's lock file (a refused run that took over a killed run's
    lock leaves it, its own pid in the holder's line)."""
    return {name: entry for name, entry in snapshot(folder).items() if name != archive.LOCK_NAME}


# ----------------------------------------------- a matching EXR proves nothing about its neighbours


@pytest.mark.parametrize("input_state", ["good", "damaged"])
def test_an_exr_copied_from_another_batch_proves_nothing_about_the_files_beside_it(
        cal, tmp_path, capsys, input_state):
    """OUT holding an empty manifest, the reflectance EXR of another batch of the same input
    (spherejax:source matches) and the user's own preview.png and quality.png: --resume replaced
    the preview (and, the input damaged, deleted both) as if one matching EXR made every name
    spherejax's. Each file must be proved on its own: none here is, so the batch is refused."""
    inputs = _inputs(tmp_path)
    other = tmp_path / "other"
    assert run(_correct(cal, [inputs], other), capsys)[0] == 0
    out = tmp_path / "out"
    (out / "in").mkdir(parents=True)
    (out / archive.MANIFEST_NAME).write_bytes(b"")
    shutil.copy2(other / "in" / "a.reflectance.exr", out / "in" / "a.reflectance.exr")
    (out / "in" / "a.preview.png").write_bytes(b"the user's own preview")
    (out / "in" / "a.quality.png").write_bytes(b"the user's own quality map")
    if input_state == "damaged":
        (inputs / "a.tif").write_bytes(b"now damaged")
    before = snapshot(out)
    line = _refused(*run(_correct(cal, [inputs], out, "--resume"), capsys))
    assert line.startswith(f"spherejax: error: {out / 'in' / 'a.reflectance.exr'}: {IN_THE_WAY} (and 2 more): ")
    assert snapshot(out) == before


def test_envi_files_copied_from_another_batch_prove_nothing_about_the_quality_png_beside_them(cal, tmp_path, capsys):
    """The same with --format envi: a matching ENVI reflectance (its "spherejax source" header
    field) beside the user's quality.png."""
    inputs = _inputs(tmp_path)
    other = tmp_path / "other"
    assert run(_correct(cal, [inputs], other, "--format", "envi"), capsys)[0] == 0
    out = tmp_path / "out"
    (out / "in").mkdir(parents=True)
    (out / archive.MANIFEST_NAME).write_bytes(b"")
    for kind in ("reflectance.hdr", "reflectance.img"):
        shutil.copy2(other / "in" / f"a.{kind}", out / "in" / f"a.{kind}")
    (out / "in" / "a.quality.png").write_bytes(b"the user's own quality map")
    before = snapshot(out)
    line = _refused(*run(_correct(cal, [inputs], out, "--resume", "--format", "envi"), capsys))
    assert line.startswith(f"spherejax: error: {out / 'in' / 'a.reflectance.img'}: {IN_THE_WAY} (and 2 more): ")
    assert snapshot(out) == before


@pytest.mark.parametrize("redo", ["other settings", "damaged input"])
def test_a_recorded_name_now_holding_the_users_bytes_is_the_users(cal, tmp_path, capsys, redo):
    """The manifest records a.preview.png with the SHA-256 of what spherejax wrote; the user then
    put their own file at that name. A name recorded proves nothing about other bytes there: the
    redo (other settings) does not replace it, a failing input does not delete it."""
    inputs = _inputs(tmp_path)
    out = tmp_path / "out"
    assert run(_correct(cal, [inputs], out), capsys)[0] == 0
    (out / "in" / "a.preview.png").write_bytes(b"the user's own preview, saved over spherejax's")
    extra = ["--illuminant", "A"]
    if redo == "damaged input":
        (inputs / "a.tif").write_bytes(b"now damaged")
        extra = []
    before = snapshot(out)
    line = _refused(*run(_correct(cal, [inputs], out, "--resume", *extra), capsys))
    assert line.startswith(f"spherejax: error: {out / 'in' / 'a.preview.png'}: {IN_THE_WAY}: ")
    assert "does not record it as written by spherejax (these bytes at this name)" in line
    assert snapshot(out) == before


def test_the_other_formats_file_edited_by_the_user_is_not_removed(cal, tmp_path, capsys):
    """An ENVI batch resumed as EXR removes the ENVI files it proves its own and leaves the header
    the user edited since (recorded by name, not with these bytes)."""
    inputs = _inputs(tmp_path)
    out = tmp_path / "out"
    assert run(_correct(cal, [inputs], out, "--format", "envi"), capsys)[0] == 0
    header = out / "in" / "a.reflectance.hdr"
    edited = header.read_bytes() + b"; a note of the user's\n"
    header.write_bytes(edited)
    status, stdout, err = run(_correct(cal, [inputs], out, "--resume"), capsys)
    assert status == 0, err
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    assert header.read_bytes() == edited
    assert not (out / "in" / "a.reflectance.img").exists()  # proved spherejax's: removed
    assert (out / "in" / "a.reflectance.exr").is_file()


# ----------------------------------------------------- a killed run's claims prove only what it made


#: `spherejax correct` in a child, one input at a time, SIGKILLed at its first manifest record:
#: the first input's outputs are in place, unrecorded; the second was claimed and never started.
_KILLED_AT_THE_FIRST_RECORD = """
import functools, os, signal, sys
from spherejax import cli
from spherejax.archive import batch, manifest

batch._in_process = functools.partial(batch._in_process, in_flight=1)
manifest.Manifest.append = lambda self, result: os.kill(os.getpid(), signal.SIGKILL)
sys.exit(cli.main(sys.argv[1:]))
"""


def _killed_run(cal, inputs, out):
    env = no_compilation_cache_writes({**os.environ, "JAX_PLATFORMS": "cpu"})
    process = subprocess.run([sys.executable, "-c", _KILLED_AT_THE_FIRST_RECORD, "-q", *_correct(cal, [inputs], out)],
                             env=env, capture_output=True, timeout=300)
    assert process.returncode == -9, process.stderr.decode()


@pytest.mark.parametrize("user_file", ["claimed, never written", "written, then replaced"])
def test_a_user_file_at_a_name_a_killed_run_claimed_is_not_replaced(cal, tmp_path, capsys, user_file):
    """After a SIGKILL, the lock file the dead run left names every output it claimed, and the
    SHA-256 of each file it put in place. A file the user put at a claimed name it never wrote
    (b's preview), or over a file it did write (a's preview), is not what it made: refused, left
    as it is. Once the user's file is gone, --resume proves a's unrecorded outputs by their bytes
    and the batch ends as an uninterrupted one."""
    inputs = _inputs(tmp_path, ("a", "b"))
    reference = tmp_path / "reference"
    assert run(_correct(cal, [inputs], reference), capsys)[0] == 0
    out = tmp_path / "out"
    _killed_run(cal, inputs, out)
    assert sorted(p.name for p in (out / "in").iterdir()) == [f"a.{kind}" for kind in sorted(archive.OUTPUT_KINDS)]
    assert (out / archive.LOCK_NAME).exists() and not manifest_records(out)
    user = out / "in" / ("b.preview.png" if user_file == "claimed, never written" else "a.preview.png")
    user.write_bytes(b"the user's own preview")
    before = _but_lock(out)
    line = _refused(*run(_correct(cal, [inputs], out, "--resume"), capsys))
    assert line.startswith(f"spherejax: error: {user}: {IN_THE_WAY}: ")
    assert _but_lock(out) == before
    user.unlink()
    status, stdout, err = run(_correct(cal, [inputs], out, "--resume"), capsys)
    assert status == 0, err
    assert stdout.strip() == "2 corrected, 0 skipped (already done), 0 failed"
    assert outputs_of(out) == outputs_of(reference)
    assert not (out / archive.LOCK_NAME).exists()


def test_a_claim_without_the_files_sha256_proves_nothing(cal, tmp_path, capsys):
    """A lock file left with claims only (names, as an older spherejax wrote them) says what a run
    meant to write, not what lies there now: the files at those names are refused, not replaced."""
    inputs = _inputs(tmp_path)
    out = tmp_path / "out"
    (out / "in").mkdir(parents=True)
    claims = [f"in/a.{kind}" for kind in archive.OUTPUT_KINDS]
    (out / archive.LOCK_NAME).write_text(json.dumps({"pid": 999999, "host": "gone", "claims": claims}) + "\n")
    for kind in archive.OUTPUT_KINDS:
        (out / "in" / f"a.{kind}").write_bytes(f"the user's a.{kind}".encode())
    before = _but_lock(out)
    line = _refused(*run(_correct(cal, [inputs], out), capsys))
    assert line.startswith(f"spherejax: error: {out / 'in' / 'a.reflectance.exr'}: {IN_THE_WAY} (and 3 more): ")
    assert _but_lock(out) == before


def test_each_input_records_what_it_made_before_it_is_in_place(cal, tmp_path, monkeypatch):
    """`record_made` gets the SHA-256 of every output while none is at its name yet (the files
    finished under their temporary names), and appends them to the lock file of the run holding
    OUT, where they are the bytes then renamed into place."""
    inputs = _inputs(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    seen = []
    recorded = lock_module.record_made

    def record_then_check(out_root, digests):
        seen.append({path: path.exists() for path in digests})
        recorded(out_root, digests)

    monkeypatch.setattr(batch_module, "record_made", record_then_check)
    held = archive.OutputLock(out)
    held.acquire()
    try:
        spec, = archive.discover_inputs([inputs / "a.tif"], out)
        result = archive.correct_input(spec, out, cal)
        assert result.status == "done", result.reason
        lines = (out / archive.LOCK_NAME).read_text().splitlines()
    finally:
        held.release()
    assert seen == [{out / f"a.{kind}": False for kind in archive.OUTPUT_KINDS}]
    made = json.loads(lines[-1])["made"]
    on_disk = {f"a.{kind}": hashlib.sha256((out / f"a.{kind}").read_bytes()).hexdigest() for kind in archive.OUTPUT_KINDS}
    assert made == on_disk == result.outputs


def test_record_made_creates_no_lock_file_where_no_run_holds_out(tmp_path):
    """`correct_input` called on its own (no run holding OUT): nothing to record into, nothing created."""
    lock_module.record_made(tmp_path, {tmp_path / "a.lab.exr": "0" * 64})
    assert list(tmp_path.iterdir()) == []


def test_made_records_survive_takeovers_and_torn_lines_are_skipped(tmp_path):
    """A run taking the lock over keeps the made records after the holder's line (only that line
    is rewritten, in place); a line torn by a kill, or not a SHA-256, proves nothing."""
    first = archive.OutputLock(tmp_path)
    first.acquire()
    first.claim(["x/a.lab.exr"])
    lock_module.record_made(tmp_path, {tmp_path / "x" / "a.lab.exr": "a" * 64})
    with open(tmp_path / archive.LOCK_NAME, "a") as handle:
        handle.write('{"made": {"x/b.lab.exr": "not a sha256"}}\n{"made": {"x/c.lab.exr": "' + "c" * 40)
    first.release(keep_claims=True)
    second = archive.OutputLock(tmp_path)
    second.acquire()
    assert second.made == {"x/a.lab.exr": {"a" * 64}} and second.claimed == {"x/a.lab.exr"}
    assert second.taken_over == f"pid {os.getpid()} on {socket.gethostname()}"
    second.release(keep_claims=True)
    third = archive.OutputLock(tmp_path)
    third.acquire()
    assert third.made == {"x/a.lab.exr": {"a" * 64}}
    holder = (tmp_path / archive.LOCK_NAME).read_bytes().split(b"\n")[0]
    assert len(holder) + 1 == lock_module.HOLDER_BYTES and json.loads(holder)["pid"] == os.getpid()
    third.release()
    assert not (tmp_path / archive.LOCK_NAME).exists()


# --------------------------------------------------------------------- OUT apart from the inputs


def _tree(tmp_path, workspace):
    """tmp/root/caps/{a,b}.tif, tmp/root/sessions/session (the workspace's), and links."""
    root = tmp_path / "root"
    caps = root / "caps"
    caps.mkdir(parents=True)
    rng = np.random.default_rng(4)
    for name in ("a", "b"):
        io.write_frame(caps / f"{name}.tif", frame(rng), channel_names=NAMES)
    shutil.copytree(workspace / "session", root / "sessions" / "session")
    (root / "archive").mkdir()
    (root / "archive" / "linked").symlink_to(root / "sessions" / "session")
    (tmp_path / "to-caps").symlink_to(caps)
    (tmp_path / "to-root").symlink_to(root)
    return root


# (inputs, OUT, how OUT meets which input, calibration): paths relative to tmp_path; "{cube}" and
# "{session}" name the two calibrations.
_AMONG_INPUTS = {
    "OUT is the inputs' folder": (["root/caps"], "root/caps", "is the input {tmp}/root/caps", "cube"),
    "OUT inside the inputs' folder": (["root/caps"], "root/caps/out", "lies inside the input {tmp}/root/caps", "cube"),
    "OUT the parent of the inputs' folder": (["root/caps"], "root", "holds the input {tmp}/root/caps", "cube"),
    "OUT the folder of an input file": (["root/caps/a.tif"], "root/caps", "holds the input {tmp}/root/caps/a.tif", "cube"),
    "OUT through a link to the inputs' folder": (["root/caps"], "to-caps", "is the input {tmp}/root/caps", "cube"),
    "OUT through ..": (["root/caps"], "root/caps/../caps/./", "is the input {tmp}/root/caps", "cube"),
    "inputs through a link, OUT their folder": (["to-caps"], "root/caps", "is the input {tmp}/to-caps", "cube"),
    "OUT through a link to the parent": (["root/caps/b.tif"], "to-root", "holds the input {tmp}/root/caps/b.tif", "cube"),
    "OUT the folder holding a session": (["root/sessions/session"], "root/sessions",
                                         "holds the input {tmp}/root/sessions/session", "session"),
    "OUT the session's frames folder": (["root/sessions/session"], "root/sessions/session/frames",
                                        "lies inside the input {tmp}/root/sessions/session", "session"),
    "OUT in a session found through a link": (["root/archive"], "root/sessions/session/out",
                                              "lies inside the input session {tmp}/root/archive/linked", "session"),
}


@pytest.mark.parametrize("case", list(_AMONG_INPUTS))
@pytest.mark.parametrize("output_format", ["exr", "envi"])
def test_out_among_the_inputs_is_refused_before_anything_is_created(
        cal, workspace, tmp_path, capsys, case, output_format):
    """`correct caps -o caps` wrote into the input folder (outputs a later batch takes for inputs),
    `-o` the parent of the inputs' folder wrote beside them, `-o` the folder holding a session
    filled its frames folder. OUT may not be, lie inside or hold an input, however spelled: one
    line naming OUT and the input, exit status 2, nothing created anywhere."""
    inputs, out, how, calibration = _AMONG_INPUTS[case]
    _tree(tmp_path, workspace)
    before = snapshot(tmp_path)
    calibration = cal if calibration == "cube" else workspace / "cal.h5"
    argv = _correct(calibration, [tmp_path / path for path in inputs], tmp_path / out, "--format", output_format)
    line = _refused(*run(argv, capsys))
    named = os.path.abspath(tmp_path / out)  # as run_batch takes it: `..` folded, links kept
    assert line.startswith(f"spherejax: error: {named}: OUT {how.format(tmp=tmp_path)} (expected ")
    assert snapshot(tmp_path) == before


def test_out_among_the_inputs_is_refused_before_a_cluster_writes(cal, workspace, tmp_path, capsys):
    """The same with dask workers (`--workers 1`): refused before any input reaches a worker."""
    _tree(tmp_path, workspace)
    before = snapshot(tmp_path)
    caps = tmp_path / "root" / "caps"
    line = _refused(*run(_correct(cal, [caps], caps, "--workers", "1"), capsys))
    assert line.startswith(f"spherejax: error: {caps}: OUT is the input {caps} (expected ")
    assert snapshot(tmp_path) == before


def test_out_beside_the_inputs_is_still_fine(cal, workspace, tmp_path, capsys):
    """Not every OUT near the inputs is refused: a sibling of the inputs' folder, holding none."""
    root = _tree(tmp_path, workspace)
    status, stdout, err = run(_correct(cal, [root / "caps"], root / "out"), capsys)
    assert status == 0, err
    assert stdout.strip() == "2 corrected, 0 skipped (already done), 0 failed"
    assert sorted(p.name for p in (root / "caps").iterdir()) == ["a.tif", "b.tif"]


# ---------------------------------------------------------------- inputs found before OUT exists


@pytest.mark.parametrize("mistake", ["a typo beside a good input", "only a typo", "a link to nothing",
                                     "a loop of links"])
def test_an_input_that_leads_to_nothing_creates_nothing(cal, tmp_path, capsys, mistake):
    """A mistyped input made OUT, its manifest and its lock (the input recorded as failed), so the
    corrected command was refused without --resume. A path given must lead to something before
    anything is created; then the corrected command is a new batch."""
    inputs = _inputs(tmp_path)
    bad = tmp_path / "in" / "a.tiff"
    if mistake == "a link to nothing":
        (tmp_path / "dangling.tif").symlink_to(tmp_path / "gone.tif")
        bad = tmp_path / "dangling.tif"
    elif mistake == "a loop of links":
        (tmp_path / "loop1").symlink_to(tmp_path / "loop2")
        (tmp_path / "loop2").symlink_to(tmp_path / "loop1")
        bad = tmp_path / "loop1"
    given = [bad] if mistake == "only a typo" else [inputs / "a.tif", bad]
    out = tmp_path / "out"
    line = _refused(*run(_correct(cal, given, out), capsys))
    what = {"a link to nothing": "is a symbolic link to nothing", "a loop of links": "is a loop of symbolic links"}
    assert line == (f"spherejax: error: {bad}: {what.get(mistake, 'no such file or folder')} "
                    "(expected an input to correct; nothing was created)")
    assert not out.exists()
    status, stdout, err = run(_correct(cal, [inputs / "a.tif"], out), capsys)
    assert status == 0 and stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed", err


def test_a_mistyped_input_to_a_resumed_batch_changes_nothing_in_out(cal, tmp_path, capsys):
    """With --resume into an existing OUT: no lock taken, no record added, nothing touched."""
    inputs = _inputs(tmp_path)
    out = tmp_path / "out"
    assert run(_correct(cal, [inputs], out), capsys)[0] == 0
    before = snapshot(out)
    line = _refused(*run(_correct(cal, [inputs, tmp_path / "typo"], out, "--resume"), capsys))
    assert line.startswith(f"spherejax: error: {tmp_path / 'typo'}: no such file or folder")
    assert snapshot(out) == before


@pytest.mark.parametrize("content", [b"my notes about this batch\n", b"spherejax 0.9 INFO corrected a.tif\n",
                                     b'{"owner": "me"}\n'])
@pytest.mark.parametrize("resume", [False, True])
def test_a_users_file_at_outs_lock_name_is_refused_not_written_over_or_removed(cal, tmp_path, capsys, content, resume):
    """OUT's lock file name holding a file no spherejax run wrote (it does not begin with the
    holder's {"pid": N, "host": ...}): the batch is refused in one line naming it, and the file is
    left as it was (it was written over, then removed when the run released its lock)."""
    inputs = _inputs(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    if resume:
        assert run(_correct(cal, [inputs], out), capsys)[0] == 0
    (out / lock_module.LOCK_NAME).write_bytes(content)
    before = snapshot(tmp_path)
    line = _refused(*run(_correct(cal, [inputs], out, *(["--resume"] if resume else [])), capsys))
    assert str(out / lock_module.LOCK_NAME) in line and "not a spherejax lock" in line
    assert snapshot(tmp_path) == before


def test_an_empty_file_or_a_lock_a_killed_run_left_at_outs_lock_name_is_taken_over(cal, tmp_path, capsys):
    """An empty file (a run killed between creating its lock and writing it) and a lock of any
    earlier format are spherejax's: taken over, and gone when the batch ends."""
    inputs = _inputs(tmp_path)
    for left in (b"", b'{"pid": 999999, "host": "lab-pc", "claims": []}\n'):
        out = tmp_path / f"out{len(left)}"
        out.mkdir()
        (out / lock_module.LOCK_NAME).write_bytes(left)
        assert run(_correct(cal, [inputs], out), capsys)[0] == 0
        assert not (out / lock_module.LOCK_NAME).exists()
