"""What an acquisition records for calibrate's noise model: the profile's [noise] section, the
camera's gain and read noise in the session's metadata "camera", and every frame's own
"frames_averaged" (the key a simulated session has)."""

from __future__ import annotations

import os
import types

import numpy as np
import pytest

from spherejax_hw import acquire, acquisition_session
from spherejax_hw.profile import NoiseSettings, ProfileError, load_profile
from spherejax import calibrate, io, simulate

from .support import SAMPLES, quiet_settings, write_profile
from .profiles import check_message, example, write

NOISE = {"gain_e_per_count": 1.04, "read_noise_counts": 5.8, "white_reflectance_u": 0.003}


@pytest.fixture
def folder(tmp_path):
    path = tmp_path / "instrument"
    path.mkdir()
    return path


# ----------------------------------------------------------------------------------- profile


def test_profile_without_noise_section_knows_nothing(folder):
    assert load_profile(write(folder, example())).noise == NoiseSettings(None, None, None)


def test_profile_noise_section_parses(folder):
    data = example()
    data["noise"] = dict(NOISE)
    assert load_profile(write(folder, data)).noise == NoiseSettings(1.04, 5.8, 0.003)
    data["noise"] = {"gain_e_per_count": 2, "read_noise_counts": 0}  # integers, no read noise
    noise = load_profile(write(folder, data)).noise
    assert noise == NoiseSettings(2.0, 0.0, None) and isinstance(noise.gain_e_per_count, float)
    data["noise"] = {"white_reflectance_u": 0}  # the certificate alone (a camera that reports its own)
    assert load_profile(write(folder, data)).noise == NoiseSettings(None, None, 0.0)


@pytest.mark.parametrize(
    ("noise", "key", "expected"),
    [
        ({"gain_e_per_count": 0, "read_noise_counts": 5}, "noise.gain_e_per_count", "a number > 0"),
        ({"gain_e_per_count": -1.0, "read_noise_counts": 5}, "noise.gain_e_per_count", "electrons per count"),
        ({"gain_e_per_count": "1.0", "read_noise_counts": 5}, "noise.gain_e_per_count", "a number > 0"),
        ({"gain_e_per_count": True, "read_noise_counts": 5}, "noise.gain_e_per_count", "a number > 0"),
        ({"gain_e_per_count": float("inf"), "read_noise_counts": 5}, "noise.gain_e_per_count", "a number > 0"),
        ({"gain_e_per_count": 1.0, "read_noise_counts": -0.5}, "noise.read_noise_counts", "a number >= 0"),
        ({"gain_e_per_count": 1.0, "read_noise_counts": float("nan")}, "noise.read_noise_counts", "a number >= 0"),
        ({"gain_e_per_count": 1.0}, "noise.read_noise_counts", "both gain_e_per_count and read_noise_counts, or neither"),
        ({"read_noise_counts": 5.0}, "noise.gain_e_per_count", "both gain_e_per_count and read_noise_counts"),
        ({"white_reflectance_u": -0.01}, "noise.white_reflectance_u", "a relative standard uncertainty >= 0"),
        ({"gain": 1.0}, "noise.gain", "one of ['gain_e_per_count', 'read_noise_counts', 'white_reflectance_u']"),
    ],
    ids=["gain-zero", "gain-negative", "gain-text", "gain-bool", "gain-inf", "read-negative", "read-nan",
         "gain-alone", "read-alone", "certificate-negative", "unknown-key"],
)
def test_bad_noise_section_is_refused_in_one_line(folder, noise, key, expected):
    data = example()
    data["noise"] = noise
    path = write(folder, data)
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    check_message(caught.value, path, key, expected)


def test_noise_that_is_not_a_table_is_refused(folder):
    data = example()
    data["noise"] = 3
    path = write(folder, data)
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    check_message(caught.value, path, "noise", "a table")


# ------------------------------------------------------------------------ the camera record


def test_camera_record_prefers_the_cameras_own_values(folder):
    data = example()
    data["noise"] = dict(NOISE)
    profile = load_profile(write(folder, data))
    real = types.SimpleNamespace(name="retiga", noise_parameters=None)
    assert acquisition_session._camera_noise(profile, real) == {
        "gain_e_per_count": 1.04, "read_noise_counts": 5.8, "white_reflectance_u": 0.003,
        "source": "profile profile.toml [noise]",
    }
    knows = types.SimpleNamespace(name="sim", noise_parameters={"gain_e_per_count": 2.0, "read_noise_counts": 3.0})
    assert acquisition_session._camera_noise(profile, knows) == {
        "gain_e_per_count": 2.0, "read_noise_counts": 3.0, "white_reflectance_u": 0.003, "source": "camera 'sim'",
    }
    bare = load_profile(write(folder, example(), "bare.toml"))
    assert acquisition_session._camera_noise(bare, real) == {}


def test_simulated_camera_reports_its_models_noise():
    from spherejax_hw.simcamera import SimulatedCamera

    instrument = simulate.InstrumentModel()
    camera = SimulatedCamera(light_path=lambda: None, shutter_open=lambda: False)
    gain = instrument.gain_e_per_dn
    assert camera.noise_parameters == {"gain_e_per_count": gain, "read_noise_counts": instrument.read_noise_e / gain}
    quiet = SimulatedCamera(light_path=lambda: None, shutter_open=lambda: False, instrument=simulate.InstrumentModel(noise=False))
    assert quiet.noise_parameters is None


# ---------------------------------------------------------------------- an emulated acquisition


def test_emulated_acquisition_records_camera_noise_and_frames(tmp_path):
    profile = write_profile(tmp_path, samples=SAMPLES[:1], extra="[noise]\nwhite_reflectance_u = 0.004\n")
    text = profile.read_text().replace("dark_frames = 2", "dark_frames = 3")
    profile.write_text(text)
    out = tmp_path / "session"
    with open(os.devnull, "w") as devnull:
        acquire.acquire(profile, out, emulate=True, operator=acquire.Operator(yes=True, stream=devnull), settings=quiet_settings())
    session = io.load_session(out)
    instrument = simulate.InstrumentModel()
    gain = instrument.gain_e_per_dn
    assert session.metadata["camera"] == {
        "gain_e_per_count": gain, "read_noise_counts": instrument.read_noise_e / gain,
        "white_reflectance_u": 0.004, "source": "camera 'sim'",
    }
    assert {f.id: f.metadata["frames_averaged"] for f in session.frames} == {"dark": 3, "white": 2, SAMPLES[0]: 2}
    for frame in session.frames:
        assert {b["frames_averaged"] for b in frame.metadata["bands"]} == {frame.metadata["frames_averaged"]}

    # calibrate reads the same keys as from a simulated session.
    rng = np.random.default_rng(0)
    bands = session.bands
    fit = types.SimpleNamespace(covariance=np.tile(np.eye(4) * 1e-4, (bands, 1, 1)))
    responses, reflectances = rng.uniform(0.05, 0.9, (40, bands)), rng.uniform(0.02, 0.95, (40, 31))
    model, notes = calibrate.build_noise_model(session, fit, responses, reflectances, rng.normal(size=(31, bands)))
    assert np.asarray(model.gain) == np.float32(gain)
    assert np.asarray(model.read_noise) == np.float32(instrument.read_noise_e / gain)
    assert np.asarray(model.white_reflectance_u) == np.float32(0.004)
    assert (float(model.dark_frames), float(model.white_frames), float(model.sample_frames)) == (3, 2, 2)
    assert notes == []
