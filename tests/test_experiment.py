"""The paper's findings on a small seeded simulated session: calibrate and evaluate.

Zou et al. (2019), Section 5: the response standard deviation falls from original to Stage I to
Stage II in every band (Tables 1, 3); reflectance consistency improves likewise (Tables 4, 5);
Stage II beats the Markov model on every metric (Table 6); the unseen test set improves too.
On a purely Lambertian sphere (no glare, no non-Lambertian coupling, no fluorescence) Stage I
alone removes the background effect (Section 3).
"""

import csv
import dataclasses
import io as text_io
import json

import numpy as np
import pytest

from spherejax import calibrate, evaluate, io, simulate

SMALL = simulate.ExperimentDesign(training_backgrounds=5, test_backgrounds=3, targets=64)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return io.write_simulated_session(tmp_path_factory.mktemp("sim") / "session", seed=1, design=SMALL)


@pytest.fixture(scope="module")
def calibrated(session):
    return calibrate.calibrate_session(session)


@pytest.fixture(scope="module")
def evaluation(session, calibrated):
    return evaluate.evaluate_session(session, calibrated[0])


def test_calibration(session, calibrated):
    calibration, report = calibrated
    assert report.reference_background in {f.background for f in session.frames_with(role="sample", set="training")}
    assert report.training_patches == 9 and report.training_backgrounds == 5
    assert report.training_samples == 45 and report.targets == 64
    assert not report.unconverged_bands and set(report.stage2_status) == {"converged"}
    assert sum(report.stage2_dropped_samples) == 0
    assert np.isfinite(np.asarray(calibration.coeffs)).all() and calibration.wiener.shape == (31, 16)
    # Stage II is a correction near Stage I: c1 near 1, the rest small (cf. the paper's Table 2).
    coeffs = np.asarray(calibration.coeffs)
    assert np.all(np.abs(coeffs[:, 0] - 1.0) < 0.3)


def test_training_response_std_falls_in_every_band(evaluation):
    """Table 1: original > Stage I > Stage II in each of the 16 bands."""
    m = evaluation.metrics["training"]
    original, stage1, stage2 = (np.asarray(m[s]["response_std_per_band"]) for s in ("original", "stage1", "stage2"))
    assert np.all(stage1 < original), (original, stage1)
    assert np.all(stage2 < stage1), (stage1, stage2)


def test_test_set_response_std_improves(evaluation):
    """Table 3, unseen patches on unseen patterned backgrounds: Stage I beats the original and
    Stage II beats Stage I, on average and in most bands.

    Not in every band for every seed. On the simulator what Stage I leaves is almost all glare
    (measured: with glare alone Stage I leaves a training response std. of 0.0020, with the
    non-Lambertian coupling or the fluorescence alone 0.0001). Stage II models glare through p,
    i.e. through the holder's mean reflectance, but on a patterned background a patch's glare
    also depends on the stripe it lies on, which p does not see. Where Stage I's residual is
    already small (at 400-420 nm the test backgrounds reflect little and glare is weak) that
    mismatch can be as large as what is left (seed 1 of the default design: 400 nm). The paper
    warns that the phenomenological model may not carry over to conditions unlike its training
    data (Section 4). Stage I too: at 400-440 nm three patterned backgrounds that reflect little
    there change the sphere's light less than the stripe beneath changes a 0.5 cm patch's glare
    (seed 1 of this design: 420 nm, 0.0015 original against 0.0021 Stage I).
    """
    m = evaluation.metrics["test"]
    original, stage1, stage2 = (np.asarray(m[s]["response_std_per_band"]) for s in ("original", "stage1", "stage2"))
    assert np.sum(stage1 < original) >= 14, (original, stage1)
    assert m["stage2"]["response_std"] < m["stage1"]["response_std"] < m["original"]["response_std"]
    assert np.sum(stage2 < stage1) >= 12, (stage1, stage2)


@pytest.mark.parametrize("set_name", ["training", "test"])
def test_reflectance_consistency_improves(evaluation, set_name):
    m = evaluation.metrics[set_name]
    for key in ("spectral_rms", "delta_e00_D65", "delta_e00_A", "delta_e00_F2"):
        assert m["stage2"][key] < m["stage1"][key] < m["original"][key], key


def test_stage2_beats_the_markov_model_on_every_table_6_metric(evaluation):
    m = evaluation.metrics["test"]
    for key in ("response_std", "spectral_rms", "delta_e00_D65", "delta_e00_A", "delta_e00_F2"):
        assert m["stage2"][key] < m["markov"][key] < m["original"][key], key


def test_tables_text_csv_json(evaluation):
    text = evaluate.format_tables(evaluation)
    for title in ("Table 1.", "Table 3.", "Table 4.", "Table 5.", "Table 6."):
        assert title in text
    tables = evaluate.tables_csv(evaluation)
    rows = list(csv.reader(text_io.StringIO(tables["table1"])))
    assert rows[0][1:] == [f"{b} nm" for b in range(400, 701, 20)] + ["Average"]
    assert [r[0] for r in rows[1:]] == ["Original", "Stage I", "Stage II"]
    table6 = list(csv.reader(text_io.StringIO(tables["table6"])))
    assert float(table6[3][1]) == pytest.approx(evaluation.metrics["test"]["stage2"]["response_std"], abs=5e-5)
    payload = json.loads(evaluate.to_json(evaluation))
    assert payload["band_centres_nm"][0] == 400 and len(payload["markov_kappa"]) == 16


def test_lambertian_sphere_stage1_alone_removes_the_background_effect(tmp_path):
    """With glare, non-Lambertian coupling and fluorescence off (and no noise, so that what is
    left is the 14-bit quantisation), Stage I responses agree across backgrounds to 1e-4 while
    the original ones differ by tenths of a percent and more."""
    instrument = dataclasses.replace(simulate.InstrumentModel().lambertian(), noise=False)
    session = io.write_simulated_session(tmp_path / "lambertian", seed=2, instrument=instrument, design=SMALL)
    calibration, _ = calibrate.calibrate_session(session)
    m = evaluate.evaluate_session(session, calibration).metrics
    for set_name in ("training", "test"):
        assert max(m[set_name]["stage1"]["response_std_per_band"]) < 1e-4
        assert m[set_name]["original"]["response_std"] > 2e-3
        assert m[set_name]["stage1"]["delta_e00_D65"] < 0.02
