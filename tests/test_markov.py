"""The Markov-model baseline (Hidović-Rowe, Rowe, Lualdi 2006)."""

import numpy as np
import pytest

import spherejax as sj
from spherejax.markov import fit_markov_kappa, markov_correct

from .helpers import lambertian_sphere_frames

H, W, B = 16, 20, 16


def frames_on(background, lamp, rng):
    """Flat-fielded g, holder mean g and the grey tile's truth on one background (Eq. 7-13)."""
    patch = np.zeros((H, W), bool)
    patch[1:4, 1:4] = True
    grey = rng.uniform(0.05, 0.9)
    rho = np.full((H, W, B), background)
    rho[8:14, 8:16] = grey
    dark = np.full((H, W, B), 100.0)
    white, raw = lambertian_sphere_frames(
        rho, 0.99, np.full(B, 0.99), patch, np.ones((H, W)), np.full(B, lamp),
        rho_wall=np.full(B, 0.97), alpha_ww=0.955, alpha_wsp=0.03, alpha_spw=0.97,
        gamma_phi0=np.full(B, 300.0), dark=dark,
    )
    v = np.asarray(sj.flat_field(raw, dark, white))
    g = v * 0.99
    holder = ~patch
    return g[8:14, 8:16].mean((0, 1)), g[holder].mean(0), np.full(B, grey), v, np.asarray(sj.white_patch_ratio(raw, dark, white, patch))


class TestIdealSphere:
    def test_recovers_exact_markov_data(self):
        rng = np.random.default_rng(0)
        kappa = rng.uniform(0.5, 2.0, B)
        R = rng.uniform(0.05, 0.9, (40, B))
        g_bar = rng.uniform(0.05, 0.8, (40, B))
        R_W = np.full(B, 0.99)
        g = R * (1.0 - kappa * (R_W - g_bar))
        fitted = np.asarray(fit_markov_kappa(g, g_bar, R, R_W))
        np.testing.assert_allclose(fitted, kappa, rtol=1e-10)
        np.testing.assert_allclose(np.asarray(markov_correct(g, g_bar, fitted, R_W)), R, rtol=1e-10)

    def test_removes_the_background_effect_under_a_constant_lamp_but_not_lamp_drift(self):
        """On a Lambertian sphere with a steady lamp the model removes most of the background
        effect; it has no white patch, so a lamp change passes straight through, where Stage I
        (Eq. 17) removes both."""
        rng = np.random.default_rng(1)
        backgrounds = np.linspace(0.05, 0.95, 8)
        train = [frames_on(b, 1.0, rng) for b in backgrounds for _ in range(3)]
        g, g_bar, R = (np.stack([t[i] for t in train]) for i in range(3))
        kappa = np.asarray(fit_markov_kappa(g, g_bar, R, np.full(B, 0.99)))

        steady = [frames_on(b, 1.0, np.random.default_rng(5)) for b in backgrounds]  # same grey
        original = np.std([s[0] for s in steady], axis=0).mean()
        corrected = np.std([np.asarray(markov_correct(s[0], s[1], kappa, np.full(B, 0.99))) for s in steady], axis=0).mean()
        assert corrected < 0.1 * original

        drifting = [frames_on(b, lamp, np.random.default_rng(5)) for b, lamp in zip(backgrounds, np.linspace(0.95, 1.05, 8))]
        markov = np.std([np.asarray(markov_correct(s[0], s[1], kappa, np.full(B, 0.99))) for s in drifting], axis=0).mean()
        stage1 = np.std([s[0] / 0.99 * s[4] for s in drifting], axis=0).mean()
        assert markov > 5 * corrected and stage1 < 1e-9


class TestBadInput:
    def test_kappa_shape(self):
        with pytest.raises(ValueError, match=r"kappa: expected shape \(16,\).*got \(15,\)"):
            markov_correct(np.ones((3, 16)), np.ones(16), np.ones(15), np.ones(16))

    def test_holder_mean_bands(self):
        with pytest.raises(ValueError, match=r"g_holder_mean: expected shape \(\.\.\., 16\)"):
            markov_correct(np.ones((3, 16)), np.ones(4), np.ones(16), np.ones(16))

    def test_fit_shapes(self):
        with pytest.raises(ValueError, match=r"reflectance: expected shape \(5, 16\)"):
            fit_markov_kappa(np.ones((5, 16)), np.ones((5, 16)), np.ones((4, 16)), np.ones(16))
