"""A plan (`spherejax.plan`) called directly checks what `correct` checks for it: frames of another
shape or dtype, and p of another shape, are refused in one ValueError naming the argument, the
shape given and the one expected (they used to fail inside JAX, naming its internals); a frame
dtype outside `SUPPORTED_DTYPES` (float128, complex, bool) is refused when the plan is made."""

import numpy as np
import pytest

import spherejax as sj
from spherejax.pipeline import SUPPORTED_DTYPES

H, W, B = 12, 10, 16


@pytest.fixture(scope="module")
def calibration():
    rng = np.random.default_rng(3)
    patch = np.zeros((H, W), bool)
    patch[2:5, 2:5] = True
    return sj.Calibration(
        dark=rng.uniform(50, 60, (H, W, B)).astype(np.float32), white=rng.uniform(9000, 12000, (H, W, B)).astype(np.float32),
        patch=patch, coeffs=np.tile([1.0, 0.0, 0.0, 0.0], (B, 1)).astype(np.float32),
        wiener=rng.uniform(0, 0.1, (31, B)).astype(np.float32), saturation=16383.0,
    )


@pytest.mark.parametrize("dtype", ["float128", "complex64", "bool", "datetime64[s]", "U4"])
def test_a_dtype_outside_the_supported_ones_is_refused_naming_them(calibration, dtype):
    with pytest.raises(ValueError) as error:
        sj.plan(calibration, (H, W, B), dtype=dtype)
    message = str(error.value)
    assert message.startswith("dtype: ") and str(np.dtype(dtype)) in message and "float32" in message and "uint16" in message
    assert "\n" not in message


@pytest.mark.parametrize("dtype", SUPPORTED_DTYPES)
def test_every_supported_dtype_makes_a_plan(calibration, dtype):
    assert sj.plan(calibration, (H, W, B), dtype=dtype).dtype == np.dtype(dtype)


@pytest.mark.parametrize("shape", [(H, W, B - 1), (W, H, B), (H - 1, W, B), (2, H, W, B), (H * W * B,)],
                         ids=["bands", "transposed", "rows", "a-stack", "flat"])
@pytest.mark.parametrize("call", ["call", "patch_ratio", "patch_ratio_u"])
def test_frames_of_another_shape_are_refused_naming_both_shapes(calibration, shape, call):
    plan = sj.plan(calibration, (H, W, B))
    raw = np.full(shape, 3000, np.uint16)
    with pytest.raises(ValueError) as error:
        if call == "call":
            plan(raw)
        elif call == "patch_ratio":
            plan.patch_ratio(raw)
        else:
            plan.patch_ratio_u(raw, sj.NoiseModel(gain=1.0, read_noise=1.0))
    message = str(error.value)
    assert message.startswith("raw: ") and str((H, W, B)) in message and str(shape) in message, message
    assert "\n" not in message


def test_frames_of_another_dtype_or_no_array_are_refused(calibration):
    plan = sj.plan(calibration, (H, W, B))
    with pytest.raises(ValueError, match=r"^raw: .*dtype uint16, got shape \(12, 10, 16\) and dtype float32$"):
        plan(np.full((H, W, B), 3000.0, np.float32))
    with pytest.raises(ValueError, match=r"^raw: .*got list$"):
        plan([[1, 2]])


def test_p_of_another_shape_is_refused_and_a_right_call_gives_correct(calibration):
    plan = sj.plan(calibration, (H, W, B))
    raw = np.random.default_rng(0).uniform(2000, 8000, (H, W, B)).astype(np.uint16)
    with pytest.raises(ValueError, match=r"^p: expected shape \(16,\) .*got \(15,\)$"):
        plan(raw, p=np.ones(B - 1, np.float32))
    with pytest.raises(ValueError, match=r"^p: expected shape \(16,\) .*got \(2, 16\)$"):
        plan(raw, p=np.ones((2, B), np.float32))
    direct, through_correct = plan(raw), sj.correct(raw, calibration)
    for name in ("reflectance", "lab", "quality"):
        np.testing.assert_array_equal(np.asarray(getattr(direct, name)), np.asarray(getattr(through_correct, name)))


def test_a_plan_of_rows_needs_p(calibration):
    rows = calibration.rows(2, 6)
    plan = sj.plan(rows, (4, W, B))
    raw = np.full((4, W, B), 3000, np.uint16)
    with pytest.raises(ValueError, match=r"^p: expected the whole image's white-patch ratio"):
        plan(raw)
    with pytest.raises(ValueError, match=r"^raw: this plan's calibration has no patch"):
        plan.patch_ratio(raw)
