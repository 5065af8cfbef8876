"""`calibrate` registers the bands (`calibrate.register_session_bands`): the maps of a simulated
session recovered from its target chart (or its registration target, when it holds one), stored
in the calibration with how they were found, shown in the report; `--no-registration` stores
none; a registration frame without structure is refused in one line; `correct` runs on the
misregistered session and registration removes the colour fringes at its patches' edges."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil

import h5py
import numpy as np
import pytest

import spherejax as sj
from spherejax import band_geometry as bg
from spherejax import calibrate, evaluate, io, simulate
from tests.helpers import assert_refused, run_cli


def session_at(tmp_path_factory, misregistration):
    instrument = dataclasses.replace(simulate.InstrumentModel(), band_misregistration_px=misregistration)
    return io.write_simulated_session(tmp_path_factory.mktemp(f"at{misregistration}") / "session", seed=9,
                                      instrument=instrument)


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    """The paper's experiment with its bands 2 px out of register (seed 9)."""
    return session_at(tmp_path_factory, 2.0)


@pytest.fixture(scope="module")
def still(tmp_path_factory):
    """The same experiment (seed 9: the same scenes and noise) with its bands in register."""
    return session_at(tmp_path_factory, 0.0)


@pytest.fixture(scope="module")
def calibrated(moved):
    return calibrate.calibrate_session(moved)


@pytest.mark.slow
def test_the_maps_are_recovered_stored_and_reported(moved, calibrated):
    calibration, report = calibrated
    errors = bg.rms_displacement(np.asarray(calibration.band_transforms, np.float64), moved.band_transforms,
                                 moved.image_shape)
    assert np.all(errors < 0.1), errors
    record = report.band_registration
    assert record["frame"] == "targets" and record["reference_band"] == bg.REFERENCE_BAND
    assert record["reference_band_nm"] == 560
    np.testing.assert_allclose(np.asarray(record["band_transforms"]), np.asarray(calibration.band_transforms), rtol=1e-6)
    assert len(record["residual_px"]) == 16 and record["residual_px"][bg.REFERENCE_BAND] == 0
    assert record["largest_displacement_px"] == pytest.approx(2.0, abs=0.1)
    line = calibrate.registration_line(report)
    assert re.match(r"bands: registered from frame 'targets' to 560 nm; largest displacement (1\.9\d|2\.0\d) px, "
                    r"tile residual at most 0\.\d\d px$", line), line
    assert json.loads(json.dumps(report.as_dict()))["band_registration"]["frame"] == "targets"


@pytest.mark.slow
def test_correct_runs_and_registration_removes_the_fringes(moved, still, calibrated):
    """Every test capture (patches on striped backgrounds) corrected through the maps and without
    them, against the same capture of the same experiment in register: at the edges of its
    materials (`evaluate.material_edges` of the in-register Lab), the colour of each pixel's 3 x 3
    neighbourhood (`evaluate.neighbourhood_delta_e`: what a fringe changes, and a sub-pixel blur
    far less) keeps to the in-register one with registration (median ΔE00 under 1) and does not
    without it (measured on seed 0 by benchmarks/bench_registration.py: 0.14 against 4.9)."""
    calibration, _ = calibrated
    reference_calibration, _ = calibrate.calibrate_session(still)
    without = dataclasses.replace(calibration, band_transforms=None)
    edge_errors = {"registered": [], "plain": []}
    for frame in moved.frames_with(role="sample", set="test"):
        reference = sj.correct(still.read(frame.id), reference_calibration)
        near = evaluate.material_edges(np.asarray(reference.lab))
        for name, cal in (("registered", calibration), ("plain", without)):
            result = sj.correct(moved.read(frame.id), cal)
            assert np.mean(np.asarray(result.quality) == 0) > 0.95
            error = evaluate.neighbourhood_delta_e(np.asarray(result.reflectance), np.asarray(reference.reflectance))
            edge_errors[name].append(error[near & np.isfinite(error)])
    registered, plain = (np.median(np.concatenate(edge_errors[k])) for k in ("registered", "plain"))
    assert registered < 1.0 and plain > 3 * registered, (registered, plain)


@pytest.mark.slow
def test_no_registration_stores_no_maps(moved, tmp_path, capsys):
    status, out, _ = run_cli(["calibrate", str(moved.path), "-o", str(tmp_path / "plain.h5"), "--no-registration"], capsys)
    assert status == 0 and "bands: not registered (taken as in register)" in out
    with h5py.File(tmp_path / "plain.h5", "r") as stored:
        assert "band_transforms" not in stored
        assert "band_registration" not in json.loads(stored.attrs["header"])
    assert io.load_calibration(tmp_path / "plain.h5")[0].band_transforms is None
    status, out, _ = run_cli(["calibrate", str(moved.path), "-o", str(tmp_path / "registered.h5")], capsys)
    assert status == 0 and "bands: registered from frame 'targets'" in out
    with h5py.File(tmp_path / "registered.h5", "r") as stored:
        assert stored["band_transforms"].shape == (16, 2, 3)
        header = json.loads(stored.attrs["header"])
    assert header["band_registration"]["frame"] == "targets"
    assert header["metadata"]["calibration_report"]["band_registration"]["reference_band_nm"] == 560


def session_with_registration_frame(moved, folder, pixels_of):
    """A copy of `moved` with a frame of role "registration" whose pixels are `pixels_of(session)`."""
    shutil.copytree(moved.path, folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    targets = next(frame for frame in manifest["frames"] if frame["id"] == "targets")
    io.write_frame(folder / "frames" / "checkerboard.tif", pixels_of(moved))
    manifest["frames"].append({**{k: v for k, v in targets.items() if k != "regions"}, "id": "checkerboard",
                               "role": "registration", "file": "frames/checkerboard.tif"})
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return io.load_session(folder)


def test_a_registration_target_is_used_in_preference_to_the_chart(moved, tmp_path):
    session = session_with_registration_frame(moved, tmp_path / "with-target", lambda s: s.read("targets"))
    assert calibrate.registration_frame(session).id == "checkerboard"
    base = calibrate.base_calibration(session)
    with_maps, record = calibrate.register_session_bands(session, base)
    assert record["frame"] == "checkerboard"
    errors = bg.rms_displacement(np.asarray(with_maps.band_transforms, np.float64), moved.band_transforms,
                                 moved.image_shape)
    assert np.all(errors < 0.1)


def test_a_registration_frame_without_structure_is_refused_in_one_line(moved, tmp_path, capsys):
    session = session_with_registration_frame(moved, tmp_path / "flat", lambda s: s.white())
    status, _, err = run_cli(["calibrate", str(session.path), "-o", str(tmp_path / "cal.h5")], capsys)
    assert_refused(status, err, "manifest.json", "frame 'checkerboard' cannot register the bands",
                   "expected at least 0.01", "--no-registration")
    assert not (tmp_path / "cal.h5").exists()


def test_material_edges_are_the_pixels_beside_a_step_in_lightness():
    lab = np.zeros((5, 6, 3))
    lab[:, 3:, 0] = 50.0  # a step between columns 2 and 3
    lab[0, 0, 0] = 2.0    # less than the 3 of a step: no edge
    lab[4, 5, 0] = np.nan
    edges = evaluate.material_edges(lab)
    expected = np.zeros((5, 6), bool)
    expected[:, 2:4] = True
    np.testing.assert_array_equal(edges, expected)


def test_a_neighbourhoods_colour_is_the_colour_of_its_mean_reflectance():
    """`evaluate.neighbourhood_delta_e`: 0 for the same cube; for two uniform cubes, the ΔE00 of
    their colours everywhere (every 3 x 3 mean is the colour itself); a NaN pixel makes its
    neighbourhoods NaN and no other."""
    first, second = np.full((6, 7, 31), 0.3), np.full((6, 7, 31), 0.3)
    second[..., 15:] = 0.45
    np.testing.assert_array_equal(evaluate.neighbourhood_delta_e(first, first), 0.0)
    expected = float(sj.delta_e_2000(sj.reflectance_to_lab(first[0, 0]), sj.reflectance_to_lab(second[0, 0])))
    np.testing.assert_allclose(evaluate.neighbourhood_delta_e(second, first), expected, rtol=1e-6)
    second[3, 3, 0] = np.nan
    error = evaluate.neighbourhood_delta_e(second, first)
    assert np.isnan(error[2:5, 2:5]).all() and np.isfinite(error).sum() == error.size - 9
