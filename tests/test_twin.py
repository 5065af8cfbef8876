"""The digital twin (spherejax.twin, `spherejax twin`, `spherejax simulate --instrument`): known
parameters of a simulated instrument recovered from its session, the instrument file's checks,
and the command line's refusals."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from spherejax import io, simulate, twin
from spherejax.simulate import InstrumentModel
from tests.helpers import assert_refused, run_cli as run

#: An instrument unlike the paper's in every parameter the twin fits.
KNOWN = InstrumentModel(
    full_well_e=15000.0, read_noise_e=8.0, vignetting=0.32, filter_gradient=0.04, stray_light_fraction=0.045,
    stray_light_core_px=6.0, wall_reflectance_400nm=0.93, wall_reflectance_700nm=0.975, lamp_fluctuation=0.02,
    band_misregistration_px=0.0,  # the twin models the bands in register (`twin` docstring)
)


def relative_error(name: str, fitted: float, true: float) -> float:
    """|fitted / true - 1|; for the wall's reflectance, of its absorptance 1 - ρ (a 10 % error
    in ρ = 0.95 would allow any wall from a mirror to 0.85)."""
    if name.startswith("wall_reflectance"):
        return abs((1.0 - fitted) / (1.0 - true) - 1.0)
    return abs(fitted / true - 1.0)


@pytest.fixture(scope="module")
def known_session(tmp_path_factory):
    return io.write_simulated_session(tmp_path_factory.mktemp("twin") / "session", seed=3, instrument=KNOWN)


@pytest.fixture(scope="module")
def known_fit(known_session):
    return twin.fit_twin(known_session)


@pytest.mark.slow
def test_it_recovers_a_simulated_instruments_parameters_within_10_percent(known_fit):
    """Measured: every parameter within 3 % (seed 3)."""
    assert tuple(known_fit.fitted) == twin.FITTED_PARAMETERS
    for name in twin.FITTED_PARAMETERS:
        error = relative_error(name, known_fit.fitted[name], getattr(KNOWN, name))
        assert error < 0.10, (name, known_fit.fitted[name], getattr(KNOWN, name))
    assert known_fit.report["white_frame"]["converged"] and known_fit.report["sphere"]["converged"]
    # What the fitted optics leave of the white frame is its noise: 0.3 % of 2 x 2 pixel means.
    assert known_fit.report["white_frame"]["relative_rms"] < 0.01
    # The rest is the base instrument's.
    for field in dataclasses.fields(InstrumentModel):
        if field.name not in twin.FITTED_PARAMETERS:
            assert getattr(known_fit.instrument, field.name) == getattr(InstrumentModel(), field.name)


@pytest.mark.slow
def test_it_recovers_the_papers_instrument_too(tmp_path):
    in_register = InstrumentModel(band_misregistration_px=0.0)  # the twin's model (`twin` docstring)
    session = io.write_simulated_session(tmp_path / "session", seed=11, instrument=in_register)
    fit = twin.fit_twin(session)
    for name in twin.FITTED_PARAMETERS:
        assert relative_error(name, fit.fitted[name], getattr(in_register, name)) < 0.10, (name, fit.fitted[name])


def test_the_noise_statistic_inverts_its_model():
    """Frames drawn from the variance model itself: gain and read noise come back to 2 %."""
    rng = np.random.default_rng(0)
    gain, read, bias, n_dark, n_white = 1.3, 7.0, 100.0, 16, 8
    shape, holder = (160, 200, 6), (0, 160, 0, 200)
    electrons = np.linspace(2000.0, 15000.0, 6)
    dark = np.round(bias + rng.normal(0, read / np.sqrt(n_dark), shape) / gain)
    noise = rng.normal(0, 1, shape) * np.sqrt((electrons + read**2) / n_white)
    white = np.round(bias + (electrons + noise) / gain)
    found = twin.fit_noise(dark, white, holder, n_dark, n_white, saturation=16383)
    assert found["gain_e_per_dn"] == pytest.approx(gain, rel=0.02)
    assert found["read_noise_e"] == pytest.approx(read, rel=0.05)
    assert found["full_well_e"] == pytest.approx(gain * 16383, rel=0.02)


def test_the_sphere_statistic_inverts_eq_9():
    """White patch ratios made by Eq. 9 from a known wall, with 1 % lamp flicker: the wall's
    400 and 700 nm values and the flicker come back."""
    base = InstrumentModel(wall_reflectance_400nm=0.94, wall_reflectance_700nm=0.985)
    rng = np.random.default_rng(1)
    alpha_ww, alpha_wsp, alpha_spw = base.port_fractions()
    weights = base.band_weights()
    wall = twin._band_means(base.wall_reflectance(), weights)
    standard = np.full(16, 0.98)
    means = rng.uniform(0.03, 0.9, (60, 16))
    k_s, k_r = alpha_ww + alpha_wsp * alpha_spw * means, alpha_ww + alpha_wsp * alpha_spw * standard
    ratios = 1.02 * (1 - k_s * wall) / (1 - k_r * wall) * np.exp(rng.normal(0, 0.01, means.shape))
    found = twin.fit_sphere(ratios, means, standard, InstrumentModel())
    assert relative_error("wall_reflectance_400nm", found["wall_reflectance_400nm"], 0.94) < 0.05
    assert relative_error("wall_reflectance_700nm", found["wall_reflectance_700nm"], 0.985) < 0.05
    assert found["lamp_fluctuation"] == pytest.approx(0.01, rel=0.1)


# ---- the instrument file ------------------------------------------------------------------------


def test_the_file_holds_every_field_of_the_model_and_reads_back(tmp_path):
    assert set(io.instruments._Instrument.model_fields) == {f.name for f in dataclasses.fields(InstrumentModel)}
    io.save_instrument(tmp_path / "i.json", KNOWN, fitted=["vignetting"], report={"note": 1})
    assert io.load_instrument(tmp_path / "i.json") == KNOWN
    doc = json.loads((tmp_path / "i.json").read_text())
    assert doc["format"] == io.INSTRUMENT_FORMAT and doc["fitted"] == ["vignetting"]


def test_fields_left_out_take_the_defaults(tmp_path):
    path = tmp_path / "by-hand.json"
    path.write_text(json.dumps({"format": "spherejax-instrument", "format_version": 1, "instrument": {"vignetting": 0.1}}))
    assert io.load_instrument(path) == InstrumentModel(vignetting=0.1)


@pytest.mark.parametrize("instrument, fragments", [
    ({"vignetting": 1.5}, ["instrument.vignetting is 1.5", "0 <= value < 1"]),
    ({"wall_reflectance_400nm": 1.0}, ["instrument.wall_reflectance_400nm is 1.0", "a reflectance"]),
    ({"adc_bits": 12.0}, ["instrument.adc_bits is 12.0", "an integer 8..16"]),
    ({"noise": 1}, ["instrument.noise is 1", "true or false"]),
    ({"full_well_e": "17000"}, ["instrument.full_well_e", "electrons, a number > 0"]),
    ({"wall": 0.9}, ["instrument.wall is not a known key"]),
    ({"sphere_diameter_m": 0.05}, ["ports and a holder that cover the sphere"]),
])
def test_a_bad_field_is_refused_in_one_line_naming_it(tmp_path, instrument, fragments):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"format": "spherejax-instrument", "format_version": 1, "instrument": instrument}))
    with pytest.raises(io.InstrumentFileError) as caught:
        io.load_instrument(path)
    message = str(caught.value)
    assert "\n" not in message and message.startswith(str(path))
    for fragment in fragments:
        assert fragment in message, (fragment, message)


@pytest.mark.parametrize("content, fragment", [
    (b"{not json", "is not JSON"),
    (b'{"format": "spherejax-session", "format_version": 1}', "format is 'spherejax-session'"),
    (b'{"format": "spherejax-instrument", "format_version": 2, "instrument": {}}', "format_version is 2"),
    (b'[1, 2]', "format is 'list'"),
])
def test_what_is_not_an_instrument_file_is_refused(tmp_path, content, fragment):
    path = tmp_path / "x.json"
    path.write_bytes(content)
    with pytest.raises(io.InstrumentFileError, match=fragment):
        io.load_instrument(path)


def test_saving_never_replaces_a_file(tmp_path):
    path = tmp_path / "mine.txt"
    path.write_text("a lab's notes")
    with pytest.raises(io.InstrumentFileError, match="exists"):
        io.save_instrument(path, KNOWN)
    assert path.read_text() == "a lab's notes"


# ---- the command line ---------------------------------------------------------------------------


@pytest.mark.slow
def test_twin_writes_what_simulate_renders(known_session, known_fit, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(twin, "fit_twin", lambda session, base=None: known_fit)  # fitted above: the command's own path
    out = tmp_path / "instrument.json"
    status, _, err = run(["twin", str(known_session.path), "-o", str(out)], capsys)
    assert status == 0, err
    assert io.load_instrument(out) == known_fit.instrument
    small = simulate.ExperimentDesign(training_backgrounds=2, training_patches=3, test_backgrounds=1, test_patches=3, targets=16)
    monkeypatch.setattr(simulate, "ExperimentDesign", lambda: small)
    status, _, err = run(["simulate", "-o", str(tmp_path / "again"), "--instrument", str(out), "--seed", "4"], capsys)
    assert status == 0, err
    simulated = io.load_session(tmp_path / "again").metadata["simulator"]["instrument"]
    assert simulated == dataclasses.asdict(known_fit.instrument)


def test_twin_refuses_an_existing_output_before_any_work(known_session_small, tmp_path, capsys, monkeypatch):
    out = tmp_path / "taken.json"
    out.write_text("someone's file")
    monkeypatch.setattr(twin, "fit_twin", lambda session, base=None: pytest.fail("fitted before refusing"))
    status, _, err = run(["twin", str(known_session_small.path), "-o", str(out)], capsys)
    assert_refused(status, err, str(out), "exists")
    assert out.read_text() == "someone's file"


def test_twin_refuses_to_write_over_the_sessions_manifest(known_session_small, capsys):
    manifest = known_session_small.manifest_path
    before = manifest.read_bytes()
    status, _, err = run(["twin", str(known_session_small.path), "-o", str(manifest)], capsys)
    assert_refused(status, err, str(manifest))
    assert manifest.read_bytes() == before


def test_twin_stopped_by_a_signal_writes_nothing(known_session_small, tmp_path, capsys, monkeypatch):
    def interrupted(session, base=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(twin, "fit_twin", interrupted)
    out = tmp_path / "instrument.json"
    status, _, _ = run(["twin", str(known_session_small.path), "-o", str(out)], capsys)
    assert status == 130
    assert list(tmp_path.iterdir()) == []


def test_a_damaged_certificate_of_the_standard_is_refused(known_session_small, tmp_path, capsys):
    manifest = json.loads(known_session_small.manifest_path.read_text())
    manifest["metadata"]["white_standard_reflectance"] = manifest["metadata"]["white_standard_reflectance"][:30]
    copy = tmp_path / "session"
    shutil.copytree(known_session_small.path, copy)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    status, _, err = run(["twin", str(copy), "-o", str(tmp_path / "i.json")], capsys)
    assert_refused(status, err, "white_standard_reflectance", "31 reflectances")
    assert not (tmp_path / "i.json").exists()


def test_a_session_without_a_certificate_takes_evaluates_default_white(known_session_small, monkeypatch):
    """As `spherejax evaluate` does (an acquired session need not carry the certificate)."""
    from spherejax import evaluate

    metadata = {k: v for k, v in known_session_small.metadata.items() if k != "white_standard_reflectance"}
    session = dataclasses.replace(known_session_small, metadata=metadata)
    twin.check_session(session)
    fit = twin.fit_twin(session)
    assert fit.report["white_standard"] == f"default {evaluate.DEFAULT_WHITE_REFLECTANCE}"
    assert 0.9 < fit.fitted["wall_reflectance_700nm"] < 1.0


def test_twin_starts_from_the_base_instrument_it_is_given(known_session_small, tmp_path, capsys, monkeypatch):
    """--instrument BASE: what the twin does not fit (here the sphere's size) is the base's, and
    the fit itself is made with it (the wall's statistic uses the sphere's port fractions)."""
    io.save_instrument(tmp_path / "base.json", InstrumentModel(sphere_diameter_m=0.4, vignetting=0.1))
    given = []

    def recording(session, base=None):
        given.append(base)
        instrument = dataclasses.replace(base, vignetting=0.3)
        return twin.TwinFit(instrument, {name: getattr(instrument, name) for name in twin.FITTED_PARAMETERS}, {})

    monkeypatch.setattr(twin, "fit_twin", recording)
    status, _, err = run(["twin", str(known_session_small.path), "-o", str(tmp_path / "i.json"),
                          "--instrument", str(tmp_path / "base.json")], capsys)
    assert status == 0, err
    assert given == [InstrumentModel(sphere_diameter_m=0.4, vignetting=0.1)]
    assert io.load_instrument(tmp_path / "i.json") == InstrumentModel(sphere_diameter_m=0.4, vignetting=0.3)


def test_fit_twin_keeps_the_bases_unfitted_fields_and_uses_its_geometry(known_session, known_fit):
    """The paper's sphere 20 % smaller: the fields the twin does not fit come from the base, and
    the wall it fits follows the port fractions (Eq. 9: where the holder is a larger share of
    the sphere, the background moves the light more, and the same white patch ratios mean a
    darker wall)."""
    base = dataclasses.replace(InstrumentModel(), sphere_diameter_m=0.4)
    fit = twin.fit_twin(known_session, base)
    assert fit.instrument.sphere_diameter_m == 0.4
    assert fit.fitted["wall_reflectance_700nm"] < known_fit.fitted["wall_reflectance_700nm"] - 0.005
    assert fit.fitted["vignetting"] == pytest.approx(known_fit.fitted["vignetting"], rel=1e-6)


def test_a_session_without_noise_is_refused_in_one_line(tmp_path, capsys):
    design = simulate.ExperimentDesign(training_backgrounds=2, training_patches=3, test_backgrounds=1, test_patches=3, targets=16)
    quiet = io.write_simulated_session(tmp_path / "quiet", seed=1, instrument=InstrumentModel(noise=False), design=design)
    status, _, err = run(["twin", str(quiet.path), "-o", str(tmp_path / "i.json")], capsys)
    assert_refused(status, err, str(quiet.manifest_path), "noise")
    assert not (tmp_path / "i.json").exists()


def test_simulate_refuses_a_bad_instrument_file_before_creating_the_session(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "spherejax-instrument", "format_version": 1, "instrument": {"vignetting": -0.1}}))
    status, _, err = run(["simulate", "-o", str(tmp_path / "s"), "--instrument", str(bad)], capsys)
    assert_refused(status, err, str(bad), "instrument.vignetting is -0.1")
    assert not (tmp_path / "s").exists()


@pytest.fixture(scope="module")
def known_session_small(tmp_path_factory):
    design = simulate.ExperimentDesign(training_backgrounds=2, training_patches=3, test_backgrounds=1, test_patches=3, targets=16)
    return io.write_simulated_session(tmp_path_factory.mktemp("small") / "session", seed=2, design=design)
