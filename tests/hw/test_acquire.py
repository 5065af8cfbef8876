"""`spherejax acquire` on emulated devices: the protocol, the session it writes, faults that stop
it with nothing lost, and --resume."""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from spherejax_hw import acquire, lamp
from spherejax import cli, io
from tests.helpers import no_compilation_cache_writes

from tests.hw.support import BANDS, SAMPLES, quiet_settings, run_acquire, write_profile


def test_emulated_acquisition_writes_a_session(tmp_path):
    profile = write_profile(tmp_path)
    out = tmp_path / "session"
    with open(os.devnull, "w") as devnull:
        acquire.acquire(profile, out, emulate=True, operator=acquire.Operator(yes=True, stream=devnull), settings=quiet_settings())
    assert not (tmp_path / "session.partial").exists()
    session = io.load_session(out)
    assert session.instrument_id == "sphere-1" and list(session.band_centres_nm) == BANDS
    assert [f.id for f in session.frames] == ["dark", "white", *SAMPLES]
    assert [f.role for f in session.frames] == ["dark", "white", "sample", "sample"]
    # One exposure per band, shared by darks, white and samples; blue needs much longer.
    exposures = {tuple(f.exposure_s) for f in session.frames}
    assert len(exposures) == 1
    exposure = dict(zip(BANDS, exposures.pop()))
    assert exposure[400] > 2 * exposure[560]
    dark, white = session.dark().astype(float), session.white().astype(float)
    assert np.all(dark.mean(axis=(0, 1)) < 0.05 * white.mean(axis=(0, 1)))
    # The white standard sits near the target level in every band, nothing saturated.
    full = 2**14 - 1
    level = np.percentile(white.reshape(-1, 16), 99.5, axis=0) / full
    assert np.all(np.abs(level - 0.8) < 0.1), level
    assert white.max() < full
    # Per band metadata: the wheels as read back put that band's filter in the path.
    for frame in session.frames:
        bands = frame.metadata["bands"]
        assert [b["band_nm"] for b in bands] == BANDS
        for i, b in enumerate(bands):
            wheel, other = ("a", "b") if i < 8 else ("b", "a")
            assert b["positions"] == {wheel: i % 8 + 1, other: 12}
            assert (b["wheel"], b["slot"]) == (wheel, i % 8 + 1)
            assert b["frames_averaged"] == (2 if frame.role != "dark" else 2)
            assert b["exposure_s"] == exposure[b["band_nm"]]
            for key in ("timestamp", "temperature_c", "lamp_hours", "saturated_pixels"):
                assert key in b
    assert session.metadata["acquisition"]["warmup"]["drift_percent"] < 0.5
    # Samples carry the simulated experiment's regions: the session calibrates like a simulated one.
    assert session.frame("train-bg00-g0").set == "training"
    assert session.frame("train-bg00-g0").regions


@pytest.mark.parametrize("fault", ["stop_answering", "answer_garbage", "vanish"])
@pytest.mark.parametrize("device", ["wheel", "shutter"])
def test_fault_stops_with_nothing_lost_and_resume_completes(tmp_path, fault, device):
    profile = write_profile(tmp_path)
    out = tmp_path / "session"
    partial = tmp_path / "session.partial"
    state = {}

    def inject(instrument):
        port = instrument.emulated["wheels"]["b"] if device == "wheel" else instrument.emulated["shutter"]
        state["shutter"] = instrument.emulated["shutter"].emulator
        camera = instrument.camera
        real_average = camera.average
        calls = {"n": 0}

        def average(n):
            calls["n"] += 1
            if calls["n"] == 25:  # in the middle of the white standard's bands
                getattr(port, fault)()
            return real_average(n)

        camera.average = average

    with open(os.devnull, "w") as devnull:
        operator = acquire.Operator(yes=True, stream=devnull)
        with pytest.raises(acquire.AcquisitionStopped) as stopped:
            acquire.acquire(profile, out, emulate=True, operator=operator, settings=quiet_settings(), on_instrument=inject)
    message = str(stopped.value)
    assert "\n" not in message and "--resume" in message and str(partial) in message
    if device == "wheel":
        assert state["shutter"].closed  # left safe by the shutter, which still answers
    # (a shutter that stopped answering, answers garbage or vanished cannot be closed by anyone)
    journal = acquire.Journal(partial)
    kept = journal.done_images()
    assert 16 <= len(kept) < 4 * 16
    kept_bytes = {key: (partial / record["file"]).read_bytes() for key, record in kept.items()}
    assert not out.exists()

    with open(os.devnull, "w") as devnull:
        acquire.acquire(profile, out, emulate=True, resume=True, operator=acquire.Operator(yes=True, stream=devnull), settings=quiet_settings())
    session = io.load_session(out)
    assert not partial.exists()
    assert [f.id for f in session.frames] == ["dark", "white", *SAMPLES]
    # Nothing retaken: the band images captured before the fault are in the session unchanged.
    for (capture, band), data in kept_bytes.items():
        plane = session.read(capture)[..., BANDS.index(band)]
        kept_plane = np.asarray(_frame_from_bytes(tmp_path, data))[..., 0]
        np.testing.assert_array_equal(plane, kept_plane, err_msg=f"{capture} {band}")


def _frame_from_bytes(tmp_path, data):
    path = tmp_path / "kept.tif"
    path.write_bytes(data)
    return io.read_frame(path)


def test_resume_refuses_another_profile(tmp_path):
    profile = write_profile(tmp_path)
    partial = tmp_path / "session.partial"
    partial.mkdir()
    (partial / "profile.json").write_text(json.dumps({"instrument_id": "other"}))
    with pytest.raises(acquire.AcquisitionError, match=r"differs from the interrupted acquisition's profile in \['bands'"):
        run_acquire(profile, tmp_path / "session", resume=True)


# ---------------------------------------------------------------------------------- command line


def cli_run(argv, capsys):
    status = cli.main(argv)
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_cli_acquire_emulated(tmp_path, capsys):
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    status, out, err = cli_run(["acquire", "--profile", str(profile), "-o", str(tmp_path / "s"), "--emulate", "--yes"], capsys)
    assert status == 0, err
    assert "session written to" in out and "Traceback" not in err
    assert "Place the white standard" in err and "assumed done (--yes)" in err
    assert "48/48 band images" in err
    assert [f.id for f in io.load_session(tmp_path / "s").frames] == ["dark", "white", SAMPLES[0]]


@pytest.mark.parametrize(
    "setup, argv_extra, match",
    [
        (lambda tmp: (tmp / "s").mkdir() or (tmp / "s" / "x").write_text("x"), ["--yes"], "already exists and is not empty"),
        (lambda tmp: (tmp / "s.partial").mkdir(), ["--yes"], "an interrupted acquisition is there"),
        (lambda tmp: None, ["--yes", "--resume"], "no interrupted acquisition to resume"),
        (lambda tmp: None, [], "pass --yes to answer every prompt"),
    ],
    ids=["exists", "partial-left", "nothing-to-resume", "no-terminal"],
)
def test_cli_acquire_refusals(tmp_path, capsys, monkeypatch, setup, argv_extra, match):
    monkeypatch.setattr(sys, "stdin", open(os.devnull))  # not a terminal
    profile = write_profile(tmp_path)
    setup(tmp_path)
    before = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
    status, out, err = cli_run(["acquire", "--profile", str(profile), "-o", str(tmp_path / "s"), "--emulate", *argv_extra], capsys)
    sys.stdin.close()
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("spherejax: error: ") and match in err
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == before


def test_wheel_count_mismatch_refused_before_anything_moves(tmp_path, monkeypatch):
    """A wheel whose pcount? disagrees with the profile: refused naming the wheel, no move."""
    from spherejax_hw import emulators

    real = emulators.FilterWheelEmulator
    made = []

    def fw102c_for_b(*, model, position, **kwargs):
        emulator = real(model="FW102C", position=6, **kwargs) if not made else real(model=model, position=position, **kwargs)
        made.append(emulator)
        return emulator

    monkeypatch.setattr(emulators, "FilterWheelEmulator", fw102c_for_b)
    profile = write_profile(tmp_path)
    with pytest.raises(acquire.AcquisitionError, match=r"wheel 'a' \(\[wheels.a\]\) failed its check: .*reports 6 positions"):
        run_acquire(profile, tmp_path / "s")
    assert all(emulator.moves == [] for emulator in made)
    assert not (tmp_path / "s").exists() and not (tmp_path / "s.partial").exists()


# ------------------------------------------------------------------------------- kill and resume


@pytest.mark.slow
def test_sigkill_then_resume_loses_and_duplicates_nothing(tmp_path):
    profile = write_profile(tmp_path)
    out = tmp_path / "s"
    command = [sys.executable, "-m", "spherejax.cli", "acquire", "--profile", str(profile), "-o", str(out), "--emulate", "--yes"]
    rng = np.random.default_rng(3)
    for attempt in range(3):
        argv = command + (["--resume"] if (tmp_path / "s.partial").exists() else [])
        process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   env=no_compilation_cache_writes(dict(os.environ)))
        # Killed while it acquires: after SESSION.partial exists (start-up, JAX's import among it,
        # takes from 3 s to over 9 s on a loaded 2-core machine), at a random moment.
        deadline = time.monotonic() + 120
        while not (tmp_path / "s.partial").exists() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(float(rng.uniform(0.5, 4.0)))
        process.send_signal(signal.SIGKILL)
        process.wait()
        if out.exists():
            break
    if not out.exists():
        # --resume only where a kill left an acquisition (one that completed removed it).
        resume = ["--resume"] if (tmp_path / "s.partial").exists() else []
        done = subprocess.run(command + resume, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
    session = io.load_session(out)
    assert [f.id for f in session.frames] == ["dark", "white", *SAMPLES]
    for frame in session.frames:
        assert [b["band_nm"] for b in frame.metadata["bands"]] == BANDS  # each band exactly once
    assert not (tmp_path / "s.partial").exists()


@pytest.mark.parametrize(
    "emulator, identity, match",
    [
        ("FilterWheelEmulator", "ACME FILTERWHEEL 2.0", r"wheel 'a' \(\[wheels.a\]\) failed its check: .*ACME FILTERWHEEL"),
        ("ShutterEmulator", "ACME SHUTTER 1.0", r"shutter \(\[shutter\]\) failed its check: .*ACME SHUTTER"),
    ],
    ids=["wheel", "shutter"],
)
def test_wrong_identity_refused_before_anything_moves(tmp_path, monkeypatch, emulator, identity, match):
    """A device whose *idn? / id? is not what the profile names: refused naming the device."""
    from spherejax_hw import emulators

    real, made = getattr(emulators, emulator), []

    def make(**kwargs):
        made.append(real(identity=identity, **kwargs))
        return made[-1]

    monkeypatch.setattr(emulators, emulator, make)
    profile = write_profile(tmp_path)
    with pytest.raises(acquire.AcquisitionError, match=match) as refused:
        run_acquire(profile, tmp_path / "s")
    assert "\n" not in str(refused.value)
    if emulator == "FilterWheelEmulator":
        assert made[0].moves == []
    else:
        assert made[0].toggles == 0
    assert not (tmp_path / "s").exists() and not (tmp_path / "s.partial").exists()


def test_sample_that_the_simulated_camera_cannot_show_is_refused(tmp_path):
    profile = write_profile(tmp_path, samples=("train-bg00-g0", "my-textile"))
    with pytest.raises(acquire.AcquisitionError, match="samples id 'my-textile' is not a scene of the simulated camera"):
        run_acquire(profile, tmp_path / "s")
    assert not (tmp_path / "s").exists() and not (tmp_path / "s.partial").exists()


def test_a_kill_after_the_session_is_written_leaves_no_partial_folder(tmp_path, monkeypatch):
    """The finished SESSION.partial is renamed aside before the devices close and before it is
    deleted: a kill there (here: the deletion never returns) leaves the session and a hidden
    staging folder, which --resume removes, and never a SESSION.partial that blocks the name."""
    from spherejax_hw import acquire as acquire_module

    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    out = tmp_path / "s"

    real_rmtree = acquire_module.shutil.rmtree

    def killed(path, **kwargs):  # only the deletion of the finished work folder (it holds the journal) "dies"
        if (pathlib.Path(path) / "journal.jsonl").is_file():
            raise SystemExit("killed")
        return real_rmtree(path, **kwargs)

    with monkeypatch.context() as patched:
        patched.setattr(acquire_module.shutil, "rmtree", killed)
        with pytest.raises(SystemExit):
            run_acquire(profile, out)
    assert (out / "manifest.json").is_file() and not (tmp_path / "s.partial").exists()
    hidden = [p.name for p in tmp_path.iterdir() if p.name.startswith(".s.") and p.name.endswith(".tmp")]
    assert len(hidden) == 1
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert run_acquire(profile, out, resume=True) == out
    assert not any(p.name.startswith(".s.") for p in tmp_path.iterdir())
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


class TestDamagedStateFiles:
    """Files acquire writes itself get the limits user files get (spherejax.jsontext): a line
    nested 100 000 deep raised RecursionError from json.loads."""

    def test_journal_line_nested_deeply_is_skipped(self, tmp_path):
        journal = acquire.Journal(tmp_path)
        journal.append({"event": "image", "capture": "dark", "band": 400, "file": "x.tif"})
        with open(journal.path, "ab") as handle:
            handle.write(b"[" * 100_000 + b"]" * 100_000 + b"\n" + b"\xff\xfe{not utf-8}\n")
        records = journal.records()
        assert [r["event"] for r in records] == ["image"]

    @pytest.mark.parametrize("payload", [b"[" * 100_000 + b"]" * 100_000, b"\xff\xfe\x00{", b"{not json"])
    def test_saved_profile_damaged_refuses_resume_in_one_line(self, tmp_path, payload):
        partial = tmp_path / "session.partial"
        partial.mkdir()
        (partial / "profile.json").write_bytes(payload)
        with pytest.raises(acquire.AcquisitionError) as refused:
            acquire._check_resume(partial, None)
        message = str(refused.value)
        assert "\n" not in message and "profile.json" in message and "not an acquisition spherejax can resume" in message


def test_a_lamp_record_that_breaks_mid_run_stops_it_like_a_device_fault(tmp_path):
    """The lamp's state file is the lamp's only record (hw.lamp): one made unreadable after the
    devices are connected stops the run as a device fault does (AcquisitionStopped, one line,
    shutter closed, SESSION.partial kept for --resume), not with the lamp's own ValueError."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    out, partial = tmp_path / "session", tmp_path / "session.partial"
    state = {}

    def break_the_lamp_record(instrument):
        state["shutter"] = instrument.emulated["shutter"].emulator
        instrument.lamp.state_file.write_text('{"format": "spherejax-lamp", "hours": "many"')

    with pytest.raises(acquire.AcquisitionStopped) as stopped:
        run_acquire(profile, out, on_instrument=break_the_lamp_record)
    message = str(stopped.value)
    assert "\n" not in message and "lamp.json" in message and "--resume" in message
    assert state["shutter"].closed and partial.is_dir() and not out.exists()


def test_a_lamp_record_with_a_naive_time_is_refused_before_anything_opens(tmp_path):
    """A lamp state whose on_since has no time zone stopped the run with "run again with
    --resume", which cannot mend it; it is refused in one line, naming the file, before any
    device opens, and the kept partial acquisition is left as it was."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    out, partial = tmp_path / "session", tmp_path / "session.partial"

    def break_the_lamp_record(instrument):
        instrument.lamp.state_file.write_text('{"format": "spherejax-lamp", "hours": "many"')

    with pytest.raises(acquire.AcquisitionStopped):
        run_acquire(profile, out, on_instrument=break_the_lamp_record)
    lamp_file = partial / "lamp.json"
    lamp_file.write_text(json.dumps({"format": lamp.FORMAT, "hours": 1.5, "on_since": "2026-11-26T09:00:00"}))
    before = {path: path.read_bytes() for path in partial.rglob("*") if path.is_file()}
    opened = []
    with pytest.raises(lamp.LampStateError) as refused:
        run_acquire(profile, out, resume=True, on_instrument=opened.append)
    message = str(refused.value)
    assert "\n" not in message and str(lamp_file) in message and "on_since" in message
    assert "--resume" not in message and opened == []
    assert {path: path.read_bytes() for path in partial.rglob("*") if path.is_file()} == before


def test_every_hw_error_has_one_root():
    """Whatever hw/ raises is an hw.errors.InstrumentError: a caller catches one class."""
    import importlib
    import inspect
    import pkgutil

    import spherejax_hw as hw
    from spherejax_hw.errors import InstrumentError

    found = {}
    for module_info in pkgutil.iter_modules(hw.__path__):
        module = importlib.import_module(f"spherejax_hw.{module_info.name}")
        for name, value in vars(module).items():
            if inspect.isclass(value) and issubclass(value, Exception) and value.__module__ == module.__name__:
                found[f"{module.__name__}.{name}"] = value
    public = {name: cls for name, cls in found.items() if not name.rsplit(".", 1)[1].startswith("_")}
    assert len(public) >= 12
    assert [name for name, cls in public.items() if not issubclass(cls, InstrumentError)] == []
