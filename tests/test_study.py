"""The differentiable calibration study (`spherejax study`)."""

import json

import numpy as np
import pytest

from spherejax import calibrate, cli, evaluate, io, simulate, study

SMALL = simulate.ExperimentDesign(training_backgrounds=4, test_backgrounds=2, targets=36)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return io.write_simulated_session(tmp_path_factory.mktemp("study") / "session", seed=4, design=SMALL)


@pytest.fixture(scope="module")
def closed_form(session):
    return calibrate.calibrate_session(session)[0]


@pytest.fixture(scope="module")
def closed_form_evaluation(session, closed_form):
    """The closed form's evaluation, which two tests compare a study with (made once: it is the
    same for both, and a whole evaluate of the session). Read-only."""
    return evaluate.evaluate_session(session, closed_form)


@pytest.mark.slow
def test_study_lowers_its_training_objective_from_the_closed_form(session, closed_form, closed_form_evaluation):
    result = study.study_session(session, closed_form, response_weight=0.0, max_steps=300)
    assert result.objective_end < 0.9 * result.objective_start
    assert np.isfinite(np.asarray(result.calibration.coeffs)).all()
    np.testing.assert_array_equal(np.asarray(result.calibration.wiener), np.asarray(closed_form.wiener))
    # Without fit_wiener the estimator's offset r0 is held too.
    np.testing.assert_array_equal(np.asarray(result.calibration.wiener_offset), np.asarray(closed_form.wiener_offset))
    # The training patches' colours really are more consistent with their reference colours.
    before = closed_form_evaluation.metrics["training"]["stage2"]["delta_e00_D65"]
    after = evaluate.evaluate_session(session, result.calibration).metrics["training"]["stage2"]["delta_e00_D65"]
    assert after < before


@pytest.mark.slow
def test_study_with_the_wiener_matrix(session, closed_form):
    result = study.study_session(session, closed_form, fit_wiener=True, max_steps=30)
    assert result.objective_end < result.objective_start
    assert not np.array_equal(np.asarray(result.calibration.wiener), np.asarray(closed_form.wiener))
    # The offset r0 is optimised with W: one affine estimator (study module docstring).
    offset = np.asarray(result.calibration.wiener_offset)
    assert offset.shape == (31,) and np.isfinite(offset).all()
    assert not np.array_equal(offset, np.asarray(closed_form.wiener_offset))


@pytest.mark.slow
def test_comparison_table_and_verdict(session, closed_form, closed_form_evaluation):
    result = study.study_session(session, closed_form, max_steps=20)
    closed = closed_form_evaluation
    studied = evaluate.evaluate_session(session, result.calibration)
    header, rows = study.comparison(closed, studied)
    assert header[1:4] == ["Response std. dev.", "Spectral rms", "ΔE00 (D65)"]
    assert [r[0] for r in rows] == ["Original", "Markov model", "Stage II, closed form (Eq. 22)", "Stage II, study (ΔE00)"]
    assert float(rows[2][3]) == pytest.approx(closed.metrics["test"]["stage2"]["delta_e00_D65"], abs=5e-5)
    assert study.verdict(closed, studied).startswith("On the held-out test set the study")


def test_command(session, tmp_path, capsys):
    out = tmp_path / "study"
    assert cli.main(["study", str(session.path), "--out", str(out), "--max-steps", "20"]) == 0
    stdout = capsys.readouterr().out
    assert "Stage II, study (ΔE00)" in stdout and "held-out test set" in stdout
    payload = json.loads((out / "study.json").read_text())
    assert payload["response_weight"] == 0.01 and set(payload["study"]) == {"training", "test"}
    assert (out / "study-calibration.h5").exists() and (out / "study.csv").exists()
    # study.csv through the csv module: the row labels with commas stay one field (pandas failed:
    # "Expected 7 fields in line 4, saw 8")
    import pandas

    table = pandas.read_csv(out / "study.csv")
    assert list(table.iloc[:, 0]) == ["Original", "Markov model", "Stage II, closed form (Eq. 22)", "Stage II, study (ΔE00)"]
    import csv

    with open(out / "study.csv", newline="") as handle:
        lines = list(csv.reader(handle))
    assert len(lines) == 5 and {len(line) for line in lines} == {table.shape[1]}
    assert table["ΔE00 (D65)"].dtype.kind == "f" and table["ΔE00 (D65)"].notna().all()


def test_negative_response_weight(session, tmp_path, capsys):
    status = cli.main(["study", str(session.path), "--out", str(tmp_path / "s"), "--response-weight", "-1"])
    err = capsys.readouterr().err
    assert status == 2 and "--response-weight: expected a value 0..1e6, got -1" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "s").exists()


def test_non_positive_max_steps(session, tmp_path, capsys):
    status = cli.main(["study", str(session.path), "--out", str(tmp_path / "s"), "--max-steps", "0"])
    err = capsys.readouterr().err
    assert status == 2 and "--max-steps: expected a positive number of BFGS iterations, at most 100000, got 0" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "s").exists()
