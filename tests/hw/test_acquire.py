"""`spherejax acquire` on emulated devices: the protocol, the session it writes, faults that stop
it with nothing lost, and --resume, after a device fault and after a kill (SIGKILL; SIGINT and
SIGTERM)."""

from __future__ import annotations

import json
import os
import pathlib
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from spherejax_hw import acquire, lamp
from spherejax import cli, io
from tests.helpers import INTERRUPTED, no_compilation_cache_writes, sigkill, wait_until

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
#
# `spherejax acquire` stopped partway, then finished with --resume: once for each way a run can be
# stopped. SIGKILL: no clean-up; the journal may end in a torn line, the session's staging folder
# may be left half-written. SIGINT / SIGTERM: the run stops at its next safe point with the
# shutter closed, one line and the exit status 130 / 143. Either way --resume takes only the
# band images not yet kept, and the session holds each exactly once. (Device faults, and the
# states a kill leaves made by hand, are tested above and below.)

IMAGES = (2 + len(SAMPLES)) * len(BANDS)  # dark, white and the samples, every band
ACQUIRE_KILLS = 8


def _start_acquire(profile: pathlib.Path, out: pathlib.Path, *, resume: bool, may_be_killed: bool = True) -> subprocess.Popen:
    """`spherejax -q acquire --emulate --yes` in a child process, stderr piped. One that may be
    killed (SIGKILL) reads the shared compilation cache but writes none."""
    command = [sys.executable, "-m", "spherejax.cli", "-q", "acquire", "--profile", str(profile), "-o", str(out),
               "--emulate", "--yes", *(["--resume"] if resume else [])]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    if may_be_killed:
        env = no_compilation_cache_writes(env)
    return subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _image_records(partial: pathlib.Path) -> list[dict]:
    """The journal's band-image records (none before SESSION.partial exists)."""
    return [r for r in acquire.Journal(partial).records() if r["event"] == "image"] if partial.is_dir() else []


def _staging(out: pathlib.Path) -> list[pathlib.Path]:
    """Session folders being written beside `out` (io.write_session's temporary name)."""
    return [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.") and p.name.endswith(".tmp")]


def _acquire_kill_plan(rng: random.Random) -> list[tuple[str, float | int]]:
    """ACQUIRE_KILLS (mode, argument) pairs, in order: `time` kills argument s after the start
    (start-up, lamp warm-up, exposures, first images), or sooner once the run has taken three
    images more than it started with; `images` once the journal holds
    `argument` band images, plus 0-30 ms (one image takes 10-40 ms); the last, `session`, as
    soon as the session's staging folder is there, plus 0-50 ms (inside io.write_session)."""
    modes = ["time"] * 2 + ["images"] * (ACQUIRE_KILLS - 3)
    rng.shuffle(modes)
    counts = iter(sorted(rng.sample(range(1, IMAGES - 1), len(modes))))
    plan = [(mode, rng.uniform(0.5, 4.0) if mode == "time" else next(counts)) for mode in modes]
    return plan + [("session", 0)]


@pytest.mark.slow
def test_kills_during_acquisition_lose_and_duplicate_no_capture(tmp_path):
    """SIGKILL at ACQUIRE_KILLS seeded moments (`_acquire_kill_plan`: start-up and warm-up,
    after a given number of band images, inside the session's write), each followed by --resume.
    At every kill the journal records each kept image once, with its file unchanged; at the end
    the session holds every band of every capture once, each image kept before a kill as it was
    taken, and nothing else is left beside it."""
    profile = write_profile(tmp_path)
    out, partial = tmp_path / "s", tmp_path / "s.partial"
    plan = _acquire_kill_plan(random.Random(8))
    delays = random.Random(9)
    kept: dict[tuple[str, int], tuple[bytes, np.ndarray, dict]] = {}  # band images kept so far
    landed = []  # per kill: (mode, band images kept, session written)
    runs = 0
    while len(landed) < ACQUIRE_KILLS and not (out / "manifest.json").exists():
        runs += 1
        assert runs <= 2 * ACQUIRE_KILLS, f"only {len(landed)} kills landed in {runs - 1} runs: {landed}"
        mode, argument = plan[len(landed)]
        process = _start_acquire(profile, out, resume=partial.exists())
        if mode == "time":
            # Start-up, warm-up and exposures; and at most a few new images: on a quick machine a
            # resumed run took every image left within the sleep, so that no later kill could
            # land mid-acquisition (CI: "2 >= 8 // 2" with kills at 7, 10, then 64 images).
            started, before = time.monotonic(), len(_image_records(partial))
            wait_until(process, lambda: time.monotonic() - started >= argument or len(_image_records(partial)) > before + 2)
        elif mode == "images":
            wait_until(process, lambda: len(_image_records(partial)) >= argument)
            time.sleep(delays.uniform(0.0, 0.030))
        else:
            wait_until(process, lambda: bool(_staging(out)))
            time.sleep(delays.uniform(0.0, 0.050))
        if not sigkill(process):  # it finished first: not a kill
            continue

        if (out / "manifest.json").exists():  # killed after the session was written: checked below
            landed.append((mode, IMAGES, True))
            break
        # At every kill: each band image the journal holds is recorded once, its file unchanged
        # (SHA-256); the images kept before this run are all still there, byte for byte.
        records = _image_records(partial)
        keys = [(r["capture"], int(r["band_nm"])) for r in records]
        assert len(keys) == len(set(keys)), f"kill {len(landed)} ({mode}): an image recorded twice"
        done = acquire.Journal(partial).done_images()
        assert len(done) == len(records), f"kill {len(landed)} ({mode}): a kept image's file changed"
        for key, (data, _, _) in kept.items():
            assert key in done, f"kill {len(landed)} ({mode}): {key}, kept before, is lost"
            assert (partial / done[key]["file"]).read_bytes() == data, f"kill {len(landed)} ({mode}): {key} retaken"
        for key, record in done.items():
            if key not in kept:
                path = partial / record["file"]
                kept[key] = (path.read_bytes(), io.read_frame(path)[..., 0], record["metadata"])
        landed.append((mode, len(done), False))

    process = _start_acquire(profile, out, resume=True)
    _, err = process.communicate(timeout=300)
    assert process.returncode == 0, err.decode()

    mid_acquisition = [kill for kill in landed if 0 < kill[1] < IMAGES]
    writing_session = [kill for kill in landed if kill[1] == IMAGES and not kill[2]]
    print(f"\n{len(landed)} kills in {runs} runs: {len(mid_acquisition)} mid-acquisition, "
          f"{len(writing_session)} while the session was written; band images kept at each kill: "
          f"{[kill[1] for kill in landed]}")
    assert len(landed) == ACQUIRE_KILLS, landed
    assert len(mid_acquisition) >= ACQUIRE_KILLS // 2, landed
    assert writing_session, landed

    # Every capture the profile asks for, each band exactly once and in the profile's order; no
    # partial session or staging folder left beside it.
    session = io.load_session(out)
    assert [f.id for f in session.frames] == ["dark", "white", *SAMPLES]
    for frame in session.frames:
        assert [b["band_nm"] for b in frame.metadata["bands"]] == BANDS, frame.id
    assert sorted(os.listdir(tmp_path)) == ["s", "sphere.toml"]
    # Nothing retaken: every band image kept before a kill is in the session as it was taken.
    assert len(kept) == IMAGES  # the kills got through the whole protocol
    for (capture, band), (_, plane, metadata) in kept.items():
        index = BANDS.index(band)
        np.testing.assert_array_equal(session.read(capture)[..., index], plane, err_msg=f"{capture} {band}")
        assert session.frame(capture).metadata["bands"][index] == metadata


def test_sigterm_during_acquire_closes_the_shutter_and_keeps_the_journal(tmp_path):
    """In process, so the emulated shutter can be looked at: the signal comes once 20 band images
    are taken (dark done, the white standard imaged with the shutter open). The stop closes the
    shutter, restores the signal handlers and keeps exactly the 20 images for --resume (which
    the test below runs)."""
    from spherejax import interrupt

    profile = write_profile(tmp_path)
    out, partial = tmp_path / "s", tmp_path / "s.partial"
    instruments, open_at_signal = [], []

    def progress(done: int, total: int) -> None:
        if done == 20:
            open_at_signal.append(not instruments[0].emulated["shutter"].emulator.closed)
            os.kill(os.getpid(), signal.SIGTERM)

    before = signal.getsignal(signal.SIGTERM)
    with open(os.devnull, "w") as devnull, pytest.raises(interrupt.Interrupted) as stopped:
        with interrupt.stop_requests():
            acquire.acquire(profile, out, emulate=True, operator=acquire.Operator(yes=True, stream=devnull),
                            settings=acquire.Settings(log=lambda line: None, progress=progress),
                            on_instrument=instruments.append)
    assert signal.getsignal(signal.SIGTERM) is before  # the handlers are restored
    assert stopped.value.exit_status == 143
    assert stopped.value.message() == f"spherejax: interrupted after 20 of {IMAGES} band images; run again with --resume"
    assert open_at_signal == [True] and instruments[0].emulated["shutter"].emulator.closed
    assert len(acquire.Journal(partial).done_images()) == 20
    assert not out.exists()
    assert sorted(os.listdir(tmp_path)) == ["s.partial", "sphere.toml"]


@pytest.mark.slow
def test_sigint_stops_the_acquire_command_and_resume_completes_it(tmp_path):
    """The command line: SIGINT once 20 band images are kept stops it with exit status 130 and
    one last line saying how many, the journal holding just those; --resume then finishes the
    session, taking each band image once, and leaves nothing beside it."""
    profile = write_profile(tmp_path)
    out, partial = tmp_path / "s", tmp_path / "s.partial"
    process = _start_acquire(profile, out, resume=False, may_be_killed=False)
    wait_until(process, lambda: len(_image_records(partial)) >= 20)
    assert process.poll() is None, "the acquisition ended before the signal"
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    err = err.decode()
    assert process.returncode == 130, err
    stops = [line for line in err.splitlines() if INTERRUPTED.fullmatch(line)]
    assert len(stops) == 1 and err.strip().splitlines()[-1] == stops[0] and "Traceback" not in err, err
    kept = int(INTERRUPTED.fullmatch(stops[0]).group(1))
    assert 20 <= kept < IMAGES and f"of {IMAGES} band images" in stops[0]
    assert len(acquire.Journal(partial).done_images()) == kept
    assert not out.exists() or not any(out.iterdir())

    process = _start_acquire(profile, out, resume=True, may_be_killed=False)
    _, err = process.communicate(timeout=300)
    assert process.returncode == 0, err.decode()
    session = io.load_session(out)
    assert [f.id for f in session.frames] == ["dark", "white", *SAMPLES]
    for frame in session.frames:
        assert [b["band_nm"] for b in frame.metadata["bands"]] == BANDS, frame.id
    assert sorted(os.listdir(tmp_path)) == ["s", "sphere.toml"]


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


def test_resume_after_a_kill_before_the_profile_was_written(tmp_path):
    """The one state a kill leaves that a random moment almost never hits (the microseconds
    between creating SESSION.partial and renaming its profile.json into place), made by hand:
    --resume starts afresh in it instead of refusing a folder only spherejax can have made."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    partial = tmp_path / "s.partial"
    partial.mkdir()
    io.temp_sibling(partial / "profile.json").write_text('{"bands": {"400"')  # cut by the kill
    run_acquire(profile, tmp_path / "s", resume=True)
    session = io.load_session(tmp_path / "s")
    assert [f.id for f in session.frames] == ["dark", "white", SAMPLES[0]]
    assert sorted(os.listdir(tmp_path)) == ["s", "sphere.toml"]


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


# ------------------------------------------------------------------------ the registration target

#: The plan's registration target, after its one sample: a name the simulated camera has no scene
#: of, so it shows its chart of colour targets.
REGISTRATION_TARGET = '[[samples]]\nid = "checkerboard"\nrole = "registration"\n'


def _edge_contrast(image: np.ndarray, holder) -> np.ndarray:
    """Mean absolute difference of neighbouring pixels along rows on the holder over its mean, (B,)."""
    r0, r1, c0, c1 = holder
    held = image[r0:r1, c0:c1].astype(np.float64)
    return np.abs(np.diff(held, axis=1)).mean(axis=(0, 1)) / held.mean(axis=(0, 1))


def test_acquisition_with_a_registration_target(tmp_path):
    """The plan's registration target is taken like a sample: the operator asked to put it in
    place, every band at the samples' exposures, frames_averaged averaged, the bands' metadata;
    the session holds it as its one frame of role "registration", without regions."""
    profile = write_profile(tmp_path, samples=SAMPLES[:1], extra=REGISTRATION_TARGET)
    out = tmp_path / "session"
    with open(tmp_path / "prompts.txt", "w") as prompts:
        acquire.acquire(profile, out, emulate=True, operator=acquire.Operator(yes=True, stream=prompts),
                        settings=quiet_settings())
    assert "Place the registration target 'checkerboard' on the sample holder" in (tmp_path / "prompts.txt").read_text()
    session = io.load_session(out)
    assert [(f.id, f.role) for f in session.frames] == [
        ("dark", "dark"), ("white", "white"), (SAMPLES[0], "sample"), ("checkerboard", "registration")]
    registration, sample = session.registration_frame(), session.frame(SAMPLES[0])
    assert registration.id == "checkerboard" and session.frames_with(role="registration") == (registration,)
    assert registration.regions == () and registration.set is None and registration.background is None
    np.testing.assert_array_equal(registration.exposure_s, sample.exposure_s)
    assert registration.metadata["frames_averaged"] == sample.metadata["frames_averaged"] == 2
    bands = registration.metadata["bands"]
    assert [b["band_nm"] for b in bands] == BANDS
    assert [b["exposure_s"] for b in bands] == [b["exposure_s"] for b in sample.metadata["bands"]]
    assert all(b["frames_averaged"] == 2 and b["saturated_pixels"] == 0 for b in bands)
    # The simulated camera showed its chart: edges on the holder, far more than the white standard's.
    assert np.all(_edge_contrast(session.read(registration), session.holder)
                  > 3 * _edge_contrast(session.white(), session.holder))


def test_resume_after_a_stop_during_the_registration_capture_takes_only_what_is_missing(tmp_path, monkeypatch):
    """SIGTERM once 5 of the registration target's bands are taken (dark, white and the sample
    before it): the journal keeps them, and --resume takes just its 11 other bands, at the
    exposures already chosen, into the same registration frame."""
    from spherejax import interrupt
    from spherejax_hw import acquisition_protocol

    profile = write_profile(tmp_path, samples=SAMPLES[:1], extra=REGISTRATION_TARGET)
    out, partial = tmp_path / "s", tmp_path / "s.partial"
    stop_at = 3 * len(BANDS) + 5

    def progress(done: int, total: int) -> None:
        assert total == 4 * len(BANDS)
        if done == stop_at:
            os.kill(os.getpid(), signal.SIGTERM)

    with open(os.devnull, "w") as devnull, pytest.raises(interrupt.Interrupted) as stopped:
        with interrupt.stop_requests():
            acquire.acquire(profile, out, emulate=True, operator=acquire.Operator(yes=True, stream=devnull),
                            settings=quiet_settings(progress))
    assert (stopped.value.done, stopped.value.total) == (stop_at, 4 * len(BANDS))
    kept = acquire.Journal(partial).done_images()
    assert sorted(band for capture, band in kept if capture == "checkerboard") == BANDS[:5]
    kept_bytes = {key: (partial / record["file"]).read_bytes() for key, record in kept.items()}
    exposures = acquire.Journal(partial).last("exposures")["exposure_s"]

    taken = []
    real_take = acquisition_protocol._take_image

    def take(instrument, partial, journal, capture, band, exposure, frames):
        taken.append((capture.id, band, exposure, frames))
        real_take(instrument, partial, journal, capture, band, exposure, frames)

    monkeypatch.setattr(acquisition_protocol, "_take_image", take)
    run_acquire(profile, out, resume=True)
    assert taken == [("checkerboard", band, exposures[str(band)], 2) for band in BANDS[5:]]
    session = io.load_session(out)
    registration = session.registration_frame()
    assert registration.id == "checkerboard" and [f.role for f in session.frames].count("registration") == 1
    np.testing.assert_array_equal(registration.exposure_s, session.frame(SAMPLES[0]).exposure_s)
    for (capture, band), data in kept_bytes.items():  # nothing retaken: the kept images, unchanged
        plane = session.read(capture)[..., BANDS.index(band)]
        np.testing.assert_array_equal(plane, np.asarray(_frame_from_bytes(tmp_path, data))[..., 0], err_msg=f"{capture} {band}")
    assert sorted(os.listdir(tmp_path)) == ["kept.tif", "s", "sphere.toml"]


def test_a_plan_without_a_registration_target_keeps_its_identity(tmp_path):
    """SESSION.partial/profile.json names a [[samples]] entry's role only for the registration
    target: a work folder left by a run before there were roles resumes as it did."""
    from spherejax_hw.acquisition_journal import _profile_identity
    from spherejax_hw.profile import load_profile

    plain = _profile_identity(load_profile(write_profile(tmp_path, samples=SAMPLES[:1])))
    assert plain["samples"] == [{"id": SAMPLES[0], "set": "training", "background": "bg"}]
    with_target = _profile_identity(load_profile(write_profile(tmp_path, samples=SAMPLES[:1], extra=REGISTRATION_TARGET)))
    assert with_target["samples"] == [*plain["samples"], {"id": "checkerboard", "set": None, "background": None, "role": "registration"}]
