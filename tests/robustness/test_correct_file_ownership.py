"""`spherejax correct` and the files it does not own: each test is a way a batch could replace,
delete or misread a file that is not its own, and checks that it does not.

- Outputs that are inputs or the calibration, however named, are refused before any work.
- Files at output names that spherejax never wrote (no manifest record, no claim of a killed run)
  are refused in one line and left as they were; clean-up removes only what spherejax recorded.
- An input replaced while it is corrected fails instead of recording the old file's hash.
- --resume redoes what other settings (illuminant, format, compression, version) would change.
- Hashing and manifest reading are safe points: a signal never waits for them.
"""

from __future__ import annotations

import json
import pathlib
import os
import shutil
import signal

import numpy as np
import pytest

from spherejax import archive, interrupt, io
from spherejax.archive import inputs

from tests.batch_support import NAMES, frame, manifest_records, outputs_of, run


@pytest.fixture
def rng():
    return np.random.default_rng(3)


def _snapshot(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _correct(cal, inputs, out, *extra):
    return ["correct", "-c", str(cal), *map(str, inputs), "-o", str(out), *extra]


# ------------------------------------------------------------------------ outputs that are inputs


def test_out_as_the_inputs_folder_never_replaces_an_input(cal, tmp_path, rng, capsys):
    """An input named like another input's output (a.lab.exr beside a.tif) is never replaced by it."""
    folder = tmp_path / "in3"
    folder.mkdir()
    io.write_frame(folder / "a.tif", frame(rng), channel_names=NAMES)
    io.write_exr(folder / "a.lab.exr", frame(rng).astype(np.float32), channel_names=NAMES)
    before = _snapshot(folder)
    status, stdout, err = run(_correct(cal, [folder / "a.lab.exr", folder / "a.tif"], folder), capsys)
    assert status != 0 and stdout == ""
    line, = err.strip().splitlines()
    # OUT holding the inputs is refused as such, before any output is looked at.
    assert line.startswith(f"spherejax: error: {folder}: OUT holds the input {folder / 'a.lab.exr'} (expected ")
    assert "Traceback" not in err
    assert _snapshot(folder) == before  # no manifest, no lock, no output


def test_an_output_reached_through_a_link_that_is_the_calibration_is_refused(cal, tmp_path, rng, capsys):
    """Links and `..` cannot hide an overlap: OUT/x/a.lab.exr is the calibration by a symbolic link."""
    io.write_frame(tmp_path / "a.tif", frame(rng), channel_names=NAMES)
    calibration = tmp_path / "cal.h5"
    shutil.copyfile(cal, calibration)
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.lab.exr").symlink_to(calibration)
    status, _, err = run(_correct(calibration, [tmp_path / "a.tif"], out), capsys)
    assert status != 0
    assert f"is the output a.lab.exr of a.tif, and also the input the calibration ({calibration})" in err
    assert calibration.read_bytes() == cal.read_bytes()


# ------------------------------------------------------------------------- files in the way


def test_files_spherejax_never_wrote_are_refused_not_deleted(cal, tmp_path, rng, capsys):
    """With no manifest in OUT, a failed input's clean-up deletes no file it did not write
    (a.preview.png, the other format's b.reflectance.hdr) and b.lab.exr is not overwritten."""
    inputs = tmp_path / "in2"
    inputs.mkdir()
    (inputs / "a.tif").write_bytes(b"not a TIFF")
    io.write_frame(inputs / "b.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "o2"
    (out / "in2").mkdir(parents=True)
    for name in ("a.preview.png", "b.lab.exr", "b.reflectance.hdr"):
        (out / "in2" / name).write_bytes(f"the user's {name}".encode())
    before = _snapshot(out)
    status, stdout, err = run(_correct(cal, [inputs], out), capsys)
    assert status != 0 and stdout == ""
    line, = err.strip().splitlines()
    # a.preview.png would be a.tif's (its damage is found only when it is read), b.lab.exr b's.
    assert line.startswith(f"spherejax: error: {out / 'in2' / 'a.preview.png'}: is in the way of an output "
                           "(and 1 more): ")
    assert "does not record it as written by spherejax" in line
    assert _snapshot(out) == before


def test_without_files_in_the_way_other_format_leftovers_of_the_user_stay(cal, tmp_path, rng, capsys):
    """The other format's clean-up removes only what the manifest records: a user's
    b.reflectance.hdr beside an EXR batch is not spherejax's to delete."""
    inputs = tmp_path / "in2"
    inputs.mkdir()
    io.write_frame(inputs / "b.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "o2"
    (out / "in2").mkdir(parents=True)
    (out / "in2" / "b.reflectance.hdr").write_bytes(b"the user's header")
    status, stdout, err = run(_correct(cal, [inputs], out), capsys)
    assert status == 0, err
    assert (out / "in2" / "b.reflectance.hdr").read_bytes() == b"the user's header"
    assert (out / "in2" / "b.reflectance.exr").is_file()


def test_a_failed_input_removes_only_its_recorded_outputs(cal, tmp_path, rng, capsys):
    """A failed input removes the outputs an earlier run recorded for it, and nothing else."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    io.write_frame(inputs / "a.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "out"
    assert run(_correct(cal, [inputs], out), capsys)[0] == 0
    (out / "in" / "a.reflectance.hdr").write_bytes(b"the user's header")  # never recorded
    (inputs / "a.tif").write_bytes(b"now damaged")
    status, stdout, _ = run(_correct(cal, [inputs], out, "--resume"), capsys)
    assert status != 0 and stdout.strip() == "0 corrected, 0 skipped (already done), 1 failed"
    assert sorted(p.name for p in (out / "in").iterdir()) == ["a.reflectance.hdr"]
    assert (out / "in" / "a.reflectance.hdr").read_bytes() == b"the user's header"


def test_outputs_left_unrecorded_by_a_killed_run_are_known_by_its_claims(cal, tmp_path, rng, capsys):
    """A run killed after putting an input's outputs in place and before its manifest record
    leaves them unrecorded; the SHA-256s it recorded in its lock file before the renames (its
    made records) prove them spherejax's."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    for name in ("a", "b"):
        io.write_frame(inputs / f"{name}.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "out"
    assert run(_correct(cal, [inputs], out), capsys)[0] == 0
    assert not (out / archive.LOCK_NAME).exists()  # a run that ends leaves no lock, no claim
    reference = outputs_of(out)
    # The state a kill after b's outputs were renamed into place leaves: b unrecorded, and the
    # lock file naming its dead holder, then the claims of the run.
    records = manifest_records(out)
    (out / archive.MANIFEST_NAME).write_text(json.dumps(records[0]) + "\n")
    claims = [name for record in records for name in sorted(record["outputs"])]
    lines = [{"pid": 999999, "host": "gone"}, {"claims": claims}, {"made": records[1]["outputs"]}]
    (out / archive.LOCK_NAME).write_text("".join(json.dumps(line) + "\n" for line in lines))
    # b's reflectance output is renamed aside: only the made records speak for b's other outputs.
    (out / "in" / "b.reflectance.exr").unlink()
    status, stdout, err = run(_correct(cal, [inputs], out, "--resume"), capsys)
    assert status == 0, err
    assert stdout.strip() == "1 corrected, 1 skipped (already done), 0 failed"
    assert outputs_of(out) == reference
    assert not (out / archive.LOCK_NAME).exists()


def test_claims_survive_a_run_taken_over_and_failing_before_its_end(tmp_path):
    """The run that takes a left lock over carries its claims on, so a second kill loses none."""
    (tmp_path / archive.LOCK_NAME).write_text('{"pid": 1, "host": "h", "claims": ["x/a.lab.exr", 5]}\n')
    lock = archive.OutputLock(tmp_path)
    lock.acquire()
    assert lock.taken_over == "pid 1 on h" and lock.claimed == {"x/a.lab.exr"}
    lock.claim(["x/b.lab.exr"])
    holder, *lines = [json.loads(line) for line in (tmp_path / archive.LOCK_NAME).read_text().splitlines()]
    assert holder["pid"] == os.getpid() and [name for line in lines for name in line["claims"]] == ["x/a.lab.exr", "x/b.lab.exr"]
    lock.release(keep_claims=True)  # as a run that failed with outputs maybe in place
    again = archive.OutputLock(tmp_path)
    again.acquire()
    assert again.claimed == {"x/a.lab.exr", "x/b.lab.exr"}
    again.release()
    assert not (tmp_path / archive.LOCK_NAME).exists()


def test_a_torn_lock_file_names_its_holder_and_claims_nothing(tmp_path):
    """A kill while the claims were written leaves a torn object: the holder is still named,
    and no claim is trusted."""
    (tmp_path / archive.LOCK_NAME).write_text('{"pid": 7, "host": "h", "claims": ["x/a.la')
    lock = archive.OutputLock(tmp_path)
    lock.acquire()
    assert lock.taken_over == "pid 7 on h" and lock.claimed == set()
    lock.release()


# ------------------------------------------------------------------- an input changed mid-run


def test_an_input_replaced_while_corrected_fails_and_leaves_nothing(cal, tmp_path, rng, monkeypatch):
    """A file put in the input's place after it was hashed is not corrected under the old
    file's hash: the manifest and the EXR record the hash of the pixels corrected."""
    source = tmp_path / "a.tif"
    io.write_frame(source, frame(rng), channel_names=NAMES)
    replacement = tmp_path / "new.tif"
    io.write_frame(replacement, frame(rng), channel_names=NAMES)
    opened = inputs.open_input

    def open_then_replace(spec, calibration):
        os.replace(replacement, source)  # another process swaps the file between hash and read
        return opened(spec, calibration)

    monkeypatch.setattr(inputs, "open_input", open_then_replace)
    out = tmp_path / "out"
    out.mkdir()
    spec, = archive.discover_inputs([source], out)
    result = archive.correct_input(spec, out, cal)
    assert result.status == "failed"
    assert result.reason == (f"{source}: was replaced while it was corrected: its outputs "
                             "would not match its hash (expected an input left alone until it is corrected; "
                             "run again with --resume)")
    assert list(out.iterdir()) == []


# -------------------------------------------------------------------------------- resume settings


@pytest.mark.parametrize("changed", [["--illuminant", "A"], ["--exr-compression", "zip"], ["--reflectance-type", "half"]])
def test_resume_redoes_inputs_corrected_with_other_settings(cal, tmp_path, rng, capsys, changed):
    """A D65 batch resumed with --illuminant A does not take the D65 outputs as done."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    for name in ("a", "b", "c"):
        io.write_frame(inputs / f"{name}.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "out"
    assert run(_correct(cal, [inputs], out), capsys)[0] == 0
    (out / "in" / "b.lab.exr").unlink()
    status, stdout, err = run(_correct(cal, [inputs], out, "--resume", *changed), capsys)
    assert status == 0, err
    assert stdout.strip() == "3 corrected, 0 skipped (already done), 0 failed"
    settings = {r["name"]: r["settings"] for r in manifest_records(out)[3:]}
    assert len(settings) == 3
    for value in settings.values():
        assert value["illuminant"] == ("A" if "A" in changed else "D65")
        assert value["exr_compression"] == ("zip" if "zip" in changed else io.DEFAULT_EXR_COMPRESSION)
        assert value["reflectance_type"] == ("half" if "half" in changed else "float")
    # The same settings again: everything is verified and skipped.
    status, stdout, _ = run(_correct(cal, [inputs], out, "--resume", *changed), capsys)
    assert status == 0 and stdout.strip() == "0 corrected, 3 skipped (already done), 0 failed"


def test_resume_redoes_records_of_another_version_or_without_settings(cal, tmp_path, rng, capsys):
    """A record without settings (an older manifest) or from another software version is not
    taken as done: the outputs carry the version, and its numbers may differ."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    for name in ("a", "b"):
        io.write_frame(inputs / f"{name}.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "out"
    assert run(_correct(cal, [inputs], out), capsys)[0] == 0
    first, second = manifest_records(out)
    del first["settings"]
    second["software_version"] = "0.0.1"
    (out / archive.MANIFEST_NAME).write_text(json.dumps(first) + "\n" + json.dumps(second) + "\n")
    status, stdout, _ = run(_correct(cal, [inputs], out, "--resume"), capsys)
    assert status == 0 and stdout.strip() == "2 corrected, 0 skipped (already done), 0 failed"


# ------------------------------------------------------------------------------------ signals


def test_hashing_an_input_is_a_safe_point(tmp_path):
    """SIGTERM during a checksum stops at the next block, not after the whole file."""
    big = tmp_path / "big.tif"
    with open(big, "wb") as handle:
        handle.write(os.urandom(4 << 20))
    spec = archive.InputSpec(name="big", source="big.tif", files=(str(big),))
    with interrupt.stop_requests():
        os.kill(os.getpid(), signal.SIGTERM)
        with pytest.raises(interrupt.Interrupted) as stopped:
            archive.input_checksum(spec)
    assert stopped.value.exit_status == 143


def test_a_sparse_manifest_is_read_by_its_data_and_stops_on_a_signal(tmp_path):
    """A manifest with a 3 GB hole (`truncate -s 3G OUT/manifest.jsonl`) is not read whole into
    memory; the records around the hole are still read, and reading is a safe point."""
    record = {"name": "a", "input": "a.tif", "status": "failed", "outputs": {}}
    path = tmp_path / archive.MANIFEST_NAME
    with open(path, "wb") as handle:
        handle.write((json.dumps(record) + "\ntorn by the hole").encode())
        handle.truncate(3 << 30)
        handle.seek((3 << 30) - 64)
        handle.write(b"x\n" + json.dumps({**record, "name": "b"}).encode() + b"\n")
    assert sorted(archive.read_manifest(tmp_path)) == ["a", "b"]
    with interrupt.stop_requests():
        os.kill(os.getpid(), signal.SIGINT)
        with pytest.raises(interrupt.Interrupted):
            archive.read_manifest(tmp_path)


_SIGTERM_WHILE_WRITING = """
import os, signal, sys, time
from spherejax import cli
from spherejax import atomic_files

opened = atomic_files.open_exclusive

def open_then_terminated(path, *args, **kwargs):
    handle = opened(path, *args, **kwargs)
    os.kill(os.getpid(), signal.SIGTERM)  # the stop lands while the temporary file is written
    time.sleep(0.5)
    return handle

atomic_files.open_exclusive = open_then_terminated
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.parametrize("command", ["calibrate", "evaluate"])
def test_sigterm_in_a_command_without_safe_points_leaves_nothing_half_written(workspace, tmp_path, command):
    """The commands without safe points of their own stop on SIGTERM with a message and leave
    no temporary file behind (Python's default SIGTERM would kill them without a word)."""
    import subprocess
    import sys

    session = tmp_path / "session"
    shutil.copytree(workspace / "session", session)
    out = tmp_path / "out"
    out.mkdir()
    argv = ({"calibrate": ["calibrate", session, "-o", out / "cal.h5"],
             "evaluate": ["evaluate", session, "-c", workspace / "cal.h5", "--out", out / "evaluation"]})[command]
    process = subprocess.run([sys.executable, "-c", _SIGTERM_WHILE_WRITING, "-q", *map(str, argv)],
                             env={**os.environ, "JAX_PLATFORMS": "cpu"}, capture_output=True, timeout=300)
    assert process.returncode == 143, process.stderr.decode()
    assert process.stderr.decode().strip().splitlines() == ["spherejax: interrupted; nothing half-written was left"]
    left = [p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()]
    assert not [name for name in left if io.is_temp_sibling(pathlib.Path(name).name)], left
    assert not (out / "cal.h5").exists()
