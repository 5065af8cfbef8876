"""`spherejax acquire` with a liquid-crystal tunable filter selecting the bands instead of wheels
([tunable_filter] in the profile): emulated Kurios and VariSpec filters on pseudo-terminals, the
simulated camera following the wavelength the emulated filter is tuned to.

What must hold: the session is the one the wheels give (same frames, bands and exposures rules),
each band image records the filter's model and the wavelength read back; the session calibrates
and evaluates like a simulated one; a profile asking a filter for a band it cannot tune is refused
when it is read, in one line; a filter that fails mid-run stops the run in one line with the
shutter closed and the partial session kept, and --resume completes it.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from spherejax import cli, io
from spherejax_hw import acquire
from spherejax_hw.profile import ProfileError, load_profile

from tests.hw.support import SAMPLES, quiet_settings, run_acquire

GRID = list(range(400, 701, 20))


def write_lctf_profile(folder, *, model="VariSpec-VIS", bands=None, samples=SAMPLES, options="") -> os.PathLike:
    lines = ["[instrument]", 'id = "sphere-lctf"', "[tunable_filter]", f'model = "{model}"', 'port = "/dev/ttyUSB0"',
             "settle_s = 0.0"]
    if bands is not None:
        lines.append(f"bands = {bands}")
    lines += [options, "[shutter]", 'port = "/dev/ttyUSB2"', 'model = "SC10"', "[camera]", 'backend = "sim"',
              "[acquisition]", "frames_averaged = 2", "dark_frames = 2", "warmup_checks = 2"]
    for sample in samples:
        set_name = "training" if sample.startswith("train") else "test"
        lines += ["[[samples]]", f'id = "{sample}"', f'set = "{set_name}"', 'background = "bg"']
    path = folder / "sphere.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.slow
def test_a_varispec_acquisition_writes_a_session_that_calibrates_and_evaluates(tmp_path, capsys):
    """The 16 default bands through an emulated VariSpec VIS (400-720 nm), by the command line,
    of the whole simulated experiment (no [[samples]]: training and test captures and the target
    chart); then `spherejax calibrate` and `evaluate` on the session, as on a simulated one, and
    the paper's result: on the test captures each stage makes the colours more consistent across
    backgrounds (CIEDE2000, D65) than the one before."""
    profile = write_lctf_profile(tmp_path, samples=())
    out = tmp_path / "session"
    status = cli.main(["acquire", "--profile", str(profile), "-o", str(out), "--emulate", "--yes"])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    session = io.load_session(out)
    assert session.instrument_id == "sphere-lctf" and list(session.band_centres_nm) == GRID
    assert [f.id for f in session.frames][:3] == ["dark", "white", "train-bg00-g0"]
    assert [f.role for f in session.frames][-1] == "target"
    for frame in session.frames:
        bands = frame.metadata["bands"]
        assert [b["band_nm"] for b in bands] == GRID
        for b in bands:
            assert b["tunable_filter"] == "VariSpec-VIS" and b["wavelength_nm"] == b["band_nm"]
            assert "wheel" not in b and "positions" not in b
    white = session.white().astype(float)
    level = np.percentile(white.reshape(-1, 16), 99.5, axis=0) / (2**14 - 1)
    assert np.all(np.abs(level - 0.8) < 0.1), level  # each band its own exposure, as with wheels
    assert json.loads((tmp_path / "session" / "manifest.json").read_text())  # readable as written

    calibration = tmp_path / "cal.h5"
    assert cli.main(["-q", "calibrate", str(out), "-o", str(calibration)]) == 0, capsys.readouterr().err
    assert cli.main(["-q", "evaluate", str(out), "-c", str(calibration), "-o", str(tmp_path / "evaluation")]) == 0
    test = json.loads((tmp_path / "evaluation" / "metrics.json").read_text())["metrics"]["test"]
    original, stage1, stage2 = (test[stage]["delta_e00_D65"] for stage in ("original", "stage1", "stage2"))
    assert stage2 < stage1 < original, (original, stage1, stage2)
    assert (tmp_path / "evaluation" / "tables.txt").is_file()


def test_a_kurios_acquisition_tunes_the_bands_the_profile_lists(tmp_path):
    """A Kurios VIS head tunes 420-730 nm: the profile lists the 15 centres from 420 nm; the
    session has those bands, each image the Kurios's wavelength and bandwidth mode."""
    bands = GRID[1:]
    profile = write_lctf_profile(tmp_path, model="Kurios-VIS", bands=bands, samples=SAMPLES[:1],
                                 options='bandwidth = "medium"')
    run_acquire(profile, tmp_path / "session")
    session = io.load_session(tmp_path / "session")
    assert list(session.band_centres_nm) == bands and session.read("white").shape[-1] == 15
    band = session.frame("white").metadata["bands"][3]
    assert band["band_nm"] == 480 and band["wavelength_nm"] == 480.0
    assert band["tunable_filter"] == "Kurios-VIS" and band["bandwidth"] == "medium"


@pytest.mark.parametrize(
    ("model", "bands", "options", "match"),
    [
        ("Kurios-VIS", None, "", r"sphere\.toml: tunable_filter\.model: has no bands list, so asks for the 16 centres "
                                r"with \[400\] nm, outside the Kurios-VIS's 420-730 nm \(expected bands = \[\.\.\.\] of "
                                r"centres inside 420-730 nm\)"),
        ("VariSpec-VIS", [400, 740], "", r"tunable_filter\.bands: lists \[740\] nm, outside the VariSpec-VIS's 400-720 nm"),
        ("VariSpec-VIS", [500, 420], "", r"tunable_filter\.bands: is \[500, 420\] \(expected band centres in increasing order"),
        ("VariSpec-VIS", None, 'bandwidth = "wide"', r"tunable_filter\.bandwidth: is given for a VariSpec-VIS "
                                                     r"\(expected no bandwidth: it is a Kurios option\)"),
        ("Kurios-VIS", [420], "warmup_s = 2.0", r"tunable_filter\.warmup_s: is given for a Kurios-VIS"),
        ("Kurios-VIS", [420], 'bandwidth = "black"', r"tunable_filter\.bandwidth: .*one of wide, medium, narrow"),
        ("Kurios-UV", [420], "", r"tunable_filter\.model: .*one of \['Kurios-NIR', 'Kurios-VIS', 'VariSpec-VIS'\]"),
    ],
    ids=["kurios-default-bands", "outside", "unsorted", "bandwidth-varispec", "warmup-kurios", "black", "model"],
)
def test_a_profile_asking_a_filter_for_what_it_cannot_do_is_refused_when_read(tmp_path, model, bands, options, match):
    profile = write_lctf_profile(tmp_path, model=model, bands=bands, options=options)
    with pytest.raises(ProfileError, match=match) as info:
        load_profile(profile)
    assert "\n" not in str(info.value)


def test_wheels_and_a_tunable_filter_in_one_profile_are_refused(tmp_path):
    profile = write_lctf_profile(tmp_path)
    profile.write_text(profile.read_text() + '[wheels.a]\nport = "/dev/ttyUSB3"\nmodel = "FW212C"\nopen_slot = 12\n')
    with pytest.raises(ProfileError, match=r"wheels: is given beside \[tunable_filter\] \(expected either \[wheels\] "
                                           r"with \[bands\], or \[tunable_filter\] with its bands = \[\.\.\.\]\)"):
        load_profile(profile)
    profile.write_text('[instrument]\nid = "x"\n[shutter]\nport = "/dev/ttyUSB2"\nmodel = "SC10"\n'
                       '[camera]\nbackend = "sim"\n')
    with pytest.raises(ProfileError, match=r"wheels: is missing \(expected a table of \[wheels\.NAME\] tables with \[bands\], "
                                           r"or a \[tunable_filter\] table\)"):
        load_profile(profile)


@pytest.mark.parametrize("fault", ["stop_answering", "vanish"])
def test_a_filter_that_fails_mid_run_stops_it_and_resume_completes_it(tmp_path, fault):
    profile = write_lctf_profile(tmp_path, model="Kurios-VIS", bands=GRID[1:], samples=SAMPLES[:1])
    out, partial = tmp_path / "session", tmp_path / "session.partial"
    state = {}

    def inject(instrument):
        port, state["shutter"] = instrument.emulated["tunable_filter"], instrument.emulated["shutter"].emulator
        instrument.bank.timeout_s = 0.3
        real_average, calls = instrument.camera.average, {"n": 0}

        def average(n):
            calls["n"] += 1
            if calls["n"] == 22:  # among the white standard's bands
                getattr(port, fault)()
            return real_average(n)

        instrument.camera.average = average

    with open(os.devnull, "w") as devnull:
        with pytest.raises(acquire.AcquisitionStopped) as stopped:
            acquire.acquire(profile, out, emulate=True, operator=acquire.Operator(yes=True, stream=devnull),
                            settings=quiet_settings(), on_instrument=inject)
    message = str(stopped.value)
    assert "\n" not in message and "--resume" in message and str(partial) in message
    assert state["shutter"].closed
    kept = acquire.Journal(partial).done_images()
    assert 15 <= len(kept) < 3 * 15 and not out.exists()
    run_acquire(profile, out, resume=True)
    assert [f.id for f in io.load_session(out).frames] == ["dark", "white", SAMPLES[0]] and not partial.exists()


def test_resume_refuses_a_profile_with_other_filter_bands(tmp_path):
    """The work folder's profile identity includes the filter and its bands: a resume with other
    bands is refused, as one with other wheel slots is."""
    profile = write_lctf_profile(tmp_path, model="VariSpec-VIS", bands=GRID[:4], samples=SAMPLES[:1])
    partial = tmp_path / "session.partial"
    state = {}

    def stop_early(instrument):
        real_average = instrument.camera.average

        def average(n):
            state["n"] = state.get("n", 0) + 1
            if state["n"] == 12:
                instrument.emulated["tunable_filter"].vanish()
            return real_average(n)

        instrument.camera.average = average
        instrument.bank.timeout_s = 0.3

    with open(os.devnull, "w") as devnull, pytest.raises(acquire.AcquisitionStopped):
        acquire.acquire(profile, tmp_path / "session", emulate=True, operator=acquire.Operator(yes=True, stream=devnull),
                        settings=quiet_settings(), on_instrument=stop_early)
    assert partial.is_dir()
    write_lctf_profile(tmp_path, model="VariSpec-VIS", bands=GRID[:5], samples=SAMPLES[:1])
    with pytest.raises(acquire.AcquisitionError, match=r"profile in \['tunable_filter'\]"):
        run_acquire(profile, tmp_path / "session", resume=True)
