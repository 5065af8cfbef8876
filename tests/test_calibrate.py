"""spherejax.calibrate's steps on their own: the region measurements, the reference background of
median brightness, the Stage II training data of Eq. 19, and the checks that refuse a session
before any pixel is read. (A whole simulated session calibrated end to end is
tests/test_experiment.py; the noise model it records, tests/test_noise_model_files.py.)"""

import dataclasses
import pathlib

import numpy as np
import pytest

from spherejax import calibrate, io
from spherejax.calibrate import RegionMeasurement
from spherejax.io import FrameInfo, Region
from spherejax.polynomial import MIN_SAMPLES


def measurement(patch, background, v, p, holder_v, frame="f"):
    return RegionMeasurement(frame, "training", background, patch, np.asarray(v, float), np.asarray(p, float),
                             np.asarray(holder_v, float), None)


def test_the_reference_background_is_the_one_of_median_brightness():
    # Brightness of a background: the mean over its captures and bands of p * holder_v.
    levels = {"dark-grey": 0.2, "white": 0.9, "mid-grey": 0.5, "black": 0.05, "light-grey": 0.7}
    measurements = [measurement("g0", name, [0.5, 0.5], [1.0, 1.2], [level, level]) for name, level in levels.items()]
    assert calibrate.reference_background(measurements) == "mid-grey"
    # Two captures of one background count by their mean.
    # black: (0.05 x 1.1 + 1.2 x 1.0) / 2 = 0.63, between mid-grey (0.55) and light-grey (0.77).
    measurements.append(measurement("g1", "black", [0.5, 0.5], [1.0, 1.0], [1.2, 1.2]))
    assert calibrate.reference_background(measurements) == "black"


def test_training_data_is_eq_19():
    """target of a sample = the mean of p * v of the same patch on the reference background; the
    samples of a patch never measured there are left out."""
    rng = np.random.default_rng(1)
    measurements = [
        measurement(patch, background, rng.uniform(0.2, 0.8, 3), rng.uniform(0.9, 1.1, 3), rng.uniform(0.3, 0.6, 3))
        for patch in ("g0", "g1") for background in ("ref", "other", "ref", "third")
    ] + [measurement("g2", "other", [0.4] * 3, [1.0] * 3, [0.5] * 3)]
    v, p, target = calibrate.stage2_training_data(measurements, "ref")
    kept = [m for m in measurements if m.patch != "g2"]
    np.testing.assert_array_equal(v, np.stack([m.v for m in kept]))
    np.testing.assert_array_equal(p, np.stack([m.p for m in kept]))
    for m, row in zip(kept, target):
        on_reference = [n.p * n.v for n in measurements if n.patch == m.patch and n.background == "ref"]
        np.testing.assert_allclose(row, np.mean(on_reference, axis=0), rtol=1e-15)
    with pytest.raises(ValueError, match="reference background 'nowhere' is not among the training backgrounds"):
        calibrate.stage2_training_data(measurements, "nowhere")


def test_region_measurements_are_the_means_of_the_corrected_frame(workspace):
    session = io.load_session(workspace / "session")
    base = calibrate.base_calibration(session)
    frame = session.frames_with(role="sample", set="training")[0]
    measured = calibrate.measure_frames(session, [frame], base)
    assert [m.patch for m in measured] == [region.patch for region in frame.regions]
    result = calibrate.correct(session.read(frame), base, intermediates=True)
    v = np.asarray(result.v, np.float64)
    holder = np.nanmean(v[session.holder_mask()], axis=0)
    for m, region in zip(measured, frame.regions):
        r0, r1, c0, c1 = region.region
        np.testing.assert_allclose(m.v, v[r0:r1, c0:c1].reshape(-1, v.shape[-1]).mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(m.holder_v, holder, rtol=1e-12)
        np.testing.assert_array_equal(m.p, np.asarray(result.p, np.float64))
        assert (m.frame_id, m.set, m.background) == (frame.id, "training", frame.background)


class SessionOf:
    """What `check_session` reads of a session: its manifest's path and its frames."""

    def __init__(self, frames):
        self.frames = tuple(frames)
        self.manifest_path = pathlib.Path("lab/session/manifest.json")

    def frames_with(self, role=None, set=None):
        return tuple(f for f in self.frames if (role is None or f.role == role) and (set is None or f.set == set))


def sample(id, background, patches, set="training"):
    regions = tuple(Region(f"{patch}-{k}", patch, (0, 2, 2 * k, 2 * k + 2)) for k, patch in enumerate(patches))
    return FrameInfo(id, "sample", f"frames/{id}.tif", np.ones(2), "2026-01-01T00:00:00+00:00", set, background, regions)


def targets(id="targets", known=3, group="a"):
    """A target capture of `known` regions of known reflectance, in hold-out group `group`."""
    regions = tuple(Region(f"{id}-{k}", f"{id}-{k}", (0, 2, 2 * k, 2 * k + 2), np.full(31, 0.5)) for k in range(known))
    return FrameInfo(id, "target", f"frames/{id}.tif", np.ones(2), "2026-01-01T00:00:00+00:00", None, None, regions,
                     {"group": group})


def a_good_session():
    return [sample("s1", "bg1", ["g0", "g1"]), sample("s2", "bg2", ["g0", "g1"]), targets("t1", group="a"),
            targets("t2", group="b")]


def test_a_calibratable_session_passes():
    calibrate.check_session(SessionOf(a_good_session()), reference="bg2")


@pytest.mark.parametrize(("frames", "reference", "message"), [
    ([sample("s1", "bg1", ["g0", "g1"], set="test"), targets()], None, "no training capture"),
    ([*a_good_session()[:2], targets(known=1)], None, "1 regions with known reflectance; the Wiener matrix needs at least 2"),
    ([sample("s1", "bg1", ["g0", "g1", "g2", "g3"]), targets()], None, "on 1 background"),
    ([sample("s1", "bg1", ["g0"]), sample("s2", "bg2", ["g0"]), targets()], None, f"at least {MIN_SAMPLES} regions, 2 patches"),
    (a_good_session(), "bg9", "no training background named 'bg9'"),
], ids=["no-training", "one-known-target", "one-background", "too-few-samples", "unknown-reference"])
def test_a_session_that_cannot_be_calibrated_is_refused_by_its_manifest(frames, reference, message):
    with pytest.raises(ValueError, match=message) as refused:
        calibrate.check_session(SessionOf(frames), reference=reference)
    text = str(refused.value)
    assert text.startswith("lab/session/manifest.json: ") and "\n" not in text


def test_hold_out_groups_need_two_groups():
    frames = [*a_good_session()[:2], targets("t1", group="only"), targets("t2", group="only")]
    with pytest.raises(ValueError, match="every target is in group 'only' of field 'group'"):
        calibrate.check_session(SessionOf(frames), wiener_groups="group")
    calibrate.check_session(SessionOf(a_good_session()), wiener_groups="group")


def test_a_target_frame_without_the_group_is_named():
    frames = [*a_good_session()[:3], dataclasses.replace(targets("t2"), metadata={})]
    with pytest.raises(ValueError, match="target frame 't2' has no 'group' to group targets by"):
        calibrate.check_session(SessionOf(frames), wiener_groups="group")
