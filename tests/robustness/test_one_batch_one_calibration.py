"""One batch, one calibration (`spherejax.archive.batch_calibration`), and what a batch leaves on its
way out: its empty output folders removed, every OSError in one line naming its file.

A calibration file replaced (`calibrate --force`), rewritten in place, copied over or removed while
`correct` runs stops the batch in one line naming the file (exit status 2); the inputs finished
before are recorded, all with the one checksum the batch read, and nothing else is left in OUT.
The change is made from the batch's own progress callback, after its first input is recorded, so
that the moment is the same in every run: in process (two inputs under way at once), through the
command line, on a dask cluster, and for one input corrected on its own (`correct_input`).
"""

from __future__ import annotations

import errno
import os
import pathlib
import shutil
import threading

import numpy as np
import pytest

from spherejax import archive, cli, interrupt, io
from spherejax.archive import batch as batch_module
from spherejax.archive.manifest import output_digest
from spherejax.cli import correct_command

from tests.batch_support import KINDS, frame, make_calibration, manifest_records, outputs_of, run


def _inputs(tmp_path: pathlib.Path, count: int = 5, folder: str = "in") -> pathlib.Path:
    rng = np.random.default_rng(11)
    (tmp_path / folder).mkdir(parents=True, exist_ok=True)
    for k in range(count):
        io.write_frame(tmp_path / folder / f"f{k}.tif", frame(rng))
    return tmp_path / folder


def _own_calibration(cal: pathlib.Path, tmp_path: pathlib.Path) -> pathlib.Path:
    path = tmp_path / "cal.h5"
    shutil.copyfile(cal, path)
    return path


def _another_calibration(path: pathlib.Path) -> None:
    """What `spherejax calibrate --force -o PATH` does: another calibration saved over it
    (atomically: a new file renamed over the old one)."""
    calibration, bands, instrument = make_calibration(np.random.default_rng(99))
    io.save_calibration(path, calibration, instrument_id=instrument, band_centres_nm=bands)


def _copied_over(path: pathlib.Path) -> None:
    """The same bytes, another file: a copy renamed over it (cp + mv)."""
    copy = path.with_name("copy.h5")
    shutil.copyfile(path, copy)
    os.replace(copy, path)


def _rewritten_in_place(path: pathlib.Path) -> None:
    """The same file (inode), other bytes: another calibration written into it."""
    other = path.with_name("other.h5")
    _another_calibration(other)
    with open(path, "r+b") as handle:
        handle.truncate(0)
        handle.write(other.read_bytes())


def _removed(path: pathlib.Path) -> None:
    path.unlink()


CHANGES = {"calibrate --force": _another_calibration, "copied over": _copied_over,
           "rewritten in place": _rewritten_in_place, "removed": _removed}


def _check_stopped_batch(out: pathlib.Path, checksum: str, at_least_recorded: int = 1) -> list[dict]:
    """OUT after a batch stopped by a calibration change: every record done with the batch's one
    checksum, every output recorded and whole, nothing else (no temporary, no lock, no folder)."""
    records = manifest_records(out)
    assert len(records) >= at_least_recorded
    assert {record["calibration_checksum"] for record in records} == {checksum}
    assert all(record["status"] == "done" for record in records)
    recorded = {name: digest for record in records for name, digest in record["outputs"].items()}
    assert sorted(outputs_of(out)) == sorted(recorded)
    assert all(output_digest(out / name) == digest for name, digest in recorded.items())
    assert [p for p in out.rglob("*") if p.is_dir() and not any(p.iterdir())] == []  # no empty folder
    assert not (out / archive.LOCK_NAME).exists()
    return records


@pytest.mark.parametrize("change", list(CHANGES), ids=list(CHANGES))
def test_a_calibration_changed_mid_batch_stops_it_in_process(cal, tmp_path, change):
    inputs = _inputs(tmp_path)
    path = _own_calibration(cal, tmp_path)
    checksum = io.open_calibration(path).header["checksum"]
    out = tmp_path / "out"
    seen = []

    def on_result(spec, result):
        seen.append(spec.name)
        if len(seen) == 1:
            CHANGES[change](path)

    with pytest.raises(archive.CalibrationChangedError) as refused:
        archive.run_batch([inputs], out, path, on_result=on_result)
    message = str(refused.value)
    assert message.startswith(f"{path}: changed during the batch"), message
    assert "\n" not in message and "the batch stopped after" in message
    records = _check_stopped_batch(out, checksum)
    assert len(records) < 5  # the inputs after the change were never corrected


def test_a_calibration_changed_mid_batch_stops_the_command_line_with_one_line(cal, tmp_path, capsys, monkeypatch):
    inputs = _inputs(tmp_path)
    path = _own_calibration(cal, tmp_path)
    checksum = io.open_calibration(path).header["checksum"]
    out = tmp_path / "out"
    progress = correct_command._BatchProgress.result

    def result_then_recalibrate(self, spec, result):
        progress(self, spec, result)
        if self.index == 1:
            _another_calibration(path)

    monkeypatch.setattr(correct_command._BatchProgress, "result", result_then_recalibrate)
    status, stdout, err = run(["-q", "correct", "-c", str(path), str(inputs), "-o", str(out)], capsys)
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"spherejax: error: {path}: changed during the batch"), err
    assert "Traceback" not in err
    _check_stopped_batch(out, checksum)
    monkeypatch.undo()

    # --resume with the new calibration: one batch, one calibration again (the new one's), every
    # input redone.
    status, stdout, err = run(["-q", "correct", "-c", str(path), str(inputs), "-o", str(out), "--resume"], capsys)
    assert status == 0, err
    last = {record["name"]: record for record in manifest_records(out)}
    assert len(last) == 5
    assert {record["calibration_checksum"] for record in last.values()} == {io.open_calibration(path).header["checksum"]}


def test_one_input_at_a_time_stops_too(cal, tmp_path, monkeypatch):
    """The in-process batch with one input under way (`INPUTS_IN_FLIGHT` 1)."""
    monkeypatch.setattr(batch_module._in_process, "__defaults__", (1,))  # in_flight=1
    inputs = _inputs(tmp_path, 3)
    path = _own_calibration(cal, tmp_path)
    checksum = io.open_calibration(path).header["checksum"]
    out = tmp_path / "out"
    with pytest.raises(archive.CalibrationChangedError, match="the batch stopped after 1 of 3 inputs"):
        archive.run_batch([inputs], out, path, on_result=lambda spec, result: _another_calibration(path))
    assert len(_check_stopped_batch(out, checksum)) == 1


def test_a_calibration_changed_while_an_input_is_corrected_leaves_nothing_of_it(cal, tmp_path, monkeypatch):
    """Changed after the input read its calibration and before its outputs go into place (while its
    strips are corrected): the input fails the check before its commit and leaves nothing."""
    inputs = _inputs(tmp_path, 1)
    path = _own_calibration(cal, tmp_path)
    out = tmp_path / "out"
    correct_into = batch_module.correct_into

    def correct_then_recalibrate(*args, **kwargs):
        _another_calibration(path)
        return correct_into(*args, **kwargs)

    monkeypatch.setattr(batch_module, "correct_into", correct_then_recalibrate)
    with pytest.raises(archive.CalibrationChangedError, match="after 0 of 1 inputs"):
        archive.run_batch([inputs], out, path)
    assert manifest_records(out) == [] and outputs_of(out) == {}


def test_a_calibration_read_by_rows_rewritten_in_place_mid_input_stops_the_batch(cal, tmp_path, monkeypatch):
    """A calibration whose dark and white stay on disk (`io.CalibrationFile.rows`) rewritten in
    place while an input reads its rows: whatever HDF5 then reads (the new bytes, or an error), the
    input is not recorded, as done or as failed, and the batch stops."""
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 4096)
    inputs = _inputs(tmp_path, 2)
    path = _own_calibration(cal, tmp_path)
    out = tmp_path / "out"
    correct_into = batch_module.correct_into

    def rewrite_then_correct(cube, calibration, *args, **kwargs):
        assert not calibration.in_memory
        _rewritten_in_place(path)
        return correct_into(cube, calibration, *args, **kwargs)

    monkeypatch.setattr(batch_module, "correct_into", rewrite_then_correct)
    with pytest.raises(archive.CalibrationChangedError, match="after 0 of 2 inputs"):
        archive.run_batch([inputs], out, path)
    assert manifest_records(out) == [] and outputs_of(out) == {}


def test_an_input_that_fails_because_the_calibration_changed_is_no_failure_but_a_stop(cal, tmp_path, monkeypatch):
    """An error inside an input (HDF5's words for rows of a rewritten file) once the calibration
    changed: the batch stops; the input is not recorded as failed."""
    inputs = _inputs(tmp_path, 1)
    path = _own_calibration(cal, tmp_path)
    out = tmp_path / "out"

    def rewrite_then_fail(*args, **kwargs):
        _rewritten_in_place(path)
        raise RuntimeError("Can't synchronously read data (wrong B-tree signature)")

    monkeypatch.setattr(batch_module, "correct_into", rewrite_then_fail)
    with pytest.raises(archive.CalibrationChangedError, match="after 0 of 1 inputs"):
        archive.run_batch([inputs], out, path)
    assert manifest_records(out) == [] and outputs_of(out) == {}


def test_a_calibration_replaced_by_one_of_the_same_time_and_size_is_read_as_it_is(cal, tmp_path):
    """Between two batches of one process, another calibration renamed over the file with the
    old one's modification time and size (cp -p, or a tool that sets the time): the second batch
    corrects with the file as it is, not the first batch's calibration kept in memory."""
    inputs = _inputs(tmp_path, 1)
    path = _own_calibration(cal, tmp_path)
    archive.run_batch([inputs], tmp_path / "first", path)
    old = os.stat(path)
    other = tmp_path / "other.h5"
    _another_calibration(other)
    assert os.path.getsize(other) == old.st_size
    os.replace(other, path)
    os.utime(path, ns=(old.st_atime_ns, old.st_mtime_ns))
    archive.run_batch([inputs], tmp_path / "second", path)
    (record,) = manifest_records(tmp_path / "second")
    assert record["calibration_checksum"] == io.open_calibration(path).header["checksum"]
    assert record["calibration_checksum"] != manifest_records(tmp_path / "first")[0]["calibration_checksum"]


def test_every_worker_verifies_the_batchs_checksum(cal, tmp_path):
    """`correct_input` as a worker runs it: with an identity that is not the file's (another
    checksum, or another file stamp), it refuses before reading the input and leaves nothing."""
    inputs = _inputs(tmp_path, 1)
    path = _own_calibration(cal, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    spec = archive.discover_inputs([inputs], out)[0]
    _, identity = archive.batch_calibration.read_once(path, None, archive.load_calibration)
    wrong_checksum = archive.CalibrationIdentity("sha256:" + "0" * 64, identity.stamp)
    with pytest.raises(archive.CalibrationChangedError, match="its checksum is sha256:.*, the batch read sha256:0000"):
        archive.correct_input(spec, out, path, calibration_identity=wrong_checksum)
    wrong_file = archive.CalibrationIdentity(identity.checksum, (identity.stamp[0] + 1, *identity.stamp[1:]))
    with pytest.raises(archive.CalibrationChangedError, match="another file is there now"):
        archive.correct_input(spec, out, path, calibration_identity=wrong_file)
    assert list(out.iterdir()) == []
    # The batch's own identity: corrected, recorded with that checksum.
    result = archive.correct_input(spec, out, path, calibration_identity=identity)
    assert result.status == "done" and result.calibration_checksum == identity.checksum


def test_a_dask_worker_that_finds_the_calibration_changed_stops_the_batch(cal, tmp_path):
    from spherejax import cluster

    inputs = _inputs(tmp_path, 3)
    path = _own_calibration(cal, tmp_path)
    checksum = io.open_calibration(path).header["checksum"]
    out = tmp_path / "out"
    with cluster.DaskExecutor(workers=1) as executor:
        with pytest.raises(archive.CalibrationChangedError, match="changed during the batch"):
            archive.run_batch([inputs], out, path, executor=executor,
                              on_result=lambda spec, result: _another_calibration(path))
    assert len(_check_stopped_batch(out, checksum)) == 1


class _FakeFuture:
    def __init__(self, function, args, kwargs):
        self.cancelled = False
        try:
            self.value, self.error = function(*args, **kwargs), None
        except Exception as error:  # noqa: BLE001
            self.value, self.error = None, error

    def result(self):
        if self.error is not None:
            raise self.error
        return self.value

    def cancel(self):
        self.cancelled = True


def test_dask_map_stops_submitting_after_a_calibration_change(monkeypatch):
    """`DaskExecutor.map` with a stand-in client: once a worker raises CalibrationChangedError,
    nothing more is submitted, the inputs under way are yielded, then the error is raised (not
    recorded as a failed input)."""
    from spherejax import cluster

    submitted = []

    def correct(spec, out_root, calibration_path, **options):
        submitted.append(spec)
        if spec == "b":
            raise archive.CalibrationChangedError(calibration_path, "changed during the batch: test")
        return f"result of {spec}"

    class Client:
        def nthreads(self):
            return {"w1": 1, "w2": 1}

        def submit(self, function, *args, key=None, pure=None, **kwargs):
            return _FakeFuture(correct, args, kwargs)

    monkeypatch.setattr(cluster, "wait", lambda futures, **kwargs: type("Done", (), {"done": list(futures)})())
    executor = cluster.DaskExecutor(workers=1)
    executor.client = Client()
    yielded = []
    with pytest.raises(archive.CalibrationChangedError, match="test"):
        for spec, result in executor.map(["a", "b", "c", "d"], "/out", "/cal.h5"):
            yielded.append((spec, result))
    assert yielded == [("a", "result of a")]
    assert submitted == ["a", "b"]


# ------------------------------------------------------------------------- empty output folders


def _session_like_inputs(tmp_path: pathlib.Path) -> pathlib.Path:
    """Inputs whose outputs share a folder OUT does not hold yet: in/sub/f0.tif, in/sub/f1.tif
    (and in/g.tif, so that the outputs go to OUT/sub/...)."""
    inputs = _inputs(tmp_path, 2, folder="in/sub")
    io.write_frame(tmp_path / "in" / "g.tif", frame(np.random.default_rng(5)))
    return inputs.parent


def _both_under_way_then(monkeypatch, error_of):
    """A full disk or a stop with two inputs under way in one folder: correct_into waits until
    both inputs of the sub folder have their output folder (each marked in use), then raises
    `error_of()` in the input that created the folder and, once that input is over (its clean-up
    done while the other still used the folder), in the other."""
    barrier = threading.Barrier(2, timeout=60)
    creator_over = threading.Event()
    creator: list[str] = []
    output_folder, correct_into, correct_input = (
        batch_module.output_folder, batch_module.correct_into, batch_module.correct_input)

    def noting_the_creator(out_root, name):
        folder, created = output_folder(out_root, name)
        if folder.name == "sub" and folder in created:
            creator.append(name)
        return folder, created

    def under_way(cube, calibration, folder, stem, *args, **kwargs):
        if folder.name == "sub":
            barrier.wait()
            if creator and not any(name.endswith(f"/{stem}") for name in creator):
                assert creator_over.wait(60)
            raise error_of()
        return correct_into(cube, calibration, folder, stem, *args, **kwargs)

    def then_over(spec, *args, **kwargs):
        try:
            return correct_input(spec, *args, **kwargs)
        finally:
            if spec.name in creator:
                creator_over.set()

    monkeypatch.setattr(batch_module, "output_folder", noting_the_creator)
    monkeypatch.setattr(batch_module, "correct_into", under_way)
    monkeypatch.setattr(batch_module, "correct_input", then_over)


def _empty_folders(out: pathlib.Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_dir() and not any(p.iterdir()))


def test_a_full_disk_with_two_inputs_under_way_leaves_no_empty_folder(cal, tmp_path, monkeypatch):
    inputs = _session_like_inputs(tmp_path)
    out = tmp_path / "out"
    _both_under_way_then(monkeypatch, lambda: OSError(errno.ENOSPC, "No space left on device"))
    summary = archive.run_batch([inputs], out, cal)
    assert len(summary.failed) == 2 and summary.corrected == 1
    assert _empty_folders(out) == []
    assert sorted(outputs_of(out)) == sorted(f"in/g.{kind}" for kind in KINDS)


def test_a_stop_with_two_inputs_under_way_leaves_no_empty_folder(cal, tmp_path, monkeypatch):
    inputs = _session_like_inputs(tmp_path)
    out = tmp_path / "out"
    _both_under_way_then(monkeypatch, lambda: interrupt.Interrupted(2))
    with pytest.raises(interrupt.Interrupted):
        archive.run_batch([inputs], out, cal)
    assert _empty_folders(out) == [] and not (out / "in" / "sub").exists()
    assert not (out / archive.LOCK_NAME).exists()


def test_a_stop_through_the_command_line_leaves_no_empty_folder(cal, tmp_path, monkeypatch, capsys):
    inputs = _session_like_inputs(tmp_path)
    out = tmp_path / "out"
    _both_under_way_then(monkeypatch, lambda: interrupt.Interrupted(15))
    status, _, err = run(["-q", "correct", "-c", str(cal), str(inputs), "-o", str(out)], capsys)
    assert status == 143, err
    assert _empty_folders(out) == [] and not (out / "in" / "sub").exists()


@pytest.mark.slow
def test_real_signals_with_inputs_under_way_in_shared_folders_leave_no_empty_folder(cal, tmp_path):
    """SIGTERM and SIGINT to `spherejax correct` (a child process) while inputs that share new
    output folders are under way, two by two: whenever the signal lands, every folder left in OUT
    holds a recorded output, and --resume finishes the batch."""
    import signal

    from tests.batch_support import holds_lock, start_correct, wait_until

    rng = np.random.default_rng(4)
    for k in range(8):
        (tmp_path / "in" / f"d{k}").mkdir(parents=True)
        for name in ("a", "b"):
            io.write_frame(tmp_path / "in" / f"d{k}" / f"{name}.tif", frame(rng))
    out = tmp_path / "out"
    stops = 0
    for signum, after in ((signal.SIGTERM, 1), (signal.SIGINT, 2), (signal.SIGTERM, 1)):
        resume = ["--resume"] if out.exists() else []
        process = start_correct(["-c", cal, tmp_path / "in", "-o", out, *resume], may_be_killed=False, quiet=True)
        wait_until(process, holds_lock(process, out))
        done = len(manifest_records(out)) if (out / archive.MANIFEST_NAME).exists() else 0
        wait_until(process, lambda: (out / archive.MANIFEST_NAME).exists() and len(manifest_records(out)) >= done + after)
        if process.poll() is not None:
            break  # the batch finished first: nothing left to stop
        process.send_signal(signum)
        _, err = process.communicate(timeout=120)
        assert process.returncode in (128 + signum, 0), err.decode()
        stops += process.returncode != 0
        assert _empty_folders(out) == [], err.decode()
        recorded = {name for record in manifest_records(out) for name in record["outputs"]}
        assert set(outputs_of(out)) == recorded
    process = start_correct(["-c", cal, tmp_path / "in", "-o", out, "--resume"], may_be_killed=False, quiet=True)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()
    assert len({record["name"] for record in manifest_records(out)}) == 16
    assert _empty_folders(out) == []
    assert stops >= 1  # a signal landed mid-batch at least once


def test_folders_the_user_made_are_left_even_when_empty(cal, tmp_path, monkeypatch):
    """Only folders this run made go: OUT/in/sub made before the run stays (empty), and so does
    an empty folder the user keeps beside the outputs."""
    inputs = _session_like_inputs(tmp_path)
    out = tmp_path / "out"
    (out / "in" / "sub").mkdir(parents=True)
    (out / "mine").mkdir()
    _both_under_way_then(monkeypatch, lambda: OSError(errno.ENOSPC, "No space left on device"))
    archive.run_batch([inputs], out, cal)
    assert _empty_folders(out) == ["in/sub", "mine"]


def test_a_dask_workers_folders_come_back_in_its_result(cal, tmp_path):
    """A worker elsewhere runs no batch: the folders it made travel in its FileResult, which the
    batch adds to its own (`_note_created`)."""
    inputs = _session_like_inputs(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    spec = next(spec for spec in archive.discover_inputs([inputs], out) if "/sub/" in spec.name)
    result = archive.correct_input(spec, out, cal)
    assert result.folders_created == (str((out / "in").resolve()), str((out / "in" / "sub").resolve()))
    assert "folders_created" not in result.to_json()


# ------------------------------------------------------------------- OSErrors on the way out


def test_a_full_disk_at_the_manifest_append_names_the_manifest(cal, tmp_path, monkeypatch, capsys):
    inputs = _inputs(tmp_path, 2)
    out = tmp_path / "out"

    def full(self, record):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io.journal.JournalWriter, "append", full)
    status, _, err = run(["-q", "correct", "-c", str(cal), str(inputs), "-o", str(out)], capsys)
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Errno" not in err, err
    assert lines[0].startswith(f"spherejax: error: {out / archive.MANIFEST_NAME}: cannot record "), err
    assert "No space left on device" in lines[0]
    # Nothing recorded; the outputs in place stay claimed, so --resume takes them over.
    monkeypatch.undo()
    status, stdout, err = run(["-q", "correct", "-c", str(cal), str(inputs), "-o", str(out), "--resume"], capsys)
    assert status == 0, err
    assert len(manifest_records(out)) == 2


def test_a_short_write_at_the_manifest_append_is_not_taken_for_a_record(tmp_path, monkeypatch):
    """A disk that fills mid-line: os.write writes part of the line, the next write fails. The
    append raises (the record is not taken as written) and the next record starts a line of its
    own, so a reader finds it whole."""
    path = tmp_path / "journal.jsonl"
    writes = []
    real_write = os.write

    def filling(fd, data):
        writes.append(len(data))
        if len(writes) == 1:
            return real_write(fd, bytes(data[:5]))
        if len(writes) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    journal = io.journal.Journal(path, key="name")
    with journal.open() as writer:
        monkeypatch.setattr(os, "write", filling)
        with pytest.raises(OSError, match="No space left"):
            writer.append({"name": "first"})
        writer.append({"name": "second"})
    monkeypatch.undo()
    assert [record["name"] for record in journal.records()] == ["second"]


@pytest.mark.parametrize("relative", ["OUT", "INPUT", "CAL"])
def test_a_deleted_working_folder_is_named(cal, tmp_path, monkeypatch, capsys, relative):
    inputs = _inputs(tmp_path, 1)
    working = tmp_path / "working"
    working.mkdir()
    monkeypatch.chdir(working)
    monkeypatch.setenv("PWD", str(working))  # as the shell that stood in it says
    working.rmdir()
    out = "out" if relative == "OUT" else str(tmp_path / "out")
    given_inputs = "in" if relative == "INPUT" else str(inputs)
    calibration = "cal.h5" if relative == "CAL" else str(cal)
    status, _, err = run(["-q", "correct", "-c", calibration, given_inputs, "-o", out], capsys)
    monkeypatch.chdir(tmp_path)
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Errno" not in err, err
    assert str(working) in lines[0] and "working folder" in lines[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("relative", ["OUT", "INPUT", "CAL"])
def test_a_deleted_working_folder_is_named_by_the_api(cal, tmp_path, monkeypatch, relative):
    inputs = _inputs(tmp_path, 1)
    working = tmp_path / "working"
    working.mkdir()
    monkeypatch.chdir(working)
    working.rmdir()
    out = "out" if relative == "OUT" else tmp_path / "out"
    given_inputs = "in" if relative == "INPUT" else inputs
    calibration = "cal.h5" if relative == "CAL" else cal
    with pytest.raises(archive.BatchError) as refused:
        archive.run_batch([given_inputs], out, calibration)
    monkeypatch.chdir(tmp_path)
    assert str(refused.value).startswith(f"{working}: the working folder cannot be used: No such file or directory")
    assert not (tmp_path / "out").exists()


def test_a_full_disk_when_claiming_outputs_names_the_lock_file(cal, tmp_path, monkeypatch):
    inputs = _inputs(tmp_path, 1)
    out = tmp_path / "out"

    claim = archive.OutputLock.claim

    def full(self, names):
        names = list(names)
        if "in/f0.reflectance.exr" in names:  # the batch's claim of its outputs
            raise OSError(errno.ENOSPC, "No space left on device")
        claim(self, names)

    monkeypatch.setattr(archive.OutputLock, "claim", full)
    with pytest.raises(archive.BatchError) as refused:
        archive.run_batch([inputs], out, cal)
    assert str(refused.value) == f"{out / archive.LOCK_NAME}: cannot record the outputs this run claims: No space left on device"
