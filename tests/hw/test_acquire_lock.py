"""One acquisition per session: SESSION.lock, an exclusive flock taken before any device opens
(`spherejax_hw.acquisition_journal._lock_session`, on `spherejax.io.exclusive_lock`, the
primitive of `correct`'s lock on OUT).

Unchecked, two `acquire` runs on one session (the second with --resume, once the first had made
SESSION.partial) both drove the instrument, and the loser left a full SESSION.partial. Now the
second is refused in one line naming SESSION.lock and its holder, before it opens a device,
touching nothing: the first's SESSION.partial is left to it, byte for byte.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pathlib
import stat
import subprocess
import sys
import threading

import pytest

from spherejax import cli, io
from spherejax.io import exclusive_lock
from spherejax_hw import acquire
from tests.hw.support import SAMPLES, run_acquire, write_profile


def snapshot(folder: pathlib.Path) -> dict[str, tuple]:
    """Every path under `folder` -> (kind, SHA-256 or link target, mtime), as
    `tests.robustness.catalogue.snapshot` gives it, but a FIFO listed by its kind alone (reading
    it for a hash would wait for a writer)."""
    found = {}
    for path in sorted(folder.rglob("*")):
        mode = path.lstat().st_mode
        key = path.relative_to(folder).as_posix()
        if stat.S_ISLNK(mode):
            found[key] = ("link", os.readlink(path), None)
        elif stat.S_ISDIR(mode):
            found[key] = ("dir", None, None)
        elif stat.S_ISFIFO(mode):
            found[key] = ("fifo", None, path.lstat().st_mtime_ns)
        else:
            found[key] = ("file", hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns)
    return found


@contextlib.contextmanager
def first_run_paused(profile: pathlib.Path, out: pathlib.Path):
    """A first acquisition on `out` in a thread, paused with its devices open and SESSION.partial
    made (at `on_instrument`) for the duration of the block, then let run to its end; the block
    gets the thread's result dict ("session" or "error" once it ends)."""
    paused, go_on, result = threading.Event(), threading.Event(), {}

    def pause(instrument) -> None:
        paused.set()
        assert go_on.wait(120), "the test never let the first run go on"

    def first() -> None:
        try:
            result["session"] = run_acquire(profile, out, on_instrument=pause)
        except BaseException as error:  # noqa: BLE001  reported by the test
            result["error"] = error
            paused.set()

    thread = threading.Thread(target=first, name="first-acquisition")
    thread.start()
    try:
        assert paused.wait(120) and "error" not in result, result
        yield result
    finally:
        go_on.set()
        thread.join(300)
    assert not thread.is_alive()


def _opened_devices(monkeypatch) -> list:
    """Record every call of acquire's `connect` (the devices opening) from here on."""
    calls = []
    real = acquire.connect

    def connect(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(acquire, "connect", connect)
    return calls


@pytest.mark.parametrize("resume", [True, False], ids=["second-resumes", "second-new"])
def test_a_second_acquisition_on_the_session_is_refused_touching_nothing(tmp_path, monkeypatch, resume):
    """unchecked (second-resumes): the second run drove the instrument beside the first."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    out = tmp_path / "s"
    with first_run_paused(profile, out) as first:
        opened = _opened_devices(monkeypatch)
        before = snapshot(tmp_path)
        with pytest.raises(acquire.AcquisitionError) as refused:
            run_acquire(profile, out, resume=resume)
        message = str(refused.value)
        assert "\n" not in message
        assert message.startswith(f"{tmp_path / 's.lock'}: is held by pid {os.getpid()} on "), message
        assert "another spherejax acquire is writing the session s" in message
        assert opened == []  # no device opened
        assert snapshot(tmp_path) == before  # the first's SESSION.partial and lock as they were
        monkeypatch.undo()
    assert first.get("session") == out, first
    assert [f.id for f in io.load_session(out).frames] == ["dark", "white", SAMPLES[0]]
    assert sorted(os.listdir(tmp_path)) == ["s", "sphere.toml"]  # no SESSION.partial, no lock left


def test_the_command_line_refuses_a_second_acquire_from_another_process(tmp_path):
    """The same through `spherejax acquire --resume` in a process of its own: exit status 2 and one
    line, the first run's work folder untouched."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    out = tmp_path / "s"
    with first_run_paused(profile, out) as first:
        before = snapshot(tmp_path)
        command = [sys.executable, "-m", "spherejax.cli", "-q", "acquire", "--profile", str(profile), "-o", str(out),
                   "--emulate", "--yes", "--resume"]
        second = subprocess.run(command, capture_output=True, text=True, timeout=300,
                                env={**os.environ, "JAX_PLATFORMS": "cpu"})
        assert second.returncode == cli.EXIT_BAD_INPUT, second.stderr
        lines = second.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"spherejax: error: {out}.lock: is held by pid {os.getpid()}"), lines
        assert snapshot(tmp_path) == before
    assert first.get("session") == out, first


def test_a_second_acquisition_through_another_path_is_refused(tmp_path, monkeypatch):
    """The lock is one file however SESSION is named: through `..` and through a linked folder."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    (tmp_path / "sub").mkdir()
    (tmp_path / "link").symlink_to(".", target_is_directory=True)
    with first_run_paused(profile, tmp_path / "s"):
        for other in (tmp_path / "sub" / ".." / "s", tmp_path / "link" / "s"):
            before = snapshot(tmp_path)
            with pytest.raises(acquire.AcquisitionError, match="is held by pid"):
                run_acquire(profile, other, resume=True)
            assert snapshot(tmp_path) == before


def test_a_lock_left_by_a_killed_run_is_taken_over_and_removed(tmp_path):
    """A killed run leaves SESSION.lock unlocked (the kernel drops a dead process's flock): the
    next run takes it over, and removes it when it ends."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    (tmp_path / "s.lock").write_text('{"pid": 999999, "host": "lab-pc", "acquiring": "s"}\n')
    assert run_acquire(profile, tmp_path / "s") == tmp_path / "s"
    assert sorted(os.listdir(tmp_path)) == ["s", "sphere.toml"]


@pytest.mark.parametrize("planted", ["a user's file", "an empty file", "a link", "a folder", "a FIFO"])
def test_something_else_at_the_locks_name_is_refused_and_left_as_it_is(tmp_path, monkeypatch, planted):
    """SESSION.lock is spherejax's only when it begins with a lock's record: a user's notes there
    are neither written over nor removed; a link is not followed, a FIFO not waited on."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    lock = tmp_path / "s.lock"
    if planted == "a user's file":
        lock.write_text("my notes on session s\n")
    elif planted == "an empty file":
        lock.write_text("")
    elif planted == "a link":
        (tmp_path / "notes.txt").write_text("mine\n")
        lock.symlink_to("notes.txt")
    elif planted == "a folder":
        lock.mkdir()
    else:
        os.mkfifo(lock)
    opened = _opened_devices(monkeypatch)
    before = snapshot(tmp_path)
    with pytest.raises(acquire.AcquisitionError) as refused:
        run_acquire(profile, tmp_path / "s")
    assert str(refused.value).startswith(f"{lock}: is in the way: "), refused.value
    assert "\n" not in str(refused.value)
    assert opened == []
    assert snapshot(tmp_path) == before


def test_the_lock_is_not_the_profile(tmp_path):
    """A session named so that SESSION.lock is the profile itself is refused before any lock."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    renamed = profile.rename(tmp_path / "s.lock")
    before = snapshot(tmp_path)
    with pytest.raises(acquire.AcquisitionError, match="SESSION.lock is also the profile"):
        run_acquire(renamed, tmp_path / "s")
    assert snapshot(tmp_path) == before


def test_the_lock_helper_names_its_holder_and_refuses_a_second_take(tmp_path):
    """`exclusive_lock.take`: the record it writes, a second take refused (another open file
    description, as another process has), the file gone on release and takeable again."""
    path = tmp_path / "x.lock"
    held = exclusive_lock.take(path, busy="busy", expected="wait", record={"what": "test"})
    assert path.read_text().startswith(f'{{"pid": {os.getpid()}, "host": ')
    assert held.taken_over is None
    with pytest.raises(io.SpherejaxFileError, match=rf"is held by pid {os.getpid()} on .*: busy \(expected wait\)"):
        exclusive_lock.take(path, busy="busy", expected="wait")
    held.release()
    assert not path.exists()
    path.write_text('{"pid": 42, "host": "elsewhere"}')
    with exclusive_lock.take(path, busy="busy", expected="wait") as again:
        assert again.taken_over == "pid 42 on elsewhere"
    assert not path.exists()


@pytest.mark.parametrize("where", ["SESSION.lock", "SESSION.partial", "the profile"])
def test_a_log_file_among_acquires_own_files_is_refused(tmp_path, capsys, where):
    """--log-file FILE is checked against acquire's files like any output, before it is opened:
    never SESSION.lock (written over, then removed), never inside SESSION.partial (renamed into
    the session), never the profile."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    (tmp_path / "s.partial").mkdir()
    log = {"SESSION.lock": tmp_path / "s.lock", "SESSION.partial": tmp_path / "s.partial" / "run.log",
           "the profile": profile}[where]
    before = snapshot(tmp_path)
    status = cli.main(["-q", "--log-file", str(log), "acquire", "--profile", str(profile), "-o", str(tmp_path / "s"),
                       "--emulate", "--yes", "--resume"])
    err = capsys.readouterr().err
    assert status == cli.EXIT_BAD_INPUT
    assert err.count("\n") == 1 and err.startswith(f"spherejax: error: {log}: --log-file FILE "), err
    assert snapshot(tmp_path) == before
