"""The default estimator's choice ("auto", `estimation.fit_estimator` = `fit_wiener`): the kernel
estimator only where cross-validation shows a real gain over the best affine method
(`KERNEL_MIN_GAIN`, `KERNEL_MIN_Z`, from `KERNEL_MIN_TARGETS` targets), every method reported;
`kernel_gain` and the random folds of the kernel estimator against numbers worked by hand."""

from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest

import spherejax as sj
from spherejax import estimation
from spherejax.cli.shared import wiener_report_table
from tests.helpers import nonlinear_targets


def test_kernel_gain_is_the_rms_ratio_and_the_paired_z_of_the_targets():
    rng = np.random.default_rng(0)
    R = rng.uniform(0, 1, (60, 31))
    mean = R + rng.normal(scale=0.02, size=R.shape)
    kernel = R + rng.normal(scale=0.015, size=R.shape)
    gain, z = estimation.kernel_gain(mean, kernel, R)
    a, k = np.mean((mean - R) ** 2, axis=1), np.mean((kernel - R) ** 2, axis=1)
    assert gain == pytest.approx(1 - np.sqrt(k.sum() / a.sum()), rel=1e-12)
    d = a - k
    assert z == pytest.approx(d.mean() / (np.sqrt(np.sum((d - d.mean()) ** 2) / (len(d) - 1)) / np.sqrt(len(d))), rel=1e-12)
    assert 0.2 < gain < 0.3 and z > 5
    # Swapped, the same numbers against it; alike, no gain; every target the same better: z capped.
    assert estimation.kernel_gain(kernel, mean, R)[1] == pytest.approx(-z, rel=1e-12)
    assert estimation.kernel_gain(mean, mean, R) == (0.0, 0.0)
    shifted = R + 0.01
    assert estimation.kernel_gain(R + 0.02, shifted, R) == (pytest.approx(0.5), 1e6)


def test_random_folds_are_balanced_and_the_same_every_time():
    labels, text = estimation.random_fold_labels(53, 5)
    again, _ = estimation.random_fold_labels(53, 5)
    np.testing.assert_array_equal(labels, again)
    assert sorted(np.bincount(labels)) == [10, 10, 11, 11, 11]
    assert text == "5 folds of targets drawn at random (seed 0)"
    assert not np.array_equal(labels, np.arange(53) % 5)  # drawn, not in order
    assert estimation.random_fold_labels(3, 5)[1] == "3 folds of targets drawn at random (seed 0)"
    with pytest.raises(ValueError, match="folds: expected an integer >= 2, got 1"):
        estimation.random_fold_labels(10, 1)


@pytest.fixture(scope="module")
def nonlinear():
    rng = np.random.default_rng(3)
    return nonlinear_targets(rng, 200)


def test_auto_takes_the_kernel_estimator_exactly_when_the_rule_says(nonlinear, monkeypatch):
    """The same targets, the same reports, the choice moved only by the thresholds: above the
    gain the cross-validation shows, the affine estimator, with the kernel's report after the
    affine methods' and the local method's (reported, never taken) last."""
    V, R = nonlinear
    chosen = estimation.fit_wiener(V, R)
    assert isinstance(chosen, estimation.ResidualKernelEstimator) and chosen.method == "kernel"
    settings = dict(chosen.cross_validation[0].settings)
    assert settings["gain"] >= estimation.KERNEL_MIN_GAIN and settings["paired_z"] >= estimation.KERNEL_MIN_Z
    assert settings["mean_spectral_rms"] * (1 - settings["gain"]) == pytest.approx(chosen.cross_validation[0].spectral_rms, rel=1e-6)
    monkeypatch.setattr(estimation, "KERNEL_MIN_GAIN", settings["gain"] + 0.01)
    affine = estimation.fit_wiener(V, R)
    assert isinstance(affine, estimation.WienerEstimator) and affine.method == chosen.affine.method
    assert [c.method for c in affine.cross_validation][-2:] == ["kernel", "local"]
    assert affine.cross_validation[-2] == chosen.cross_validation[0]
    assert affine.cross_validation[-1] == chosen.cross_validation[-1]
    np.testing.assert_array_equal(np.asarray(affine.matrix), np.asarray(chosen.affine.matrix))
    monkeypatch.setattr(estimation, "KERNEL_MIN_GAIN", 0.05)
    monkeypatch.setattr(estimation, "KERNEL_MIN_Z", settings["paired_z"] + 1)
    assert estimation.fit_wiener(V, R).method == affine.method


def test_targets_an_affine_map_explains_keep_the_affine_estimator():
    """Reflectances an affine map of the responses plus independent noise: nothing for the kernel
    to learn, so its cross-validated gain stays below the rule's and "auto" stays affine; the
    kernel is still reported, on its own folds."""
    rng = np.random.default_rng(4)
    V = rng.uniform(0.05, 0.9, (150, 16))
    R = 0.2 + V @ rng.normal(scale=0.05, size=(16, 31)) + rng.normal(scale=0.01, size=(150, 31))
    estimator = sj.fit_wiener(V, R)
    assert isinstance(estimator, estimation.WienerEstimator)
    kernel, local = estimator.cross_validation[-2:]
    assert kernel.method == "kernel" and kernel.folds == "5 folds of targets drawn at random (seed 0)"
    assert local.method == "local" and local.folds == kernel.folds
    settings = dict(kernel.settings)
    assert settings["gain"] < estimation.KERNEL_MIN_GAIN or settings["paired_z"] < estimation.KERNEL_MIN_Z


def test_few_targets_or_no_offset_keep_auto_affine_and_kernel_may_still_be_asked_for(nonlinear):
    V, R = nonlinear
    few = estimation.fit_wiener(V[: estimation.KERNEL_MIN_TARGETS - 1], R[: estimation.KERNEL_MIN_TARGETS - 1])
    assert isinstance(few, estimation.WienerEstimator) and "kernel" not in {c.method for c in few.cross_validation}
    no_offset = estimation.fit_wiener(V, R, offset=False)
    assert isinstance(no_offset, estimation.WienerEstimator) and "kernel" not in {c.method for c in no_offset.cross_validation}
    asked = estimation.fit_estimator(V[:30], R[:30], method="kernel")
    settings = dict(asked.cross_validation[0].settings)
    # With fewer targets than a count, every target an inducing point is tried (30); forward
    # selection's 16 may fit as well, and then the cheaper is taken.
    assert asked.method == "kernel" and {m for m, _, _ in settings["tried"]} == {16, 30}
    assert settings["inducing_points"] in (16, 30)
    assert estimation.fit_wiener is estimation.fit_estimator and sj.fit_estimator is estimation.fit_estimator


def test_bad_combinations_are_refused_in_one_line(nonlinear):
    V, R = nonlinear
    with pytest.raises(ValueError, match=r"^offset: the kernel estimator's affine mean has an offset; got offset=False with method='kernel'$"):
        estimation.fit_estimator(V, R, method="kernel", offset=False)
    with pytest.raises(ValueError, match=r"^noise_variance: applies to the training form; got it with method='kernel'$"):
        estimation.fit_estimator(V, R, 1e-4, method="kernel")
    with pytest.raises(ValueError, match=r"^inducing_points: expected an integer >= 1, got 0$"):
        estimation.fit_estimator(V, R, inducing_points=0)


def test_the_report_table_names_the_kernel_estimator_s_own_folds(nonlinear):
    V, R = nonlinear
    estimator = estimation.fit_wiener(V, R)

    class Report:
        wiener_method = estimator.method
        targets = len(V)
        wiener_cross_validation = [c.as_dict() for c in estimator.cross_validation]

    table = wiener_report_table(Report)
    lines = table.splitlines()
    # The chosen one's folds in the head line, the others' where they differ.
    assert lines[0] == (f"reflectance estimator: kernel (cross-validated on {len(V)} targets, "
                        "5 folds of targets drawn at random (seed 0))")
    kernel_line = next(line for line in lines if line.startswith("* kernel"))
    assert "gain=" in kernel_line and "paired_z=" in kernel_line and "folds=" not in kernel_line
    # The lengthscales as their range; every (m, r) tried stays in the file's report, not the table.
    assert re.search(r"lengthscales=[0-9.e+-]+\.\.[0-9.e+-]+,", kernel_line) and "tried=" not in kernel_line
    affine_lines = [line for line in lines[2:] if line.startswith(("  training", "  model"))]
    assert len(affine_lines) == 2
    assert all(line.endswith(", folds=5 folds of spectrally alike targets (k-means)") for line in affine_lines)
    assert all(f"cost_per_pixel={31 * V.shape[1]}," in line for line in affine_lines)
    local_line = lines[-1]  # the local method, on the kernel's folds: no folds= of its own
    assert local_line.startswith("  local") and "folds=" not in local_line and len(lines) == 2 + 4


def test_the_local_method_is_left_out_beyond_its_target_bound(nonlinear, monkeypatch):
    """Past `LOCAL_MAX_TARGETS` targets auto does not cross-validate the local method (its n^2
    work); below it, it reports it last."""
    V, R = nonlinear
    assert estimation.fit_wiener(V, R).cross_validation[-1].method == "local"
    monkeypatch.setattr(estimation, "LOCAL_MAX_TARGETS", len(V) - 1)
    assert "local" not in {c.method for c in estimation.fit_wiener(V, R).cross_validation}


def test_a_kernel_fit_without_x64_warns_of_nothing():
    """Without JAX's x64 (a user's default), fitting the kernel estimator in float32 warns of
    nothing: its report's ΔE00 once took a float64 copy of the reflectances, which JAX truncated
    with a UserWarning in every `calibrate`."""
    script = (
        "import warnings, numpy as np\n"
        "warnings.simplefilter('error')\n"
        "from spherejax import estimation\n"
        "from tests.helpers import nonlinear_targets\n"
        "V, R = nonlinear_targets(np.random.default_rng(3), 120)\n"
        "e = estimation.fit_kernel_estimator(V.astype(np.float32), R.astype(np.float32))\n"
        "print(e.kernel.weights.dtype)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                         cwd=pathlib.Path(__file__).resolve().parent.parent)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["float32"]
