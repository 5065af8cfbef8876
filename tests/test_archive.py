"""Batch correction (`spherejax correct`, spherejax.archive): outputs, names, bad inputs, the lock,
resume, and kill-and-resume byte identity (SIGKILL; SIGINT and SIGTERM, in process and on dask)."""

from __future__ import annotations

import argparse
import collections
import fcntl
import json
import os
import pathlib
import random
import shutil
import signal
import subprocess
import time

import colour
import numpy as np
import OpenImageIO as oiio
import pytest

import spherejax
from spherejax import archive, cli, io
from spherejax.archive.manifest import output_digest
from spherejax.grid import WAVELENGTHS_NM

from .batch_support import (
    B, BANDS, H, KINDS, NAMES, W, frame, holds_lock, make_calibration, manifest_records, outputs_of, read_exr, run,
    spec_alpha, start_correct,
)
from .helpers import INTERRUPTED, sigkill, wait_until


@pytest.fixture
def rng():
    return np.random.default_rng(1)

# --------------------------------------------------------------------------------------- outputs


def test_outputs_channels_metadata_and_values(cal, tmp_path, rng, capsys):
    raw = frame(rng)
    (tmp_path / "in" / "batch").mkdir(parents=True)
    io.write_frame(tmp_path / "in" / "batch" / "a.tif", raw, channel_names=NAMES)
    out = tmp_path / "out"
    status, stdout, err = run(["correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)], capsys)
    assert status == 0, err
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    stem = out / "in" / "batch" / "a"
    assert sorted(outputs_of(out)) == sorted(f"in/batch/a.{k}" for k in KINDS)

    calibration, header = io.load_calibration(cal)
    expected = spherejax.correct(raw, calibration)
    refl, names, attributes = read_exr(f"{stem}.reflectance.exr")
    assert names == [f"T.{nm}nm" for nm in WAVELENGTHS_NM.tolist()]  # Fichet et al. (2021)
    assert attributes["spectralLayoutVersion"] == "1.0"
    np.testing.assert_array_equal(refl, np.asarray(expected.reflectance))
    assert np.isnan(refl[0, 0]).all()
    # colour-science's reader of the published layout: 31 wavelengths, the same values.
    components = colour.io.read_spectral_image_Fichet2021(f"{stem}.reflectance.exr")
    assert list(components) == ["T"]
    wavelengths, values = components["T"]
    np.testing.assert_array_equal(wavelengths, WAVELENGTHS_NM.astype(float))
    np.testing.assert_array_equal(values, refl)
    assert attributes["spherejax:calibration_checksum"] == header["checksum"]
    assert attributes["spherejax:software_version"] == spherejax.__version__
    assert attributes["spherejax:source"] == "in/batch/a.tif"
    assert attributes["spherejax:illuminant"] == "D65"
    assert "DateTime" not in attributes

    lab, names, _ = read_exr(f"{stem}.lab.exr")
    assert names == ["L*", "a*", "b*"] and spec_alpha(f"{stem}.lab.exr") == -1
    np.testing.assert_array_equal(lab, np.asarray(expected.lab))

    image = oiio.ImageInput.open(f"{stem}.preview.png")
    spec = image.spec()
    assert (image.format_name(), spec.nchannels, str(spec.format)) == ("png", 3, "uint8")
    preview = image.read_image(oiio.UINT8)
    image.close()
    assert tuple(preview[0, 0]) == archive.PREVIEW_BAD_PIXEL
    np.testing.assert_array_equal(preview, archive.srgb_preview(np.asarray(expected.reflectance)))

    # A palette PNG whose indices are the bits (tests/test_quality_png.py), read by Pillow.
    from PIL import Image

    with Image.open(f"{stem}.quality.png") as image:
        assert image.mode == "P"
        quality = np.asarray(image)
    np.testing.assert_array_equal(quality, np.asarray(expected.quality))
    assert quality[0, 0] == spherejax.QUALITY_SATURATED

    (record,) = manifest_records(out)
    assert record["status"] == "done" and record["input"] == "in/batch/a.tif"
    assert record["calibration_checksum"] == header["checksum"]
    assert set(record["outputs"]) == {f"in/batch/a.{k}" for k in KINDS}


def test_srgb_preview_is_colour_sciences_srgb_to_a_level():
    """The preview (float32, matrices folded) against colour-science's XYZ -> sRGB in float64
    (ASTM E308 D65 XYZ, IEC 61966-2-1 matrix and encoding, clipped, 8 bits): at most a level
    apart, in about one value in 100,000 (within float32 rounding of a level's edge);
    a pixel with a NaN band is magenta."""
    from spherejax.colorimetry import tristimulus_weights

    rng = np.random.default_rng(3)
    reflectance = rng.uniform(-0.02, 1.08, (512, 512, 31)).astype(np.float32)  # clipped both ways too
    reflectance[7, 9, 30] = np.nan
    xyz = reflectance.astype(np.float64) @ (np.asarray(tristimulus_weights("D65"), np.float64) / 100.0)
    expected = np.round(np.clip(colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=True), 0.0, 1.0) * 255.0)
    preview = archive.srgb_preview(reflectance)
    assert tuple(preview[7, 9]) == archive.PREVIEW_BAD_PIXEL
    good = np.all(np.isfinite(expected), axis=-1)
    difference = np.abs(preview[good].astype(float) - expected[good])
    assert difference.max() <= 1
    assert np.count_nonzero(difference) <= 3e-5 * difference.size  # measured 1.0e-5 here, 0.7e-5 at 1 MP


def test_srgb_preview_of_a_perfect_white_is_white():
    assert tuple(archive.srgb_preview(np.ones((1, 1, 31), np.float32))[0, 0]) == (255, 255, 255)
    assert tuple(archive.srgb_preview(np.zeros((1, 1, 31), np.float32))[0, 0]) == (0, 0, 0)


def test_illuminant_option_changes_lab_only(cal, tmp_path, rng, capsys):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    assert run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(tmp_path / "d65")], capsys)[0] == 0
    assert run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(tmp_path / "f2"), "--illuminant", "F2"], capsys)[0] == 0
    _, _, attributes = read_exr(tmp_path / "f2" / "a.lab.exr")
    assert attributes["spherejax:illuminant"] == "F2"
    d65, f2 = outputs_of(tmp_path / "d65"), outputs_of(tmp_path / "f2")
    assert d65["a.preview.png"] == f2["a.preview.png"] and d65["a.lab.exr"] != f2["a.lab.exr"]


def write_layouts(root: pathlib.Path, rng) -> dict[str, np.ndarray]:
    """One cube in every input layout; returns output name -> raw cube."""
    cubes = {}
    root.mkdir(parents=True)
    cubes["multi"] = frame(rng)
    io.write_frame(root / "multi.tif", cubes["multi"], channel_names=NAMES)
    # Multi-page TIFF, one page per band.
    cubes["pages"] = frame(rng)
    spec = oiio.ImageSpec(W, H, 1, oiio.UINT16)
    output = oiio.ImageOutput.create("tiff")
    output.open(str(root / "pages.tif"), [spec] * B)
    for band in range(B):
        if band:
            output.open(str(root / "pages.tif"), spec, "AppendSubimage")
        output.write_image(np.ascontiguousarray(cubes["pages"][..., band : band + 1]))
    output.close()
    # OpenEXR float cube (channels stored sorted by name, read back in band order).
    cubes["float"] = frame(rng).astype(np.float32)
    io.write_exr(root / "float.exr", cubes["float"], channel_names=NAMES)
    # A folder of band files: two captures, a_ and b_, plus one with no prefix.
    (root / "bands").mkdir()
    (root / "bare").mkdir()
    for prefix in ("a", "b"):
        cubes[f"bands/{prefix}"] = frame(rng)
        for band, nm in enumerate(BANDS):
            io.write_frame(root / "bands" / f"{prefix}_{nm}nm.tif", cubes[f"bands/{prefix}"][..., band : band + 1])
    cubes["bare"] = frame(rng)
    for band, nm in enumerate(BANDS):
        io.write_frame(root / "bare" / f"{nm}nm.tif", cubes["bare"][..., band : band + 1])
    (root / "bands" / "notes.txt").write_text("ignored: not a cube")
    return cubes


def test_every_input_layout_and_name_mirroring(cal, tmp_path, rng, capsys):
    cubes = write_layouts(tmp_path / "in" / "data", rng)
    out = tmp_path / "out"
    status, stdout, err = run(["correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)], capsys)
    assert status == 0, err
    assert stdout.strip().startswith(f"{len(cubes)} corrected")
    calibration, _ = io.load_calibration(cal)
    for name, raw in cubes.items():
        refl, _, _ = read_exr(out / "in" / "data" / f"{name}.reflectance.exr")
        np.testing.assert_array_equal(refl, np.asarray(spherejax.correct(raw, calibration).reflectance), err_msg=name)
    # Plain log lines (stderr is not a terminal): one per input.
    assert len([line for line in err.splitlines() if ": done (" in line]) == len(cubes)


def test_session_frames_are_inputs(cal, tmp_path, rng, capsys):
    frames = [
        ({"id": "dark", "role": "dark", "exposure_s": [1.0] * B, "timestamp": "2026-01-01T00:00:00"}, frame(rng)),
        ({"id": "white", "role": "white", "exposure_s": [1.0] * B, "timestamp": "2026-01-01T00:00:00"}, frame(rng)),
        ({"id": "s1", "role": "sample", "exposure_s": [1.0] * B, "timestamp": "2026-01-01T00:00:00",
          "set": "test", "background": "bg"}, frame(rng)),
    ]
    common = dict(band_centres_nm=BANDS, image_shape=[H, W], saturation=16383, white_patch=[2, 8, 2, 8], holder=[10, 30, 10, 40], frames=frames)
    io.write_session(tmp_path / "sess", instrument_id="sphere-1", **common)
    io.write_session(tmp_path / "other", instrument_id="sphere-2", **common)
    out = tmp_path / "out"
    status, stdout, err = run(["correct", "-c", str(cal), str(tmp_path / "sess"), str(tmp_path / "other"), "-o", str(out)], capsys)
    assert status == 1
    assert sorted(outputs_of(out)) == sorted(f"sess/frames/s1.{k}" for k in KINDS)
    assert "failed other/frames/s1.tif:" in err and "'sphere-2', the calibration was built for 'sphere-1'" in err
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 1 failed"


# ------------------------------------------------------------------------------------ bad inputs


def test_bad_inputs_fail_alone(cal, tmp_path, rng, capsys, monkeypatch):
    inputs = tmp_path / "in"
    (inputs / "ok").mkdir(parents=True)
    io.write_frame(inputs / "ok" / "good1.tif", frame(rng))
    io.write_frame(inputs / "ok" / "good2.tif", frame(rng))
    (inputs / "bad").mkdir()
    (inputs / "bad" / "text.tif").write_text("not an image")
    io.write_frame(inputs / "bad" / "cut.tif", frame(rng))
    data = (inputs / "bad" / "cut.tif").read_bytes()
    (inputs / "bad" / "cut.tif").write_bytes(data[: len(data) // 2])
    io.write_frame(inputs / "bad" / "bands15.tif", frame(rng, (H, W, 15)))
    io.write_frame(inputs / "bad" / "size.tif", frame(rng, (H, W + 2, B)))
    other_bands = [b + 5 for b in BANDS]
    io.write_frame(inputs / "bad" / "otherbands.tif", frame(rng), channel_names=[f"{b}nm" for b in other_bands])
    for nm in BANDS[:-1]:  # a band folder missing its last band
        io.write_frame(inputs / "bad" / f"short_{nm}nm.tif", frame(rng, (H, W, 1)))
    # Outputs of "unwritable" would go into a folder that cannot be created (a file is in the way).
    (inputs / "unwritable").mkdir()
    io.write_frame(inputs / "unwritable" / "x.tif", frame(rng))
    # Outputs of "escape" would go through a link in OUT to a folder outside it.
    (inputs / "escape").mkdir()
    io.write_frame(inputs / "escape" / "y.tif", frame(rng))
    out, outside = tmp_path / "out", tmp_path / "outside"
    (out / "in").mkdir(parents=True)
    outside.mkdir()
    (out / "in" / "unwritable").write_text("a file where a folder must go")
    (out / "in" / "escape").symlink_to(outside)
    # A full disk when the preview of "full.tif" is renamed into place: its outputs already in
    # place must go.
    io.write_frame(inputs / "ok" / "full.tif", frame(rng))
    real_commit = io.AtomicImageWriter.commit

    def full_disk(writer):
        if writer.path.name == "full.preview.png":
            writer.abort()
            raise io.SpherejaxFileError(writer.path, "could not be written: [Errno 28] No space left on device")
        return real_commit(writer)

    monkeypatch.setattr(io.AtomicImageWriter, "commit", full_disk)

    # (A path given that leads to nothing refuses the whole batch before OUT is created:
    # tests/robustness/test_correct_ownership_proved.py.)
    status, stdout, err = run(["correct", "-c", str(cal), str(inputs), "-o", str(out)], capsys)
    assert status == 1
    assert stdout.strip() == "2 corrected, 0 skipped (already done), 9 failed"
    failures = {line.split(": ", 2)[1].removeprefix("failed "): line for line in err.splitlines() if line.startswith("spherejax: failed ")}
    expected_reasons = {
        "in/bad/text.tif": "not a readable image",
        "in/bad/cut.tif": "corrupted",
        "in/bad/bands15.tif": "has 15 channels",
        "in/bad/size.tif": "is 40 x 50 pixels",
        "in/bad/otherbands.tif": "has bands 405..705 nm step 20",
        "in/bad/short*nm": "has band files for",
        "in/unwritable/x.tif": "is not a folder",
        "in/escape/y.tif": "would be written outside OUT",
        "in/ok/full.tif": "No space left on device",
    }
    assert set(failures) == set(expected_reasons)
    for source, reason in expected_reasons.items():
        assert reason in failures[source], failures[source]
    assert "Traceback" not in err
    # The failures were logged as they happened and summarised at the end: one line each time.
    assert sum(line.startswith("spherejax: [") and ": failed: " in line for line in err.splitlines()) == 9
    # Nothing partial: the good inputs' outputs only, no temporaries, nothing outside OUT.
    assert sorted(outputs_of(out)) == sorted([f"in/ok/good{i}.{k}" for i in (1, 2) for k in KINDS] + ["in/unwritable"])
    assert list(outside.iterdir()) == []
    statuses = {r["input"]: r["status"] for r in manifest_records(out)}
    assert sorted(s for s, v in statuses.items() if v == "failed") == sorted(expected_reasons)
    assert all("reason" in r for r in manifest_records(out) if r["status"] == "failed")


def test_calibration_for_other_bands_fails_every_file(tmp_path, rng, capsys):
    calibration, _, _ = make_calibration(rng, bands=BANDS[:8])
    io.save_calibration(tmp_path / "cal8.h5", calibration, instrument_id="other", band_centres_nm=BANDS[:8])
    io.write_frame(tmp_path / "a.tif", frame(rng), channel_names=NAMES)
    status, stdout, err = run(["correct", "-c", str(tmp_path / "cal8.h5"), str(tmp_path / "a.tif"), "-o", str(tmp_path / "out")], capsys)
    assert status == 1 and "has 16 channels (expected 8 channels" in err
    assert outputs_of(tmp_path / "out") == {}


@pytest.mark.parametrize("problem", ["missing", "corrupt"])
def test_bad_calibration_is_refused_before_writing(tmp_path, rng, capsys, problem):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    cal = tmp_path / "cal.h5"
    if problem == "corrupt":
        cal.write_bytes(b"not a calibration")
    status, stdout, err = run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(tmp_path / "out")], capsys)
    assert status == cli.EXIT_BAD_INPUT
    assert len(err.strip().splitlines()) == 1 and err.startswith("spherejax: error: ") and "cal.h5" in err
    assert not (tmp_path / "out").exists()


def test_existing_batch_needs_resume(cal, tmp_path, rng, capsys):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    argv = ["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(tmp_path / "out")]
    assert run(argv, capsys)[0] == 0
    status, _, err = run(argv, capsys)
    assert status == cli.EXIT_BAD_INPUT and "already holds a batch" in err and "--resume" in err


# ------------------------------------------------------------------------------------------ lock


def test_second_run_is_refused_while_the_lock_is_held(cal, tmp_path, rng, capsys):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    out = tmp_path / "out"
    out.mkdir()
    holder = archive.OutputLock(out)
    holder.acquire()
    try:
        status, _, err = run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(out)], capsys)
    finally:
        holder.release()
    assert status == cli.EXIT_BAD_INPUT and len(err.strip().splitlines()) == 1
    assert archive.LOCK_NAME in err and f"pid {os.getpid()}" in err
    assert sorted(p.name for p in out.iterdir()) == []  # released, nothing written


def test_stale_lock_is_taken_over(cal, tmp_path, rng, capsys):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    out = tmp_path / "out"
    out.mkdir()
    # What a killed run leaves: its lock file, no longer locked (the kernel dropped the flock).
    (out / archive.LOCK_NAME).write_text(json.dumps({"pid": 999999, "host": "crashed-host"}))
    status, _, err = run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(out)], capsys)
    assert status == 0
    assert "took over the lock left by pid 999999 on crashed-host" in err
    assert not (out / archive.LOCK_NAME).exists()


def test_lock_is_exclusive_between_open_files(tmp_path):
    lock = archive.OutputLock(tmp_path)
    lock.acquire()
    try:
        fd = os.open(tmp_path / archive.LOCK_NAME, os.O_RDWR)
        with pytest.raises(BlockingIOError):
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.close(fd)
        with pytest.raises(archive.BatchError, match="is held by pid"):
            archive.OutputLock(tmp_path).acquire()
    finally:
        lock.release()


# ---------------------------------------------------------------------------------------- resume


def test_resume_skips_verified_and_redoes_the_rest(cal, tmp_path, rng, capsys):
    (tmp_path / "in").mkdir()
    for name in "abcd":
        io.write_frame(tmp_path / "in" / f"{name}.tif", frame(rng))
    out = tmp_path / "out"
    argv = ["correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)]
    assert run(argv, capsys)[0] == 0
    reference = outputs_of(out)
    (out / "in" / "a.lab.exr").write_bytes(b"corrupted")  # a damaged output
    (out / "in" / "b.preview.png").unlink()  # a missing output
    io.write_frame(tmp_path / "in" / "c.tif", frame(rng))  # a changed input
    # Bytes spherejax never recorded at that name are not provably its own: refused, kept.
    status, _, err = run([*argv, "--resume"], capsys)
    assert status == cli.EXIT_BAD_INPUT and "a.lab.exr: is in the way of an output" in err
    assert (out / "in" / "a.lab.exr").read_bytes() == b"corrupted"
    (out / "in" / "a.lab.exr").unlink()
    status, stdout, err = run([*argv, "--resume"], capsys)
    assert status == 0
    assert stdout.strip() == "3 corrected, 1 skipped (already done), 0 failed"
    assert "in/d.tif: skipped (already done)" in err
    after = outputs_of(out)
    assert {k: v for k, v in after.items() if not k.startswith("in/c.")} == {
        k: v for k, v in reference.items() if not k.startswith("in/c.")
    }
    assert after["in/c.reflectance.exr"] != reference["in/c.reflectance.exr"]
    latest = archive.read_manifest(out)
    for name in "abcd":
        for output, digest in latest[f"in/{name}"]["outputs"].items():
            assert output_digest(out / output) == digest


def test_resume_ignores_a_torn_manifest_line_and_stale_temporaries(cal, tmp_path, rng, capsys):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    io.write_frame(tmp_path / "b.tif", frame(rng))
    out = tmp_path / "out"
    argv = ["correct", "-c", str(cal), str(tmp_path / "a.tif"), str(tmp_path / "b.tif"), "-o", str(out)]
    assert run(argv, capsys)[0] == 0
    reference = outputs_of(out)
    manifest = out / archive.MANIFEST_NAME
    lines = manifest.read_bytes().splitlines(keepends=True)
    manifest.write_bytes(lines[0] + lines[1][:40])  # killed halfway through the second record
    # What the killed run left in its lock file: b's outputs, recorded before they were renamed.
    made = {"made": json.loads(lines[1])["outputs"]}
    (out / archive.LOCK_NAME).write_text(json.dumps({"pid": 999999, "host": "gone"}) + "\n" + json.dumps(made) + "\n")
    (out / ".b.lab.exr.0123456789ab.tmp").write_bytes(b"half")
    status, stdout, _ = run([*argv, "--resume"], capsys)
    assert status == 0 and stdout.strip() == "1 corrected, 1 skipped (already done), 0 failed"
    assert outputs_of(out) == reference
    assert set(archive.read_manifest(out)) == {"a", "b"}


# ------------------------------------------------------------------------------ kill and resume
#
# `spherejax correct` run as a child process, stopped partway, then finished with --resume: once
# for each way a run can be stopped. SIGKILL: no clean-up at all; the run leaves whatever it cut
# short (temporary files, its lock file, outputs in place before their manifest line).
# SIGINT / SIGTERM: the run stops at its next safe point, cleaned up, with one line and the exit
# status 130 / 143 (on dask, with the cluster shut down). Either way --resume finishes the batch
# with the bytes of an uninterrupted run. (The states a kill leaves, made by hand, are tested
# above; stops without a child process in tests/robustness/.)


def _temporaries(out: pathlib.Path) -> set[str]:
    """The temporary files under OUT (io's naming: ".<name>.<12 hex>.tmp")."""
    return {p.relative_to(out).as_posix() for p in out.rglob("*") if io.is_temp_sibling(p.name)}


def _tree(folder: pathlib.Path) -> list[str]:
    """Every file and folder under `folder`, relative."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def _done(out: pathlib.Path) -> dict[str, dict]:
    return {name: record for name, record in archive.read_manifest(out).items() if record["status"] == "done"}


def _unrecorded(out: pathlib.Path) -> set[str]:
    """Inputs with an output renamed into place that the manifest does not call done (yet).
    Names only, nothing read: this is polled while a run goes on."""
    skip = {archive.MANIFEST_NAME, archive.LOCK_NAME}
    present = {
        p.relative_to(out).as_posix().rsplit(".", 2)[0] for p in out.rglob("*")
        if p.name not in skip and not io.is_temp_sibling(p.name) and p.is_file()
    }
    return present - set(_done(out))


def _cubes(folder: pathlib.Path, count: int, seed: int) -> dict[str, bytes]:
    """`count` cubes in `folder`, cube00.tif on; returns each file's bytes (inputs are never written)."""
    rng = np.random.default_rng(seed)
    folder.mkdir()
    for index in range(count):
        io.write_frame(folder / f"cube{index:02d}.tif", frame(rng), channel_names=NAMES)
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _manifest_lines(out: pathlib.Path) -> list[bytes]:
    return sorted(line for line in (out / archive.MANIFEST_NAME).read_bytes().split(b"\n") if line)


INPUTS = 16
KILLS = 20


def _correct_kill_plan(rng: random.Random, lock_s: float, done_s: float) -> list[tuple[str, float | int]]:
    """KILLS (mode, argument) pairs, in the order they are used.

    start-up: argument s after the start, well before JAX has started and the lock is taken;
    time: argument s after the start, from 0 to a quarter into the batch of an uninterrupted run
        that took the lock after lock_s and had done every input after done_s (start-up, the
        first compilation, the first inputs; much later, a resumed run that has fewer inputs left
        could finish the batch before it is killed);
    after-inputs: once the manifest holds `argument` done inputs, plus 0-20 ms (the next input
        takes about 20 ms: between inputs or anywhere inside one input's writes);
    in-writes: as after-inputs, then as soon as this run has a temporary output file open;
    renamed: as after-inputs, then as soon as an output of the input in progress is renamed into
        place (its other outputs, or its manifest line, still to come; a window of a few ms that
        the poll catches in most runs, not all: counted, not required).
    The input counts are sorted, so the kills walk through the whole batch; they stop one short
    of its end, so the kills (and not a run left alone) finish the batch.
    """
    modes = ["start-up"] * 3 + ["time"] * 4 + ["after-inputs"] * 6 + ["in-writes"] * 4 + ["renamed"] * 3
    rng.shuffle(modes)
    counts = iter(sorted(rng.randrange(1, INPUTS - 1) for _ in modes))
    plan = []
    for mode in modes:
        count = next(counts)
        if mode == "start-up":
            plan.append((mode, rng.uniform(0.0, 1.0)))
        elif mode == "time":
            plan.append((mode, rng.uniform(0.0, lock_s + (done_s - lock_s) / 4)))
        else:
            plan.append((mode, count))
    return plan


@pytest.mark.slow
def test_twenty_kills_and_resumes_give_byte_identical_outputs(cal, tmp_path):
    """SIGKILL at KILLS seeded moments spread over the whole batch (`_correct_kill_plan`: during
    start-up, at random times, between inputs, inside an input's writes, between an output's
    rename and its manifest line), each followed by --resume. At every kill, whatever is under
    its final name is complete and everything the manifest calls done is on disk as recorded; at
    the end, every output is the uninterrupted run's to the byte, each input recorded once, and
    nothing else is left in OUT or beside it."""
    cubes = _cubes(tmp_path / "in", INPUTS, seed=11)
    names = [f"in/cube{index:02d}" for index in range(INPUTS)]
    reference, killed = tmp_path / "reference", tmp_path / "killed"
    argv = ["-c", str(cal), str(tmp_path / "in"), "-o"]

    started = time.perf_counter()
    process = start_correct([*argv, str(reference)], may_be_killed=False)
    lock_s = wait_until(process, holds_lock(process, reference)) - started
    done_s = wait_until(process, lambda: len(_done(reference)) == INPUTS) - started
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()
    expected = outputs_of(reference)
    assert len(expected) == INPUTS * len(archive.OUTPUT_KINDS)

    plan = _correct_kill_plan(random.Random(5), lock_s, done_s)
    delays = random.Random(6)
    landed = []  # per kill: (mode, inputs done, lock held, temporaries left, outputs not yet recorded)
    runs = 0
    while len(landed) < KILLS:
        runs += 1
        assert runs <= 2 * KILLS, f"only {len(landed)} of {KILLS} kills landed in {runs - 1} runs: {landed}"
        mode, argument = plan[len(landed)]
        stale = _temporaries(killed) if killed.exists() else set()
        process = start_correct([*argv, str(killed), *(["--resume"] if killed.exists() else [])])
        if mode in ("start-up", "time"):
            time.sleep(argument)
        else:
            wait_until(process, holds_lock(process, killed))
            wait_until(process, lambda: len(_done(killed)) >= argument)
            # (Should the poll miss the moment, an input finishing first ends the wait: a kill
            # never lets a run get far ahead.)
            reached = len(_done(killed))
            if mode == "in-writes":
                wait_until(process, lambda: bool(_temporaries(killed) - stale) or len(_done(killed)) > reached)
                time.sleep(delays.uniform(0.0, 0.005))
            elif mode == "renamed":
                wait_until(process, lambda: bool(_unrecorded(killed)) or len(_done(killed)) > reached)
            else:
                time.sleep(delays.uniform(0.0, 0.020))
        if not sigkill(process):  # it finished first: not a kill; the next run gets this one
            # The plan's times come from the first, uninterrupted run; a resumed run with few
            # inputs left, or a quicker machine, finishes before them. Bring a time kill forward,
            # and give a run that finished the whole batch a fresh OUT: no later kill could land
            # in a batch that is complete (CI saw "only 4 of 20 kills landed").
            if mode == "time":
                plan[len(landed)] = (mode, argument / 2)
            if len(_done(killed)) == INPUTS:
                shutil.rmtree(killed)
            continue

        # At every kill: whatever is under its final name is complete (the reference's bytes), and
        # every input the manifest calls done has its outputs there with the recorded SHA-256.
        done = _done(killed)
        temporaries = _temporaries(killed)
        present = {name: data for name, data in outputs_of(killed).items() if name not in temporaries}
        for name, data in present.items():
            assert data == expected[name], f"kill {len(landed)} ({mode}): {name} differs from the reference"
        for record in done.values():
            for output, digest in record["outputs"].items():
                assert output_digest(killed / output) == digest, f"kill {len(landed)}: {output}"
        unrecorded = _unrecorded(killed)
        lock = (json.loads((killed / archive.LOCK_NAME).read_text().partition("\n")[0])  # the holder's line
                if (killed / archive.LOCK_NAME).exists() else {})
        landed.append((mode, len(done), lock.get("pid") == process.pid, len(temporaries), len(unrecorded)))

    before_final = len(_done(killed))
    process = start_correct([*argv, str(killed), "--resume"])
    _, err = process.communicate(timeout=120)
    log = err.decode()
    assert process.returncode == 0, log
    # Only what was not done yet was corrected; what was done was verified and skipped.
    assert sum(line.endswith(": skipped (already done)") for line in log.splitlines()) == before_final, log
    assert sum(": done (" in line for line in log.splitlines()) == INPUTS - before_final, log

    mid_batch = [kill for kill in landed if 0 < kill[1] < INPUTS]
    in_batch = [kill for kill in landed if kill[2]]  # the killed run held the lock
    in_writes = [kill for kill in landed if kill[3]]  # it left temporary files behind
    print(f"\n{len(landed)} kills in {runs} runs: {len(mid_batch)} mid-batch, {len(in_batch)} with the lock held, "
          f"{len(in_writes)} inside an input's writes, {sum(1 for kill in landed if kill[4])} with outputs not yet "
          f"in the manifest; inputs done at each kill: {[kill[1] for kill in landed]}")
    assert len(landed) == KILLS
    assert len(mid_batch) >= 3 * KILLS // 4, landed
    assert len(in_batch) >= KILLS // 2 and in_writes, landed

    # Every output byte-identical to the uninterrupted run's, and nothing else in OUT: no
    # temporary file, no lock, no stray folder; nothing beside OUT, the inputs untouched.
    got = outputs_of(killed)
    assert sorted(got) == sorted(expected)
    assert [name for name in expected if got[name] != expected[name]] == []
    assert _tree(killed) == _tree(reference)
    assert not (killed / archive.LOCK_NAME).exists()
    assert sorted(os.listdir(tmp_path)) == ["in", "killed", "reference"]
    assert {p.name: p.read_bytes() for p in sorted((tmp_path / "in").iterdir())} == cubes
    # The manifest: whole lines only, each input done exactly once over all the runs (never redone
    # once recorded, never failed), every output's SHA-256 that of its file: line for line the
    # uninterrupted run's manifest, in another order.
    records = [json.loads(line) for line in _manifest_lines(killed)]
    assert collections.Counter(r["name"] for r in records) == collections.Counter(names)
    assert {r["status"] for r in records} == {"done"}
    for record in records:
        for output, digest in record["outputs"].items():
            assert output_digest(killed / output) == digest
    assert (killed / archive.MANIFEST_NAME).read_bytes().endswith(b"\n")
    assert _manifest_lines(killed) == _manifest_lines(reference)


def _check_stopped(process: subprocess.Popen, signum: int, out: pathlib.Path) -> int:
    """The run stopped cleanly: exit status 128 + signum, one line saying how far it got, no
    temporary, no lock, a manifest of complete inputs only, no output the manifest does not list.
    Returns the inputs done."""
    _, err = process.communicate(timeout=120)
    err = err.decode()
    assert process.returncode == 128 + signum, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    match = INTERRUPTED.fullmatch(lines[0])
    assert match and int(match.group(2)) == INPUTS and match.group(3) == "inputs", err
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
def test_sigint_and_sigterm_stop_correct_cleanly_and_resume_finishes_it(cal, tmp_path):
    """SIGINT and SIGTERM at several moments, in process and on dask, each stop checked by
    `_check_stopped`, then --resume: the uninterrupted run's bytes, each input recorded once,
    nothing else left. On dask the stop also lets the inputs under way on the workers finish (the
    manifest records them) and shuts the cluster down: no worker process outlives the command."""
    import psutil  # with dask.distributed

    cubes = _cubes(tmp_path / "in", INPUTS, seed=3)
    reference, out = tmp_path / "reference", tmp_path / "out"
    argv = ["-c", cal, tmp_path / "in", "-o"]
    process = start_correct([*argv, reference], may_be_killed=False, quiet=True)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()

    # (signal, moment): just after start-up (the lock taken; a new OUT: a resumed run stopped
    # before it has verified the inputs done earlier counts none of them); a dask batch (two
    # worker processes) once 2 more inputs are done; mid-batch (3 more inputs done); inside an
    # input's writes (a temporary output there; the poll may see it late, when the input is
    # already complete: then it is between inputs).
    moments = [(signal.SIGINT, "start-up"), (signal.SIGTERM, "dask"), (signal.SIGTERM, "mid-batch"),
               (signal.SIGTERM, "in-writes"), (signal.SIGINT, "in-writes")]
    done = 0
    in_writes = 0
    for signum, moment in moments:
        resume = ["--resume"] if out.exists() else []
        if moment == "dask":
            process = start_correct([*argv, out, *resume, "--workers", "2"], may_be_killed=False, quiet=True,
                                    env={"SPHEREJAX_COMPILATION_CACHE": str(tmp_path / "jax-cache")})
            wait_until(process, lambda: len(_done(out)) >= done + 2)
            assert process.poll() is None, f"{moment}: the run ended before the signal"
            workers = psutil.Process(process.pid).children(recursive=True)
            assert workers
        else:
            process = start_correct([*argv, out, *resume], may_be_killed=False, quiet=True)
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
        if moment == "dask":
            assert now >= done + 2
            # The cluster is shut down with the client: no worker process outlives the command.
            gone, alive = psutil.wait_procs(workers, timeout=20)
            assert not alive, alive
        assert now >= done
        done = now
    assert done < INPUTS
    print(f"\n{len(moments)} stops, {in_writes} seen inside an input's writes; {done} inputs done before the last --resume")

    process = start_correct([*argv, out, "--resume"], may_be_killed=False, quiet=True)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()
    got, expected = outputs_of(out), outputs_of(reference)
    assert sorted(got) == sorted(expected)
    assert [name for name in expected if got[name] != expected[name]] == []
    assert _tree(out) == _tree(reference)
    assert sorted(os.listdir(tmp_path)) == ["in", "jax-cache", "out", "reference"]
    assert {p.name: p.read_bytes() for p in sorted((tmp_path / "in").iterdir())} == cubes
    # Every input recorded exactly once over all the runs, as the uninterrupted run recorded it.
    assert _manifest_lines(out) == _manifest_lines(reference)


def test_executor_gets_absolute_paths_whatever_its_folder(cal, tmp_path, rng, monkeypatch):
    """Workers of a running scheduler may start in another folder: relative OUT and CAL given on
    the command line must reach them absolute, or outputs land outside the locked OUT."""
    import shutil

    (tmp_path / "client" / "in").mkdir(parents=True)
    (tmp_path / "worker").mkdir()
    shutil.copy(cal, tmp_path / "client" / "cal.h5")
    io.write_frame(tmp_path / "client" / "in" / "a.tif", frame(rng))
    monkeypatch.chdir(tmp_path / "client")

    class ElsewhereExecutor:
        def map(self, specs, out_root, calibration_path, **options):
            assert pathlib.Path(out_root).is_absolute() and pathlib.Path(calibration_path).is_absolute()
            here = os.getcwd()
            os.chdir(tmp_path / "worker")  # the worker's own folder
            try:
                for spec in specs:
                    yield spec, archive.correct_input(spec, out_root, calibration_path, **options)
            finally:
                os.chdir(here)

    summary = archive.run_batch(["in"], "out", "cal.h5", executor=ElsewhereExecutor())
    assert summary.corrected == 1 and not summary.failed
    assert sorted(outputs_of(tmp_path / "client" / "out")) == sorted(f"in/a.{k}" for k in KINDS)
    assert list((tmp_path / "worker").iterdir()) == []


@pytest.mark.parametrize("compression", ["piz", "zip", "none"])
def test_exr_compression_is_lossless(cal, tmp_path, rng, capsys, compression):
    raw = frame(rng)
    io.write_frame(tmp_path / "a.tif", raw)
    out = tmp_path / "out"
    status, _, err = run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(out), "--exr-compression", compression], capsys)
    assert status == 0, err
    image = oiio.ImageInput.open(str(out / "a.reflectance.exr"))
    assert image.spec().get_string_attribute("compression") == compression
    image.close()
    refl, _, _ = read_exr(out / "a.reflectance.exr")
    expected = np.asarray(spherejax.correct(raw, io.load_calibration(cal)[0]).reflectance)
    assert refl.tobytes() == expected.tobytes()


def test_unknown_exr_compression_is_refused_before_anything(cal, tmp_path, rng):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    with pytest.raises(ValueError, match=r"exr_compression: expected one of \['piz', 'zip', 'none'\], got 'lzw'"):
        archive.run_batch([tmp_path / "a.tif"], tmp_path / "out", cal, exr_compression="lzw")
    assert not (tmp_path / "out").exists()


def test_the_command_lines_exr_options_are_ios(capsys):
    """`spherejax correct`'s --exr-compression and --reflectance-type offer what io writes, with
    io's defaults (the parser spells them out so as not to import OpenImageIO)."""
    commands = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    actions = {action.dest: action for action in commands.choices["correct"]._actions}
    assert actions["exr_compression"].default == io.DEFAULT_EXR_COMPRESSION
    assert tuple(actions["exr_compression"].choices) == io.EXR_COMPRESSIONS
    assert actions["reflectance_type"].default == "float"
    assert tuple(actions["reflectance_type"].choices) == io.EXR_PIXEL_TYPES


def test_half_float_reflectance_is_the_float_rounded_to_half(cal, tmp_path, rng, capsys):
    """--reflectance-type half: the reflectance EXR holds OpenEXR half floats, each the float32
    reflectance rounded to the nearest half (NaN kept), half the size uncompressed; Lab, quality
    and preview are those of the float batch, and the manifest records the setting."""
    raw = frame(rng)
    io.write_frame(tmp_path / "a.tif", raw)
    status, _, err = run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(tmp_path / "half"),
                          "--reflectance-type", "half"], capsys)
    assert status == 0, err
    assert run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(tmp_path / "float")], capsys)[0] == 0
    image = oiio.ImageInput.open(str(tmp_path / "half" / "a.reflectance.exr"))
    assert image.spec().format == oiio.TypeDesc("half")
    stored = image.read_image("half")
    image.close()
    expected = np.asarray(spherejax.correct(raw, io.load_calibration(cal)[0]).reflectance)
    np.testing.assert_array_equal(stored, expected.astype(np.float16))
    half_size, float_size = ((tmp_path / o / "a.reflectance.exr").stat().st_size for o in ("half", "float"))
    assert half_size < 0.55 * float_size
    for kind in ("lab.exr", "quality.png", "preview.png"):
        assert (tmp_path / "half" / f"a.{kind}").read_bytes() == (tmp_path / "float" / f"a.{kind}").read_bytes()
    assert manifest_records(tmp_path / "half")[0]["settings"]["reflectance_type"] == "half"
    assert manifest_records(tmp_path / "float")[0]["settings"]["reflectance_type"] == "float"


def test_an_unknown_reflectance_type_is_refused_before_anything(cal, tmp_path, rng):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    with pytest.raises(ValueError, match=r"^reflectance_type: expected one of \['float', 'half'\], got 'double'$"):
        archive.run_batch([tmp_path / "a.tif"], tmp_path / "out", cal, reflectance_type="double")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match=r"^pixel_type: expected one of \['float', 'half'\], got 'double'$"):
        io.open_exr(tmp_path / "b.exr", (2, 2, 1), channel_names=["Y"], pixel_type="double")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tif"]


def test_half_float_envi_is_refused_before_anything(cal, tmp_path, rng, capsys):
    io.write_frame(tmp_path / "a.tif", frame(rng))
    status, _, err = run(["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(tmp_path / "out"),
                          "--format", "envi", "--reflectance-type", "half"], capsys)
    assert status == 2
    assert err.strip().splitlines() == [
        "spherejax: error: reflectance_type: expected 'float' with output_format 'envi' (half floats are an OpenEXR type; "
        "ENVI has none), got 'half'"
    ]
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------ ENVI


def test_envi_outputs_read_by_spectral_python_and_xarray(cal, tmp_path, rng, capsys):
    """--format envi: reflectance and Lab as ENVI images that Spectral Python reads with their
    wavelengths and values (flagged pixels at the data ignore value), and that open_corrected
    reads as it reads the EXR outputs of the same input."""
    import spectral

    raw = frame(rng)
    io.write_frame(tmp_path / "a.tif", raw, channel_names=NAMES)
    argv = ["correct", "-c", str(cal), str(tmp_path / "a.tif")]
    assert run([*argv, "-o", str(tmp_path / "envi"), "--format", "envi"], capsys)[0] == 0
    assert run([*argv, "-o", str(tmp_path / "exr")], capsys)[0] == 0
    assert sorted(outputs_of(tmp_path / "envi")) == sorted(f"a.{k}" for k in archive.OUTPUT_KINDS_BY_FORMAT["envi"])
    calibration, header = io.load_calibration(cal)
    expected = spherejax.correct(raw, calibration)
    good = np.asarray(expected.quality) == 0

    image = spectral.open_image(str(tmp_path / "envi" / "a.reflectance.hdr"))
    np.testing.assert_array_equal(image.bands.centers, WAVELENGTHS_NM.astype(float))
    assert image.metadata["wavelength units"] == "Nanometers"
    assert image.metadata["spherejax calibration checksum"] == header["checksum"]
    pixels = np.asarray(image.load())
    np.testing.assert_array_equal(pixels[good], np.asarray(expected.reflectance)[good])
    assert (pixels[~good] == float(image.metadata["data ignore value"])).all() and (~good).any()
    lab = np.asarray(spectral.open_image(str(tmp_path / "envi" / "a.lab.hdr")).load())
    np.testing.assert_array_equal(lab[good], np.asarray(expected.lab)[good])

    from_envi = spherejax.open_corrected(tmp_path / "envi" / "a.reflectance.hdr")
    from_exr = spherejax.open_corrected(tmp_path / "exr" / "a")
    for name in ("reflectance", "lab", "quality"):
        np.testing.assert_array_equal(from_envi[name].values, from_exr[name].values, err_msg=name)
    np.testing.assert_array_equal(from_envi["wavelength"], from_exr["wavelength"])
    assert from_envi.attrs["spherejax:calibration_checksum"] == from_exr.attrs["spherejax:calibration_checksum"]
    # Quality and preview are the same files in either format.
    envi_files, exr_files = outputs_of(tmp_path / "envi"), outputs_of(tmp_path / "exr")
    assert envi_files["a.quality.png"] == exr_files["a.quality.png"]


def test_resume_in_envi_verifies_envi_outputs(cal, tmp_path, rng, capsys):
    io.write_frame(tmp_path / "a.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "out"
    argv = ["correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(out)]
    assert run([*argv, "--format", "envi"], capsys)[0] == 0
    status, stdout, _ = run([*argv, "--format", "envi", "--resume"], capsys)
    assert status == 0 and stdout.strip() == "0 corrected, 1 skipped (already done), 0 failed"
    (out / "a.reflectance.img").write_bytes(b"damaged")
    status, _, err = run([*argv, "--format", "envi", "--resume"], capsys)  # not its bytes: refused
    assert status == cli.EXIT_BAD_INPUT and "a.reflectance.img: is in the way of an output" in err
    (out / "a.reflectance.img").unlink()
    status, stdout, _ = run([*argv, "--format", "envi", "--resume"], capsys)
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    # The same batch resumed in the other format has none of its outputs: redone, and the files
    # of the first format go (the manifest lists only the new ones).
    status, stdout, _ = run([*argv, "--resume"], capsys)
    assert stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    assert sorted(outputs_of(out)) == sorted(f"a.{kind}" for kind in archive.OUTPUT_KINDS)
    assert sorted(archive.read_manifest(out)["a"]["outputs"]) == sorted(outputs_of(out))


def test_unknown_output_format_is_refused_before_anything(cal, tmp_path, rng, capsys):
    with pytest.raises(ValueError, match=r"output_format: expected one of \['exr', 'envi'\], got 'tiff'"):
        archive.run_batch([tmp_path / "a.tif"], tmp_path / "out", cal, output_format="tiff")
    with pytest.raises(SystemExit):
        cli.main(["correct", "-c", str(cal), str(tmp_path), "-o", str(tmp_path / "o"), "--format", "tiff"])
    assert "invalid choice: 'tiff'" in capsys.readouterr().err and not (tmp_path / "out").exists()
