"""`spherejax.io.atomic`: the one way spherejax and hw/ write a file, and its one rule for
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
from hw.lamp import Lamp
from spherejax import cli, io, measurement_files
from spherejax.io import atomic


def leftovers(folder: pathlib.Path) -> list[str]:
    return sorted(name for name in os.listdir(folder) if name.startswith("."))


def test_bytes_and_text_replace_the_target(tmp_path):
    target = tmp_path / "state.json"
    target.write_text("old")
    atomic.write_atomic(target, "new ünïcode\n")
    assert target.read_text(encoding="utf-8") == "new ünïcode\n"
    atomic.write_atomic(target, b"\x00\x01bytes")
    assert target.read_bytes() == b"\x00\x01bytes"
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_a_new_file_gets_the_mode_the_umask_gives(tmp_path, umask):
    previous = os.umask(umask)
    try:
        atomic.write_atomic(tmp_path / "out.csv", b"a,b\n")
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
        with atomic.atomic_file(target) as handle:
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
    atomic.write_atomic(tmp_path / "a.json", "{}")
    assert events == ["fsync file", "rename", "fsync folder"]


def test_the_temporary_name_is_created_exclusively(tmp_path, monkeypatch):
    """A file (or a link planted) at the temporary name is never opened or followed."""
    fixed = uuid.UUID(int=0xABCDEF)
    monkeypatch.setattr(uuid, "uuid4", lambda: fixed)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.write_bytes(b"not to be touched")
    planted = atomic.temp_sibling(tmp_path / "out.json")
    planted.symlink_to(elsewhere)
    with pytest.raises(FileExistsError):
        atomic.write_atomic(tmp_path / "out.json", b"new")
    assert elsewhere.read_bytes() == b"not to be touched"
    assert not (tmp_path / "out.json").exists()


def test_the_name_rule():
    name = atomic.temp_sibling(pathlib.Path("/x/frames/dark.tif")).name
    assert atomic.is_temp_sibling(name) and atomic.is_temp_sibling(name, "dark.tif")
    assert not atomic.is_temp_sibling(name, "white.tif")
    for other in (".dark.tif.tmp", ".dark.tif.tmp-1234", "dark.tif", ".dark.tif.0123456789AB.tmp"):
        assert not atomic.is_temp_sibling(other)
    assert io.temp_sibling is atomic.temp_sibling and io.is_temp_sibling is atomic.is_temp_sibling


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
    assert source.parent == target.parent and atomic.is_temp_sibling(source.name, target.name), (what, source.name)
    assert leftovers(target.parent) == [], what
