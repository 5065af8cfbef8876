"""FIFOs and sparse files (docs/reliability.md, section 5) beyond `correct`'s lock and manifest:
in every other file a command reads whole or opens: a session's manifest and frames, the cube
`measure` reads, the files `measure` writes, an instrument profile and the lamp's state.
Unchecked, each would be waited on, read whole (a 3 GB sparse manifest.json into memory; a 5 GB
sparse cube takes OpenImageIO minutes), or replaced (a FIFO at `measure -o`'s name, exit 0).
"""

from __future__ import annotations

import os
import shutil
import stat

import pytest

from spherejax import cli, io
from spherejax_hw import lamp, profile
from tests.hw.support import write_profile


def _run(argv, capsys):
    status = cli.main(["-q", *map(str, argv)])
    captured = capsys.readouterr()
    return status, captured.err.strip()


@pytest.fixture
def session(workspace, tmp_path):
    copy = tmp_path / "session"
    shutil.copytree(workspace / "session", copy)
    return copy


def _fifo(path):
    path.unlink(missing_ok=True)
    os.mkfifo(path)
    return path


def test_a_fifo_as_a_sessions_manifest_is_refused_by_what_it_is(session, tmp_path, capsys):
    _fifo(session / "manifest.json")
    status, err = _run(["calibrate", session, "-o", tmp_path / "cal.h5"], capsys)
    assert status == 2
    assert err == (f"spherejax: error: {session / 'manifest.json'}: cannot be read: it is a FIFO "
                   "(expected the manifest of a spherejax session)")


def test_a_fifo_as_a_sessions_frame_is_refused_by_what_it_is(session, tmp_path, capsys):
    _fifo(session / "frames" / "dark.tif")
    status, err = _run(["calibrate", session, "-o", tmp_path / "cal.h5"], capsys)
    assert status == 2 and err.startswith(f"spherejax: error: {session / 'frames' / 'dark.tif'}: is a FIFO (expected ")
    assert not (tmp_path / "cal.h5").exists()


def test_a_sparse_sessions_manifest_is_refused_before_it_is_read(session, tmp_path, capsys):
    """`truncate -s 3G manifest.json`: refused by its size, not read whole into memory."""
    os.truncate(session / "manifest.json", 3 << 30)
    status, err = _run(["calibrate", session, "-o", tmp_path / "cal.h5"], capsys)
    assert status == 2
    assert f"manifest.json: cannot be read: it is {3 << 30} bytes, more than such a file holds" in err


def test_a_frame_grown_far_past_its_image_is_refused_before_it_is_read(session, tmp_path, capsys):
    """A frame TIFF padded to 3 GB (sparse): far more than a frame of the session's shape needs."""
    os.truncate(session / "frames" / "dark.tif", 3 << 30)
    status, err = _run(["calibrate", session, "-o", tmp_path / "cal.h5"], capsys)
    assert status == 2 and f"dark.tif: is {3 << 30} bytes, more than a " in err


def test_measure_refuses_a_fifo_or_a_sparse_file_as_its_cube(workspace, tmp_path, capsys):
    cal = workspace / "cal.h5"
    fifo = _fifo(tmp_path / "fifo.tif")
    status, err = _run(["measure", "-c", cal, fifo, "--region", "a=0,5,0,5"], capsys)
    assert status == 2 and err.startswith(f"spherejax: error: {fifo}: is a FIFO (expected a cube")
    big = tmp_path / "big.tif"
    with open(big, "wb") as handle:
        handle.truncate(5 << 30)  # OpenImageIO's readers took minutes over it
    status, err = _run(["measure", "-c", cal, big, "--region", "a=0,5,0,5"], capsys)
    assert status == 2 and f"{big}: is {5 << 30} bytes, more than a " in err


@pytest.mark.parametrize("option", ["-o", "--cgats"])
def test_measure_never_replaces_a_fifo_at_an_outputs_name(workspace, tmp_path, capsys, option):
    """A FIFO at an output's name is in the way, not replaced by the new file."""
    cube = workspace / "session" / "frames" / "targets.tif"
    fifo = _fifo(tmp_path / "out.csv")
    value = tmp_path / "out" if option == "-o" else fifo
    status, err = _run(["measure", "-c", workspace / "cal.h5", cube, "--region", "a=0,5,0,5", option, value], capsys)
    assert status == 2 and f"{fifo}: " in err and "is in the way: a FIFO" in err
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not (tmp_path / "out.json").exists()


def test_an_instrument_profile_that_is_a_fifo_or_huge_is_refused(tmp_path):
    fifo = _fifo(tmp_path / "sphere.toml")
    with pytest.raises(profile.ProfileError, match="cannot be read: it is a FIFO"):
        profile.load_profile(fifo)
    fifo.unlink()
    path = write_profile(tmp_path)
    os.truncate(path, 3 << 30)
    with pytest.raises(profile.ProfileError, match=f"cannot be read: it is {3 << 30} bytes"):
        profile.load_profile(path)


def test_a_profile_reached_through_a_link_is_read(tmp_path):
    """Documents are read through links (a lab's current.toml -> sphere-2026.toml)."""
    real = write_profile(tmp_path)
    link = tmp_path / "current.toml"
    link.symlink_to(real)
    assert profile.load_profile(link).band_centres_nm == profile.load_profile(real).band_centres_nm


def test_a_lamp_state_that_is_a_fifo_is_refused_without_waiting(tmp_path):
    state = _fifo(tmp_path / "lamp.json")
    with pytest.raises(lamp.LampStateError, match="lamp state cannot be read: it is a FIFO"):
        lamp.Lamp(state).is_on


def test_read_small_reads_what_fits_and_refuses_the_rest(tmp_path):
    path = tmp_path / "doc.json"
    path.write_bytes(b"x" * 100)
    assert io.read_small(path, 100) == b"x" * 100
    with pytest.raises(OSError, match="it is 100 bytes, more than such a file holds \\(99 at most\\)"):
        io.read_small(path, 99)
    with pytest.raises(OSError, match="it is a folder"):
        io.read_small(tmp_path)
    with pytest.raises(FileNotFoundError):
        io.read_small(tmp_path / "missing.json")
