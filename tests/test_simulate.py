"""The physical simulator: geometry, reproducibility, exposure, and the phenomena it renders."""

import dataclasses

import numpy as np
import pytest

import spherejax as sj
from spherejax import kubelka_munk as km
from spherejax import simulate

SMALL = simulate.ExperimentDesign(training_backgrounds=3, training_patches=3, test_backgrounds=2, test_patches=3, targets=16)


@pytest.fixture(scope="module")
def experiment():
    return simulate.simulate_experiment(seed=3, design=SMALL)


def frame(experiment, frame_id):
    return next(f for f in experiment.frames if f.id == frame_id)


def test_port_fraction_is_the_papers():
    """Section 5: entrance 6 cm, detector 5 cm, holder 10 x 8 cm on a 50 cm sphere: 1.63 %."""
    alpha_ww, alpha_wsp, alpha_spw = simulate.InstrumentModel().port_fractions()
    assert 1.0 - alpha_ww == pytest.approx(0.0163, abs=5e-5)
    assert alpha_wsp == pytest.approx(0.10 * 0.08 / (np.pi * 0.5**2))
    assert 0.99 < alpha_spw < 1.0


def test_seeded_and_reproducible(experiment):
    again = simulate.simulate_experiment(seed=3, design=SMALL)
    for a, b in zip(experiment.frames, again.frames):
        assert a.id == b.id
        np.testing.assert_array_equal(a.pixels, b.pixels)
    other = simulate.simulate_experiment(seed=4, design=SMALL)
    assert not np.array_equal(frame(experiment, "train-bg00-g0").pixels, frame(other, "train-bg00-g0").pixels)


def test_exposure_puts_the_white_standard_near_80_percent(experiment):
    instrument = experiment.instrument
    white = frame(experiment, "white").pixels.astype(float) - instrument.bias_dn
    peak = np.percentile(white, 99.9, axis=(0, 1))
    np.testing.assert_allclose(peak / instrument.saturation_dn, 0.8, atol=0.05)
    assert white.max() < instrument.saturation_dn - instrument.bias_dn
    # Blue bands need longer exposures (less lamp power and quantum efficiency there).
    assert experiment.exposure_s[0] > 2 * experiment.exposure_s[8]


def test_dark_frame_is_bias_and_read_noise(experiment):
    dark = frame(experiment, "dark").pixels.astype(float)
    assert dark.mean() == pytest.approx(experiment.instrument.bias_dn, abs=0.5)
    assert 0.5 < dark.std() < 3.0  # 6 e- read noise / sqrt(16 frames) at ~1 e-/DN, plus rounding


def test_a_dark_sample_darkens_the_sphere(experiment):
    """Eq. 9-15: p > 1 when the holder is darker than the white standard, more so the darker."""
    dark, white = frame(experiment, "dark").pixels, frame(experiment, "white").pixels
    r0, r1, c0, c1 = experiment.white_patch
    patch = np.zeros(experiment.image_shape, bool)
    patch[r0:r1, c0:c1] = True
    p_dark_background = np.asarray(sj.white_patch_ratio(frame(experiment, "train-bg00-g0").pixels, dark, white, patch))
    p_bright_background = np.asarray(sj.white_patch_ratio(frame(experiment, "train-bg02-g0").pixels, dark, white, patch))
    assert np.all(p_dark_background > p_bright_background) and np.all(p_bright_background > 1.0)


def darkest_patch_after_stage1(instrument, design):
    """(on the darkest training background, on the next) Stage I responses (16,) of the darkest
    training patch of the first group, noise-free instruments: what glare lifts."""
    exp = simulate.simulate_experiment(seed=0, instrument=instrument, design=design)
    dark, white = frame(exp, "dark").pixels, frame(exp, "white").pixels
    r0, r1, c0, c1 = exp.white_patch
    patch = np.zeros(exp.image_shape, bool)
    patch[r0:r1, c0:c1] = True
    means = []
    for fid in ("train-bg00-g0", "train-bg01-g0"):
        f = frame(exp, fid)
        darkest = min(f.regions, key=lambda r: np.mean(r["reflectance"]))
        a0, a1, b0, b1 = darkest["region"]
        v = np.asarray(sj.stage1(sj.flat_field(f.pixels, dark, white), sj.white_patch_ratio(f.pixels, dark, white, patch)))
        means.append(v[a0:a1, b0:b1].mean(axis=(0, 1)))
    return means


def test_glare_lifts_a_dark_patch_on_a_bright_background():
    """Stray light: after Stage I a black patch still reads brighter on a bright background than
    on a dark one; without glare it does not."""
    design = simulate.ExperimentDesign(training_backgrounds=2, training_patches=3, test_backgrounds=1, test_patches=1, targets=4)
    no_noise = dataclasses.replace(simulate.InstrumentModel(), noise=False, non_lambertian_spread=0.0, fluorescence_strength=0.0)
    on_dark, on_bright = (m.mean() for m in darkest_patch_after_stage1(no_noise, design))
    assert on_bright > 1.05 * on_dark
    on_dark, on_bright = (m.mean() for m in darkest_patch_after_stage1(dataclasses.replace(no_noise, stray_light_fraction=0.0), design))
    assert on_bright == pytest.approx(on_dark, rel=2e-3)


def test_a_smaller_patch_gets_more_glare_from_its_background():
    """Why the simulated patches are the paper's 0.5 cm: the share of the long-tailed glare PSF
    that reaches a patch's centre from beyond it falls as the patch grows, so after Stage I a
    black patch's lift from a dark to a bright background is larger for a 12 px (0.5 cm) patch
    than for a 42 px (1.75 cm) one, and close to what the PSF predicts for each."""
    instrument = dataclasses.replace(simulate.InstrumentModel(), noise=False, non_lambertian_spread=0.0, fluorescence_strength=0.0)

    def lift(patch_px, region_px):
        design = simulate.ExperimentDesign(training_backgrounds=2, training_patches=3, test_backgrounds=1, test_patches=1,
                                           targets=4, patch_px=patch_px, region_px=region_px)
        on_dark, on_bright = darkest_patch_after_stage1(instrument, design)
        return np.mean(on_bright - on_dark)

    small, large = lift(12, 4), lift(42, 35)  # measured: 0.0143 and 0.0068, a ratio of 2.1
    assert small > 1.3 * large > 0
    # The PSF's share from beyond a radius R at the centre is 1 / sqrt(1 + (R / core)^2): for
    # R = 6 px and 21 px and an 8 px core, 0.80 and 0.36, a ratio of 2.2; a square patch and a
    # region of finite size put the measured ratio a little below that.
    core = instrument.stray_light_core_px
    predicted = (1 + (21 / core) ** 2) ** 0.5 / (1 + (6 / core) ** 2) ** 0.5
    assert 1.3 < small / large < predicted


def test_fluorescent_background_peaks_near_440nm():
    instrument = simulate.InstrumentModel()
    emission = instrument.fluorescence_emission()
    assert simulate.FINE_WAVELENGTHS_NM[np.argmax(emission)] == pytest.approx(440.0, abs=2.0)
    design = simulate.ExperimentDesign(training_backgrounds=2, training_patches=3, test_backgrounds=1, test_patches=1, targets=4,
                                       fluorescent_training_backgrounds=1)
    exp = simulate.simulate_experiment(seed=0, design=design)
    bright = next(m for m in exp.materials.values() if m.fluorescence > 0)
    assert bright.name.startswith("CES")


def test_reference_surfaces_are_lambertian_and_others_spread(experiment):
    spread = experiment.instrument.non_lambertian_spread
    for material in experiment.materials.values():
        if material.source in ("PTFE board", "ceramic tile", "black anodised"):
            assert material.coupling == 1.0
        else:
            assert abs(material.coupling - 1.0) <= spread


def test_layout(experiment):
    height, width = experiment.image_shape
    r0, r1, c0, c1 = experiment.white_patch
    assert c0 >= experiment.holder[3] and c1 <= width  # beside the holder
    for f in experiment.frames:
        assert f.pixels.shape == (height, width, 16) and f.pixels.dtype == np.uint16
        for region in f.regions:
            a0, a1, b0, b1 = region["region"]
            assert 0 <= a0 < a1 <= height and 0 <= b0 < b1 <= experiment.holder[3]
    training = [f for f in experiment.frames if f.set == "training"]
    assert len({f.background for f in training}) == SMALL.training_backgrounds
    assert all(r["region"][1] - r["region"][0] == SMALL.region_px for f in training for r in f.regions)
    # The paper's patches: 0.5 cm (Section 4), the region in their centre.
    assert SMALL.patch_px / SMALL.pixels_per_cm == pytest.approx(0.5, abs=0.01)


def test_patches_are_opaque_unless_a_scattering_power_is_given():
    """By default a patch is the patch wherever it lies; a translucent one (a scattering power
    S X > 0) reads, over each material beneath it, as Kubelka's layer over that material: on a
    uniform background one material, on a patterned one one per stripe beneath."""
    design = simulate.ExperimentDesign(training_backgrounds=3, training_patches=3, test_backgrounds=2, test_patches=3, targets=4)
    thin_instrument = dataclasses.replace(simulate.InstrumentModel(), sample_layer_scattering_power=2.0)
    opaque = simulate.experiment_layout(seed=0, design=design)
    thin = simulate.experiment_layout(seed=0, design=design, instrument=thin_instrument)
    shown = []
    for name in ("train-bg01-g0", "test-bg01-g0"):
        for region in opaque.scenes[name].regions:
            patch = opaque.materials[region["patch"]]
            r0, r1, c0, c1 = region["region"]
            scene = opaque.scenes[name]
            assert [scene.table[i] for i in np.unique(scene.holder_map[r0:r1, c0:c1])] == [patch]
            scene = thin.scenes[name]
            seen = [scene.table[i] for i in np.unique(scene.holder_map[r0:r1, c0:c1])]
            assert all(m.name == patch.name and m.coupling == patch.coupling for m in seen)
            backgrounds = [m for m in scene.table if not m.name.startswith(("BabelColor", "ColorChecker"))]
            expected = [km.layer_over_background(patch.reflectance, 2.0, m.reflectance) for m in backgrounds]
            for m in seen:
                assert any(np.allclose(m.reflectance, e) for e in expected)
                shown.append(np.max(np.abs(m.reflectance - patch.reflectance)))
            if name.startswith("train"):  # a uniform background
                assert len(seen) == 1 and len(backgrounds) == 1
    assert max(shown) > 0.02  # a light patch shows its background (a black one hides it)
