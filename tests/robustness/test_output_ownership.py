"""Ownership (docs/reliability.md, section 3): spherejax writes and deletes only
what it created. Every output path of calibrate, evaluate, study, simulate, demo and acquire is
checked against every input, the calibration and every other output before any work, by resolved
path and by (st_dev, st_ino), so that links and `..` cannot hide an overlap; what already lies at
an output's name is replaced only when spherejax wrote it (`spherejax.io.ownership`).

Each refusal: exit status 2, one line "spherejax: error: PATH: problem (expected ...)" naming the
output, no traceback, and every file under the case's folder as it was (bytes, links, nothing new).
A case's docstring starting "unchecked:" says what happens without the check: a file the user
had lost or changed, or a failure only after all the work.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import shutil
import sys

import pytest

from spherejax import io, simulate
from spherejax.io import SpherejaxFileError, ownership
from tests.helpers import SMALL
from tests.hw.support import write_profile
from tests.robustness.catalogue import refused_unchanged, snapshot
from tests.robustness.catalogue import run_quietly as run


@pytest.fixture
def root(workspace, tmp_path) -> pathlib.Path:
    """A private copy of the shared session (session/) and its calibration (cal.h5)."""
    shutil.copytree(workspace / "session", tmp_path / "session")
    shutil.copyfile(workspace / "cal.h5", tmp_path / "cal.h5")
    return tmp_path


# --------------------------------------------------------------------------------------------
# calibrate SESSION -o CAL


def _link_dot_dot_manifest(root):
    """unchecked: the calibration replaced the session's manifest (exit 0)."""
    (root / "link").symlink_to("session")
    return root / "link" / "frames" / ".." / "manifest.json", "the session's manifest"


def _frame(root):
    """unchecked: the calibration replaced a frame of the session (exit 0)."""
    return root / "session" / "frames" / "white.tif", "the session's frame 'white'"


def _session_folder(root):
    """unchecked: all the work, then "Is a directory" at the rename."""
    return root / "session", "the session folder"


def _users_file(root):
    """unchecked: the user's file replaced by the calibration (exit 0)."""
    (root / "notes.h5").write_text("my notes, not a calibration\n")
    return root / "notes.h5", "is in the way: a file that is not a spherejax calibration"


def _link_to_users_file(root):
    """unchecked: the link replaced by the calibration (exit 0)."""
    (root / "mine.txt").write_text("mine\n")
    (root / "out.h5").symlink_to("mine.txt")
    return root / "out.h5", "is in the way: a symbolic link (to mine.txt)"


@pytest.mark.parametrize("target", [_link_dot_dot_manifest, _frame, _session_folder, _users_file, _link_to_users_file],
                         ids=["manifest-through-link-and-dotdot", "frame", "session-folder", "users-file", "link"])
def test_calibrate_writes_over_no_input_and_no_file_of_the_users(root, capsys, target):
    output, fragment = target(root)
    refused_unchanged(root, ["calibrate", root / "session", "-o", output], capsys, output, "-o CAL", fragment)


def test_calibrate_refuses_a_hard_link_to_a_frame(root, capsys):
    os.link(root / "session" / "frames" / "dark.tif", root / "dark-too.h5")
    refused_unchanged(root, ["calibrate", root / "session", "-o", root / "dark-too.h5"], capsys,
                      root / "dark-too.h5", "is also the session's frame 'dark'")


def test_calibrate_may_replace_a_calibration_in_the_session_folder(root, capsys):
    """A new file beside the session's own, or a spherejax calibration there, is CAL's to replace."""
    target = root / "session" / "cal.h5"
    shutil.copyfile(root / "cal.h5", target)
    session_before = {k: v for k, v in snapshot(root / "session").items() if k != "cal.h5"}
    status, _, err = run(["calibrate", root / "session", "-o", target, "--force"], capsys)
    assert status == 0, err
    io.load_calibration(target)
    assert {k: v for k, v in snapshot(root / "session").items() if k != "cal.h5"} == session_before


# --------------------------------------------------------------------------------------------
# evaluate SESSION [-c CAL] --out DIR


def test_evaluate_into_the_session_folder_is_refused(root, capsys):
    """unchecked: tables and figures written among the session's files (exit 0)."""
    refused_unchanged(root, ["evaluate", root / "session", "-c", root / "cal.h5", "--out", root / "session"], capsys,
                      root / "session", "--out DIR holds the session's manifest")


def test_evaluate_into_the_frames_folder_through_a_link_is_refused(root, capsys):
    """unchecked: tables and figures written beside the frames (exit 0)."""
    (root / "frames-link").symlink_to(root / "session" / "frames")
    refused_unchanged(root, ["evaluate", root / "session", "-c", root / "cal.h5", "--out", root / "frames-link"], capsys,
                      root / "frames-link", "--out DIR holds the session's frame")


def test_evaluate_does_not_replace_the_users_figure(root, capsys):
    """unchecked: the user's figure5.png replaced by the evaluation's (exit 0)."""
    (root / "paper").mkdir()
    (root / "paper" / "figure5.png").write_bytes(b"the figure of my paper")
    refused_unchanged(root, ["evaluate", root / "session", "-c", root / "cal.h5", "--out", root / "paper"], capsys,
                      root / "paper" / "figure5.png", "is in the way: a file spherejax did not write")


def test_evaluate_refuses_a_calibration_that_is_an_output(root, capsys):
    """-c names the file an output would be (here through `..`): refused before any work."""
    (root / "e").mkdir()
    shutil.copyfile(root / "cal.h5", root / "e" / "metrics.json")
    refused_unchanged(root, ["evaluate", root / "session", "-c", root / "e" / ".." / "e" / "metrics.json",
                             "--out", root / "e"], capsys, root / "e" / "metrics.json", "is also the calibration (-c)")


@pytest.mark.slow
def test_evaluate_again_replaces_its_own_tables_and_nothing_else(root, capsys):
    out = root / "e"
    argv = ["evaluate", root / "session", "-c", root / "cal.h5", "--out", out]
    assert run(argv, capsys)[0] == 0
    (out / "notes.txt").write_text("mine")
    # Its own tables, as its metrics.json records their bytes (one the user edited is not its
    # own: test_writers_own_only_theirs.py), are replaced: a new file at the name.
    before = (out / "tables.txt").stat().st_ino
    status, _, err = run(argv, capsys)
    assert status == 0, err
    assert (out / "tables.txt").stat().st_ino != before
    assert (out / "tables.txt").read_text().startswith("Table 1.")
    assert (out / "notes.txt").read_text() == "mine"


# --------------------------------------------------------------------------------------------
# study SESSION [-c CAL] --out DIR


def test_study_does_not_replace_its_starting_calibration(root, capsys):
    """unchecked: -c OUT/study-calibration.h5, the calibration an earlier study wrote, was replaced by
    the new study's (exit 0)."""
    (root / "s").mkdir()
    shutil.copyfile(root / "cal.h5", root / "s" / "study-calibration.h5")
    refused_unchanged(root, ["study", root / "session", "-c", root / "s" / "study-calibration.h5", "--out", root / "s",
                             "--max-steps", "1"], capsys,
                      root / "s" / "study-calibration.h5", "--out DIR/study-calibration.h5 is also the calibration (-c)")


def test_study_into_the_session_folder_is_refused(root, capsys):
    """unchecked: the study's files written among the session's (exit 0)."""
    refused_unchanged(root, ["study", root / "session", "-c", root / "cal.h5", "--out", root / "session",
                             "--max-steps", "1"], capsys, root / "session", "--out DIR holds the session's manifest")


def test_study_does_not_replace_the_users_files(root, capsys):
    (root / "s").mkdir()
    (root / "s" / "study.txt").write_text("my notes on the study")
    refused_unchanged(root, ["study", root / "session", "-c", root / "cal.h5", "--out", root / "s", "--max-steps", "1"],
                      capsys, root / "s" / "study.txt", "is in the way: a file spherejax did not write")


@pytest.mark.slow
def test_study_again_replaces_its_own_files(root, capsys):
    argv = ["study", root / "session", "-c", root / "cal.h5", "--out", root / "s", "--max-steps", "1"]
    assert run(argv, capsys)[0] == 0
    status, _, err = run(argv, capsys)
    assert status == 0, err
    assert sorted(p.name for p in (root / "s").iterdir()) == ["study-calibration.h5", "study.csv", "study.json", "study.txt"]


# --------------------------------------------------------------------------------------------
# simulate OUT


@pytest.fixture
def small_design(monkeypatch):
    """simulate's experiment made small, so that a run the refusal should have stopped is short."""
    monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)


def test_simulate_into_a_link_to_an_empty_folder_is_refused_before_the_work(tmp_path, capsys, small_design):
    """unchecked: the whole simulation, then "could not be written: Not a directory" at the rename."""
    (tmp_path / "empty").mkdir()
    (tmp_path / "out").symlink_to("empty")
    refused_unchanged(tmp_path, ["simulate", tmp_path / "out"], capsys, tmp_path / "out", "is a symbolic link (to empty)")


def test_simulate_into_a_dangling_link_is_refused(tmp_path, capsys, small_design):
    (tmp_path / "out").symlink_to("nowhere")
    refused_unchanged(tmp_path, ["simulate", tmp_path / "out"], capsys, tmp_path / "out", "is a symbolic link (to nowhere)")


def test_simulate_into_a_link_to_a_folder_with_files_is_refused(tmp_path, capsys, small_design):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "keep.txt").write_text("mine")
    (tmp_path / "out").symlink_to("mine")
    refused_unchanged(tmp_path, ["simulate", tmp_path / "out"], capsys, tmp_path / "out", "symbolic link")


def test_simulate_into_dot_dot_is_refused(tmp_path, capsys, small_design):
    """unchecked: the whole simulation, the folder `new` left behind, then a failed rename."""
    (tmp_path / "keep.txt").write_text("mine")
    refused_unchanged(tmp_path, ["simulate", tmp_path / "new" / ".."], capsys, tmp_path / "new" / "..", "through '..'")


# --------------------------------------------------------------------------------------------
# demo --out DIR


@pytest.fixture
def demo_out(root, monkeypatch) -> pathlib.Path:
    """A demo folder whose session is already there, the one `demo --seed 5` asks for: the shared
    session is seed 5 of the SMALL design, made the simulator's default here (demo reuses it)."""
    from spherejax import simulate
    from tests.helpers import SMALL

    monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)
    out = root / "demo"
    out.mkdir()
    shutil.copytree(root / "session", out / "session")
    return out


def test_demo_does_not_replace_a_users_file_named_calibration_h5(root, demo_out, capsys):
    """unchecked: the user's file replaced by the demo's calibration (exit 0)."""
    (demo_out / "calibration.h5").write_text("my notes\n")
    refused_unchanged(root, ["demo", "--out", demo_out, "--seed", "5"], capsys, demo_out / "calibration.h5",
                      "OUT/calibration.h5 is in the way: a file that is not a spherejax calibration")


def test_demo_does_not_replace_the_users_tables(root, demo_out, capsys):
    """unchecked: the user's tables.txt replaced by the demo's (exit 0)."""
    (demo_out / "evaluation").mkdir()
    (demo_out / "evaluation" / "tables.txt").write_text("my tables\n")
    refused_unchanged(root, ["demo", "--out", demo_out, "--seed", "5"], capsys, demo_out / "evaluation" / "tables.txt",
                      "OUT/evaluation/tables.txt is in the way: a file spherejax did not write")


def test_demo_evaluation_folder_linked_to_its_session_is_refused(root, demo_out, capsys):
    (demo_out / "evaluation").symlink_to("session")
    refused_unchanged(root, ["demo", "--out", demo_out, "--seed", "5"], capsys, demo_out / "evaluation",
                      "OUT/evaluation holds the session's manifest")


def test_demo_refuses_a_session_folder_of_other_files_before_simulating(tmp_path, capsys, small_design):
    """unchecked: refused too, but after the whole simulation."""
    (tmp_path / "demo" / "session").mkdir(parents=True)
    (tmp_path / "demo" / "session" / "keep.txt").write_text("mine")
    refused_unchanged(tmp_path, ["demo", "--out", tmp_path / "demo"], capsys, tmp_path / "demo" / "session",
                      "not an empty folder")


@pytest.mark.slow
def test_demo_again_replaces_what_an_earlier_demo_wrote(root, demo_out, capsys):
    """An earlier demo's calibration (its mark in the signed header) and evaluation (tables whose
    bytes its metrics.json records) are the demo's to replace; a file of the user's beside them stays."""
    from spherejax.cli.session_commands import DEMO_MARK

    calibration, header = io.load_calibration(root / "cal.h5")
    io.save_calibration(demo_out / "calibration.h5", calibration, instrument_id=header["instrument_id"],
                        band_centres_nm=header["band_centres_nm"], metadata={**header["metadata"], **DEMO_MARK})
    (demo_out / "evaluation").mkdir()
    tables = b"an earlier demo's tables"
    record = {"band_centres_nm": [], "markov_kappa": [], "metrics": {}, "files": {"tables.txt": hashlib.sha256(tables).hexdigest()}}
    (demo_out / "evaluation" / "metrics.json").write_text(json.dumps(record))
    (demo_out / "evaluation" / "tables.txt").write_bytes(tables)
    (demo_out / "evaluation" / "notes.txt").write_text("mine")
    status, _, err = run(["demo", "--out", demo_out, "--seed", "5"], capsys)
    assert status == 0, err
    assert (demo_out / "evaluation" / "tables.txt").read_text().startswith("Table 1.")
    assert (demo_out / "evaluation" / "notes.txt").read_text() == "mine"
    io.load_calibration(demo_out / "calibration.h5")


# --------------------------------------------------------------------------------------------
# acquire --profile FILE -o SESSION


def test_acquire_resume_does_not_remove_a_work_folder_holding_its_profile(root, capsys):
    """unchecked: S complete, its profile in S.partial: --resume removed S.partial, profile and all
    (exit 0)."""
    shutil.copytree(root / "session", root / "S")
    (root / "S.partial").mkdir()
    profile = write_profile(root / "S.partial")
    refused_unchanged(root, ["acquire", "--profile", profile, "-o", root / "S", "--resume", "--emulate", "--yes"], capsys,
                      root / "S.partial", "SESSION.partial holds the profile (--profile)")


def test_acquire_resume_leaves_a_folder_it_did_not_make(root, capsys):
    """unchecked: S complete, S.partial a folder of the user's: --resume removed it (exit 0)."""
    shutil.copytree(root / "session", root / "S")
    (root / "S.partial").mkdir()
    (root / "S.partial" / "keep.txt").write_text("mine")
    (root / "profiles").mkdir()
    profile = write_profile(root / "profiles")
    before = snapshot(root)
    status, _, err = run(["acquire", "--profile", profile, "-o", root / "S", "--resume", "--emulate", "--yes"], capsys)
    assert status == 0, err
    assert snapshot(root) == before


def test_acquire_work_folder_holding_the_lamp_state_file_is_refused(tmp_path, capsys):
    """The lamp's record (lamp hours) in SESSION.partial would go when the finished work folder is
    removed: refused before any device is opened (here, none is there to open)."""
    profile = write_profile(tmp_path, samples=("train-bg00-g0",), extra='[lamp]\nstate_file = "S.partial/lamp.json"\n')
    refused_unchanged(tmp_path, ["acquire", "--profile", profile, "-o", tmp_path / "S", "--yes"], capsys,
                      tmp_path / "S.partial", "SESSION.partial holds the profile's lamp state file")


def test_acquire_into_a_link_is_refused_before_anything_is_opened(tmp_path, capsys, monkeypatch):
    """unchecked: the whole acquisition, then a failed rename of the session onto the link."""
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    profile = write_profile(tmp_path, samples=("train-bg00-g0",))
    (tmp_path / "empty").mkdir()
    (tmp_path / "S").symlink_to("empty")
    try:
        refused_unchanged(tmp_path, ["acquire", "--profile", profile, "-o", tmp_path / "S", "--emulate", "--yes"], capsys,
                          tmp_path / "S", "-o SESSION is a symbolic link (to empty)")
    finally:
        sys.stdin.close()


# --------------------------------------------------------------------------------------------
# io.ownership's folder checks


@pytest.fixture
def tree(tmp_path) -> pathlib.Path:
    (tmp_path / "session" / "frames").mkdir(parents=True)
    (tmp_path / "session" / "manifest.json").write_text("{}")
    (tmp_path / "session" / "frames" / "a.tif").write_bytes(b"frame")
    (tmp_path / "link").symlink_to("session/frames")
    return tmp_path


def inputs(tree):
    return {"the manifest": tree / "session" / "manifest.json", "frame a": tree / "session" / "frames" / "a.tif"}


@pytest.mark.parametrize("spelling, what", [
    ("session", "holds the manifest"), ("session/frames", "holds frame a"), ("link", "holds frame a"),
    ("session/frames/../../session", "holds the manifest"), ("session/manifest.json", "is also the manifest"),
])
def test_refuse_holding_directly(tree, spelling, what):
    with pytest.raises(SpherejaxFileError) as raised:
        ownership.refuse_holding({"--out DIR": tree / spelling}, inputs(tree), directly=True)
    assert str(raised.value).startswith(f"{tree / spelling}: --out DIR {what} (")


def test_refuse_holding_directly_passes_folders_above_and_beside(tree):
    for spelling in (".", "session/frames/new", "elsewhere"):
        ownership.refuse_holding({"--out DIR": tree / spelling}, inputs(tree), directly=True)


def test_refuse_holding_at_any_depth(tree):
    above = tree / "link" / ".." / ".."  # link -> session/frames: above is tree itself
    with pytest.raises(SpherejaxFileError, match="SESSION.partial holds the manifest"):
        ownership.refuse_holding({"SESSION.partial": above}, inputs(tree))
    ownership.refuse_holding({"SESSION.partial": above}, inputs(tree), directly=True)
    ownership.refuse_holding({"SESSION.partial": tree / "other"}, inputs(tree))


def test_refuse_in_the_way_names_what_is_there(tree):
    (tree / "fifo").mkdir()
    os.mkfifo(tree / "fifo" / "x")
    cases = {tree / "session": "Is a directory", tree / "link": "a symbolic link (to session/frames)",
             tree / "fifo" / "x": "a FIFO", tree / "session" / "manifest.json": "not mine"}
    for path, fragment in cases.items():
        with pytest.raises(SpherejaxFileError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
            ownership.refuse_in_the_way({"OUT": path}, replaceable=lambda p: "not mine", expected="x")
    ownership.refuse_in_the_way({"OUT": tree / "session" / "manifest.json"}, replaceable=lambda p: None, expected="x")
    ownership.refuse_in_the_way({"OUT": tree / "new"}, replaceable=lambda p: "not mine", expected="x")


def test_earlier_run_reads_only_a_small_regular_record(tree):
    keys = {"metrics"}
    (tree / "m.json").write_text(json.dumps({"metrics": {}, "more": 1}))
    assert ownership.earlier_run(tree / "m.json", keys)
    (tree / "n.json").write_text(json.dumps({"other": 1}))
    assert not ownership.earlier_run(tree / "n.json", keys)
    os.mkfifo(tree / "fifo.json")  # never waited on
    assert not ownership.earlier_run(tree / "fifo.json", keys)
    (tree / "l.json").symlink_to("m.json")
    assert not ownership.earlier_run(tree / "l.json", keys)
    with open(tree / "big.json", "wb") as big:
        big.truncate(ownership.MAX_RECORD_BYTES + 1)
    assert not ownership.earlier_run(tree / "big.json", keys)
