"""A stop (SIGINT, SIGTERM, SIGHUP) is never lost, never raised where it corrupts a library's state,
and ends every command with 128 + the signal, its clean-up done (`spherejax.interrupt`).

Each test sends the signal at a known point -- from a hook placed where the signal must land (a
garbage-collector callback, h5py's file-object driver calling back while the calibration is
written, a function of calibrate) -- never after a fixed delay, so the outcome does not depend on
the machine's speed. The reproducers: a SIGTERM that landed in JAX's `_xla_gc_callback` was printed
as "Exception ignored ... Interrupted: 15" and `measure` ran to completion with exit 0; a SIGTERM
raised inside h5py's callback ("SystemError: ... returned a result with an exception set", the
stop lost and the file written, or "Fatal Python error: Segmentation fault", exit 139); SIGHUP
killed the process with its temporaries and lock left.
"""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from spherejax import interrupt, number_text

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: The line every at_once command prints when stopped.
STOPPED = "spherejax: interrupted; nothing half-written was left"


def _spherejax_work(times: int = 200) -> int:
    """Calls of a spherejax function from this (foreign) module: where a stop is raised."""
    done = 0
    for _ in range(times):
        number_text.number_text(1.5)
        done += 1
    return done


def test_a_stop_landing_in_a_gc_callback_is_not_lost(capfd):
    """The signal is handled inside a garbage-collector callback (as JAX's `_xla_gc_callback`):
    no "Exception ignored", and the block stops at the next call of spherejax's code."""
    landed = []

    def callback(phase, info):
        if phase == "start" and not landed:
            landed.append(phase)
            signal.raise_signal(signal.SIGTERM)  # handled here, inside the callback

    calls = []
    with pytest.raises(interrupt.Interrupted) as stopped:
        with interrupt.at_once():
            gc.callbacks.append(callback)
            try:
                gc.collect()
            finally:
                gc.callbacks.remove(callback)
            calls.append(_spherejax_work())
    assert landed and not calls, calls  # stopped at the first call, not after the work
    assert stopped.value.exit_status == 143 and stopped.value.message() == STOPPED
    assert "Exception ignored" not in capfd.readouterr().err


def test_a_stop_swallowed_in_the_block_is_raised_at_its_end():
    """A raise caught by an `except BaseException` that drops it: the record stays, and the
    end of the block raises it (the command exits 143, never 0)."""
    with pytest.raises(interrupt.Interrupted) as stopped:
        with interrupt.at_once():
            try:
                signal.raise_signal(signal.SIGHUP)
                _spherejax_work()
            except BaseException:  # noqa: BLE001 - what a careless library might do
                pass
    assert stopped.value.exit_status == 129


def test_a_second_signal_is_not_raised_into_the_clean_up():
    """One stop per block: a second SIGINT while the first stop unwinds through a `finally` does
    not cut the clean-up short."""
    cleaned = []
    with pytest.raises(interrupt.Interrupted) as stopped:
        with interrupt.at_once():
            try:
                signal.raise_signal(signal.SIGTERM)
                _spherejax_work()
            finally:
                signal.raise_signal(signal.SIGINT)
                _spherejax_work(5)
                cleaned.append(True)
    assert cleaned == [True] and stopped.value.signum == signal.SIGTERM


def test_a_stop_is_not_raised_in_spherejax_code_a_library_calls_back(tmp_path):
    """spherejax calling a library that calls spherejax back (h5py's file-object driver): not
    raised inside the callback, where the library could not take it, but once the library has
    returned. Here `sha256_file` stands for the caller and the test's `check` for the library."""
    from spherejax.io import hashing

    data = tmp_path / "data"
    data.write_bytes(bytes(3 * hashing.BLOCK_BYTES))
    seen = []

    def library_calling_back():  # a frame of another library between spherejax's frames
        if not seen:
            signal.raise_signal(signal.SIGTERM)
        seen.append(number_text.number_text(len(seen)))  # spherejax, called back

    with pytest.raises(interrupt.Interrupted):
        with interrupt.at_once():
            hashing.sha256_file(data, check=library_calling_back)
            _spherejax_work()
    assert seen == ["0", "1", "2"]  # each callback ran to its end; the hash, with no call of
    # spherejax's own between its blocks, finished before the stop


def test_stop_requests_and_immediately_still_behave(monkeypatch):
    """Inside stop_requests() (correct, acquire) a signal is only recorded, for check(); inside
    immediately() it is raised from the handler (a prompt waiting on input)."""
    with interrupt.stop_requests():
        signal.raise_signal(signal.SIGHUP)
        _spherejax_work()
        assert interrupt.requested() == signal.SIGHUP
        with pytest.raises(interrupt.Interrupted) as stopped:
            interrupt.check()
        assert stopped.value.exit_status == 129
    with interrupt.stop_requests(), interrupt.immediately(), pytest.raises(interrupt.Interrupted):
        signal.raise_signal(signal.SIGINT)
        raise AssertionError("not reached: raised by the handler")
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL or callable(signal.getsignal(signal.SIGHUP))


# --------------------------------------------------------------- h5py's callback (the segfault)

SAVE_WITH_A_SIGNAL_IN_H5PY = textwrap.dedent("""
    import os, pathlib, signal, sys
    import numpy as np
    sys.path.insert(0, sys.argv[3])
    from spherejax import interrupt, io
    from spherejax.io import calibration_hdf5
    from tests.batch_support import make_calibration

    calibration, bands, instrument = make_calibration(np.random.default_rng(0))
    out = pathlib.Path(sys.argv[2]) / "cal.h5"
    original, calls = calibration_hdf5._FailureKeepingFile.write, [0]

    def write(self, data):  # HDF5 calls it back, through h5py's file-object driver
        calls[0] += 1
        if calls[0] == int(sys.argv[1]):
            signal.raise_signal(signal.SIGTERM)
        return original(self, data)

    calibration_hdf5._FailureKeepingFile.write = write
    try:
        with interrupt.at_once():
            io.save_calibration(out, calibration, instrument_id=instrument, band_centres_nm=bands)
        print("completed", sorted(os.listdir(out.parent)))
    except interrupt.Interrupted as stop:
        print("stopped", sorted(os.listdir(out.parent)))
        sys.exit(stop.exit_status)
""")


@pytest.mark.parametrize("write", [1, 2, 4])
def test_a_stop_while_h5py_writes_the_calibration_leaves_nothing_and_no_torn_state(tmp_path, write):
    """The signal handled inside h5py's file-object callback: the save stops once HDF5 has
    returned (exit 143, nothing written, no SystemError, no segmentation fault). Before, the raise
    inside the callback broke h5py's call ("returned a result with an exception set") and the
    stop was lost with the file written."""
    result = subprocess.run([sys.executable, "-c", SAVE_WITH_A_SIGNAL_IN_H5PY, str(write), str(tmp_path), ROOT],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 143, result.stdout + result.stderr
    assert result.stdout.strip() == "stopped []", result.stdout
    for word in ("SystemError", "Segmentation", "Exception ignored", "Traceback"):
        assert word not in result.stderr, result.stderr


# ---------------------------------------------------------------- commands stopped at known points

#: Run `spherejax` (argv after the hook's three arguments) with SIGNAL sent the N-th time
#: MODULE:QUALNAME is called (before it runs), then exit with main's status.
COMMAND_WITH_A_HOOK = textwrap.dedent("""
    import functools, gc, importlib, signal, sys
    target, count, signum, *argv = sys.argv[1:]
    count, signum, calls = int(count), getattr(signal, signum), [0]

    def hit():
        calls[0] += 1
        if calls[0] == count:
            signal.raise_signal(signum)

    if target == "gc":  # inside a garbage-collector callback (as JAX's _xla_gc_callback), once
        import contextlib  # the command runs (inside at_once: before it, the signal would kill)
        from spherejax import interrupt
        at_once = interrupt.at_once

        @contextlib.contextmanager
        def at_once_then_gc():
            with at_once():
                gc.callbacks.append(lambda phase, info: phase == "start" and hit())
                yield

        interrupt.at_once = at_once_then_gc
    else:
        module_name, _, qualname = target.partition(":")
        owner = importlib.import_module(module_name)
        *path, name = qualname.split(".")
        for part in path:
            owner = getattr(owner, part)
        original = getattr(owner, name)

        @functools.wraps(original)
        def hooked(*args, **kwargs):
            hit()
            return original(*args, **kwargs)

        setattr(owner, name, hooked)
    from spherejax import cli
    sys.exit(cli.main(argv))
""")


def _run_with_hook(target: str, count: int, signum: str, argv: list, *, cwd) -> subprocess.CompletedProcess:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT}
    return subprocess.run([sys.executable, "-c", COMMAND_WITH_A_HOOK, target, str(count), signum, *map(str, argv)],
                          capture_output=True, text=True, timeout=300, env=env, cwd=cwd)


def _assert_stopped(result, status: int, folder) -> None:
    err = result.stderr
    assert result.returncode == status, err
    assert err.strip().splitlines()[-1] == STOPPED, err
    for word in ("Segmentation", "Fatal Python error", "Exception ignored", "Traceback", "SystemError"):
        assert word not in err, err
    assert sorted(os.listdir(folder)) == [], sorted(os.listdir(folder))


@pytest.mark.slow
@pytest.mark.parametrize("target, count, signum", [
    ("spherejax.calibrate:base_calibration", 1, "SIGTERM"),  # early: the session read
    ("spherejax.calibrate:stage2_training_data", 1, "SIGTERM"),  # mid-fit
    ("gc", 3, "SIGTERM"),  # a garbage-collector callback
    ("spherejax.io.calibration_hdf5:_FailureKeepingFile.write", 2, "SIGTERM"),  # h5py writing
    ("spherejax.io.calibration_hdf5:_FailureKeepingFile.write", 1, "SIGHUP"),
    ("spherejax.calibrate:stage2_training_data", 1, "SIGINT"),
], ids=["session-read", "stage2", "gc-callback", "h5py-write", "h5py-write-sighup", "stage2-sigint"])
def test_calibrate_stopped_at_several_points_exits_128_plus_the_signal(workspace, tmp_path, target, count, signum):
    """`calibrate` with the signal sent at each point: exit 128 + the signal, one line, no
    segmentation fault, no "Exception ignored", and no calibration file or temporary left."""
    out = tmp_path / "out"
    out.mkdir()
    result = _run_with_hook(target, count, signum, ["calibrate", workspace / "session", "-o", out / "cal.h5"], cwd=tmp_path)
    _assert_stopped(result, 128 + getattr(signal, signum), out)


@pytest.mark.slow
def test_measure_stopped_in_a_gc_callback_exits_143(workspace, tmp_path):
    """The reproducer: `measure` with SIGTERM handled in a garbage-collector callback ran to its
    end and exited 0; now exit 143 with nothing written."""
    from spherejax import io

    session = io.load_session(workspace / "session")
    sample = tmp_path / "sample.tif"
    io.write_frame(sample, session.read(session.frames[-1].id),
                   channel_names=[f"{int(b)}nm" for b in session.band_centres_nm])
    out = tmp_path / "out"
    out.mkdir()
    result = _run_with_hook("gc", 2, "SIGTERM",
                            ["measure", "-c", workspace / "cal.h5", sample, "--region", "a=0,4,0,4", "-o", out / "m"],
                            cwd=tmp_path)
    _assert_stopped(result, 143, out)


@pytest.mark.slow
def test_sighup_stops_correct_like_sigterm_with_129_and_its_clean_up(cal, tmp_path):
    """SIGHUP (the terminal closed) inside an input's writes: exit 129 with the stop's line, no
    temporary, OUT's lock removed and the manifest true, as for SIGINT and SIGTERM (before: the
    default action killed the process with its temporaries and lock left)."""
    from spherejax import archive, io
    from tests.batch_support import NAMES, frame

    rng = np.random.default_rng(1)
    (tmp_path / "in").mkdir()
    for index in range(3):
        io.write_frame(tmp_path / "in" / f"cube{index}.tif", frame(rng), channel_names=NAMES)
    out = tmp_path / "out"
    result = _run_with_hook("spherejax.archive.outputs:srgb_preview", 1, "SIGHUP",
                            ["-q", "correct", "-c", cal, tmp_path / "in", "-o", out], cwd=tmp_path)
    err = result.stderr
    assert result.returncode == 129, err
    assert err.strip().splitlines()[-1].startswith("spherejax: interrupted after "), err
    assert "run again with --resume" in err and "Traceback" not in err, err
    assert not [p for p in out.rglob("*") if io.is_temp_sibling(p.name)]
    assert not (out / archive.LOCK_NAME).exists()
    done = [name for name, record in archive.read_manifest(out).items() if record["status"] == "done"]
    assert len(done) < 3
