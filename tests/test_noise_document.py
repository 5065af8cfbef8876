"""A NoiseModel's JSON as a declared document (spherejax.noise_document): what the hand-written
`to_json` of earlier releases wrote reads back and is written again byte for byte, every number
reads back as the same float64, strict types and unknown keys are refused in one line naming the
key, the value and what was expected, and the per-band values are checked against the bands by the
rule `NoiseModel.check_bands` applies in memory."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pydantic
import pytest

import spherejax as sj
from spherejax import io, noise_document
from spherejax.io import CalibrationFileError
from spherejax.uncertainty import NoiseModel
from tests.helpers import calibration_entries, write_calibration_entries


def legacy_to_json(model: NoiseModel) -> dict:
    """`NoiseModel.to_json` as written by hand before the document model (spherejax 0.1.0),
    verbatim: the format every calibration file of format version 3 and 4 holds."""
    def value(x):
        return None if x is None else np.asarray(x, np.float64).tolist()

    estimator = model.estimator_covariance
    return {
        "gain_e_per_count": value(model.gain),
        "read_noise_counts": value(model.read_noise),
        "dark_frames": value(model.dark_frames),
        "white_frames": value(model.white_frames),
        "sample_frames": value(model.sample_frames),
        "white_reflectance_u": value(model.white_reflectance_u),
        "coeffs_covariance": value(model.coeffs_covariance),
        "estimator_covariance": None if estimator is None else {
            "gram": value(estimator.gram), "residual": value(estimator.residual),
        },
    }


#: Two documents as the hand-written `to_json` wrote them (json.dumps of its output), from float32
#: models with x64 off: one of scalars, one of two bands with both covariances.
WRITTEN_BEFORE = [
    ('{"gain_e_per_count": 1.899999976158142, "read_noise_counts": 3.200000047683716, "dark_frames": 16.0, '
    '"white_frames": 8.0, "sample_frames": 4.0, "white_reflectance_u": 0.003000000026077032, '
    '"coeffs_covariance": null, "estimator_covariance": null}'),
    ('{"gain_e_per_count": [1.899999976158142, 2.049999952316284], "read_noise_counts": [3.200000047683716, '
    '0.10000000149011612], "dark_frames": 16.0, "white_frames": 8.0, "sample_frames": 1.0, "white_reflectance_u": 0.0, '
    '"coeffs_covariance": [[[9.999999747378752e-05, 0.0, 0.0, 0.0], [0.0, 9.999999747378752e-05, 0.0, 0.0], '
    '[0.0, 0.0, 9.999999747378752e-05, 0.0], [0.0, 0.0, 0.0, 9.999999747378752e-05]], [[0.3333333432674408, '
    '0.3333333432674408, 0.3333333432674408, 0.3333333432674408], [0.3333333432674408, 0.3333333432674408, '
    '0.3333333432674408, 0.3333333432674408], [0.3333333432674408, 0.3333333432674408, 0.3333333432674408, '
    '0.3333333432674408], [0.3333333432674408, 0.3333333432674408, 0.3333333432674408, 0.3333333432674408]]], '
    '"estimator_covariance": {"gram": [[0.5, 0.1, -0.2], [0.1, 0.25, 0.0], [-0.2, 0.0, 0.3333333333333333]], '
    '"residual": [[9.999999747378752e-06, 1.9999999949504854e-06], [1.9999999949504854e-06, 2.9999999242136255e-05]]}}'),
]


def random_model(rng, *, bands=16, per_band=True, covariances=True, dtype=np.float64) -> NoiseModel:
    def values(low, high, shape=()):
        return rng.uniform(low, high, shape).astype(dtype)

    def spd(n):
        a = rng.normal(size=(n, n))
        return (a @ a.T / n).astype(dtype)

    shape = (bands,) if per_band else ()
    return NoiseModel(
        gain=values(0.5, 2.0, shape), read_noise=values(1.0, 8.0, shape),
        dark_frames=16, white_frames=8, sample_frames=3,
        white_reflectance_u=values(0.001, 0.004, shape),
        coeffs_covariance=np.stack([spd(4) * 1e-4 for _ in range(bands)]) if covariances else None,
        estimator_covariance=sj.EstimatorCovariance(gram=spd(bands + 1), residual=spd(31) * 1e-5) if covariances else None,
    )


def valid_document(**changes) -> dict:
    return {**json.loads(WRITTEN_BEFORE[1]), **changes}


# ------------------------------------------------------------------------------- what was written


@pytest.mark.parametrize("text", WRITTEN_BEFORE, ids=["scalars", "two-bands-covariances"])
def test_what_the_hand_written_to_json_wrote_reads_back_and_is_written_again_byte_for_byte(text):
    document = json.loads(text)
    model = NoiseModel.from_json(document)
    assert json.dumps(model.to_json()) == text
    assert np.asarray(model.gain).tolist() == document["gain_e_per_count"]
    assert np.asarray(model.dark_frames).dtype == np.float32 and float(model.dark_frames) == document["dark_frames"]


@pytest.mark.parametrize("per_band", [True, False], ids=["per-band", "scalars"])
@pytest.mark.parametrize("covariances", [True, False], ids=["covariances", "none"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_to_json_writes_what_the_hand_written_one_wrote(per_band, covariances, dtype):
    model = random_model(np.random.default_rng(3), per_band=per_band, covariances=covariances, dtype=dtype)
    written = model.to_json()
    assert written == legacy_to_json(model)
    assert json.dumps(written) == json.dumps(legacy_to_json(model))  # the same keys in the same order
    assert list(written) == list(noise_document.NoiseModelDocument.model_fields)


def test_a_calibration_file_holding_the_hand_written_json_opens_as_written(tmp_path):
    """A calibration file as spherejax wrote it before the document model: its header's
    "noise_model" is the hand-written to_json's output. It opens with the same model, every
    value to the last bit, and a file saved from that model holds the same header JSON."""
    rng = np.random.default_rng(5)
    bands = list(range(400, 701, 20))
    model = random_model(rng, dtype=np.float32)
    patch = np.zeros((6, 5), bool)
    patch[:2, :2] = True
    calibration = sj.Calibration(
        dark=rng.uniform(50, 60, (6, 5, 16)).astype(np.float32), white=rng.uniform(9000, 12000, (6, 5, 16)).astype(np.float32),
        patch=patch, coeffs=rng.normal(size=(16, 4)).astype(np.float32), wiener=rng.normal(size=(31, 16)).astype(np.float32),
        wiener_offset=np.zeros(31, np.float32),
    )
    path = tmp_path / "written-before.h5"
    io.save_calibration(path, calibration, instrument_id="sphere-1", band_centres_nm=bands)
    entries = calibration_entries(path)
    header = json.loads(entries["header"].tobytes())
    header["noise_model"] = legacy_to_json(model)
    arrays = {name: entries[name] for name in io.CALIBRATION_ARRAYS}
    header["checksum"] = io.calibration_hdf5._checksum(header, arrays)
    write_calibration_entries(path, {**entries, "header": np.frombuffer(json.dumps(header).encode(), np.uint8)})

    with io.open_calibration(path) as opened:
        loaded = opened.noise_model
        assert opened.header["noise_model"] == legacy_to_json(model)
    for name in ("gain", "read_noise", "white_reflectance_u", "coeffs_covariance"):
        assert np.asarray(getattr(loaded, name)).astype(np.float32).tobytes() == np.asarray(getattr(model, name)).tobytes(), name
    for name in ("gram", "residual"):
        found = np.asarray(getattr(loaded.estimator_covariance, name)).astype(np.float32)
        assert found.tobytes() == np.asarray(getattr(model.estimator_covariance, name)).tobytes(), name
    again = io.save_calibration(tmp_path / "again.h5", calibration, instrument_id="sphere-1", band_centres_nm=bands,
                                noise_model=loaded)
    assert json.dumps(again["noise_model"]) == json.dumps(legacy_to_json(model))


# --------------------------------------------------------------------------------- the document


def test_every_number_reads_back_as_the_same_float64():
    hard = [0.1 + 0.2, 1 / 3, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, 2.0**-30, 123456789.12345679]
    document = {"gain_e_per_count": hard, "read_noise_counts": [0.0] * len(hard)}
    model = NoiseModel.from_json(json.loads(json.dumps(document)))
    assert np.asarray(model.gain).dtype == np.float64  # x64 on in the tests
    assert np.asarray(model.gain).tolist() == hard
    assert json.loads(json.dumps(model.to_json()))["gain_e_per_count"] == hard


def test_integers_read_as_floats_and_are_written_as_floats():
    model = NoiseModel.from_json({"gain_e_per_count": 2, "read_noise_counts": [3, 4], "dark_frames": 16})
    assert float(model.gain) == 2.0 and np.asarray(model.read_noise).tolist() == [3.0, 4.0]
    written = model.to_json()
    assert written["gain_e_per_count"] == 2.0 and type(written["gain_e_per_count"]) is float
    assert written["dark_frames"] == 16.0 and type(written["dark_frames"]) is float


def test_absent_keys_take_the_defaults():
    model = NoiseModel.from_json({"gain_e_per_count": 2.0, "read_noise_counts": 3.0})
    assert (float(model.dark_frames), float(model.white_frames), float(model.sample_frames)) == (1.0, 1.0, 1.0)
    assert float(model.white_reflectance_u) == 0.0
    assert model.coeffs_covariance is None and model.estimator_covariance is None


def test_the_document_is_frozen_and_its_arrays_read_only():
    checked = noise_document.check(valid_document())
    assert isinstance(checked.coeffs_covariance, np.ndarray) and checked.coeffs_covariance.shape == (2, 4, 4)
    with pytest.raises(ValueError, match="read-only"):
        checked.gain_e_per_count[0] = 1.0
    with pytest.raises(pydantic.ValidationError):
        checked.gain_e_per_count = np.ones(2)
    assert checked.model_dump() == valid_document()


#: (the change to a valid two-band document, a fragment of the one-line message): each message
#: names the key, the value found (repr) and what was expected.
REFUSED = [
    ("bool", {"gain_e_per_count": True}, "gain_e_per_count is True, expected numbers > 0"),
    ("text-number", {"read_noise_counts": "3.2"}, "read_noise_counts is '3.2', expected numbers >= 0"),
    ("null-frames", {"dark_frames": None}, "dark_frames is None, expected a number >= 1"),
    ("nan", {"gain_e_per_count": [1.0, float("nan")]}, "gain_e_per_count expected finite numbers; got [1.0, nan]"),
    ("minus-inf", {"white_reflectance_u": float("-inf")}, "white_reflectance_u expected finite numbers; got -inf"),
    ("huge-integer", {"sample_frames": 10**400}, "sample_frames expected finite numbers; got an int too large for a float64 (401 digits)"),
    ("zero-gain", {"gain_e_per_count": [0.0, 1.0]}, "gain_e_per_count expected numbers > 0: the camera gain in electrons per count, one or one per band; got [0.0, 1.0]"),
    ("negative-u", {"white_reflectance_u": -0.001}, "white_reflectance_u expected numbers >= 0"),
    ("fractional-frames", {"white_frames": 0.5}, "white_frames expected a number >= 1: the frames averaged in the calibration's white-standard frame; got 0.5"),
    ("empty-list", {"gain_e_per_count": []}, "gain_e_per_count expected numbers > 0"),
    ("ragged-coefficients", {"coeffs_covariance": [[[0.0] * 4] * 3 + [[0.0] * 3]] * 2}, "coeffs_covariance expected shape (B, 4, 4)"),
    ("ragged-gram", {"estimator_covariance": {"gram": [[1.0], [1.0, 2.0]], "residual": [[1.0]]}},
     "estimator_covariance.gram expected a square matrix of numbers"),
    ("estimator-text", {"estimator_covariance": "none"}, "estimator_covariance expected an object with 'gram' and 'residual'"),
    ("estimator-key", {"estimator_covariance": {"gram": [[1.0]], "residual": [[1.0]], "mean": [0.0]}},
     "unknown key 'estimator_covariance.mean'; expected some of ['gram', 'residual']"),
    ("estimator-missing", {"estimator_covariance": {"gram": [[1.0]]}}, "missing 'estimator_covariance.residual', expected a square matrix"),
]


@pytest.mark.parametrize(("change", "fragment"), [case[1:] for case in REFUSED], ids=[case[0] for case in REFUSED])
def test_refusals_are_one_line_naming_key_value_and_expectation(change, fragment):
    with pytest.raises(ValueError) as caught:
        NoiseModel.from_json(valid_document(**change))
    message = str(caught.value)
    assert message.startswith("noise model: ") and "\n" not in message and fragment in message, message
    assert len(message) < 300


def test_unknown_keys_come_before_missing_ones():
    with pytest.raises(ValueError, match=r"^noise model: unknown key 'gian'; expected some of \['coeffs_covariance'"):
        NoiseModel.from_json({"gian": 2.0, "read_noise_counts": 1.0})


def test_a_long_value_is_shown_cut_short():
    with pytest.raises(ValueError) as caught:
        NoiseModel.from_json(valid_document(read_noise_counts=["x"] * 10_000))
    assert "read_noise_counts is ['x', 'x', 'x', 'x', 'x', 'x', ...], expected" in str(caught.value)


# ------------------------------------------------------------------------------------- the bands


@pytest.mark.parametrize(("change", "fragment"), [
    ({"gain_e_per_count": [1.0, 2.0, 3.0]}, "gain has 3 values in gain_e_per_count, expected one or 2 (one per band)"),
    ({"read_noise_counts": [1.0]}, "read_noise has 1 values in read_noise_counts, expected one or 2 (one per band)"),
    ({"white_reflectance_u": [0.0, 0.0, 0.0]}, "white_reflectance_u has 3 values, expected one or 2 (one per band)"),
    ({"coeffs_covariance": [[[0.0] * 4] * 4] * 3}, "coeffs_covariance has shape (3, 4, 4), expected (2, 4, 4)"),
    ({"estimator_covariance": {"gram": [[1.0]], "residual": [[1.0]]}}, "estimator_covariance.gram has shape (1, 1), expected (3, 3)"),
])
def test_per_band_values_are_checked_against_the_bands_where_known(change, fragment):
    document = valid_document(**change)
    NoiseModel.from_json(document)  # no bands given: any number of bands, all alike
    with pytest.raises(ValueError) as caught:
        NoiseModel.from_json(document, bands=2)
    assert str(caught.value) == f"noise model: {fragment}"
    assert NoiseModel.from_json(valid_document(), bands=2).gain.shape == (2,)


def test_the_document_and_check_bands_apply_one_rule():
    model = NoiseModel(gain=[1.0, 2.0, 3.0], read_noise=1.0)
    with pytest.raises(ValueError, match=r"^NoiseModel: gain has 3 values, expected one or 2 \(one per band\)$"):
        model.check_bands(2)
    with pytest.raises(ValueError, match=r"^noise model: gain has 3 values in gain_e_per_count, expected one or 2"):
        NoiseModel.from_json(model.to_json(), bands=2)
    model.check_bands(3)
    NoiseModel.from_json(model.to_json(), bands=3)


def test_a_calibration_file_names_the_file_and_the_key(tmp_path):
    rng = np.random.default_rng(1)
    bands = list(range(400, 701, 20))
    calibration = sj.Calibration(
        dark=np.full((4, 4, 16), 50, np.float32), white=np.full((4, 4, 16), 9000, np.float32),
        patch=np.ones((4, 4), bool), coeffs=rng.normal(size=(16, 4)).astype(np.float32),
        wiener=rng.normal(size=(31, 16)).astype(np.float32),
    )
    path = tmp_path / "cal.h5"
    with pytest.raises(CalibrationFileError) as caught:
        io.save_calibration(path, calibration, instrument_id="sphere-1", band_centres_nm=bands,
                            noise_model=NoiseModel(gain=np.ones(15), read_noise=1.0))
    assert str(caught.value).startswith(
        f"{path}: header.noise_model is not valid: noise model: gain has 15 values in gain_e_per_count, expected one or 16"
    )
    assert not path.exists()


# ---------------------------------------------------------------------------------- the writing


def test_to_json_refuses_a_model_no_document_can_hold():
    model = NoiseModel(gain=1.0, read_noise=1.0,
                       estimator_covariance=sj.EstimatorCovariance(gram=np.ones((3, 2)), residual=np.eye(31)))
    with pytest.raises(ValueError, match=r"^noise model: estimator_covariance\.gram expected a square matrix"):
        model.to_json()


def test_import_spherejax_does_not_import_pydantic():
    """The document module loads when a model is first read or written, not with spherejax."""
    code = ("import sys, spherejax; assert 'pydantic' not in sys.modules, 'pydantic imported'; "
            "spherejax.NoiseModel.from_json({'gain_e_per_count': 1.0, 'read_noise_counts': 1.0}); "
            "assert 'spherejax.noise_document' in sys.modules")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180,
                            env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert result.returncode == 0, result.stderr
