"""Every writing command replaces only what it can prove it wrote (docs/reliability.md, "Files"):
a file at an output's name counts as spherejax's only through its own signature on that very
file (measure's CSV header, its JSON's "format", its CGATS ORIGINATOR; a demo's mark in its
calibration's signed header; a log's first line), never by its name, its folder or its being a
regular file. And --log-file FILE is checked like any output against every input and output of
the command, before any work.

Each refusal: exit status 2, one line "spherejax: error: PATH: problem (expected ...)" naming the
file, no traceback, and every file under the case's folder as it was (bytes, links, nothing new).
A case's docstring starting "unchecked:" says what happened without the check.
"""

from __future__ import annotations

import os
import pathlib
import shutil

import pytest

import spherejax
from spherejax import cli, console, io
from tests.robustness.catalogue import refused_unchanged
from tests.robustness.catalogue import run_quietly as run

REGION = "a=2,8,2,8"


@pytest.fixture
def root(workspace, tmp_path) -> pathlib.Path:
    """The shared calibration (cal.h5), one of its session's test frames (cube.tif) and mdir/."""
    shutil.copyfile(workspace / "cal.h5", tmp_path / "cal.h5")
    shutil.copyfile(workspace / "session" / "frames" / "targets.tif", tmp_path / "cube.tif")
    (tmp_path / "mdir").mkdir()
    return tmp_path


def measure_argv(root, *options):
    return ["measure", "-c", root / "cal.h5", root / "cube.tif", "--region", REGION, *options]


# --------------------------------------------------------------------------------------------
# measure: OUT.csv, OUT.json, --cgats FILE and the default names


USERS_FILES = {"user.csv": "name,colour\nshirt,red\n", "user.json": '{"my": "notes"}\n', "user.txt": "my notes\n"}


@pytest.mark.parametrize("name", sorted(USERS_FILES))
def test_measure_does_not_replace_a_users_file_at_one_of_its_names(root, capsys, name):
    """unchecked: `measure -o mdir/user --cgats mdir/user.txt` replaced the user's user.csv,
    user.json and user.txt (exit 0)."""
    (root / "mdir" / name).write_text(USERS_FILES[name])
    refused_unchanged(root, measure_argv(root, "-o", root / "mdir" / "user", "--cgats", root / "mdir" / "user.txt"),
                      capsys, root / "mdir" / name, "is in the way: a file spherejax measure did not write")


def test_measure_refuses_a_users_file_at_its_default_name_in_the_working_folder(root, capsys, monkeypatch):
    """unchecked: the default OUT (cube.measure, in the working folder) replaced the user's
    cube.measure.json (exit 0)."""
    monkeypatch.chdir(root / "mdir")
    (root / "mdir" / "cube.measure.json").write_text('{"mine": true}\n')
    refused_unchanged(root, measure_argv(root), capsys, "cube.measure.json",
                      "OUT.json is in the way: a file spherejax measure did not write")


@pytest.mark.parametrize("how", ["dot-dot", "linked folder", "hard link", "empty file", "another output's kind"])
def test_measure_refuses_a_users_file_however_it_is_reached(root, capsys, how):
    """The file's own bytes decide, whatever the path: `..`, a folder reached through a link, a
    hard link to a user's file, an empty file (no signature), and a spherejax measurement's JSON
    at the CSV's name (the signature of another output is not this output's)."""
    mdir = root / "mdir"
    (mdir / "sub").mkdir()
    base, named = mdir / "sub" / ".." / "user", mdir / "user.csv"
    if how == "dot-dot":
        named.write_text("mine\n")
    elif how == "linked folder":
        (root / "link").symlink_to("mdir")
        base = root / "link" / "user"
        named.write_text("mine\n")
    elif how == "hard link":
        (root / "notes.csv").write_text("mine\n")
        os.link(root / "notes.csv", named)
    elif how == "empty file":
        named.write_text("")
    else:
        assert run(measure_argv(root, "-o", root / "first"), capsys)[0] == 0
        shutil.copyfile(root / "first.json", named)
    refused_unchanged(root, measure_argv(root, "-o", base), capsys, f"{base}.csv", "OUT.csv is in the way")


def test_measure_replaces_its_own_earlier_outputs_and_leaves_the_users(root, capsys, monkeypatch):
    """Its own files, found by their signatures, are replaced; a user's file beside them stays."""
    options = ["-o", root / "mdir" / "user", "--cgats", root / "mdir" / "user.txt"]
    assert run(measure_argv(root, *options), capsys)[0] == 0
    (root / "mdir" / "mine.txt").write_text("mine\n")
    for name in ("user.csv", "user.json", "user.txt"):
        # A visible change, so the second run's replacement can be seen; the signature stays.
        with open(root / "mdir" / name, "a") as handle:
            handle.write("\n")
    status, _, err = run(measure_argv(root, *options), capsys)
    assert status == 0, err
    for name in ("user.csv", "user.json", "user.txt"):
        assert not (root / "mdir" / name).read_text().endswith("\n\n"), name
    assert (root / "mdir" / "mine.txt").read_text() == "mine\n"
    # The default names too.
    monkeypatch.chdir(root / "mdir")
    assert run(measure_argv(root), capsys)[0] == 0
    assert run(measure_argv(root), capsys)[0] == 0
    assert (root / "mdir" / "cube.measure.csv").is_file() and (root / "mdir" / "cube.measure.json").is_file()


# --------------------------------------------------------------------------------------------
# --log-file FILE against the command's own files


def _a_spherejax_log(path: pathlib.Path, capsys) -> pathlib.Path:
    """A log an earlier spherejax run wrote (a bad command: nothing else written)."""
    assert cli.main(["-q", "--log-file", str(path), "calibrate", str(path.parent / "nowhere"), "-o",
                     str(path.parent / "nothing.h5")]) == cli.EXIT_BAD_INPUT
    capsys.readouterr()
    assert console.not_a_log(path) is None
    return path


def test_a_log_at_outs_lock_is_refused_not_overwritten_and_deleted(root, capsys):
    """unchecked: `--log-file OUT/.spherejax.lock` holding an earlier spherejax log: correct
    wrote its lock over the log, then deleted it."""
    (root / "out").mkdir()
    log = _a_spherejax_log(root / "out" / ".spherejax.lock", capsys)
    refused_unchanged(root, ["--log-file", log, "correct", "-c", root / "cal.h5", root / "cube.tif", "-o", root / "out"],
                      capsys, log, "--log-file FILE is also OUT's lock")


@pytest.mark.parametrize("name", ["manifest.jsonl", "cube.reflectance.exr", "other.preview.png"])
def test_a_log_at_an_output_name_of_correct_is_refused(root, capsys, name):
    """OUT's manifest and any name an output of correct takes (an input's name plus an output's
    kind: the inputs are not found yet)."""
    (root / "out").mkdir()
    log = _a_spherejax_log(root / "out" / name, capsys)
    refused_unchanged(root, ["correct", "-c", root / "cal.h5", root / "cube.tif", "-o", root / "out", "--log-file", log],
                      capsys, log, "--log-file FILE")


@pytest.mark.parametrize("which", ["csv", "json", "cgats", "default csv"])
def test_a_log_at_an_output_of_measure_is_refused(root, capsys, monkeypatch, which):
    """unchecked: `--log-file mdir/lg.csv measure ... -o mdir/lg`: the log replaced by the CSV."""
    mdir = root / "mdir"
    if which == "default csv":
        monkeypatch.chdir(mdir)
        log = _a_spherejax_log(mdir / "cube.measure.csv", capsys)
        argv, label = ["--log-file", "cube.measure.csv", *measure_argv(root)], "OUT.csv"
        log = pathlib.Path("cube.measure.csv")
    else:
        log = _a_spherejax_log(mdir / ("lg.txt" if which == "cgats" else f"lg.{which}"), capsys)
        argv = ["--log-file", log, *measure_argv(root, "-o", mdir / "lg", "--cgats", mdir / "lg.txt")]
        label = {"csv": "OUT.csv", "json": "OUT.json", "cgats": "--cgats FILE"}[which]
    refused_unchanged(root, argv, capsys, log, f"--log-file FILE is also {label}")


def test_a_log_reached_through_a_link_or_dot_dot_is_still_the_output(root, capsys):
    """A new log (nothing there yet) at measure's OUT.csv through `..` and a linked folder."""
    (root / "mdir" / "sub").mkdir()
    (root / "link").symlink_to("mdir")
    log = root / "link" / "sub" / ".." / "lg.csv"
    refused_unchanged(root, ["--log-file", log, *measure_argv(root, "-o", root / "mdir" / "lg")], capsys, log,
                      "--log-file FILE is also OUT.csv")


@pytest.mark.parametrize("command", ["a log as measure's input", "calibrate's output", "measure's input",
                                     "measure's calibration"])
def test_a_log_that_is_an_input_or_the_calibration_output_is_refused(root, workspace, capsys, command):
    """An input is never written, even a spherejax log given as one; -o CAL is calibrate's (a new
    log there: nothing is created)."""
    if command == "a log as measure's input":
        log = _a_spherejax_log(root / "input.log", capsys)
        argv, label = ["measure", "-c", root / "cal.h5", log, "--region", REGION, "-o", root / "m"], "INPUT"
    elif command == "calibrate's output":
        log = root / "new.h5"
        argv, label = ["calibrate", workspace / "session", "-o", log], "-o CAL"
    elif command == "measure's input":
        log, argv, label = root / "cube.tif", measure_argv(root), "INPUT"
    else:
        log, argv, label = root / "cal.h5", measure_argv(root), "the calibration (-c)"
    refused_unchanged(root, ["--log-file", log, *argv], capsys, log, f"--log-file FILE is also {label}")


@pytest.mark.parametrize("command", ["simulate", "demo session"])
def test_a_log_inside_a_folder_the_command_writes_whole_is_refused(root, capsys, command):
    """simulate's session folder and demo's OUT/session are created whole: a log there would be
    a file of nobody's in them (simulate then refused its own folder as not empty)."""
    folder = root / "s" if command == "simulate" else root / "demo" / "session"
    folder.mkdir(parents=True)
    log = folder / "run.log"
    argv = ["simulate", "-o", folder] if command == "simulate" else ["demo", "-o", root / "demo"]
    refused_unchanged(root, ["--log-file", log, *argv], capsys, log, "a folder the command writes whole")


def test_a_new_log_begins_with_its_signature_and_an_empty_file_is_not_one(root, capsys):
    """A log spherejax creates holds its first line from the start; an empty file (a user's
    `touch`) is no proof of anything, so it is refused, not appended to."""
    log = root / "run.log"
    status, _, err = run(["--log-file", log, "calibrate", root / "nowhere", "-o", root / "x.h5"], capsys)
    assert status == cli.EXIT_BAD_INPUT
    first = log.read_text().splitlines()[0]
    assert first.endswith(f"DEBUG spherejax.cli: log file created by spherejax {spherejax.__version__}"), first
    assert console.not_a_log(log) is None
    assert not [name for name in os.listdir(root) if name.endswith(".tmp")]
    (root / "empty.log").write_text("")
    refused_unchanged(root, ["--log-file", root / "empty.log", "calibrate", root / "nowhere", "-o", root / "x.h5"],
                      capsys, root / "empty.log", "an empty file, not a spherejax log")


def test_a_log_beside_the_outputs_is_still_written(root, capsys):
    """What is apart from the command's files stays allowed: a log in OUT under a name no output
    takes, and one beside measure's files."""
    (root / "out").mkdir()
    status, _, err = run(["--log-file", root / "out" / "run.log", *measure_argv(root, "-o", root / "out" / "m")], capsys)
    assert status == 0, err
    assert console.not_a_log(root / "out" / "run.log") is None
    assert (root / "out" / "m.csv").is_file()


# --------------------------------------------------------------------------------------------
# demo -o DIR: OUT/calibration.h5


@pytest.fixture
def demo_out(root, workspace, monkeypatch) -> pathlib.Path:
    """A demo folder whose session is the one `demo --seed 5` asks for (the shared session, seed 5
    of the SMALL design, made the simulator's default here: demo reuses it)."""
    from spherejax import simulate
    from tests.helpers import SMALL

    monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)
    out = root / "demo"
    out.mkdir()
    shutil.copytree(workspace / "session", out / "session")
    return out


def resaved(source: pathlib.Path, target: pathlib.Path, *, instrument_id: str | None = None, marks=None) -> pathlib.Path:
    """`source`'s calibration saved at `target` by spherejax, for `instrument_id` and with `marks`
    in its metadata."""
    calibration, header = io.load_calibration(source)
    io.save_calibration(target, calibration, instrument_id=instrument_id or header["instrument_id"],
                        band_centres_nm=header["band_centres_nm"], metadata={**header["metadata"], **(marks or {})})
    return target


@pytest.mark.parametrize("which", ["calibrate's, same instrument", "another instrument's", "hard link to a lab's"])
def test_demo_does_not_replace_a_spherejax_calibration_no_demo_wrote(root, demo_out, capsys, which):
    """unchecked: `demo -o D` replaced D/calibration.h5 made for another instrument (exit 0):
    any spherejax calibration counted as the demo's."""
    target = demo_out / "calibration.h5"
    if which == "calibrate's, same instrument":
        shutil.copyfile(root / "cal.h5", target)
    elif which == "another instrument's":
        resaved(root / "cal.h5", target, instrument_id="lab-sphere-2")
    else:
        os.link(resaved(root / "cal.h5", root / "lab.h5", instrument_id="lab-sphere-2"), target)
    refused_unchanged(root, ["demo", "--out", demo_out, "--seed", "5"], capsys, target,
                      "OUT/calibration.h5 is in the way: a spherejax calibration that no demo wrote", "--force")


def test_a_demo_mark_is_proof_only_inside_the_signed_header(root, tmp_path):
    """A demo's calibration carries its mark; a file whose checksum fails does not count, mark or not."""
    from spherejax.cli import session_commands

    marked = resaved(root / "cal.h5", root / "marked.h5", marks=session_commands.DEMO_MARK)
    assert session_commands.not_a_demo_calibration(marked) is None
    assert "no demo wrote" in session_commands.not_a_demo_calibration(root / "cal.h5")
    damaged = root / "damaged.h5"
    data = bytearray(marked.read_bytes())
    data[len(data) // 2] ^= 0xFF
    damaged.write_bytes(bytes(data))
    assert "not a spherejax calibration" in session_commands.not_a_demo_calibration(damaged)


@pytest.mark.slow
def test_demo_force_replaces_a_spherejax_calibration_and_marks_its_own(root, demo_out, capsys):
    """--force replaces a spherejax calibration (never another file); the new one is the demo's,
    which the next demo may replace without --force."""
    from spherejax.cli import session_commands

    resaved(root / "cal.h5", demo_out / "calibration.h5", instrument_id="lab-sphere-2")
    status, _, err = run(["demo", "--out", demo_out, "--seed", "5", "--force"], capsys)
    assert status == 0, err
    _, header = io.load_calibration(demo_out / "calibration.h5")
    assert header["instrument_id"] != "lab-sphere-2"
    assert session_commands.not_a_demo_calibration(demo_out / "calibration.h5") is None
    (demo_out / "calibration.h5").unlink()
    (demo_out / "calibration.h5").write_text("my notes\n")
    refused_unchanged(root, ["demo", "--out", demo_out, "--seed", "5", "--force"], capsys, demo_out / "calibration.h5",
                      "a file that is not a spherejax calibration")


def test_a_new_log_in_a_folder_that_cannot_be_written_is_refused_naming_the_log(root, capsys):
    """The log's first line goes through a temporary sibling: a folder that refuses it is said of
    the log file, in one line, with nothing left."""
    from tests.robustness.catalogue import read_only

    (root / "ro").mkdir()
    log = root / "ro" / "run.log"
    with read_only(root / "ro"):
        refused_unchanged(root, ["--log-file", log, "calibrate", root / "nowhere", "-o", root / "x.h5"], capsys, log,
                          "cannot be created")


# --------------------------------------------------------------------------------------------
# evaluate, study and demo: a file beside an earlier run's record is replaced only when the
# record lists its very bytes


def _record(folder: pathlib.Path, name: str, keys, files: dict[str, bytes]) -> None:
    """An earlier run's record (`name`, with `keys`) listing the SHA-256 of `files`."""
    import hashlib
    import json

    folder.mkdir(parents=True, exist_ok=True)
    document = {key: [] for key in keys}
    document["files"] = {file: hashlib.sha256(data).hexdigest() for file, data in files.items()}
    (folder / name).write_text(json.dumps(document))


EVALUATION_KEYS = ("band_centres_nm", "markov_kappa", "metrics")
STUDY_KEYS = ("objective_start", "objective_end", "closed_form", "study")


@pytest.mark.parametrize("case", ["evaluate, unlisted", "evaluate, edited", "study, unlisted", "demo, edited"])
def test_a_users_file_beside_an_earlier_runs_record_is_not_replaced(root, workspace, demo_out, capsys, case):
    """unchecked: a spherejax metrics.json (or study.json) beside them made every output name
    count as spherejax's: the user's tables.txt replaced, or one the user edited since."""
    session = workspace / "session"
    if case.startswith("evaluate"):
        folder, record, keys, named = root / "e", "metrics.json", EVALUATION_KEYS, "tables.txt"
        argv = ["evaluate", session, "-c", root / "cal.h5", "--out", folder]
    elif case.startswith("study"):
        folder, record, keys, named = root / "s", "study.json", STUDY_KEYS, "study.txt"
        argv = ["study", session, "-c", root / "cal.h5", "--out", folder, "--max-steps", "1"]
    else:
        folder, record, keys, named = demo_out / "evaluation", "metrics.json", EVALUATION_KEYS, "tables.txt"
        argv = ["demo", "--out", demo_out, "--seed", "5"]
    listed = {} if case.endswith("unlisted") else {named: b"the tables an earlier run wrote\n"}
    _record(folder, record, keys, listed)
    (folder / named).write_text("my own tables, or the run's edited by me\n")
    refused_unchanged(root, argv, capsys, folder / named, "is in the way: a file spherejax did not write")


@pytest.mark.slow
def test_evaluate_again_replaces_what_it_wrote_and_nothing_else(root, workspace, capsys):
    """A real run's metrics.json lists its files, so the next run replaces them; one the user
    edited in between is refused."""
    argv = ["evaluate", workspace / "session", "-c", root / "cal.h5", "--out", root / "e"]
    assert run(argv, capsys)[0] == 0
    import json

    listed = json.loads((root / "e" / "metrics.json").read_text())["files"]
    assert set(listed) == {p.name for p in (root / "e").iterdir()} - {"metrics.json"}
    assert run(argv, capsys)[0] == 0
    with open(root / "e" / "table1.csv", "a") as handle:
        handle.write("my note\n")
    refused_unchanged(root, argv, capsys, root / "e" / "table1.csv", "its bytes are not those")
