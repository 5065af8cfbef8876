"""Differentiable calibration: gradients through `correct` and the consistency metrics.

jax.grad and jax.jacrev with respect to the Stage II coefficients, the Wiener matrix and
floating white-patch weights, in float64: finite, and equal to central finite differences to
1e-5 relative. The scene is a Lambertian sphere (tests/helpers.py) with P patches on J
backgrounds, plus what Stage I cannot remove (stray light from the background that varies
across the image) and a little pixel noise, so that every derivative checked is well away from
0. The consistency metrics are also checked against a plain numpy implementation.
"""

import warnings

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import spectra
from spherejax.pipeline import patch_bounding_box

from .helpers import gaussian_sensitivity, lambertian_sphere_frames

H, W, B = 24, 32, 16
SATURATION = 16383.0
#: Patch regions (r0, r1, c0, c1), one per patch, at the same place on every background.
REGIONS = [(8, 14, 4, 10), (8, 14, 14, 20), (16, 22, 24, 30)]
P, J = len(REGIONS), 3
#: (patch, background) pairs that were not measured.
ABSENT = [(2, 1)]
#: Relative tolerance of the finite-difference checks of the gradients.
RTOL = 1e-5


@pytest.fixture(scope="module")
def scene():
    """J sample frames (J, H, W, B) of P patches on J backgrounds, float64 counts, with a
    calibration whose patch is a float weight map, and the functions of (coeffs, wiener,
    weights) the tests differentiate."""
    rng = np.random.default_rng(4)
    sets = spectra.reflectance_sets()
    M = gaussian_sensitivity()
    train = np.concatenate([v for k, v in sets.items() if k.startswith(("ColorChecker", "TCS"))])
    estimator = sj.fit_wiener(train @ M.T, train, noise_variance=1e-7)
    # The matrix is differentiated; the affine estimator's offset r0 rides along as a constant
    # (its gradient: tests/test_pipeline.py, TestWienerOffset).
    wiener_matrix, wiener_offset = np.asarray(estimator.matrix), np.asarray(estimator.offset)
    ces = sets["CES (TM-30)"]
    patch_spectra = ces[rng.choice(len(ces), P, replace=False)]
    background_levels = (0.15, 0.5, 0.85)

    white_patch = np.zeros((H, W), bool)
    white_patch[1:5, 1:5] = True
    yy, xx = np.mgrid[0:H, 0:W]
    beta = 1.0 - 0.5 * (((yy - H / 2) / H) ** 2 + ((xx - W / 2) / W) ** 2)
    dark = rng.uniform(95, 105, (H, W, B))
    truth = np.empty((J, H, W, 31))
    white = None
    raws = []
    for j, level in enumerate(background_levels):
        background = level * (0.9 + 0.2 * np.linspace(0, 1, 31))  # gently sloping spectrum
        t = np.broadcast_to(background, (H, W, 31)).copy()
        for (r0, r1, c0, c1), spectrum in zip(REGIONS, patch_spectra):
            t[r0:r1, c0:c1] = spectrum
        truth[j] = t
        white, raw = lambertian_sphere_frames(
            t @ M.T, 1.0, np.ones(B), white_patch, beta, np.full(B, 1.02),
            rho_wall=np.full(B, 0.97), alpha_ww=0.955, alpha_wsp=0.03, alpha_spw=0.97,
            gamma_phi0=np.full(B, 400.0), dark=dark,
        )
        # Stray light from the background, stronger towards the right: a background effect
        # that Stage I does not remove, and a white-patch ratio that varies over the patch.
        stray = 6.0 * level * beta * (0.5 + xx / W)
        raw = raw + stray[..., None] * np.linspace(1.0, 0.6, B)
        raws.append(dark + (raw - dark) * (1.0 + 2e-3 * rng.standard_normal(raw.shape)))
    raw = np.stack(raws)
    raw[0, 10, 6, 3] = np.nan  # a bad pixel inside region 0: left out of the region mean
    raw[1, 2, 3, :] = SATURATION  # a saturated pixel in the white patch: weight 0 in p

    weights = np.where(white_patch, rng.uniform(0.5, 1.5, (H, W)), 0.0)
    region_masks = np.zeros((P, H, W))
    for i, (r0, r1, c0, c1) in enumerate(REGIONS):
        region_masks[i, r0:r1, c0:c1] = 1.0
    present = np.ones((P, J), bool)
    for i, j in ABSENT:
        present[i, j] = False
    reference = np.asarray(sj.reflectance_to_lab(truth))

    def correct(coeffs, wiener_matrix, patch_weights):
        calibration = sj.Calibration(
            dark=dark, white=white, patch=patch_weights, coeffs=coeffs, wiener=wiener_matrix,
            saturation=SATURATION, wiener_offset=wiener_offset,
        )
        return sj.correct(raw, calibration, intermediates=True)

    def region_means(result):
        """Stage II responses (P, J, B) and reflectances (P, J, 31) of a `correct` result
        averaged over the good pixels of each region, NaN where the patch was not measured (as
        `evaluate` has them)."""
        valid = result.valid.astype(jnp.float64)  # (J, H, W)
        counts = jnp.einsum("phw,jhw->pj", region_masks, valid)

        def mean(x):  # (J, H, W, C) -> (P, J, C); bad pixels are NaN, so mask before summing
            x = jnp.where(result.valid[..., None], x, 0.0)
            m = jnp.einsum("phw,jhwc->pjc", region_masks, x) / counts[..., None]
            return jnp.where(present[..., None], m, jnp.nan)

        return mean(result.v_stage2), mean(result.reflectance)

    def losses(coeffs, wiener_matrix, patch_weights):
        """(4,): mean ΔE00 of the good pixels to the truth, then the band-averaged response std,
        the pairwise spectral rms and the pairwise ΔE00 (D65) of the region means."""
        result = correct(coeffs, wiener_matrix, patch_weights)
        de = sj.delta_e_2000(result.lab, reference)
        de_mean = jnp.sum(jnp.where(result.valid, de, 0.0)) / jnp.sum(result.valid).astype(jnp.float64)
        responses, reflectance = region_means(result)
        return jnp.stack([
            de_mean,
            jnp.mean(sj.response_std(responses, present)),
            sj.pairwise_spectral_rms(reflectance, present),
            sj.pairwise_delta_e(reflectance, present, "D65"),
        ])

    # A Stage II away from the identity, so that every coefficient matters.
    coeffs = np.tile([0.95, 0.05, 0.08, -0.09], (B, 1)) + 0.01 * rng.standard_normal((B, 4))
    return dict(
        args=(jnp.asarray(coeffs), jnp.asarray(wiener_matrix), jnp.asarray(weights)),
        raw=raw, dark=dark, white=white, white_patch=white_patch, present=present,
        correct=correct, region_means=jax.jit(lambda *args: region_means(correct(*args))),
        losses=jax.jit(losses),
        # jax.grad of one scalar u . losses: with u = e_k, the gradient of loss k, and one
        # compilation serves all four.
        grad=jax.jit(jax.grad(lambda args, u: u @ losses(*args))),
        jacobian=jax.jit(jax.jacrev(losses, argnums=(0, 1, 2))),
    )


@pytest.fixture(scope="module")
def derivatives(scene):
    """jax.grad of each loss (4 tuples of 3 arrays) and jax.jacrev of all four (3 arrays of
    shape (4, *argument shape)), at the scene's arguments."""
    args = scene["args"]
    gradients = [scene["grad"](args, jnp.eye(4)[k]) for k in range(4)]
    return dict(
        grad=[[np.asarray(g) for g in gradient] for gradient in gradients],
        jacobian=[np.asarray(jac) for jac in scene["jacobian"](*args)],
    )


NAMES = ("delta_e_to_truth", "response_std", "spectral_rms", "pairwise_delta_e")
ARGUMENTS = ("coeffs", "wiener", "patch weights")


def central_difference(fn, args, argnum, index, step):
    """(fn(x + h e) - fn(x - h e)) / 2h for entry `index` of argument `argnum`."""
    def shifted(sign):
        moved = list(args)
        moved[argnum] = args[argnum].at[index].add(sign * step)
        return np.asarray(fn(*moved))

    return (shifted(1.0) - shifted(-1.0)) / (2.0 * step)


def entries_to_check(gradient, count, rng):
    """The largest entry and `count - 1` random others among those at least 1 % of it: well
    above the finite differences' rounding floor, so that 1e-5 relative is a fair test."""
    magnitude = np.abs(np.asarray(gradient))
    large = np.argwhere(magnitude >= 0.01 * magnitude.max())
    picks = rng.choice(len(large), min(count - 1, len(large)), replace=False)
    chosen = {tuple(int(k) for k in np.unravel_index(magnitude.argmax(), magnitude.shape))}
    chosen |= {tuple(int(k) for k in large[p]) for p in picks}
    return sorted(chosen)


def step_for(x):
    """1e-6 relative, 1e-6 absolute for entries at or near 0 (the c2..c4 and weights of 0)."""
    return 1e-6 * max(abs(float(x)), 1.0)


class TestScene:
    def test_metrics_are_well_away_from_zero(self, scene):
        """Guards the other tests: a scene Stage I corrected perfectly would give zero
        metrics, whose gradients are 0 by convention and test nothing."""
        values = np.asarray(scene["losses"](*scene["args"]))
        assert np.all(np.isfinite(values)) and np.all(values > 1e-4), values
        responses, reflectance = scene["region_means"](*scene["args"])
        assert responses.shape == (P, J, B) and reflectance.shape == (P, J, 31)
        assert np.array_equal(np.isfinite(np.asarray(responses)).all(-1), scene["present"])

    def test_weights_equal_to_the_mask_reproduce_it(self, scene):
        """A float patch of 0/1 weights gives the boolean mask's result: same box, same p."""
        args = scene["args"]
        with_mask = scene["correct"](args[0], args[1], scene["white_patch"])
        with_weights = scene["correct"](args[0], args[1], scene["white_patch"].astype(np.float64))
        np.testing.assert_array_equal(np.asarray(with_weights.p), np.asarray(with_mask.p))
        np.testing.assert_array_equal(np.asarray(with_weights.lab), np.asarray(with_mask.lab))


class TestGradients:
    @pytest.mark.parametrize("loss", range(4), ids=NAMES)
    @pytest.mark.parametrize("argnum", [0, 1, 2], ids=ARGUMENTS)
    def test_grad_matches_central_differences(self, scene, derivatives, argnum, loss):
        """jax.grad of each loss against central differences of the same jitted losses, on
        the largest entry and a few others (the image has a NaN and a saturated pixel, and one
        patch was not measured on one background)."""
        args = scene["args"]
        gradient = derivatives["grad"][loss][argnum]
        assert gradient.shape == args[argnum].shape and np.isfinite(gradient).all()
        if (NAMES[loss], ARGUMENTS[argnum]) == ("response_std", "wiener"):
            np.testing.assert_array_equal(gradient, 0.0)  # responses come before the Wiener step
            return
        assert np.abs(gradient).max() > 0
        for index in entries_to_check(gradient, 4, np.random.default_rng(10 * argnum + loss)):
            fd = central_difference(scene["losses"], args, argnum, index, step_for(args[argnum][index]))
            assert gradient[index] == pytest.approx(float(fd[loss]), rel=RTOL), (loss, index)

    @pytest.mark.parametrize("argnum", [0, 1, 2], ids=ARGUMENTS)
    def test_jacrev_equals_grad(self, scene, derivatives, argnum):
        """jax.jacrev of the four losses: finite, shaped (4, *argument), and row k is jax.grad
        of loss k (so it matches the finite differences too)."""
        jacobian = derivatives["jacobian"][argnum]
        assert jacobian.shape == (4, *scene["args"][argnum].shape) and np.isfinite(jacobian).all()
        for loss in range(4):
            want = derivatives["grad"][loss][argnum]
            # Reverse mode of four cotangents at once and of one sum in different orders: float64
            # rounding, relative to the gradient's scale. An entry that is itself small next to
            # the others (cancellation) cannot be held to rtol alone: with the affine Wiener
            # estimate's offset one entry of d loss/dW, 1/150 of the largest, differed by 1e-10
            # of itself, 1e-12 of the largest.
            np.testing.assert_allclose(jacobian[loss], want, rtol=1e-10, atol=max(1e-16, 1e-11 * float(np.abs(want).max())))

    def test_gradient_of_a_zero_weight(self, scene, derivatives):
        """d/d(weight) of a pixel outside the patch, at weight 0, is not 0: p would change if
        the pixel were let in. (Masking zero weights out of p would make it 0.)"""
        args = scene["args"]
        outside = (6, 12)  # background, not patch; not in any region either
        assert args[2][outside] == 0.0
        jacobian = derivatives["jacobian"][2][:, outside[0], outside[1]]
        fd = central_difference(scene["losses"], args, 2, outside, 1e-6)
        assert np.all(jacobian != 0.0)
        np.testing.assert_allclose(jacobian, fd, rtol=RTOL)

    def test_jacrev_of_the_per_band_response_std(self, scene):
        def std_per_band(coeffs, wiener_matrix, weights):
            responses, _ = scene["region_means"](coeffs, wiener_matrix, weights)
            return sj.response_std(responses, scene["present"])

        args = scene["args"]
        jac_coeffs, jac_weights = jax.jit(jax.jacrev(std_per_band, argnums=(0, 2)))(*args)
        assert jac_coeffs.shape == (B, B, 4) and jac_weights.shape == (B, H, W)
        assert np.isfinite(np.asarray(jac_coeffs)).all() and np.isfinite(np.asarray(jac_weights)).all()
        # Band b's std depends on band b's coefficients only.
        jac_coeffs = np.asarray(jac_coeffs)
        assert np.all(jac_coeffs[~np.eye(B, dtype=bool)] == 0.0)
        assert np.all(np.abs(jac_coeffs[np.arange(B), np.arange(B)]).sum(-1) > 0)


# ------------------------------------------------------------------------------------------------
# The metrics on their own: a plain numpy oracle, zero spread, input checks.


def numpy_response_std(responses, present):
    per_patch = []
    for i in range(responses.shape[0]):
        measured = responses[i][present[i]]
        if len(measured):
            per_patch.append(np.std(measured, axis=0))
    return np.mean(per_patch, axis=0)


def numpy_pairwise(values, present, distance):
    per_patch = []
    for i in range(values.shape[0]):
        backgrounds = np.flatnonzero(present[i])
        pairs = [(a, b) for n, a in enumerate(backgrounds) for b in backgrounds[n + 1:]]
        if pairs:
            per_patch.append(np.mean([distance(values[i, a], values[i, b]) for a, b in pairs]))
    return np.mean(per_patch)


@pytest.fixture
def random_measurements():
    """(P, J) = (7, 5) responses and reflectances, NaN where absent; one patch with a single
    background (no pair) and one with none."""
    rng = np.random.default_rng(3)
    present = rng.random((7, 5)) > 0.3
    present[0] = [True, False, False, False, False]
    present[1] = False
    present[2] = True
    responses = np.where(present[..., None], rng.uniform(0.05, 1.0, (7, 5, B)), np.nan)
    reflectance = np.where(present[..., None], rng.uniform(0.02, 0.95, (7, 5, 31)), np.nan)
    return responses, reflectance, present


class TestConsistencyMetrics:
    def test_against_numpy(self, random_measurements, maybe_jit):
        responses, reflectance, present = random_measurements
        np.testing.assert_allclose(
            np.asarray(maybe_jit(sj.response_std)(responses, present)),
            numpy_response_std(responses, present), rtol=1e-12,
        )
        rms = numpy_pairwise(reflectance, present, lambda a, b: np.sqrt(np.mean((a - b) ** 2)))
        assert float(maybe_jit(sj.pairwise_spectral_rms)(reflectance, present)) == pytest.approx(rms, rel=1e-12)
        for illuminant in ("D65", "A", "F2"):
            lab = np.asarray(sj.reflectance_to_lab(np.nan_to_num(reflectance), illuminant))
            de = numpy_pairwise(lab, present, lambda a, b: colour.difference.delta_E_CIE2000(a, b))
            value = maybe_jit(sj.pairwise_delta_e, static_argnames="illuminant")(reflectance, present, illuminant)
            assert float(value) == pytest.approx(de, rel=1e-10), illuminant

    def test_per_band_presence(self, random_measurements):
        """present (P, J, B): a band missing on its own is left out of that band only."""
        responses, _, present = random_measurements
        responses = responses.copy()
        responses[2, 3, 5] = np.nan
        per_band = np.broadcast_to(present[..., None], responses.shape) & np.isfinite(responses)
        std = np.asarray(sj.response_std(responses, per_band))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # nanstd of the unmeasured patch
            expected = np.nanmean(np.nanstd(responses, axis=1), axis=0)
        np.testing.assert_allclose(std, expected, rtol=1e-12)

    def test_gradients_finite_with_nan_in_absent_entries(self, random_measurements):
        responses, reflectance, present = random_measurements
        for fn, x in [
            (lambda x: jnp.mean(sj.response_std(x, present)), responses),
            (lambda x: sj.pairwise_spectral_rms(x, present), reflectance),
            (lambda x: sj.pairwise_delta_e(x, present, "A"), reflectance),
        ]:
            gradient = np.asarray(jax.jit(jax.grad(fn))(x))
            assert np.isfinite(gradient).all()
            assert np.all(gradient[~present] == 0.0)  # absent entries do not matter
            assert np.abs(gradient[present]).max() > 0

    def test_identical_backgrounds_give_exactly_zero(self, random_measurements):
        """Every background gives the same responses: all three metrics are exactly 0 and their
        gradients finite (0: safe sqrt at the minimum)."""
        responses, reflectance, present = random_measurements
        same_responses = np.where(present[..., None], np.nan_to_num(responses[:, 2:3]), np.nan)
        same_reflectance = np.where(present[..., None], np.nan_to_num(reflectance[:, 2:3]), np.nan)
        cases = [
            (lambda x: jnp.mean(sj.response_std(x, present)), same_responses),
            (lambda x: sj.pairwise_spectral_rms(x, present), same_reflectance),
            (lambda x: sj.pairwise_delta_e(x, present, "D65"), same_reflectance),
        ]
        for fn, x in cases:
            value, gradient = jax.jit(jax.value_and_grad(fn))(x)
            assert float(value) == 0.0
            np.testing.assert_array_equal(np.asarray(gradient), 0.0)

    def test_no_patch_qualifies_gives_nan(self):
        """One background: no pair, so NaN; one measurement per patch is a std of 0; no
        measurement at all, NaN. (Jitted: eager dispatch would compile each op for the shape.)"""
        one_background = np.full((3, 1, 31), 0.5)
        present = np.ones((3, 1), bool)
        assert np.isnan(float(jax.jit(sj.pairwise_spectral_rms)(one_background, present)))
        assert np.isnan(float(jax.jit(sj.pairwise_delta_e)(one_background, present)))
        response_std = jax.jit(sj.response_std)
        np.testing.assert_array_equal(np.asarray(response_std(one_background[..., :B], present)), 0.0)
        assert np.isnan(np.asarray(response_std(one_background[..., :B], ~present))).all()

    def test_float32_stays_float32(self, random_measurements):
        responses, reflectance, present = (
            jax.ShapeDtypeStruct(x.shape, np.float32 if x.dtype == np.float64 else x.dtype)
            for x in random_measurements
        )
        assert jax.eval_shape(sj.response_std, responses, present).dtype == np.float32
        assert jax.eval_shape(sj.pairwise_spectral_rms, reflectance, present).dtype == np.float32
        assert jax.eval_shape(sj.pairwise_delta_e, reflectance, present).dtype == np.float32

    @pytest.mark.parametrize(
        "call, match",
        [
            (lambda: sj.response_std(np.zeros((3, 4)), np.ones((3, 4), bool)), r"responses: expected shape \(P, J, B\), got \(3, 4\)"),
            (lambda: sj.response_std(np.zeros((3, 4, B)), np.ones((3, 4), int)), "present: expected a boolean array, got dtype int64"),
            (lambda: sj.response_std(np.zeros((3, 4, B)), np.ones((4, 3), bool)), r"present: expected shape \(3, 4\) or \(3, 4, 16\)"),
            (lambda: sj.pairwise_spectral_rms(np.zeros((3, 4, 16)), np.ones((3, 4), bool)), r"reflectance: expected shape \(\.\.\., 31\)"),
            (lambda: sj.pairwise_delta_e(np.zeros((3, 4, 31)), np.ones((3, 4, 31), bool)), r"present: expected shape \(3, 4\) \("),
            (lambda: sj.pairwise_delta_e(np.zeros((3, 4, 31)), np.ones((3, 4), bool), "D50"), "illuminant: unknown illuminant 'D50'"),
        ],
        ids=["rank", "present-dtype", "present-shape", "wavelengths", "present-per-channel", "illuminant"],
    )
    def test_bad_input(self, call, match):
        with pytest.raises(ValueError, match=match):
            call()


# ------------------------------------------------------------------------------------------------
# Patch weights in a Calibration.


class TestPatchWeights:
    @pytest.fixture
    def fields(self, scene):
        return dict(
            dark=scene["dark"], white=scene["white"], coeffs=np.asarray(scene["args"][0]),
            wiener=np.asarray(scene["args"][1]),
        )

    def test_box_comes_from_the_nonzero_weights(self, scene, fields):
        """Concrete weights: p over their bounding box equals p over the whole image (traced)."""
        weights = np.asarray(scene["args"][2])
        calibration = sj.Calibration(patch=weights, saturation=SATURATION, **fields)
        direct = sj.correct(scene["raw"], calibration)
        traced = jax.jit(lambda c: sj.correct(scene["raw"], c))(calibration)
        np.testing.assert_allclose(np.asarray(direct.p), np.asarray(traced.p), rtol=1e-12)
        assert patch_bounding_box(calibration.patch) == (1, 5, 1, 5)

    @pytest.mark.parametrize(
        "patch, match",
        [
            (np.zeros((H, W)), "patch: the weights select no pixel"),
            (np.where(np.eye(H, W, dtype=bool), -0.5, 1.0), "patch: expected weights that are finite and >= 0, got 24 that are not"),
            (np.full((H, W), np.nan), "patch: expected weights that are finite and >= 0"),
            (np.ones((H, W), np.int32), "patch: expected a boolean mask, got dtype int32"),
            (np.ones((H, W), np.complex64), "patch: expected a boolean mask, got dtype complex64"),
        ],
        ids=["all-zero", "negative", "nan", "int", "complex"],
    )
    def test_refused(self, fields, patch, match):
        with pytest.raises(ValueError, match=match):
            sj.Calibration(patch=patch, **fields)

    def test_not_checked_when_traced(self, fields):
        """Under jit the weights are values of the computation: no check, no error."""
        result = jax.jit(lambda w: sj.Calibration(patch=w, **fields).patch.sum())(np.zeros((H, W)))
        assert float(result) == 0.0
