"""Per-band geometry of the simulated filter-wheel instrument: the optics behind each band's map,
the maps' conventions, the simulator rendering each band where its map says, and the truth a
session records under "band_transforms"."""

import dataclasses
import json

import numpy as np
import pytest

from spherejax import band_geometry as bg
from spherejax import io, simulate
from spherejax.grid import BAND_CENTRES_NM
from tests.helpers import SMALL, assert_refused, run_cli

SHAPE = (192, 272)
IDENTITY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def test_a_tilted_plate_displaces_as_the_textbook_says():
    """t sin θ (1 - cos θ / sqrt(n² - sin² θ)): none untilted, odd in θ, t θ (1 - 1/n) for small θ,
    and exact at a large angle computed by Snell's law."""
    assert bg.plate_displacement_mm(3.0, 1.5, 0.0) == 0.0
    assert bg.plate_displacement_mm(3.0, 1.5, -0.01) == pytest.approx(-bg.plate_displacement_mm(3.0, 1.5, 0.01))
    assert bg.plate_displacement_mm(3.0, 1.5, 1e-4) == pytest.approx(3.0 * 1e-4 * (1 - 1 / 1.5), rel=1e-6)
    theta = np.radians(30.0)
    refracted = np.arcsin(np.sin(theta) / 1.5)
    # The ray crosses the plate along t / cos θ' and leaves parallel, offset by that times sin(θ - θ').
    assert bg.plate_displacement_mm(3.0, 1.5, theta) == pytest.approx(3.0 / np.cos(refracted) * np.sin(theta - refracted), rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_filters_and_lens_misregister_bands_by_fractions_of_a_pixel(seed):
    """The default instrument's physics, relative to the 560 nm band: its map the identity, the
    others a scale and a shift (no rotation or shear: tilts and wedges shift, focus and lateral
    colour scale), their largest displacement 0.1-1 frame pixel (1-10 of the QI695's)."""
    transforms = bg.physical_transforms(simulate.InstrumentModel(), SHAPE, 24.0, seed)
    assert transforms.shape == (16, 2, 3)
    np.testing.assert_array_equal(transforms[bg.REFERENCE_BAND], IDENTITY)
    assert BAND_CENTRES_NM[bg.REFERENCE_BAND] == 560
    np.testing.assert_array_equal(transforms[:, 0, 1], 0.0)
    np.testing.assert_array_equal(transforms[:, 1, 0], 0.0)
    np.testing.assert_allclose(transforms[:, 0, 0], transforms[:, 1, 1])
    assert 0.1 < bg.largest_displacement(transforms, SHAPE) < 1.0
    # Tilt dominates: without it the largest displacement is a fraction of that.
    untilted = bg.physical_transforms(dataclasses.replace(simulate.InstrumentModel(), filter_tilt_deg=0.0), SHAPE, 24.0, seed)
    assert bg.largest_displacement(untilted, SHAPE) < bg.largest_displacement(transforms, SHAPE)


def test_the_misregistration_sets_the_largest_displacement():
    instrument = simulate.InstrumentModel()
    in_register = dataclasses.replace(instrument, band_misregistration_px=0.0)
    np.testing.assert_array_equal(bg.band_transforms(in_register, SHAPE, 24.0, 0), np.broadcast_to(IDENTITY, (16, 2, 3)))
    # The default: the maps as the filters and lens make them (0.2-0.5 px at most, seeds 0-3).
    for seed in range(4):
        default = bg.band_transforms(instrument, SHAPE, 24.0, seed)
        np.testing.assert_array_equal(default, bg.physical_transforms(instrument, SHAPE, 24.0, seed))
        assert 0.15 < bg.largest_displacement(default, SHAPE) < 0.6
    for px in (0.3, 2.0, 7.5):
        transforms = bg.band_transforms(dataclasses.replace(instrument, band_misregistration_px=px), SHAPE, 24.0, 0)
        assert bg.largest_displacement(transforms, SHAPE) == pytest.approx(px, rel=1e-12)
        # At a corner, as the maps are affine: no pixel moves further.
        assert np.max(np.linalg.norm(bg.displacements(transforms, SHAPE), axis=-1)) == pytest.approx(px, rel=1e-12)


def test_each_band_pixel_integrates_its_footprint():
    """box_weights: in register a pixel sees itself alone; shifted by 0.3 px to the right it sees
    70 % of its own pixel and 30 % of the one to its left; scaled, the shares sum to one and their
    centre of mass is where the inverse map sends the pixel's centre."""
    identity = np.broadcast_to(IDENTITY, (1, 2, 3)).copy()
    indices, weights = bg.box_weights(identity, (6, 8))
    flat = np.arange(48)
    np.testing.assert_allclose(np.sum(weights * (indices == flat[None, None]), axis=1), 1.0)
    shifted = identity.copy()
    shifted[0, 0, 2] = 0.3
    indices, weights = bg.box_weights(shifted, (6, 8))
    pixel = 2 * 8 + 4  # row 2, column 4
    shares = {int(i): float(w) for i, w in zip(indices[0, :, pixel], weights[0, :, pixel]) if w > 0}
    assert shares == pytest.approx({pixel: 0.7, pixel - 1: 0.3})
    transforms = bg.band_transforms(dataclasses.replace(simulate.InstrumentModel(), band_misregistration_px=3.0), SHAPE, 24.0, 1)
    indices, weights = bg.box_weights(transforms, SHAPE)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, rtol=1e-12)
    rows, cols = np.divmod(indices, SHAPE[1])
    centre = np.stack([np.sum(weights * cols, axis=1), np.sum(weights * rows, axis=1)], axis=-1)  # (16, H W, 2)
    y, x = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    band_pixels = np.stack([x.ravel(), y.ravel()], axis=-1)
    inverse = np.einsum("bij,bnj->bni", np.linalg.inv(transforms[:, :, :2]), band_pixels[None] - transforms[:, None, :, 2])
    inside = (inverse[..., 0] > 1) & (inverse[..., 0] < SHAPE[1] - 2) & (inverse[..., 1] > 1) & (inverse[..., 1] < SHAPE[0] - 2)
    # To the footprint's scale: a side of 1/s != 1 covers its end pixels in part, off their centres.
    np.testing.assert_allclose(centre[inside], inverse[inside], atol=5e-3)


def test_rms_displacement_between_maps():
    shifted = np.broadcast_to(IDENTITY, (2, 2, 3)).copy()
    shifted[0, :, 2] = (0.3, 0.4)
    np.testing.assert_allclose(bg.rms_displacement(shifted, np.broadcast_to(IDENTITY, (2, 2, 3)), SHAPE), [0.5, 0.0])


def _centroid(image):
    weight = np.clip(image, 0.0, None)
    y, x = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    return np.array([np.sum(weight * x), np.sum(weight * y)]) / np.sum(weight)


def test_each_band_is_rendered_where_its_map_says():
    """The white patch (flat 0.97 on the 0.05 mount, the same in every band) moves in each band's
    frame as the recorded map moves its centre, to 0.005 px (measured 0.001: each band pixel
    integrates the scene over its footprint exactly); with the bands in register the frames are
    the same as ever, and the reference band's to a count."""
    design = simulate.ExperimentDesign(training_backgrounds=2, training_patches=3, test_backgrounds=1, test_patches=1, targets=4)
    optics = dict(noise=False, stray_light_fraction=0.0, vignetting=0.0, filter_gradient=0.0, lamp_fluctuation=0.0, lamp_drift_per_hour=0.0,
                  band_misregistration_px=0.0)
    plain = dataclasses.replace(simulate.InstrumentModel(), **optics)
    moved = dataclasses.replace(plain, band_misregistration_px=1.0)
    reference = simulate.simulate_experiment(seed=4, instrument=plain, design=design)
    misregistered = simulate.simulate_experiment(seed=4, instrument=moved, design=design)
    np.testing.assert_array_equal(reference.band_transforms, np.broadcast_to(IDENTITY, (16, 2, 3)))
    transforms = misregistered.band_transforms
    assert bg.largest_displacement(transforms, reference.image_shape) == pytest.approx(1.0)

    # The patch and the mount around it, 3 px of it on every side: no band moves the holder's
    # white standard into the window or the patch out of it.
    r0, r1, c0, c1 = reference.white_patch
    assert c1 + 3 <= reference.image_shape[1] and c0 - 3 > reference.holder[3]
    window = (slice(r0 - 3, r1 + 3), slice(c0 - 3, c1 + 3))
    origin = np.array([c0 - 3, r0 - 3], float)
    white_in, white_moved = (next(f for f in e.frames if f.id == "white").pixels.astype(float) for e in (reference, misregistered))

    def centre(frame, band):
        patch = frame[window][..., band]
        return _centroid(patch - np.median(patch[0])) + origin  # the mount's level off

    before = centre(white_in, bg.REFERENCE_BAND)
    errors = []
    for band in range(16):
        expected = transforms[band, :, :2] @ before + transforms[band, :, 2]
        errors.append(np.linalg.norm(centre(white_moved, band) - expected))
    assert max(errors) < 0.005  # measured 0.001
    np.testing.assert_allclose(white_moved[..., bg.REFERENCE_BAND], white_in[..., bg.REFERENCE_BAND], atol=1)


def test_the_session_records_the_truth(tmp_path, capsys):
    """`simulate --band-misregistration PX`: the manifest's "band_transforms", 16 maps whose
    largest displacement is PX, loaded back as `Session.band_transforms`; identities without."""
    assert run_cli(["simulate", "-o", str(tmp_path / "moved"), "--band-misregistration", "1.5", "-q"], capsys)[0] == 0
    manifest = json.loads((tmp_path / "moved" / "manifest.json").read_text())
    transforms = np.asarray(manifest["band_transforms"])
    assert transforms.shape == (16, 2, 3)
    session = io.load_session(tmp_path / "moved")
    np.testing.assert_array_equal(session.band_transforms, transforms)
    assert bg.largest_displacement(transforms, session.image_shape) == pytest.approx(1.5)
    np.testing.assert_array_equal(transforms[bg.REFERENCE_BAND], IDENTITY)


def test_a_misregistration_out_of_range_is_refused_before_anything_is_written(tmp_path, capsys):
    for value in ("-1", "51", "nan", "two"):
        status, _, err = run_cli(["simulate", "-o", str(tmp_path / "s"), "--band-misregistration", value], capsys)
        assert_refused(status, err, "--band-misregistration", "0..50")
        assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("bad, problem", [
    ("mirrored", "a e - b d > 0"),
    ("short", "16 2 x 3 affine maps"),
    ("not numbers", "16 2 x 3 affine maps"),
])
def test_a_manifest_with_bad_band_transforms_is_refused(tmp_path, bad, problem):
    folder = tmp_path / "session"
    io.write_simulated_session(folder, seed=0, design=SMALL)
    manifest_path = folder / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    transforms = np.broadcast_to(IDENTITY, (16, 2, 3)).tolist()
    if bad == "mirrored":
        transforms[3] = [[-1.0, 0.0, 271.0], [0.0, 1.0, 0.0]]
    elif bad == "short":
        transforms = transforms[:15]
    else:
        transforms[0][0][0] = "one"
    manifest["band_transforms"] = transforms
    manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(io.SessionError) as caught:
        io.load_session(folder)
    assert "band_transforms" in str(caught.value) and problem in str(caught.value)
