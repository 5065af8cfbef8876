"""`spherejax.atomic_files`: the one way spherejax and hw/ write a file, and its one rule for
temporary names.

Checked by what the steps are for: the target holds the old bytes or the new ones and nothing
else, no temporary file outlives a failure, the file and its folder are fsynced, the temporary
name is created exclusively with the mode a new file at the target's name would get, and every
writer's temporary names are ones cleanup recognises (`is_temp_sibling`).
"""

import os
import pathlib
import stat
import uuid

import numpy as np
import pytest

import spherejax as sj
from spherejax import atomic_files, cli, io, measurement_files
from spherejax_hw.lamp import Lamp


def leftovers(folder: pathlib.Path) -> list[str]:
    return sorted(name for name in os.listdir(folder) if name.startswith("."))


def test_bytes_and_text_replace_the_target(tmp_path):
    target = tmp_path / "state.json"
    target.write_text("old")
    atomic_files.write_atomic(target, "new ünïcode\n")
    assert target.read_text(encoding="utf-8") == "new ünïcode\n"
    atomic_files.write_atomic(target, b"\x00\x01bytes")
    assert target.read_bytes() == b"\x00\x01bytes"
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_a_new_file_gets_the_mode_the_umask_gives(tmp_path, umask):
    previous = os.umask(umask)
    try:
        atomic_files.write_atomic(tmp_path / "out.csv", b"a,b\n")
        plain = tmp_path / "plain.csv"
        plain.write_bytes(b"a,b\n")  # what open() gives a new file under the same umask
    finally:
        os.umask(previous)
    mode = stat.S_IMODE((tmp_path / "out.csv").stat().st_mode)
    assert mode == 0o666 & ~umask == stat.S_IMODE(plain.stat().st_mode)


def test_an_error_in_the_block_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "calibration.h5"
    target.write_bytes(b"the old calibration")
    with pytest.raises(RuntimeError, match="disk full"):
        with atomic_files.atomic_file(target) as handle:
            handle.write(b"half of the new")
            raise RuntimeError("disk full")
    assert target.read_bytes() == b"the old calibration"
    assert leftovers(tmp_path) == []


def test_the_file_and_then_its_folder_are_fsynced_before_and_after_the_rename(tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(descriptor):
        events.append("fsync folder" if stat.S_ISDIR(os.fstat(descriptor).st_mode) else "fsync file")
        real_fsync(descriptor)

    def replace(source, destination):
        events.append("rename")
        real_replace(source, destination)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    atomic_files.write_atomic(tmp_path / "a.json", "{}")
    assert events == ["fsync file", "rename", "fsync folder"]


def test_the_temporary_name_is_created_exclusively(tmp_path, monkeypatch):
    """A file (or a link planted) at the temporary name is never opened or followed."""
    fixed = uuid.UUID(int=0xABCDEF)
    monkeypatch.setattr(uuid, "uuid4", lambda: fixed)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.write_bytes(b"not to be touched")
    planted = atomic_files.temp_sibling(tmp_path / "out.json")
    planted.symlink_to(elsewhere)
    with pytest.raises(FileExistsError):
        atomic_files.write_atomic(tmp_path / "out.json", b"new")
    assert elsewhere.read_bytes() == b"not to be touched"
    assert not (tmp_path / "out.json").exists()


def test_the_name_rule():
    name = atomic_files.temp_sibling(pathlib.Path("/x/frames/dark.tif")).name
    assert atomic_files.is_temp_sibling(name) and atomic_files.is_temp_sibling(name, "dark.tif")
    assert not atomic_files.is_temp_sibling(name, "white.tif")
    for other in (".dark.tif.tmp", ".dark.tif.tmp-1234", "dark.tif", ".dark.tif.0123456789AB.tmp"):
        assert not atomic_files.is_temp_sibling(other)
    assert io.temp_sibling is atomic_files.temp_sibling and io.is_temp_sibling is atomic_files.is_temp_sibling


def small_calibration():
    rng = np.random.default_rng(1)
    dark = rng.uniform(90, 110, (6, 8, 4)).astype(np.float32)
    patch = np.zeros((6, 8), bool)
    patch[1:3, 1:3] = True
    return sj.Calibration(
        dark=dark, white=dark + 1000, patch=patch, coeffs=np.asarray(sj.identity_coeffs(4, np.float32)),
        wiener=rng.uniform(0, 0.1, (31, 4)).astype(np.float32),
    )


def writers(tmp_path):
    """(what, target, write) for every writer of spherejax and hw that renames a file into place."""
    frame = np.arange(6 * 8 * 4, dtype=np.uint16).reshape(6, 8, 4)
    return [
        ("calibration file", tmp_path / "cal.h5", lambda p: io.save_calibration(p, small_calibration(), instrument_id="test", band_centres_nm=[400, 500, 600, 700])),
        ("camera frame", tmp_path / "frame.tif", lambda p: io.write_frame(p, frame)),
        ("output image", tmp_path / "lab.exr", lambda p: io.write_exr(p, frame.astype(np.float32), channel_names=list("abcd"))),
        ("command outputs", tmp_path / "out" / "table.csv", lambda p: cli._write_files(p.parent, {p.name: b"a\n"})),
        ("measurement files", tmp_path / "m.csv", lambda p: measurement_files.write_files({p: b"a\n"})),
        ("lamp state", tmp_path / "lamp.json", lambda p: Lamp(p).switch_on()),
    ]


@pytest.mark.parametrize("index", range(6), ids=lambda k: ["calibration", "frame", "exr", "cli", "measurement", "lamp"][k])
def test_every_writer_renames_from_a_name_cleanup_recognises(tmp_path, monkeypatch, index):
    what, target, write = writers(tmp_path)[index]
    renamed = []
    real_replace = os.replace

    def replace(source, destination):
        renamed.append((pathlib.Path(source), pathlib.Path(destination)))
        real_replace(source, destination)

    monkeypatch.setattr(os, "replace", replace)
    write(target)
    assert target.is_file(), what
    assert renamed and renamed[-1][1] == target, what
    source = renamed[-1][0]
    assert source.parent == target.parent and atomic_files.is_temp_sibling(source.name, target.name), (what, source.name)
    assert leftovers(target.parent) == [], what


def test_a_set_of_files_is_written_together(tmp_path):
    old = tmp_path / "tables.txt"
    old.write_bytes(b"old tables")
    atomic_files.write_together({old: b"new tables", tmp_path / "figure.png": b"\x89PNG"})
    assert old.read_bytes() == b"new tables" and (tmp_path / "figure.png").read_bytes() == b"\x89PNG"
    assert leftovers(tmp_path) == []


def test_a_full_disk_changes_none_of_the_set(tmp_path, monkeypatch):
    """The second file's contents cannot be flushed (ENOSPC): the first, already complete in its
    temporary file, is not renamed either, and the error names the second target."""
    old = tmp_path / "a.csv"
    old.write_bytes(b"old")
    real_fsync, calls = os.fsync, []

    def fsync(descriptor):
        calls.append(descriptor)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        real_fsync(descriptor)

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(OSError) as raised:
        atomic_files.write_together({old: b"new", tmp_path / "b.json": b"{}"})
    assert raised.value.filename == str(tmp_path / "b.json")
    assert old.read_bytes() == b"old" and sorted(os.listdir(tmp_path)) == ["a.csv"]


def test_a_failed_rename_removes_what_the_set_created(tmp_path, monkeypatch):
    """Renames need no space, but one can still fail (a folder where the file should go): the
    targets the call created are removed, the one it replaced stays replaced, no temporaries."""
    replaced, created, blocked = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    replaced.write_bytes(b"old")
    blocked.mkdir()
    (blocked / "inside").write_bytes(b"x")  # a non-empty folder: os.replace of a file onto it fails
    with pytest.raises(OSError) as raised:
        atomic_files.write_together({replaced: b"new a", created: b"new b", blocked: b"new c"})
    assert raised.value.filename == str(blocked)
    assert replaced.read_bytes() == b"new a" and not created.exists() and blocked.is_dir()
    assert sorted(os.listdir(tmp_path)) == ["a.csv", "c.csv"]


def test_the_command_line_outputs_of_a_failed_set_leave_no_folder(tmp_path, monkeypatch):
    def full_disk(descriptor):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError):
        cli._write_files(tmp_path / "evaluation", {"tables.txt": b"t", "figure5.png": b"f"})
    assert os.listdir(tmp_path) == []


def test_measurement_files_word_a_failure_for_their_file(tmp_path):
    target = tmp_path / "missing-folder" / "m.csv"
    with pytest.raises(io.SpherejaxFileError, match="m.csv.*could not be written"):
        measurement_files.write_files({target: b"a\n"})
