"""Noise models in calibration files (format version 3 on): written, read back bit for bit, older
versions still read, tampering and malformed models refused in one line; and the noise model
calibration builds from what a session records (`calibrate_session`, `spherejax calibrate`)."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import shutil

import numpy as np
import pytest

import spherejax as sj
from spherejax import calibrate, cli, io, simulate
from spherejax.io import CalibrationFileError
from spherejax.uncertainty import NoiseModel
from spherejax.wiener_estimation import EstimatorCovariance
from tests.helpers import calibration_entries, write_calibration_entries

H, W = 12, 10
BANDS = list(range(400, 701, 20))
B = len(BANDS)
ARRAYS_V1 = ("dark", "white", "patch", "coeffs", "wiener")
ARRAYS_V2 = (*ARRAYS_V1, "wiener_offset")
#: Format version 5 added the estimator's kernel residual (four arrays, m = 0 for an affine one).
RESIDUAL = ("wiener_residual_centre", "wiener_residual_whitening", "wiener_residual_inducing", "wiener_residual_weights")
ARRAYS_V5 = (*ARRAYS_V2, *RESIDUAL)


# --------------------------------------------------------------------------------------- helpers


@contextlib.contextmanager
def refused(path, match):
    """A CalibrationFileError whose message is one line, starts with `path`, matches `match`
    and says what was expected."""
    with pytest.raises(CalibrationFileError, match=match) as info:
        yield info
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{path}: ") and "(expected " in message, message


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def make_calibration(rng) -> sj.Calibration:
    patch = np.zeros((H, W), dtype=bool)
    patch[0:2, 8:10] = True
    return sj.Calibration(
        dark=rng.uniform(50, 60, (H, W, B)).astype(np.float32),
        white=rng.uniform(9000, 12000, (H, W, B)).astype(np.float32),
        patch=patch, coeffs=rng.normal(size=(B, 4)).astype(np.float32),
        wiener=rng.normal(size=(31, B)).astype(np.float32),
        wiener_offset=rng.normal(scale=0.05, size=31).astype(np.float32),
    )


def make_noise_model(rng, *, per_band=False, covariances=True, dtype=np.float32) -> NoiseModel:
    """A noise model with values that need every digit of `dtype` (frames: float32, as
    NoiseModel keeps them)."""
    def band_or_number(low, high):
        return rng.uniform(low, high, B).astype(dtype) if per_band else dtype(rng.uniform(low, high))

    def spd(n):
        a = rng.normal(size=(n, n))
        return a @ a.T / n

    return NoiseModel(
        gain=band_or_number(0.5, 2.0), read_noise=band_or_number(3.0, 8.0),
        dark_frames=np.float32(16), white_frames=np.float32(8), sample_frames=np.float32(4),
        white_reflectance_u=band_or_number(0.001, 0.004),
        coeffs_covariance=np.stack([spd(4) * 1e-4 for _ in range(B)]).astype(dtype) if covariances else None,
        estimator_covariance=EstimatorCovariance(
            gram=spd(B + 1).astype(dtype), residual=(spd(31) * 1e-5).astype(dtype),
        ) if covariances else None,
    )


def leaves(model: NoiseModel) -> dict[str, np.ndarray | None]:
    estimator = model.estimator_covariance
    out = {name: getattr(model, name) for name in (
        "gain", "read_noise", "dark_frames", "white_frames", "sample_frames", "white_reflectance_u", "coeffs_covariance",
    )}
    out["estimator.gram"] = None if estimator is None else estimator.gram
    out["estimator.residual"] = None if estimator is None else estimator.residual
    return {name: None if value is None else np.asarray(value) for name, value in out.items()}


def assert_same_model(loaded: NoiseModel, original: NoiseModel) -> None:
    """Every field of the same shape and the same value to the last bit: as the original's
    dtype, the loaded bytes are the original bytes (`NoiseModel.from_json` may hold a float32
    model's numbers as float64, exactly), and the JSON of both is the same."""
    expected, found = leaves(original), leaves(loaded)
    for name, value in expected.items():
        if value is None:
            assert found[name] is None, name
            continue
        assert found[name].shape == value.shape, name
        assert np.array_equal(found[name].astype(np.float64), value.astype(np.float64)), name
        assert found[name].astype(value.dtype).tobytes() == value.tobytes(), name
    assert loaded.to_json() == original.to_json()


def save(path, rng, noise_model=None) -> dict:
    return io.save_calibration(
        path, make_calibration(rng), instrument_id="sim-sphere-1", band_centres_nm=BANDS, noise_model=noise_model,
    )


def header_of(entries) -> dict:
    return json.loads(entries["header"].tobytes().decode("utf-8"))


def written_checksum(header: dict, entries: dict, names) -> str:
    """The checksum as the io module docstring specifies it, written out here (not taken from
    io) so that a change of the checksum shows: SHA-256 of the canonical header JSON without the
    checksum, then per array the line "<name> <dtype.str> <shape>\\n" and its bytes."""
    digest = hashlib.sha256(json.dumps(
        {k: v for k, v in header.items() if k != "checksum"},
        sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False,
    ).encode("utf-8"))
    for name in names:
        array = entries[name]
        digest.update(f"{name} {array.dtype.str} {json.dumps(list(array.shape))}\n".encode("ascii"))
        digest.update(np.ascontiguousarray(array).tobytes())
    return "sha256:" + digest.hexdigest()


def rewrite(path, entries, header, *, names=None, checksum=True) -> dict:
    """Write `entries` back with `header` (its checksum recomputed unless `checksum` is False):
    HDF5, or an .npz as the writers of format versions 1 to 3 wrote (`write_calibration_entries`);
    for a header of format version 4 or older without the kernel residual's arrays, which came in
    version 5, as those writers wrote. `names`: the arrays the checksum covers (default: the
    header's version's)."""
    header = dict(header)
    if header["format_version"] < 5:
        entries = {k: v for k, v in entries.items() if k not in RESIDUAL}
        header["arrays"] = {k: v for k, v in header["arrays"].items() if k not in RESIDUAL}
    if names is None:
        names = ARRAYS_V5 if header["format_version"] >= 5 else ARRAYS_V2
    if checksum:
        header["checksum"] = written_checksum(header, entries, names)
    entries = {**entries, "header": np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)}
    write_calibration_entries(path, entries)
    return header


def write_older(path, rng, version: int, noise_model="absent") -> dict:
    """A calibration file as the format `version` (1 or 2) writer wrote it, an .npz: no
    "noise_model" (or the given value), version 1 also without wiener_offset. Returns the header."""
    save(path, rng)
    entries = calibration_entries(path)
    header = {k: v for k, v in header_of(entries).items() if k not in ("checksum", "noise_model")}
    header["format_version"] = version
    if noise_model != "absent":
        header["noise_model"] = noise_model
    names = ARRAYS_V2
    if version == 1:
        del entries["wiener_offset"]
        header["arrays"] = {k: v for k, v in header["arrays"].items() if k != "wiener_offset"}
        names = ARRAYS_V1
    return rewrite(path, entries, header, names=names)


# ------------------------------------------------------------------------------ the file format


@pytest.mark.parametrize("per_band", [False, True], ids=["scalar", "per-band"])
def test_noise_model_round_trips_bit_for_bit(tmp_path, rng, per_band, dtype):
    model = make_noise_model(rng, per_band=per_band, dtype=dtype)
    path = tmp_path / "cal.h5"
    written = save(path, rng, model)
    assert written["format_version"] == 7 and written["noise_model"] == model.to_json()

    calibration, header = io.load_calibration(path, band_centres_nm=BANDS)
    assert header == written and header["noise_model"] == model.to_json()
    assert_same_model(NoiseModel.from_json(header["noise_model"]), model)
    with io.open_calibration(path) as opened:
        assert_same_model(opened.noise_model, model)
    # What h5py alone reads: the header's JSON, the model inside it.
    assert header_of(calibration_entries(path))["noise_model"] == model.to_json()
    # Large files (read by rows) carry it too.
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)
        with io.open_calibration(path) as opened:
            assert_same_model(opened.noise_model, model)


def test_noise_model_without_covariances_round_trips(tmp_path, rng):
    model = make_noise_model(rng, covariances=False)
    path = tmp_path / "cal.h5"
    save(path, rng, model)
    with io.open_calibration(path) as opened:
        assert_same_model(opened.noise_model, model)
        assert opened.noise_model.coeffs_covariance is None and opened.noise_model.estimator_covariance is None
    assert io.load_calibration(path)[1]["noise_model"]["estimator_covariance"] is None


def test_no_noise_model_is_stored_as_null(tmp_path, rng):
    path = tmp_path / "cal.h5"
    assert save(path, rng)["noise_model"] is None
    with io.open_calibration(path) as opened:
        assert opened.noise_model is None and opened.header["noise_model"] is None


def test_header_with_a_noise_model_stays_small(tmp_path, rng):
    path = tmp_path / "cal.h5"
    save(path, rng, make_noise_model(rng, per_band=True))
    size = calibration_entries(path)["header"].nbytes
    assert size < 100_000 and size * 100 < io.calibration_files._MAX_HEADER_BYTES


@pytest.mark.parametrize("version", [1, 2])
def test_older_versions_open_without_a_noise_model(tmp_path, rng, version):
    path = tmp_path / f"v{version}.npz"
    written = write_older(path, rng, version)
    calibration, header = io.load_calibration(path, band_centres_nm=BANDS)
    assert header == written and header["format_version"] == version and "noise_model" not in header
    with io.open_calibration(path) as opened:
        assert opened.noise_model is None
    assert calibration.wiener_offset.shape == (31,)


@pytest.mark.parametrize("version", [1, 2])
def test_older_versions_with_a_null_noise_model_open(tmp_path, rng, version):
    path = tmp_path / f"v{version}.npz"
    write_older(path, rng, version, noise_model=None)
    with io.open_calibration(path) as opened:
        assert opened.noise_model is None


def test_version_3_npz_opens_with_its_noise_model(tmp_path, rng):
    """Format version 3, the last .npz, added the noise model: it reads back as written."""
    model = make_noise_model(rng)
    path = tmp_path / "v3.npz"
    save(path, rng, model)
    entries = calibration_entries(path)
    header = rewrite(path, entries, {**header_of(entries), "format_version": 3})
    assert path.read_bytes()[:4] == b"PK\x03\x04"
    with io.open_calibration(path) as opened:
        assert opened.header == header and opened.header["format_version"] == 3
        assert_same_model(opened.noise_model, model)


def test_older_version_holding_a_noise_model_is_refused(tmp_path, rng):
    path = tmp_path / "v2.npz"
    write_older(path, rng, 2, noise_model=make_noise_model(rng).to_json())
    with refused(path, r"header\.noise_model holds a noise model in a format version 2 file"):
        io.load_calibration(path)


def test_tampered_noise_model_fails_the_checksum(tmp_path, rng):
    path = tmp_path / "cal.h5"
    save(path, rng, make_noise_model(rng))
    entries = calibration_entries(path)
    header = header_of(entries)
    header["noise_model"]["read_noise_counts"] *= 0.5  # still a valid model: only the checksum tells
    rewrite(path, entries, header, checksum=False)
    with refused(path, "does not match its checksum: tampered or corrupted"):
        io.load_calibration(path)
    with refused(path, "does not match its checksum"):
        io.open_calibration(path)


def _set(key, value):
    def change(doc):
        doc[key] = value
    return change


def _delete(key):
    def change(doc):
        del doc[key]
    return change


def _estimator(key, value):
    def change(doc):
        doc["estimator_covariance"][key] = value
    return change


MALFORMED = [
    ("gain-negative", _set("gain_e_per_count", -1.0), "gain"),
    ("gain-zero", _set("gain_e_per_count", 0), "gain"),
    ("gain-text", _set("gain_e_per_count", "high"), "gain_e_per_count"),
    ("gain-huge-integer", _set("gain_e_per_count", 10**400), "int too large"),
    ("gain-other-bands", _set("gain_e_per_count", [1.0] * (B - 1)), f"gain has {B - 1} values"),
    ("read-noise-missing", _delete("read_noise_counts"), "missing 'read_noise_counts'"),
    ("read-noise-nested", _set("read_noise_counts", [[1.0]]), "read_noise"),
    ("frames-zero", _set("dark_frames", 0), "dark_frames"),
    ("frames-list", _set("white_frames", [8, 8]), "white_frames"),
    ("unknown-key", _set("shot_noise", 1.0), "unknown key 'shot_noise'"),
    ("coeffs-shape", _set("coeffs_covariance", [[0.0] * 4] * 4), r"coeffs_covariance expected shape \(B, 4, 4\)"),
    ("coeffs-other-bands", _set("coeffs_covariance", [[[0.0] * 4] * 4] * 3), "coeffs_covariance has shape"),
    ("estimator-not-object", _set("estimator_covariance", [1, 2]), "estimator_covariance expected an object"),
    ("gram-shape", _estimator("gram", [[1.0]]), "gram has shape"),
    ("residual-shape", _estimator("residual", [[1.0] * 30] * 30), r"residual has shape \(30, 30\)"),
    ("residual-null", _estimator("residual", None), "residual"),
    ("not-an-object", lambda doc: doc.clear() or doc.update(x=1), "unknown key"),
]


@pytest.mark.parametrize(("change", "match"), [case[1:] for case in MALFORMED], ids=[case[0] for case in MALFORMED])
def test_malformed_noise_model_is_refused_in_one_line(tmp_path, rng, change, match):
    path = tmp_path / "cal.h5"
    save(path, rng, make_noise_model(rng))
    entries = calibration_entries(path)
    header = header_of(entries)
    change(header["noise_model"])
    rewrite(path, entries, header)  # a valid checksum: only the model's check can refuse it
    with refused(path, rf"header\.noise_model is not valid: .*{match}") as info:
        io.load_calibration(path)
    assert len(str(info.value)) < 600


@pytest.mark.parametrize("value", ["a model", 3, ["gain", 1]])
def test_noise_model_that_is_not_an_object_is_refused(tmp_path, rng, value):
    path = tmp_path / "cal.h5"
    save(path, rng)
    entries = calibration_entries(path)
    header = header_of(entries)
    header["noise_model"] = value
    rewrite(path, entries, header)
    with refused(path, r"header\.noise_model is not valid: noise model: expected a JSON object"):
        io.open_calibration(path)


def test_save_refuses_what_is_not_a_noise_model_for_its_bands(tmp_path, rng):
    path = tmp_path / "cal.h5"
    with refused(path, "cannot hold a noise model of type dict"):
        save(path, rng, make_noise_model(rng).to_json())
    eight_bands = dataclasses.replace(make_noise_model(rng), coeffs_covariance=np.zeros((8, 4, 4), np.float32))
    with refused(path, r"header\.noise_model is not valid: .*coeffs_covariance has shape \(8, 4, 4\), expected \(16, 4, 4\)"):
        save(path, rng, eight_bands)
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary left


# ------------------------------------------------------------------- sessions and calibration

#: Enough targets (more than B + 1) for the estimator's covariance; small enough to be quick.
DESIGN = simulate.ExperimentDesign(training_backgrounds=3, training_patches=3, test_backgrounds=1, test_patches=2, targets=30)
INSTRUMENT = simulate.InstrumentModel()
GAIN = INSTRUMENT.gain_e_per_dn
READ_NOISE = INSTRUMENT.read_noise_e / GAIN


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """(session, calibration, report) of a small simulated session, made once for the module."""
    root = tmp_path_factory.mktemp("noise")
    session = io.write_simulated_session(root / "session", seed=3, design=DESIGN)
    calibration, report = calibrate.calibrate_session(session)
    return session, calibration, report


def test_simulated_session_records_the_camera_and_frames(simulated):
    session, _, _ = simulated
    assert session.metadata["camera"] == {"gain_e_per_count": GAIN, "read_noise_counts": READ_NOISE}
    expected = {"dark": INSTRUMENT.frames_averaged_dark, "white": INSTRUMENT.frames_averaged_white}
    for frame in session.frames:
        assert frame.metadata["frames_averaged"] == expected.get(frame.role, INSTRUMENT.frames_averaged_sample)
    assert (INSTRUMENT.frames_averaged_dark, INSTRUMENT.frames_averaged_white, INSTRUMENT.frames_averaged_sample) == (16, 8, 4)


def test_noiseless_simulation_records_no_camera(tmp_path):
    tiny = simulate.ExperimentDesign(training_backgrounds=2, training_patches=2, test_backgrounds=1, test_patches=1, targets=4)
    session = io.write_simulated_session(tmp_path / "s", seed=1, design=tiny, instrument=simulate.InstrumentModel(noise=False))
    assert "camera" not in session.metadata


def test_calibrate_session_builds_the_noise_model(simulated):
    session, calibration, report = simulated
    model = report.noise_model
    assert isinstance(model, NoiseModel)
    model.check_bands(B)
    assert np.asarray(model.gain).tobytes() == np.float32(GAIN).tobytes()
    assert np.asarray(model.read_noise).tobytes() == np.float32(READ_NOISE).tobytes()
    assert (float(model.dark_frames), float(model.white_frames), float(model.sample_frames)) == (16, 8, 4)
    assert float(model.white_reflectance_u) == 0.0
    cov = np.asarray(model.coeffs_covariance)
    assert cov.shape == (B, 4, 4) and cov.dtype == np.float32 and np.all(np.isfinite(cov))
    assert np.allclose(cov, np.swapaxes(cov, 1, 2), rtol=1e-5, atol=0)
    assert np.all(np.diagonal(cov, axis1=1, axis2=2) > 0)
    gram, residual = (np.asarray(x) for x in (model.estimator_covariance.gram, model.estimator_covariance.residual))
    assert gram.shape == (B + 1, B + 1) and residual.shape == (31, 31)
    assert gram.dtype == residual.dtype == np.float32 and np.all(np.isfinite(gram)) and np.all(np.isfinite(residual))
    assert any("certificate" in note for note in report.noise_notes)
    # The model goes into a calibration file and comes back the same.
    summary = report.as_dict()["noise_model"]
    # The float32 gain and read noise as the shortest decimals of their float32 values.
    shortest = lambda x: float(np.format_float_positional(np.float32(x), unique=True))  # noqa: E731
    assert summary == {
        "gain_e_per_count": shortest(GAIN), "read_noise_counts": shortest(READ_NOISE),
        "dark_frames": 16, "white_frames": 8, "sample_frames": 4, "white_reflectance_u": 0,
        "coeffs_covariance": True, "estimator_covariance": True,
    }
    json.dumps(report.as_dict(), allow_nan=False)  # plain JSON, no arrays
    assert calibrate.noise_model_line(report).startswith("noise model: gain 1.038 e-/count, read noise 5.782 counts, 16 dark / 8 white / 4 sample")


def test_calibration_file_carries_the_session_noise_model(simulated, tmp_path):
    session, calibration, report = simulated
    path = tmp_path / "cal.h5"
    io.save_calibration(path, calibration, instrument_id=session.instrument_id, band_centres_nm=BANDS,
                        noise_model=report.noise_model)
    with io.open_calibration(path) as opened:
        assert_same_model(opened.noise_model, report.noise_model)


class FakeFit:
    """What `build_noise_model` takes of a Stage2Fit: its covariance."""

    def __init__(self, covariance):
        self.covariance = covariance


def training(rng, n):
    responses = rng.uniform(0.05, 0.9, (n, B))
    reflectances = rng.uniform(0.02, 0.95, (n, 31))
    return responses, reflectances, rng.normal(scale=0.1, size=(31, B))


def good_covariance():
    return np.tile(np.eye(4) * 1e-4, (B, 1, 1))


def test_build_noise_model_arguments_override_the_session(simulated, rng):
    session = simulated[0]
    responses, reflectances, matrix = training(rng, 40)
    model, notes = calibrate.build_noise_model(
        session, FakeFit(good_covariance()), responses, reflectances, matrix,
        gain=2.5, read_noise=np.full(B, 4.0), white_reflectance_u=0.003,
    )
    assert float(model.gain) == 2.5 and np.asarray(model.read_noise).shape == (B,) and np.all(np.asarray(model.read_noise) == 4)
    assert np.asarray(model.white_reflectance_u) == np.float32(0.003)
    assert (float(model.dark_frames), float(model.white_frames), float(model.sample_frames)) == (16, 8, 4)
    assert notes == []


def _without_frames(session, roles):
    frames = tuple(
        dataclasses.replace(f, metadata={k: v for k, v in f.metadata.items() if k != "frames_averaged"})
        if f.role in roles else f
        for f in session.frames
    )
    return dataclasses.replace(session, frames=frames)


def test_build_noise_model_without_camera_gives_none_and_says_how(simulated, rng):
    session = dataclasses.replace(simulated[0], metadata={})
    responses, reflectances, matrix = training(rng, 40)
    model, notes = calibrate.build_noise_model(session, FakeFit(good_covariance()), responses, reflectances, matrix)
    assert model is None and len(notes) == 1 and "--gain" in notes[0] and "--read-noise" in notes[0]
    # One of the two given is not enough either.
    model, notes = calibrate.build_noise_model(session, FakeFit(good_covariance()), responses, reflectances, matrix, gain=1.0)
    assert model is None and "read_noise unknown" in notes[0]
    report = dataclasses.replace(simulated[2], noise_model=None)
    assert "--gain E_PER_COUNT --read-noise COUNTS" in calibrate.noise_model_line(report)
    assert report.as_dict()["noise_model"] is None


def test_build_noise_model_notes_what_it_assumed(simulated, rng):
    session = _without_frames(simulated[0], ("dark", "white", "sample", "target"))
    session = dataclasses.replace(session, metadata={"camera": {"gain_e_per_count": 1.5, "read_noise_counts": 6, "white_reflectance_u": 0.002}})
    responses, reflectances, matrix = training(rng, B + 1)  # no degree of freedom left
    covariance = good_covariance()
    covariance[3] = np.nan
    model, notes = calibrate.build_noise_model(session, FakeFit(covariance), responses, reflectances, matrix)
    assert (float(model.dark_frames), float(model.white_frames), float(model.sample_frames)) == (1, 1, 1)
    assert float(model.gain) == 1.5 and float(model.read_noise) == 6 and model.white_reflectance_u == np.float32(0.002)
    assert model.coeffs_covariance is None and model.estimator_covariance is None
    text = " | ".join(notes)
    assert "dark frame 'dark' records no frames_averaged: taken as 1" in text
    assert "white frame 'white' records no frames_averaged: taken as 1" in text
    assert "sample_frames taken as 1" in text
    assert "Stage II covariance not finite in 1 band(s), first 460 nm" in text
    assert "no estimator covariance" in text and "degree of freedom" in text


def test_build_noise_model_takes_the_most_common_sample_frames(simulated, rng):
    session = simulated[0]
    frames = tuple(
        dataclasses.replace(f, metadata={**f.metadata, "frames_averaged": 2}) if f.role == "target" else f
        for f in session.frames
    )
    responses, reflectances, matrix = training(rng, 40)
    model, notes = calibrate.build_noise_model(dataclasses.replace(session, frames=frames), FakeFit(good_covariance()),
                                               responses, reflectances, matrix)
    assert float(model.sample_frames) == 4 and "[2, 4]" in " ".join(notes)


@pytest.mark.parametrize(
    ("metadata", "frame_metadata", "match"),
    [
        ({"camera": {"gain_e_per_count": -1, "read_noise_counts": 5}}, None, r"metadata camera\.gain_e_per_count is -1"),
        ({"camera": {"gain_e_per_count": 1, "read_noise_counts": "low"}}, None, r"metadata camera\.read_noise_counts is 'low'"),
        ({"camera": {"gain_e_per_count": [1.0, 2.0], "read_noise_counts": 5}}, None, "one per band"),
        (None, {"frames_averaged": 0}, "frame 'dark' has metadata frames_averaged 0"),
        (None, {"frames_averaged": "many"}, "frames_averaged 'many'"),
    ],
)
def test_build_noise_model_refuses_bad_session_records(simulated, rng, metadata, frame_metadata, match):
    session = simulated[0]
    if metadata is not None:
        session = dataclasses.replace(session, metadata=metadata)
    if frame_metadata is not None:
        frames = tuple(dataclasses.replace(f, metadata=frame_metadata) if f.role == "dark" else f for f in session.frames)
        session = dataclasses.replace(session, frames=frames)
    responses, reflectances, matrix = training(rng, 40)
    with pytest.raises(ValueError, match=match) as info:
        calibrate.build_noise_model(session, FakeFit(good_covariance()), responses, reflectances, matrix)
    assert str(info.value).startswith(f"{session.manifest_path}: ") and "\n" not in str(info.value)


def test_a_camera_record_that_is_not_an_object_is_not_used(simulated, rng):
    session = dataclasses.replace(simulated[0], metadata={"camera": "QImaging Retiga"})
    responses, reflectances, matrix = training(rng, 40)
    model, notes = calibrate.build_noise_model(session, FakeFit(good_covariance()), responses, reflectances, matrix)
    assert model is None and "not used" in notes[0]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"gain": 0.0}, "gain: expected electrons per count"),
        ({"gain": float("nan")}, "gain: expected"),
        ({"read_noise": -1.0}, "read_noise: expected"),
        ({"white_reflectance_u": float("inf")}, "white_reflectance_u: expected"),
        ({"gain": [1.0] * 3}, "one per band"),
    ],
)
def test_calibrate_session_refuses_bad_noise_arguments_first(simulated, kwargs, match):
    with pytest.raises(ValueError, match=match):
        calibrate.calibrate_session(simulated[0], **kwargs)


# --------------------------------------------------------------------------------- the CLI


def run(argv, capsys):
    status = cli.main(argv)
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_cli_calibrate_stores_the_session_noise_model(simulated, tmp_path, capsys):
    session = simulated[0]
    status, out, err = run(["calibrate", str(session.path), "-o", str(tmp_path / "cal.h5")], capsys)
    assert status == 0, err
    with io.open_calibration(tmp_path / "cal.h5") as opened:
        model = opened.noise_model
        report = opened.header["metadata"]["calibration_report"]
    assert np.asarray(model.gain) == np.float32(GAIN) and np.asarray(model.read_noise) == np.float32(READ_NOISE)
    assert model.coeffs_covariance.shape == (B, 4, 4) and model.estimator_covariance.residual.shape == (31, 31)
    assert report["noise_model"]["dark_frames"] == 16 and report["noise_model"]["estimator_covariance"] is True
    lines = [line for line in out.splitlines() if line.startswith("noise model:")]
    assert len(lines) == 1 and "gain 1.038 e-/count" in lines[0] and "covariances: Stage II, estimator" in lines[0]


def test_cli_calibrate_options_override_and_supply_the_noise_model(simulated, tmp_path, capsys):
    """A session whose camera record has a gain but no read noise: --gain overrides its gain,
    --read-noise supplies the read noise, the frames still come from the session."""
    source = simulated[0]
    session_path = tmp_path / "session"
    shutil.copytree(source.path, session_path)
    manifest = json.loads((session_path / "manifest.json").read_text())
    del manifest["metadata"]["camera"]["read_noise_counts"]
    (session_path / "manifest.json").write_text(json.dumps(manifest))
    argv = ["calibrate", str(session_path), "-o", str(tmp_path / "cal.h5"),
            "--gain", "2.5", "--read-noise", "4", "--white-reflectance-u", "0.003"]
    status, out, err = run(argv, capsys)
    assert status == 0, err
    with io.open_calibration(tmp_path / "cal.h5") as opened:
        model = opened.noise_model
    assert float(model.gain) == 2.5 and float(model.read_noise) == 4.0
    assert np.asarray(model.white_reflectance_u) == np.float32(0.003)
    assert (float(model.dark_frames), float(model.white_frames), float(model.sample_frames)) == (16, 8, 4)
    assert "noise model: gain 2.5 e-/count, read noise 4 counts" in out


@pytest.mark.parametrize(
    ("option", "value", "match"),
    [
        ("--gain", "0", "--gain '0': expected electrons per count"),
        ("--gain", "abc", "--gain 'abc': expected"),
        ("--gain", "nan", "--gain 'nan'"),
        ("--read-noise", "-1", "--read-noise '-1': expected one frame's read noise"),
        ("--read-noise", "inf", "--read-noise 'inf'"),
        ("--white-reflectance-u", "-0.1", "--white-reflectance-u '-0.1': expected the white standard's"),
    ],
)
def test_cli_calibrate_refuses_bad_noise_options(tmp_path, capsys, option, value, match):
    # The session need not exist: the options are checked before anything is read or written.
    status, out, err = run(["calibrate", str(tmp_path / "session"), "-o", str(tmp_path / "cal.h5"), option, value], capsys)
    assert status == cli.EXIT_BAD_INPUT
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("spherejax: error: ") and match in lines[0], err
    assert "Traceback" not in err and out == ""
    assert list(tmp_path.iterdir()) == []


def test_save_calibration_keeps_a_noise_model_of_the_report(simulated, tmp_path):
    """`cli._save_calibration` (calibrate, demo) stores the report's model; a study's
    calibration (no report) stores none."""
    session, calibration, report = simulated
    cli._save_calibration(tmp_path / "a.npz", calibration, report, session)
    cli._save_calibration(tmp_path / "b.npz", calibration, None, session)
    with io.open_calibration(tmp_path / "a.npz") as a, io.open_calibration(tmp_path / "b.npz") as b:
        assert_same_model(a.noise_model, report.noise_model)
        assert b.noise_model is None
