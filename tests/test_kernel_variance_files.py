"""Calibration files with the kernel residual's predictive variance (E15, format version 6): the
five optional datasets round trip bit for bit and into the same propagated uncertainties, the
checksum covers them in the documented order, older files and residuals without them open with
no variance, and bad values or shapes are refused in one line naming the file, the dataset, the
value and what was expected; `spherejax measure` reads them into its expanded uncertainty U."""

import csv
import dataclasses
import hashlib
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import cli, io, uncertainty
from spherejax.estimation.estimator import KernelResidual, ResidualVariance
from spherejax.io import CalibrationFileError
from spherejax.io.calibration_checks import VARIANCE_ARRAYS

from .helpers import calibration_entries, refused, write_calibration_entries

H, W = 12, 10
BANDS = list(range(400, 701, 20))
B = len(BANDS)
M, RANK = 6, 3  # inducing points, residual components
WAVELENGTHS = np.arange(400, 701, 10)
FIELDS = ("components", "prior", "projection", "weights", "noise")


def kernel_calibration(rng, dtype=np.float32, *, variance=True) -> sj.Calibration:
    """Identity Stage II, a smooth Wiener matrix (the bands interpolated to 31 wavelengths) and a
    kernel residual of M inducing points about reflectance 0.5, with a variance of rank RANK."""
    patch = np.zeros((H, W), bool)
    patch[0:3, 7:10] = True
    dark = rng.uniform(50, 60, (H, W, B))
    white = dark + rng.uniform(20000, 30000, (H, W, B))
    wiener = np.stack([np.interp(WAVELENGTHS, BANDS, np.eye(B)[b]) for b in range(B)], axis=1)
    residual_variance = None
    if variance:
        residual_variance = ResidualVariance(*(jnp.asarray(x, dtype) for x in (
            np.linalg.qr(rng.normal(size=(31, RANK)))[0].T, rng.uniform(1e-5, 4e-5, RANK), rng.normal(size=(M, M)) * 0.3,
            rng.uniform(0, 1e-6, (RANK, M)), np.full(31, 1e-7))))
    residual = KernelResidual(
        jnp.asarray(np.full(B, 0.5), dtype), jnp.asarray(np.eye(B) * 2.0, dtype),
        jnp.asarray(rng.normal(size=(M, B)), dtype), jnp.asarray(rng.normal(scale=0.02, size=(31, M)), dtype),
        variance=residual_variance,
    )
    return sj.Calibration(dark=dark.astype(dtype), white=white.astype(dtype), patch=patch,
                          coeffs=np.tile([0.0, 1.0, 0.0, 0.0], (B, 1)).astype(dtype), wiener=wiener.astype(dtype),
                          wiener_residual=residual)


def raw_frame(calibration, rng) -> np.ndarray:
    """uint16 counts of a sample about reflectance 0.5 (the residual's centre), the patch white."""
    dark, white = np.asarray(calibration.dark, np.float64), np.asarray(calibration.white, np.float64)
    reflectance = 0.5 + rng.normal(scale=0.01, size=(H, W, B))
    reflectance[np.asarray(calibration.patch)] = 1.0
    return np.clip(np.rint(dark + reflectance * (white - dark)), 0, 65535).astype(np.uint16)


def save(path, calibration, **kwargs) -> dict:
    return io.save_calibration(path, calibration, instrument_id="sphere-1", band_centres_nm=BANDS, **kwargs)


def rewritten(path, entries, header) -> None:
    """`entries` and `header` written back as save_calibration lays them out, the checksum
    computed again (`io.calibration_files._checksum`)."""
    arrays = {k: v for k, v in entries.items() if k != "header"}
    header = {**header, "checksum": io.calibration_files._checksum(header, arrays)}
    write_calibration_entries(path, {**arrays, "header": np.frombuffer(json.dumps(header).encode("utf-8"), np.uint8)}, "hdf5")


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_variance_round_trips_bit_for_bit(tmp_path, rng, dtype):
    """Format version 6 stores the variance's five arrays beside the residual's four; the whole
    calibration, its rows and a region's propagated uncertainty read back as saved."""
    calibration = kernel_calibration(rng, dtype)
    path = tmp_path / "kernel.h5"
    header = save(path, calibration)
    assert header["format_version"] == io.CALIBRATION_FORMAT_VERSION == 7
    assert [header["arrays"][name]["shape"] for name in VARIANCE_ARRAYS] == [[RANK, 31], [RANK], [M, M], [RANK, M], [31]]
    assert all(header["arrays"][name]["dtype"] == np.dtype(dtype).str for name in VARIANCE_ARRAYS)
    loaded, _ = io.load_calibration(path)
    with io.open_calibration(path) as opened:
        rows = opened.rows(2, 5)
    for got in (loaded.wiener_residual.variance, rows.wiener_residual.variance):
        for field in FIELDS:
            original = np.asarray(getattr(calibration.wiener_residual.variance, field))
            assert np.asarray(getattr(got, field)).tobytes() == original.tobytes(), field
    raw = raw_frame(calibration, rng)
    noise = sj.NoiseModel(gain=2.0, read_noise=3.0)
    a, b = sj.correct(raw, calibration, noise=noise), sj.correct(raw, loaded, noise=noise)
    assert np.asarray(a.reflectance_u).tobytes() == np.asarray(b.reflectance_u).tobytes()
    assert np.asarray(a.lab_covariance).tobytes() == np.asarray(b.lab_covariance).tobytes()


def test_the_checksum_covers_the_variance_in_the_documented_order(tmp_path, rng):
    """The io docstring's checksum, written out here: the canonical header JSON, then for each
    array in the order dark .. wiener_residual_weights and the variance's five
    (components, prior, projection, weights, noise), "<name> <dtype.str> <shape>\\n" and its
    bytes; and a changed variance value no longer matches."""
    path = tmp_path / "kernel.h5"
    header = save(path, kernel_calibration(rng))
    entries = calibration_entries(path)
    names = ("dark", "white", "patch", "coeffs", "wiener", "wiener_offset", "wiener_residual_centre",
             "wiener_residual_whitening", "wiener_residual_inducing", "wiener_residual_weights",
             *(f"wiener_residual_variance_{field}" for field in FIELDS))
    assert set(names) == set(entries) - {"header"}
    digest = hashlib.sha256(json.dumps({k: v for k, v in header.items() if k != "checksum"}, sort_keys=True,
                                       separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode("utf-8"))
    for name in names:
        array = entries[name]
        digest.update(f"{name} {array.dtype.str} {json.dumps(list(array.shape))}\n".encode("ascii"))
        digest.update(np.ascontiguousarray(array).tobytes())
    assert header["checksum"] == "sha256:" + digest.hexdigest()
    entries["wiener_residual_variance_prior"] = entries["wiener_residual_variance_prior"] * 2
    write_calibration_entries(path, entries, "hdf5")
    with refused(CalibrationFileError, path, "does not match its checksum"):
        io.load_calibration(path)


def test_a_residual_without_variance_and_an_older_file_open_without_one(tmp_path, rng):
    """No variance, no variance datasets; a format version 5 file (the same arrays, the version
    before the variance) opens with variance None and corrects as the version 6 one does; a
    version 5 file holding variance arrays is not what that version's writer wrote."""
    calibration = kernel_calibration(rng, variance=False)
    path, old = tmp_path / "plain.h5", tmp_path / "v5.h5"
    header = save(path, calibration)
    assert not set(VARIANCE_ARRAYS) & set(header["arrays"]) and not set(VARIANCE_ARRAYS) & set(calibration_entries(path))
    entries = calibration_entries(path)
    rewritten(old, entries, {**json.loads(entries["header"].tobytes()), "format_version": 5})
    (new, _), (older, older_header) = io.load_calibration(path), io.load_calibration(old)
    assert older_header["format_version"] == 5
    assert new.wiener_residual.variance is None and older.wiener_residual.variance is None
    raw = raw_frame(calibration, rng)
    noise = sj.NoiseModel(gain=2.0, read_noise=3.0)
    assert (np.asarray(sj.correct(raw, new, noise=noise).reflectance_u).tobytes()
            == np.asarray(sj.correct(raw, older, noise=noise).reflectance_u).tobytes())

    with_variance = tmp_path / "kernel.h5"
    save(with_variance, kernel_calibration(np.random.default_rng(1)))
    entries = calibration_entries(with_variance)
    rewritten(old, entries, {**json.loads(entries["header"].tobytes()), "format_version": 5})
    with refused(CalibrationFileError, old, r"header\.arrays has unknown fields \['wiener_residual_variance_components'"):
        io.load_calibration(old)


def _edited(entries, name, value):
    """`entries` with array `name` replaced (None: removed), the header's description of it too."""
    entries = dict(entries)
    header = json.loads(entries.pop("header").tobytes())
    if value is None:
        del entries[name], header["arrays"][name]
    else:
        entries[name] = value
        header["arrays"][name] = {**header["arrays"].get(name, {"description": "edited"}),
                                  "shape": list(value.shape), "dtype": value.dtype.str}
    return entries, header


@pytest.mark.parametrize("name, change, match", [
    ("wiener_residual_variance_prior", lambda x: x * np.float32(-1),
     (r"array 'wiener_residual_variance_prior' holds -[0-9.e-]+ at index 0 \(3 entries not finite and >= 0\) "
      r"\(expected variances: finite numbers >= 0\)")),
    ("wiener_residual_variance_noise", lambda x: np.where(np.arange(31) == 4, np.float32(-2e-7), x).astype(np.float32),
     r"array 'wiener_residual_variance_noise' holds -2e-07 at index 4 \(1 entries not finite and >= 0\)"),
    ("wiener_residual_variance_prior", lambda x: np.where(np.arange(RANK) == 1, np.float32(np.nan), x).astype(np.float32),
     r"wiener_residual_variance_prior: 1 entries are not finite \(the first, nan, at \(1,\)\); expected finite"),
    ("wiener_residual_variance_projection", lambda x: x[:-1],
     (rf"array 'wiener_residual_variance_projection' has shape \[{M - 1}, {M}\] \(expected a kernel residual's variance "
      rf"for its {M} inducing points: .* projection \({M}, q\)")),
    ("wiener_residual_variance_components", lambda x: x[:, :30],
     r"array 'wiener_residual_variance_components' has shape \[3, 30\] \(expected .*components \(r, 31\)"),
    ("wiener_residual_variance_weights", lambda x: x[:2],
     r"array 'wiener_residual_variance_weights' has shape \[2, 6\] \(expected .*weights \(r, q\)"),
    ("wiener_residual_variance_noise", None,
     (r"header\.arrays lists \['wiener_residual_variance_components', .*'wiener_residual_variance_weights'\] of the "
      r"kernel residual's variance but not \['wiener_residual_variance_noise'\] \(expected all of .* or none\)")),
])
def test_bad_variance_arrays_are_refused_in_one_line(tmp_path, rng, name, change, match):
    path = tmp_path / "kernel.h5"
    save(path, kernel_calibration(rng))
    entries = calibration_entries(path)
    entries, header = _edited(entries, name, None if change is None else change(entries[name]))
    rewritten(path, entries, header)
    for opening in (io.open_calibration, io.load_calibration):
        # A non-finite value gets the message every parameter array gets ("...; expected finite numbers").
        with refused(CalibrationFileError, path, match, says_expected="are not finite" not in match):
            opening(path)


def test_a_variance_without_a_residual_is_refused(tmp_path, rng):
    """An affine estimator (m = 0 inducing points) has no variance to carry."""
    path = tmp_path / "affine.h5"
    calibration = kernel_calibration(rng)
    save(path, dataclasses.replace(calibration, wiener_residual=None))
    entries = calibration_entries(path)
    save(tmp_path / "kernel.h5", calibration)
    kernel = calibration_entries(tmp_path / "kernel.h5")
    header = json.loads(entries.pop("header").tobytes())
    kernel_header = json.loads(kernel["header"].tobytes())
    for name in VARIANCE_ARRAYS:
        entries[name] = kernel[name]
        header["arrays"][name] = kernel_header["arrays"][name]
    rewritten(path, entries, header)
    match = r"array 'wiener_residual_variance_components' holds a kernel residual's variance with no inducing point \(m = 0\)"
    with refused(CalibrationFileError, path, match):
        io.load_calibration(path)


def test_a_calibration_with_a_negative_variance_is_refused_where_built_and_saved(tmp_path, rng):
    calibration = kernel_calibration(rng)
    residual = calibration.wiener_residual
    negative = dataclasses.replace(residual.variance, prior=residual.variance.prior.at[2].set(-1e-6))
    with pytest.raises(ValueError, match=r"^wiener_residual\.variance\.prior: -1e-06 at index 2; expected variances >= 0$"):
        dataclasses.replace(calibration, wiener_residual=dataclasses.replace(residual, variance=negative))
    target = residual.variance.noise  # tree_map builds a calibration that was never checked
    unchecked = jax.tree_util.tree_map(lambda leaf: -leaf if leaf is target else leaf, calibration)
    path = tmp_path / "negative.h5"
    match = r"does not hold a valid calibration: wiener_residual\.variance\.noise: -1e-07 at index 0; expected variances >= 0$"
    with refused(CalibrationFileError, path, match, says_expected=False):  # the Calibration's own check, quoted
        save(path, unchecked)
    assert not path.exists()


def test_measure_command_includes_the_kernel_residual_in_U(tmp_path, rng, capsys):
    """`spherejax measure` on a kernel calibration with its variance: the region's Lab covariance,
    u and U = 2 u are `measure`'s with the "kernel residual" source in the budget, above those of
    the same calibration without the variance."""
    calibration = kernel_calibration(rng)
    noise = sj.NoiseModel(gain=np.float32(2), read_noise=np.float32(3), dark_frames=16, white_frames=16)
    raw = raw_frame(calibration, rng)
    io.write_frame(tmp_path / "sample.tif", raw, channel_names=[f"{b}nm" for b in BANDS])
    save(tmp_path / "cal.h5", calibration, noise_model=noise)
    bare = dataclasses.replace(calibration, wiener_residual=dataclasses.replace(calibration.wiener_residual, variance=None))
    save(tmp_path / "bare.h5", bare, noise_model=noise)
    rect = (4, 9, 1, 6)
    mask = np.zeros((H, W), bool)
    mask[rect[0]:rect[1], rect[2]:rect[3]] = True
    expanded = {}
    for name in ("cal", "bare"):
        status = cli.main(["measure", "-c", str(tmp_path / f"{name}.h5"), str(tmp_path / "sample.tif"),
                           "--region", "swatch=" + ",".join(map(str, rect)), "-o", str(tmp_path / name)])
        assert status == 0, capsys.readouterr().err
        document = json.loads((tmp_path / f"{name}.json").read_text(encoding="utf-8"))
        with open(tmp_path / f"{name}.csv", newline="", encoding="utf-8") as handle:
            row = next(csv.DictReader(handle))
        entry = document["regions"][0]
        expected = sj.measure(raw, io.load_calibration(tmp_path / f"{name}.h5")[0], mask, noise)
        np.testing.assert_allclose(entry["lab_covariance"], expected.lab_covariance, rtol=1e-5, atol=1e-12)
        np.testing.assert_allclose([float(row[k]) for k in ("U_L", "U_a", "U_b")], 2 * expected.lab_u, rtol=1e-5)
        assert (uncertainty.RESIDUAL_SOURCE in entry["lab_u_by_source"]) == (name == "cal")
        expanded[name] = np.array([float(row[k]) for k in ("U_L", "U_a", "U_b")])
    assert np.all(expanded["cal"] > expanded["bare"]), expanded
