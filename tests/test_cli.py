"""The `spherejax` command line: simulate, calibrate, evaluate, demo, and every bad input.

Each bad input must give exit status 2, one line on stderr naming the file and the problem, no
traceback, and nothing new on disk.
"""

import json
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

from spherejax import cli, io, simulate
from tests.helpers import SMALL, assert_refused, calibration_entries, write_calibration_entries
from tests.helpers import run_cli as run


# `workspace` (tests/conftest.py): a small simulated session of the SMALL design and its
# calibration file, made once for the run.


def snapshot(folder: pathlib.Path) -> dict:
    """Every file under `folder` with its size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


class TestCommands:
    def test_calibrate_writes_a_loadable_file(self, workspace):
        calibration, header = io.load_calibration(workspace / "cal.h5", band_centres_nm=list(range(400, 701, 20)))
        assert header["metadata"]["calibration_report"]["training_patches"] == 3
        assert calibration.wiener.shape == (31, 16)

    def test_calibrate_with_a_robust_loss(self, workspace, tmp_path, capsys):
        status, _, err = run(["calibrate", str(workspace / "session"), "-o", str(tmp_path / "h.h5"), "--loss", "huber"], capsys)
        assert status == 0 and "warning" not in err
        _, header = io.load_calibration(tmp_path / "h.h5")
        report = header["metadata"]["calibration_report"]
        assert report["stage2_loss"] == "huber" and set(report["stage2_status"]) == {"converged"}

    def test_calibrate_reports_the_reflectance_estimator(self, workspace, tmp_path, capsys):
        """Per method tried: the cross-validated spectral rms and mean ΔE00 (D65), on stdout and
        in the file's report; the chosen estimator's offset is in the calibration."""
        status, stdout, _ = run(["calibrate", str(workspace / "session"), "-o", str(tmp_path / "c.h5")], capsys)
        assert status == 0
        calibration, header = io.load_calibration(tmp_path / "c.h5")
        report = header["metadata"]["calibration_report"]
        tried = report["wiener_cross_validation"]
        assert {entry["method"] for entry in tried} == {"training", "model"}
        assert tried[0]["method"] == report["wiener_method"]
        assert tried[0]["spectral_rms"] <= tried[1]["spectral_rms"]
        assert "k-means" in tried[0]["folds"]
        lines = stdout.splitlines()
        assert lines[0].startswith(f"reflectance estimator: {report['wiener_method']} (cross-validated on 16 targets")
        for entry in tried:
            row = next(line for line in lines if line[2:].startswith(entry["method"]))
            assert f"{entry['spectral_rms']:.5f}" in row and f"{entry['delta_e_d65']:.3f}" in row
        assert np.any(np.asarray(calibration.wiener_offset) != 0)

    def test_calibrate_with_one_wiener_method(self, workspace, tmp_path, capsys):
        status, _, _ = run(["-q", "calibrate", str(workspace / "session"), "-o", str(tmp_path / "t.h5"),
                            "--wiener-method", "training"], capsys)
        assert status == 0
        _, header = io.load_calibration(tmp_path / "t.h5")
        report = header["metadata"]["calibration_report"]
        assert report["wiener_method"] == "training" and len(report["wiener_cross_validation"]) == 1

    def test_calibrate_with_the_kernel_estimator_and_use_it(self, workspace, tmp_path, capsys):
        """--wiener-method kernel: the file stores the kernel residual (format version 5), the
        report puts the kernel's cross-validated errors first, then the affine methods', and
        evaluate corrects the session through it."""
        status, _, _ = run(["-q", "calibrate", str(workspace / "session"), "-o", str(tmp_path / "k.h5"),
                            "--wiener-method", "kernel"], capsys)
        assert status == 0
        calibration, header = io.load_calibration(tmp_path / "k.h5")
        report = header["metadata"]["calibration_report"]
        assert report["wiener_method"] == "kernel"
        assert [entry["method"] for entry in report["wiener_cross_validation"]][0] == "kernel"
        assert {entry["method"] for entry in report["wiener_cross_validation"][1:]} == {"training", "model"}
        residual = calibration.wiener_residual
        assert residual is not None and residual.inducing.shape == (16, 16)  # every one of the 16 targets
        assert header["arrays"]["wiener_residual_weights"]["shape"] == [31, 16]
        status, _, err = run(["-q", "evaluate", str(workspace / "session"), "-c", str(tmp_path / "k.h5"),
                              "--out", str(tmp_path / "e")], capsys)
        assert status == 0, err

    def test_calibrate_holds_out_named_groups_of_targets(self, workspace, tmp_path, capsys):
        """Two target charts named by a metadata field: each is held out in turn."""
        session = tmp_path / "session"
        shutil.copytree(workspace / "session", session)

        def split_chart(manifest):
            chart = next(f for f in manifest["frames"] if f["role"] == "target")
            second = json.loads(json.dumps(chart))
            half = len(chart["regions"]) // 2
            chart["regions"], second["regions"] = chart["regions"][:half], chart["regions"][half:]
            chart["metadata"] = {**chart.get("metadata", {}), "chart": "A"}
            second["id"], second["metadata"] = "targets-b", {**second.get("metadata", {}), "chart": "B"}
            manifest["frames"].append(second)

        edit_manifest(session, split_chart)
        status, stdout, _ = run(["calibrate", str(session), "-o", str(tmp_path / "g.h5"), "--wiener-groups", "chart"], capsys)
        assert status == 0
        _, header = io.load_calibration(tmp_path / "g.h5")
        assert header["metadata"]["calibration_report"]["wiener_cross_validation"][0]["folds"] == "leave one group out (2 groups)"
        assert "leave one group out (2 groups)" in stdout

    def test_cli_losses_are_the_library_losses(self):
        from spherejax.polynomial import LOSSES

        assert cli.LOSSES == LOSSES

    def test_evaluate_with_calibration_writes_tables_and_figures(self, workspace, tmp_path, capsys):
        out = tmp_path / "evaluation"
        status, stdout, _ = run(["evaluate", str(workspace / "session"), "-c", str(workspace / "cal.h5"), "--out", str(out)], capsys)
        assert status == 0
        assert "Table 6. Comparison with the Markov model" in stdout
        names = {p.name for p in out.iterdir()}
        assert {"tables.txt", "metrics.json", "figure5.png", "figure6.png"} <= names
        assert {f"table{k}.csv" for k in (1, 3, 4, 5, 6)} <= names
        assert (out / "figure5.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        metrics = json.loads((out / "metrics.json").read_text())
        assert set(metrics["metrics"]) == {"training", "test"}
        assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left

    def test_evaluate_without_calibration_calibrates_first(self, workspace, tmp_path, capsys):
        status, _, err = run(["evaluate", str(workspace / "session"), "--out", str(tmp_path / "e")], capsys)
        assert status == 0 and "[1/2] calibrating" in err

    def test_simulate_is_reproducible(self, tmp_path, capsys, monkeypatch):
        monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)
        assert run(["-q", "simulate", str(tmp_path / "a"), "--seed", "9"], capsys)[0] == 0
        assert run(["-q", "simulate", str(tmp_path / "b"), "--seed", "9"], capsys)[0] == 0
        a, b = io.load_session(tmp_path / "a"), io.load_session(tmp_path / "b")
        for frame in a.frames:
            np.testing.assert_array_equal(a.read(frame), b.read(frame.id))

    def test_demo_reuses_its_session(self, workspace, tmp_path, capsys, monkeypatch):
        """Only when the session there is the one asked for: the workspace's, seed 5 of SMALL."""
        monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)
        shutil.copytree(workspace / "session", tmp_path / "demo" / "session")
        status, stdout, err = run(["demo", "--out", str(tmp_path / "demo"), "--seed", "5"], capsys)
        assert status == 0
        assert "reusing the session" in err and "Table 1." in stdout
        assert (tmp_path / "demo" / "calibration.h5").exists()
        assert (tmp_path / "demo" / "evaluation" / "table6.csv").exists()

    def test_an_undocumented_kernel_switch_is_refused(self, workspace, tmp_path, capsys, monkeypatch):
        """SPHEREJAX_FUSED=off is not a documented value: taken as "on", it would leave the fused
        kernel on, silently."""
        monkeypatch.setenv("SPHEREJAX_FUSED", "off")
        before = snapshot(tmp_path)
        status, _, err = run(["correct", "-c", str(workspace / "cal.h5"), str(workspace / "session"), "-o", str(tmp_path / "out")], capsys)
        assert_refused(status, err, "SPHEREJAX_FUSED", "'off'", "'portable'")
        assert snapshot(tmp_path) == before

    def test_no_traceback_through_the_real_entry_point(self, tmp_path):
        result = subprocess.run(
            [sys.executable, "-m", "spherejax.cli", "calibrate", str(tmp_path / "nowhere"), "-o", str(tmp_path / "c.h5")],
            capture_output=True, text=True, timeout=120,
        )
        assert result.returncode == 2
        assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
        assert "nowhere" in result.stderr
        assert not (tmp_path / "c.h5").exists()


@pytest.fixture
def broken(workspace, tmp_path):
    """A private copy of the session to damage."""
    target = tmp_path / "session"
    shutil.copytree(workspace / "session", target)
    return target


def edit_manifest(session: pathlib.Path, change):
    path = session / "manifest.json"
    manifest = json.loads(path.read_text())
    change(manifest)
    path.write_text(json.dumps(manifest))


class TestBadSessions:
    """calibrate and evaluate on broken sessions: refused, nothing written."""

    def refuse(self, session, capsys, tmp_path, *fragments):
        before = snapshot(tmp_path)
        status, _, err = run(["calibrate", str(session), "-o", str(tmp_path / "out.h5")], capsys)
        assert_refused(status, err, *fragments)
        status, _, err = run(["evaluate", str(session), "--out", str(tmp_path / "evaluation")], capsys)
        assert_refused(status, err, *fragments)
        assert snapshot(tmp_path) == before

    def test_missing_folder(self, tmp_path, capsys):
        self.refuse(tmp_path / "absent", capsys, tmp_path, "absent")

    def test_no_manifest(self, broken, tmp_path, capsys):
        (broken / "manifest.json").unlink()
        self.refuse(broken, capsys, tmp_path, "manifest.json")

    def test_manifest_not_json(self, broken, tmp_path, capsys):
        (broken / "manifest.json").write_text("{ not json")
        self.refuse(broken, capsys, tmp_path, "manifest.json", "JSON")

    @pytest.mark.parametrize("field", ["band_centres_nm", "frames", "white_patch", "image_shape"])
    def test_manifest_lacks_a_field(self, broken, tmp_path, capsys, field):
        edit_manifest(broken, lambda m: m.pop(field))
        self.refuse(broken, capsys, tmp_path, "manifest.json", field)

    def test_training_samples_that_cannot_determine_stage2(self, broken, tmp_path, capsys):
        """One training capture (3 patches on one background): 3 samples for 4 coefficients.
        The closed form would write NaN coefficients into the calibration."""
        def one_capture(manifest):
            training = [f for f in manifest["frames"] if f.get("set") == "training"]
            manifest["frames"] = [f for f in manifest["frames"] if f.get("set") != "training" or f is training[0]]

        edit_manifest(broken, one_capture)
        self.refuse(broken, capsys, tmp_path, "manifest.json", "3 patch regions of 3 patch(es) on 1 background(s)")

    def test_training_captures_saturated_but_one(self, broken, tmp_path, capsys):
        """The manifest is fine, the pixels are not: every training capture but one saturated in
        a band, so that no patch has a usable Stage I target on the reference background (the
        check after the pixels are read, so that the message names the file, which the fit's
        own error cannot)."""
        manifest = json.loads((broken / "manifest.json").read_text())
        training = [f for f in manifest["frames"] if f.get("set") == "training"]
        for frame_info in training[1:]:
            path = broken / frame_info["file"]
            frame = io.read_frame(path).copy()
            frame[..., 5] = manifest["saturation"]
            frame[slice(*manifest["white_patch"][:2]), slice(*manifest["white_patch"][2:]), 5] = 1000  # the patch stays usable
            path.unlink()
            io.write_frame(path, frame)
        before = snapshot(tmp_path)
        # -q: the refusal comes after the pixels are read, when the progress line is out already.
        status, _, err = run(["-q", "calibrate", str(broken), "-o", str(tmp_path / "out.h5")], capsys)
        assert_refused(status, err, "manifest.json", "Stage II cannot be fitted in 16 band(s), first 400 nm", "only 0 finite samples")
        assert snapshot(tmp_path) == before

    def test_training_on_one_background(self, broken, tmp_path, capsys):
        """Every capture on one background: p barely varies, c1 p v + c2 v and c3 p + c4 cannot be
        told apart (the closed form gave NaN coefficients)."""
        def one_background(manifest):
            for frame in manifest["frames"]:
                if frame.get("set") == "training":
                    frame["background"] = "only"

        edit_manifest(broken, one_background)
        self.refuse(broken, capsys, tmp_path, "manifest.json", "on 1 background(s)", "2 backgrounds")

    def test_wiener_groups_field_missing(self, broken, tmp_path, capsys):
        before = snapshot(tmp_path)
        status, _, err = run(["calibrate", str(broken), "-o", str(tmp_path / "out.h5"), "--wiener-groups", "chart"], capsys)
        assert_refused(status, err, "manifest.json", "'targets'", "'chart'")
        assert snapshot(tmp_path) == before

    def test_wiener_groups_of_one_group(self, broken, tmp_path, capsys):
        before = snapshot(tmp_path)
        status, _, err = run(["calibrate", str(broken), "-o", str(tmp_path / "out.h5"), "--wiener-groups", "id"], capsys)
        assert_refused(status, err, "manifest.json", "every target is in group 'targets'", "at least 2 groups")
        assert snapshot(tmp_path) == before

    def test_frame_missing(self, broken, tmp_path, capsys):
        (broken / "frames" / "train-bg01-g0.tif").unlink()
        self.refuse(broken, capsys, tmp_path, "train-bg01-g0.tif")

    def test_frame_of_the_wrong_size(self, broken, tmp_path, capsys):
        frame = io.read_frame(broken / "frames" / "train-bg00-g0.tif")
        (broken / "frames" / "train-bg00-g0.tif").unlink()
        io.write_frame(broken / "frames" / "train-bg00-g0.tif", np.ascontiguousarray(frame[:-4]))
        self.refuse(broken, capsys, tmp_path, "train-bg00-g0.tif")

    def test_frame_with_the_wrong_band_count(self, broken, tmp_path, capsys):
        frame = io.read_frame(broken / "frames" / "white.tif")
        (broken / "frames" / "white.tif").unlink()
        io.write_frame(broken / "frames" / "white.tif", np.ascontiguousarray(frame[..., :15]))
        self.refuse(broken, capsys, tmp_path, "white.tif")

    def test_frame_not_an_image(self, broken, tmp_path, capsys):
        (broken / "frames" / "dark.tif").write_bytes(b"this is not a TIFF")
        self.refuse(broken, capsys, tmp_path, "dark.tif")

    def test_empty_patch_region(self, broken, tmp_path, capsys):
        edit_manifest(broken, lambda m: m.__setitem__("white_patch", [8, 8, 250, 260]))
        self.refuse(broken, capsys, tmp_path, "manifest.json", "white_patch")

    def test_patch_region_outside_the_image(self, broken, tmp_path, capsys):
        edit_manifest(broken, lambda m: m.__setitem__("white_patch", [8, 32, 300, 400]))
        self.refuse(broken, capsys, tmp_path, "manifest.json", "white_patch")

    def test_sample_region_outside_the_image(self, broken, tmp_path, capsys):
        def change(manifest):
            frame = next(f for f in manifest["frames"] if f["role"] == "sample")
            frame["regions"][0]["region"] = [-5, 30, 0, 35]
        edit_manifest(broken, change)
        self.refuse(broken, capsys, tmp_path, "manifest.json", "region")


class TestBadCalibrationFiles:
    def refuse(self, workspace, calibration, capsys, tmp_path, *fragments):
        out = tmp_path / "evaluation"
        status, _, err = run(["evaluate", str(workspace / "session"), "-c", str(calibration), "--out", str(out)], capsys)
        assert_refused(status, err, str(calibration), *fragments)
        assert not out.exists()

    def test_missing(self, workspace, tmp_path, capsys):
        self.refuse(workspace, tmp_path / "none.h5", capsys, tmp_path)

    def test_truncated(self, workspace, tmp_path, capsys):
        data = (workspace / "cal.h5").read_bytes()
        (tmp_path / "cut.h5").write_bytes(data[: len(data) // 2])
        self.refuse(workspace, tmp_path / "cut.h5", capsys, tmp_path)

    def test_tampered(self, workspace, tmp_path, capsys):
        arrays = calibration_entries(workspace / "cal.h5")
        arrays["coeffs"] = arrays["coeffs"].copy()
        arrays["coeffs"][3, 1] += 0.01
        write_calibration_entries(tmp_path / "tampered.h5", arrays)
        self.refuse(workspace, tmp_path / "tampered.h5", capsys, tmp_path, "checksum")

    def test_newer_format_version(self, workspace, tmp_path, capsys):
        arrays = calibration_entries(workspace / "cal.h5")
        header = json.loads(bytes(arrays["header"]).decode())
        header["format_version"] = 99
        arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
        write_calibration_entries(tmp_path / "newer.h5", arrays)
        self.refuse(workspace, tmp_path / "newer.h5", capsys, tmp_path, "99")

    def test_built_for_other_bands(self, workspace, tmp_path, capsys):
        calibration, _ = io.load_calibration(workspace / "cal.h5")
        io.save_calibration(tmp_path / "other.h5", calibration, instrument_id="x",
                            band_centres_nm=list(range(410, 711, 20)))
        self.refuse(workspace, tmp_path / "other.h5", capsys, tmp_path, "bands")

    @pytest.mark.parametrize("name", ["text.h5", "text.npz"])
    def test_not_a_calibration_file(self, workspace, tmp_path, capsys, name):
        (tmp_path / name).write_text("hello\n")
        self.refuse(workspace, tmp_path / name, capsys, tmp_path, "is neither HDF5 nor an .npz (zip) archive")


class TestBadOutputs:
    def test_simulate_into_a_non_empty_folder(self, tmp_path, capsys):
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "keep.txt").write_text("mine")
        before = snapshot(tmp_path)
        status, _, err = run(["simulate", str(tmp_path / "out")], capsys)
        assert_refused(status, err, "out")
        assert snapshot(tmp_path) == before

    def test_unknown_reference_background(self, workspace, tmp_path, capsys):
        status, _, err = run(["calibrate", str(workspace / "session"), "-o", str(tmp_path / "c.h5"),
                              "--reference-background", "velvet"], capsys)
        assert_refused(status, err, "velvet")
        assert not (tmp_path / "c.h5").exists()
