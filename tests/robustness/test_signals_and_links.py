"""Reliability of `spherejax correct` and `spherejax acquire` against what the file system and the
scheduler do to them: symbolic-link loops, one input named several ways, FIFOs, sockets and
devices among the inputs, and SIGINT / SIGTERM in the middle of a run (in process, on dask, and
during an acquisition).

Each bad input must give one clear line and never hang; each stop must leave OUT as a
consistent, resumable batch (no temporary file, no lock, a manifest that lists complete inputs
only), and --resume must then finish it with the bytes of an uninterrupted run.
"""

from __future__ import annotations

import os
import pathlib
import re
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest

from spherejax_hw import acquire
from spherejax import archive, io
from spherejax.archive.manifest import output_digest
from tests.hw.support import BANDS as ACQUIRED_BANDS
from tests.hw.support import SAMPLES, run_acquire, write_profile
from tests.batch_support import KINDS, NAMES, holds_lock, wait_until, frame, manifest_records, outputs_of, run

ENV = {**os.environ, "JAX_PLATFORMS": "cpu"}
IMAGES = (2 + len(SAMPLES)) * len(ACQUIRED_BANDS)  # dark, white and the samples, every band
INTERRUPTED = re.compile(r"spherejax: interrupted after (\d+) of (\d+) (inputs|band images); run again with --resume")


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


# ---------------------------------------------------------------------------- signals: correct

BATCH = 12


def _start(*argv) -> subprocess.Popen:
    command = [sys.executable, "-m", "spherejax.cli", "-q", *map(str, argv)]
    return subprocess.Popen(command, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _temporaries(out: pathlib.Path) -> set[str]:
    return {p.relative_to(out).as_posix() for p in out.rglob("*") if io.is_temp_sibling(p.name)}


def _done(out: pathlib.Path) -> dict[str, dict]:
    return {name: record for name, record in archive.read_manifest(out).items() if record["status"] == "done"}


def _batch(folder: pathlib.Path, rng) -> None:
    for index in range(BATCH):
        _cube(folder / f"cube{index:02d}.tif", rng)


def _check_stopped(process: subprocess.Popen, signum: int, out: pathlib.Path, unit: str = "inputs") -> int:
    """The run stopped cleanly: exit status, one line, no temporary, no lock, a manifest of
    complete inputs only, no output the manifest does not list. Returns the inputs done."""
    _, err = process.communicate(timeout=120)
    err = err.decode()
    assert process.returncode == 128 + signum, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    match = INTERRUPTED.fullmatch(lines[0])
    assert match and int(match.group(2)) == BATCH and match.group(3) == unit, err
    assert not _temporaries(out)
    assert not (out / archive.LOCK_NAME).exists()
    records = archive.read_manifest(out)
    assert all(record["status"] == "done" for record in records.values())
    assert int(match.group(1)) == len(records)
    for record in records.values():
        for output, digest in record["outputs"].items():
            assert output_digest(out / output) == digest, output
    recorded = {output for record in records.values() for output in record["outputs"]}
    assert set(outputs_of(out)) == recorded
    return len(records)


@pytest.mark.slow
def test_sigint_and_sigterm_stop_correct_cleanly_and_resume_finishes_it(cal, tmp_path, rng):
    _batch(tmp_path / "in", rng)
    reference, out = tmp_path / "reference", tmp_path / "out"
    process = _start("correct", "-c", cal, tmp_path / "in", "-o", reference)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()

    # (signal, moment): just after start-up (the lock taken), mid-batch (some inputs done), and
    # inside an input's writes (a temporary output there; the poll may see it late, when the
    # input is already complete: then it is between inputs).
    moments = [(signal.SIGINT, "start-up"), (signal.SIGTERM, "mid-batch"), (signal.SIGTERM, "in-writes"),
               (signal.SIGINT, "in-writes")]
    done = 0
    in_writes = 0
    for signum, moment in moments:
        process = _start("correct", "-c", cal, tmp_path / "in", "-o", out, *(["--resume"] if out.exists() else []))
        wait_until(process, holds_lock(process, out))
        if moment == "mid-batch":
            wait_until(process, lambda: len(_done(out)) >= done + 3)
        elif moment == "in-writes":
            wait_until(process, lambda: len(_done(out)) >= done + 1)
            reached = len(_done(out))
            wait_until(process, lambda: bool(_temporaries(out)) or len(_done(out)) > reached)
            in_writes += bool(_temporaries(out))
        assert process.poll() is None, f"{moment}: the run ended before the signal"
        process.send_signal(signum)
        now = _check_stopped(process, signum, out)
        assert now >= done
        done = now
    assert done < BATCH
    print(f"\n{len(moments)} stops, {in_writes} seen inside an input's writes; {done} inputs done before the last --resume")

    process = _start("correct", "-c", cal, tmp_path / "in", "-o", out, "--resume")
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()
    assert outputs_of(out) == outputs_of(reference)
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == sorted(p.relative_to(reference) for p in reference.rglob("*"))
    # Every input recorded exactly once over all the runs, as the uninterrupted run recorded it.
    lines = [line for line in (out / archive.MANIFEST_NAME).read_bytes().split(b"\n") if line]
    assert sorted(lines) == sorted(line for line in (reference / archive.MANIFEST_NAME).read_bytes().split(b"\n") if line)


@pytest.mark.slow
def test_sigterm_stops_a_dask_batch_cleanly(cal, tmp_path, rng):
    psutil = pytest.importorskip("psutil")
    _batch(tmp_path / "in", rng)
    out = tmp_path / "out"
    env_cache = tmp_path / "jax-cache"
    command = [sys.executable, "-m", "spherejax.cli", "-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)]
    process = subprocess.Popen([*command, "--workers", "2"], env={**ENV, "SPHEREJAX_COMPILATION_CACHE": str(env_cache)},
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    wait_until(process, lambda: len(_done(out)) >= 2)
    assert process.poll() is None, "the batch ended before the signal"
    workers = psutil.Process(process.pid).children(recursive=True)
    assert workers
    process.send_signal(signal.SIGTERM)
    done = _check_stopped(process, signal.SIGTERM, out)
    assert 2 <= done < BATCH
    # The cluster is shut down with the client: no worker process outlives the command.
    gone, alive = psutil.wait_procs(workers, timeout=20)
    assert not alive, alive

    process = subprocess.Popen([*command, "--resume"], env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()
    records = archive.read_manifest(out)
    assert len(records) == BATCH and all(r["status"] == "done" for r in records.values())
    assert len(outputs_of(out)) == BATCH * len(KINDS)


# ---------------------------------------------------------------------------- signals: acquire


def test_sigterm_during_acquire_closes_the_shutter_and_keeps_the_journal(tmp_path):
    """In process, so the emulated shutter can be looked at: the signal comes once 20 band images
    are taken (dark done, the white standard imaged with the shutter open)."""
    from spherejax import interrupt

    profile = write_profile(tmp_path)
    out, partial = tmp_path / "s", tmp_path / "s.partial"
    instruments, open_at_signal = [], []

    def progress(done: int, total: int) -> None:
        if done == 20:
            open_at_signal.append(not instruments[0].emulated["shutter"].emulator.closed)
            os.kill(os.getpid(), signal.SIGTERM)

    before = signal.getsignal(signal.SIGTERM)
    with open(os.devnull, "w") as devnull, pytest.raises(interrupt.Interrupted) as stopped:
        with interrupt.stop_requests():
            acquire.acquire(profile, out, emulate=True, operator=acquire.Operator(yes=True, stream=devnull),
                            settings=acquire.Settings(log=lambda line: None, progress=progress),
                            on_instrument=instruments.append)
    assert signal.getsignal(signal.SIGTERM) is before  # the handlers are restored
    assert stopped.value.exit_status == 143
    assert stopped.value.message() == f"spherejax: interrupted after 20 of {IMAGES} band images; run again with --resume"
    assert open_at_signal == [True] and instruments[0].emulated["shutter"].emulator.closed
    assert len(acquire.Journal(partial).done_images()) == 20
    assert not out.exists()

    run_acquire(profile, out, resume=True)
    session = io.load_session(out)
    assert [f.id for f in session.frames] == ["dark", "white", *SAMPLES]
    assert sorted(os.listdir(tmp_path)) == ["s", "sphere.toml"]


@pytest.mark.slow
def test_sigint_stops_the_acquire_command_and_resume_completes_it(tmp_path):
    profile = write_profile(tmp_path)
    out, partial = tmp_path / "s", tmp_path / "s.partial"
    command = [sys.executable, "-m", "spherejax.cli", "-q", "acquire", "--profile", str(profile), "-o", str(out),
               "--emulate", "--yes"]
    process = subprocess.Popen(command, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def images() -> int:
        return sum(1 for r in acquire.Journal(partial).records() if r["event"] == "image") if partial.is_dir() else 0

    wait_until(process, lambda: images() >= 20)
    assert process.poll() is None, "the acquisition ended before the signal"
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    err = err.decode()
    assert process.returncode == 130, err
    stops = [line for line in err.splitlines() if INTERRUPTED.fullmatch(line)]
    assert len(stops) == 1 and err.strip().splitlines()[-1] == stops[0] and "Traceback" not in err, err
    kept = int(INTERRUPTED.fullmatch(stops[0]).group(1))
    assert 20 <= kept < IMAGES and f"of {IMAGES} band images" in stops[0]
    assert len(acquire.Journal(partial).done_images()) == kept
    assert not out.exists() or not any(out.iterdir())

    done = subprocess.run([*command, "--resume"], env=ENV, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    session = io.load_session(out)
    assert [f.id for f in session.frames] == ["dark", "white", *SAMPLES]
    assert not partial.exists()
