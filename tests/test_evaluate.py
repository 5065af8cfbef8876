"""spherejax.evaluate on its own: the consistency figures of Tables 1 and 3-6 for given stage data,
checked against numpy and colour-science written out from their definitions (the module
docstring of spherejax.consistency), and the tables as text, CSV and JSON read back by Python's
own csv and json modules. (The whole simulated experiment, evaluated end to end against the
paper's findings, is tests/test_experiment.py.)"""

import csv
import io as text_io
import itertools
import json
import warnings

import colour
import numpy as np
import pytest

from spherejax import evaluate, spectra
from spherejax.evaluate import ILLUMINANTS, STAGES, Evaluation, StageData

BANDS = list(range(400, 701, 20))
WAVELENGTHS = np.arange(400, 701, 10)


def stage_data(rng, patches=3, backgrounds=4, missing=((0, 3),)):
    """Responses (P, J, 16) and measured reflectances (P, J, 31) around known spectra, NaN where a
    patch was not measured on a background (`missing`), and the truth (P, 31)."""
    truth = np.stack([np.clip(spectrum, 0.02, 0.98) for spectrum in spectra.all_reflectances()[::40][:patches]])
    responses = rng.uniform(0.2, 0.8, (patches, 1, 16)) + rng.normal(0, 0.01, (patches, backgrounds, 16))
    reflectance = np.clip(truth[:, None] + rng.normal(0, 0.01, (patches, backgrounds, 31)), 0.0, 1.0)
    for p, j in missing:
        responses[p, j] = np.nan
        reflectance[p, j] = np.nan
    data = {stage: responses for stage in STAGES}
    return StageData([f"patch{k}" for k in range(patches)], [f"bg{k}" for k in range(backgrounds)],
                     data, {stage: reflectance for stage in STAGES}, truth)


def lab_colour(reflectance, illuminant):
    """CIELAB of a 400..700 nm step 10 reflectance through colour-science (ASTM E308, CIE 1931 2°,
    the perfect diffuser under the illuminant as white), as tests/test_colorimetry.py calls it."""
    def xyz(values):
        distribution = colour.SpectralDistribution(values, WAVELENGTHS.astype(float))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # colour's "Trimming ..." notice for a 400-700 nm input
            return colour.sd_to_XYZ(distribution, colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"],
                                    colour.SDS_ILLUMINANTS[{"F2": "FL2"}.get(illuminant, illuminant)], method="ASTM E308")

    return colour.XYZ_to_Lab(xyz(reflectance) / 100.0, colour.XYZ_to_xy(xyz(np.ones(31)) / 100.0))


def test_consistency_metrics_are_their_definitions(rng=np.random.default_rng(3)):
    data = stage_data(rng)
    metrics = evaluate.consistency_metrics(data, "stage2")
    responses, reflectance = data.responses["stage2"], data.reflectance["stage2"]
    present = np.all(np.isfinite(reflectance), axis=-1)

    # Tables 1/3: per band, the mean over patches of the population std over the backgrounds present.
    std = np.mean([np.std(responses[p][present[p]], axis=0) for p in range(len(responses))], axis=0)
    np.testing.assert_allclose(metrics["response_std_per_band"], std, rtol=1e-10, atol=1e-13)
    assert metrics["response_std"] == pytest.approx(np.mean(std), rel=1e-10)

    # Tables 4/5: per patch the mean over pairs of present backgrounds, then the mean over patches.
    def pairwise(difference):
        per_patch = []
        for p in range(len(reflectance)):
            pairs = [(j, k) for j, k in itertools.combinations(range(reflectance.shape[1]), 2) if present[p, j] and present[p, k]]
            per_patch.append(np.mean([difference(reflectance[p, j], reflectance[p, k]) for j, k in pairs]))
        return np.mean(per_patch)

    rms = pairwise(lambda a, b: np.sqrt(np.mean((a - b) ** 2)))
    assert metrics["spectral_rms"] == pytest.approx(rms, rel=1e-10)
    for illuminant in ILLUMINANTS:
        de = pairwise(lambda a, b: colour.delta_E(lab_colour(a, illuminant), lab_colour(b, illuminant), method="CIE 2000"))
        assert metrics[f"delta_e00_{illuminant}"] == pytest.approx(de, rel=1e-9), illuminant

    # Accuracy against the known spectra, under D65, over the measured entries only.
    accuracy = np.mean([colour.delta_E(lab_colour(reflectance[p, j], "D65"), lab_colour(data.truth[p], "D65"), method="CIE 2000")
                        for p in range(len(reflectance)) for j in range(reflectance.shape[1]) if present[p, j]])
    assert metrics["accuracy_delta_e00_D65"] == pytest.approx(accuracy, rel=1e-9)


def test_identical_backgrounds_give_zero_and_unknown_truth_gives_no_accuracy():
    data = stage_data(np.random.default_rng(4), missing=())
    data.responses["original"] = np.broadcast_to(data.responses["original"][:, :1], data.responses["original"].shape).copy()
    data.reflectance["original"] = np.broadcast_to(data.reflectance["original"][:, :1], data.reflectance["original"].shape).copy()
    metrics = evaluate.consistency_metrics(data, "original")
    assert metrics["response_std"] == 0.0 and metrics["spectral_rms"] == 0.0
    assert all(metrics[f"delta_e00_{illuminant}"] == 0.0 for illuminant in ILLUMINANTS)
    data.truth[1] = np.nan  # a patch of unknown reflectance: no accuracy figure at all
    assert "accuracy_delta_e00_D65" not in evaluate.consistency_metrics(data, "original")


def an_evaluation(with_test_set=True) -> Evaluation:
    rng = np.random.default_rng(5)
    sets = {"training": stage_data(rng)}
    if with_test_set:
        sets["test"] = stage_data(rng, missing=())
    metrics = {name: {stage: evaluate.consistency_metrics(data, stage) for stage in STAGES} for name, data in sets.items()}
    return Evaluation(BANDS, [0.5] * 16, sets, metrics)


def test_tables_read_back_through_csv_and_json():
    evaluation = an_evaluation()
    tables = evaluate.tables(evaluation)
    assert list(tables) == ["table1", "table3", "table4", "table5", "table6"]
    for name, text in evaluate.tables_csv(evaluation).items():
        _, header, rows = tables[name]
        assert list(csv.reader(text_io.StringIO(text))) == [header, *rows], name
    header, rows = tables["table1"][1:]
    assert header == ["", *[f"{b} nm" for b in BANDS], "Average"]
    original = evaluation.metrics["training"]["original"]
    assert rows[0] == ["Original", *[f"{x:.4f}" for x in original["response_std_per_band"]], f"{original['response_std']:.4f}"]
    assert [row[0] for row in tables["table6"][2]] == ["Original", "Markov model", "Ours (Stage II)"]

    document = json.loads(evaluate.to_json(evaluation))
    assert document["band_centres_nm"] == BANDS and document["markov_kappa"] == [0.5] * 16
    assert document["metrics"] == json.loads(json.dumps(evaluation.metrics))


def test_a_session_without_test_captures_gets_the_training_tables_only():
    assert list(evaluate.tables(an_evaluation(with_test_set=False))) == ["table1", "table4"]


def test_text_tables_are_aligned():
    text = evaluate.format_table(["", "a", "longer"], [["Stage II", "1.0", "2"], ["x", "10.25", "3.5"]])
    lines = text.splitlines()
    assert len({len(line) for line in lines}) == 1  # every line as wide
    assert lines[1] == "--------  -----  ------"
    assert lines[2].startswith("Stage II") and lines[3].startswith("x       ")  # first column left
    assert lines[3].endswith("10.25     3.5")  # the others right-aligned
