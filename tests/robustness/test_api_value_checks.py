"""Values the Python API would take and silently change, each refused with a ValueError naming
the argument (docs/reliability.md, section 1).

The related file cases live beside the code they test: `measure` outputs that are inputs,
CGATS names readers merge and CSV formulas in tests/test_measure_cli.py, damaged ENVI headers in
tests/test_io_envi.py, the ownership check itself in tests/test_io_ownership.py.
"""

from __future__ import annotations

import os
import re
import stat
import subprocess
import sys

import jax
import numpy as np
import pytest

import spherejax as sj

H, W, B = 4, 5, 3


def _calibration(**changes) -> sj.Calibration:
    fields = dict(dark=np.zeros((H, W, B), np.float32), white=np.ones((H, W, B), np.float32),
                  patch=np.ones((H, W), bool), coeffs=np.zeros((B, 4), np.float32),
                  wiener=np.full((31, B), 1.0 / B, np.float32))
    fields.update(changes)
    return sj.Calibration(**fields)


@pytest.mark.parametrize("field, value", [
    ("dark", np.zeros((H, W, B), np.complex64)), ("white", np.ones((H, W, B)) + 1j),
    ("coeffs", np.zeros((B, 4)) + 0j), ("wiener", np.full((31, B), 0.3 + 0.1j)),
    ("wiener_offset", np.zeros(31, np.complex128)),
])
def test_a_complex_calibration_array_is_refused(field, value):
    """sj.Calibration(dark=complex) kept only the real part, without a word."""
    with pytest.raises(ValueError, match=rf"^{field}: expected real numbers, got complex(64|128) "):
        _calibration(**{field: value})


def test_complex_responses_or_raw_are_refused():
    """sj.fit_wiener(V + 5j V, R) fitted the real part; correct likewise."""
    rng = np.random.default_rng(0)
    V, R = rng.uniform(0.1, 1.0, (40, 16)), rng.uniform(0.1, 0.9, (40, 31))
    with pytest.raises(ValueError, match=r"^responses: expected real numbers, got complex128 "):
        sj.fit_wiener(V + 5j * V, R)
    with pytest.raises(ValueError, match=r"^reflectances: expected real numbers"):
        sj.fit_wiener(V, R + 0j)
    with pytest.raises(ValueError, match=r"^raw: expected real numbers"):
        sj.correct(np.ones((H, W, B), np.complex64), _calibration())


@pytest.mark.parametrize("shape", [(H, W, 0), (0, W, B), (H, 0, B)])
def test_a_calibration_without_bands_or_pixels_is_refused_naming_dark(shape):
    """A 0-band calibration failed inside correct with "zero-size array to reduction operation
    min", naming no argument."""
    bands = shape[2]
    with pytest.raises(ValueError, match=rf"^dark: expected at least one pixel and one band, got shape \({shape[0]}, {shape[1]}, {bands}\)"):
        sj.Calibration(dark=np.zeros(shape, np.float32), white=np.ones(shape, np.float32),
                       patch=np.ones(shape[:2], bool), coeffs=np.zeros((bands, 4), np.float32),
                       wiener=np.zeros((31, bands), np.float32))


OVERFLOW_SCRIPT = """
import numpy as np, spherejax as sj
rng = np.random.default_rng(0)
V, R = rng.uniform(0.1, 1.0, (40, 16)), rng.uniform(0.1, 0.9, (40, 31))
try:
    sj.fit_wiener(V * 1e300, R)
except ValueError as error:
    print(error)
fit = sj.fit_wiener(V * 1e30, R)  # inside float32's range: fitted
print(np.isfinite(np.asarray(fit.matrix)).all())
"""


def test_float64_values_beyond_float32_are_named_not_called_non_finite():
    """With float64 off (JAX's default; this suite turns it on, hence a child process),
    sj.fit_wiener(V * 1e300, R) said "target 0 has a non-finite value" of values all finite."""
    done = subprocess.run([sys.executable, "-c", OVERFLOW_SCRIPT], capture_output=True, text=True, timeout=300,
                          env={"JAX_ENABLE_X64": "0", "JAX_PLATFORMS": "cpu", "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    message, fitted = done.stdout.strip().splitlines()
    assert message.startswith("responses: values up to 1e+300 overflow float32 (largest 3.4e+38)")
    assert "jax_enable_x64" in message and fitted == "True"


@pytest.mark.parametrize("field, shape, index, value", [
    ("coeffs", (B, 4), (1, 0), np.nan), ("wiener", (31, B), (4, 2), np.inf), ("wiener_offset", (31,), (7,), -np.inf),
])
def test_a_calibration_with_a_parameter_not_finite_is_refused(field, shape, index, value):
    """sj.Calibration(coeffs with one NaN) was taken: every reflectance NaN, every quality flag 0,
    against the rule that a pixel is NaN exactly where quality flags it. Under jit the values
    are traced and pass, as every value of the per-pixel path does."""
    array = np.zeros(shape, np.float32)
    array[index] = value
    with pytest.raises(ValueError, match=rf"^{field}: 1 entries are not finite \(the first, {value}, at {re.escape(str(index))}\)"):
        _calibration(**{field: array})
    traced = jax.jit(lambda a: _calibration(**{field: a}).bands)(array)
    assert traced == B


@pytest.mark.parametrize("planted", [".spherejax.lock", "manifest.jsonl"])
def test_a_fifo_in_place_of_the_lock_or_the_manifest_is_refused_at_once(cal, tmp_path, planted):
    """`mkfifo OUT/.spherejax.lock` would make `correct` wait forever (a read of the lock), and
    `mkfifo OUT/manifest.jsonl` `--resume` (an open for appending). One line naming the file and
    what it is, at once; the FIFO is left as it was."""
    from spherejax import io
    from tests.batch_support import NAMES, frame

    (tmp_path / "in").mkdir()
    io.write_frame(tmp_path / "in" / "a.tif", frame(np.random.default_rng(3)), channel_names=NAMES)
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / planted)
    command = [sys.executable, "-m", "spherejax.cli", "-q", "correct", "-c", str(cal), str(tmp_path / "in"),
               "-o", str(out), "--resume"]
    done = subprocess.run(command, env={**os.environ, "JAX_PLATFORMS": "cpu"}, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert str(out / planted) in lines[0] and "it is a FIFO" in lines[0], lines[0]
    assert stat.S_ISFIFO(os.lstat(out / planted).st_mode)
    assert not (out / "a.reflectance.exr").exists()


def test_a_raw_value_far_below_the_dark_level_is_flagged_not_reported_as_good():
    """A raw value of -1000 counts gave reflectance -0.14 with quality 0; beyond
    BELOW_DARK_LIMIT of the white signal below the dark frame it is flagged, on every route,
    while a value below dark by what noise allows is not."""
    dark = np.full((H, W, B), 100.0, np.float32)
    white = np.full((H, W, B), 10100.0, np.float32)
    raw = np.full((H, W, B), 5100.0, np.float32)
    raw[0, 1, 2] = -1000.0  # v = -0.11
    raw[1, 1, 0] = 100.0 - 0.01 * 10000.0  # v = -0.01: within what noise allows
    calibration = _calibration(dark=dark, white=white, patch=np.eye(H, W, dtype=bool))
    result = sj.correct(raw, calibration)
    quality = np.asarray(result.quality)
    assert quality[0, 1] == sj.QUALITY_BELOW_DARK and quality[1, 1] == 0
    assert (quality != 0).sum() == 1
    assert np.isnan(np.asarray(result.reflectance)[0, 1]).all()
    assert np.isfinite(np.asarray(result.reflectance)[1, 1]).all()


def test_a_patch_pixel_below_dark_is_left_out_of_the_patch_ratio():
    """A flagged pixel carries no information: in the white patch it counts as a NaN one does."""
    dark = np.full((H, W, B), 100.0, np.float32)
    white = np.full((H, W, B), 10100.0, np.float32)
    rng = np.random.default_rng(0)
    raw = rng.uniform(8000, 9000, (H, W, B)).astype(np.float32)
    calibration = _calibration(dark=dark, white=white, patch=np.ones((H, W), bool))
    below, missing = raw.copy(), raw.copy()
    below[2, 3, 1], missing[2, 3, 1] = -1000.0, np.nan
    np.testing.assert_array_equal(np.asarray(sj.patch_ratio(below, calibration)),
                                  np.asarray(sj.patch_ratio(missing, calibration)))
    assert not np.array_equal(np.asarray(sj.patch_ratio(below, calibration)), np.asarray(sj.patch_ratio(raw, calibration)))
