"""`spherejax acquire`: the acquisition protocol of docs/instrument.md, written as a session.

    connect      wheels (*idn?, pcount? against the profile, sensors=0) or a tunable filter
                 (identity, tuning range against the bands, warm-up), shutter (id?, closed),
                 camera, lamp state; nothing moves before every check has passed
    warm-up      white standard in place: one band's central-region mean imaged every interval
                 until it drifts less than warmup_drift_percent over warmup_checks intervals
    exposures    per band on the white standard: a high percentile near target_level of full
                 scale, nothing saturated (blue bands get much longer exposures)
    dark         shutter closed, per band at that band's exposure, dark_frames averaged
    white        the white standard, per band, frames_averaged averaged
    samples      each sample of the plan, per band, frames_averaged averaged, the reference
                 patch in view; the plan's registration target (a [[samples]] entry with role =
                 "registration", at most one) is taken the same way where it stands in the plan,
                 the operator asked to put it in place, into the frame of role "registration"
    session      the frames assembled into a spherejax session (`spherejax.io.write_session`)

Nothing is lost on a fault. Work goes to SESSION.partial/ beside SESSION: every band image is
written (atomically) as captures/<capture>/<nm>nm.tif with its metadata, then recorded as one
fsynced line of journal.jsonl; exposures and the warm-up result are journal lines too. When the
last band image is in, the session is written (all or nothing) and SESSION.partial/ removed. A
device that stops answering, answers garbage or vanishes stops the run with one line; the shutter
is closed if it still answers, and `--resume` re-runs the warm-up check and takes only the band
images the journal does not hold (verified by SHA-256), with the exposures already chosen, so
darks, whites and samples always share exposures. A kill while the session is written leaves its
hidden staging folder beside SESSION; `--resume` removes it.

SIGINT (Ctrl-C) or SIGTERM, when the command line has turned them into stop requests
(`spherejax.interrupt`), stop the run between band images (or warm-up checks, or exposure
choices): the shutter is closed, the journal and SESSION.partial are kept for `--resume`, and
`acquire` raises `interrupt.Interrupted` saying how many band images are kept.

Per band image the metadata holds: band centre, every wheel's slot read back with pos?, the
exposure, frames averaged, time stamp (UTC), sensor temperature, lamp hours and the count of
saturated pixels. Averages are rounded to 16-bit counts for the session's frames. Each session
frame's metadata holds these per band ("bands") and, as a simulated session does, the frames
averaged for the frame ("frames_averaged": dark_frames for the dark, frames_averaged for the
white standard, samples and registration target; the fewest of its bands should a resumed run have changed them).
The session's metadata "camera" holds the camera's gain ("gain_e_per_count") and read noise
("read_noise_counts") when known, for calibrate's noise model: the camera's own (the simulated
camera's model), else the profile's [noise]; and the profile's white_reflectance_u if given.

The modules of the acquisition, each one job; every public name is importable from here:

    acquisition_devices    `connect`: open and check every device (`Instrument`)
    acquisition_protocol   the plan of captures, the warm-up, the exposures and the capture loop
    acquisition_journal    SESSION.partial: the journal, and the checks that let a run resume
    acquisition_session    the band images assembled into the session
    acquire (this)         `acquire`: one run, start to finish, and what it does on a fault
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import pathlib
import shutil
from collections.abc import Callable

from spherejax import interrupt

# acquire() finds connect by this module's name: tests replace `acquire.connect` to wrap the devices.
from .acquisition_devices import Instrument, connect
from .acquisition_journal import (
    PARTIAL_SUFFIX,
    Journal,
    _check_ownership,
    _check_resume,
    _is_work_folder,
    _lock_session,
    _profile_identity,
    _remove_stale_staging,
)
from .acquisition_protocol import Operator, Settings, _captures, _run_protocol, choose_exposure
from .acquisition_session import _layout, _write_session
from .errors import AcquisitionError, AcquisitionStopped, InstrumentError
from .lamp import Lamp, LampStateError
from .profile import load_profile

# Public names of the acquisition that acquire() does not use, importable from here too.
from .acquisition_journal import JOURNAL_NAME as JOURNAL_NAME
from .acquisition_protocol import Capture as Capture


def acquire(
    profile_path,
    out,
    *,
    emulate: bool = False,
    real_camera: bool = False,
    through_gige: bool = False,
    resume: bool = False,
    operator: Operator,
    settings: Settings | None = None,
    on_instrument: Callable[[Instrument], None] | None = None,
) -> pathlib.Path:
    """Run the acquisition protocol (module docstring) into the session folder `out`.

    Args:
      profile_path: the instrument profile (TOML, `hw.profile`).
      out: the session folder to write; SESSION.partial beside it holds the work in progress.
      emulate: emulated wheels or tunable filter and shutter on pseudo-terminals and the simulated camera
        (whatever the profile's ports and camera), the lamp state kept in SESSION.partial.
      real_camera: with `emulate`, open the profile's [camera] instead of the simulated one
        (a real camera, or Aravis's fake GigE Vision camera, behind emulated wheels and shutter).
      through_gige: with `emulate` and the simulated camera, its frames served through Aravis's
        fake GigE Vision camera on 127.0.0.1 and read by the GenICam backend
        (`hw.simulated_gige`): the real camera protocol end to end, the simulator's pixels.
      resume: continue an interrupted acquisition of the same profile.
      operator: prompts (`Operator`).
      settings: sleep / log / progress hooks.
      on_instrument: called with the connected `Instrument` before the protocol starts (tests
        use it to inject faults into emulated devices).

    Returns:
      The session folder.

    Raises:
      ProfileError: a profile that is invalid, before anything is opened.
      AcquisitionError: SESSION or SESSION.partial a symbolic link, or holding the profile or
        its lamp state file (before anything is opened); another acquisition holding the
        session's lock, SESSION.lock (before anything is opened or touched); a device check
        failed (before anything moved), or a fault stopped the run (what was captured stays in
        SESSION.partial for --resume).
    """
    settings = settings or Settings()
    if through_gige and (not emulate or real_camera):
        raise ValueError("through_gige: the simulated camera's route, with emulate and without real_camera")
    profile = load_profile(profile_path)
    out = pathlib.Path(out)
    partial = out.with_name(out.name + PARTIAL_SUFFIX)
    if emulate and not real_camera and profile.camera.backend != "sim":
        profile = dataclasses.replace(profile, camera=dataclasses.replace(profile.camera, backend="sim", options={}))
    _check_ownership(profile, out, partial, emulate=emulate)
    # One acquisition per session: the lock before anything opens, and before SESSION.partial is
    # looked at, created, resumed or removed; a second run is refused here, touching nothing.
    with _lock_session(out):
        return _acquire_locked(profile, out, partial, emulate=emulate, through_gige=through_gige, resume=resume,
                               operator=operator, settings=settings, on_instrument=on_instrument)


def _acquire_locked(profile, out: pathlib.Path, partial: pathlib.Path, *, emulate: bool, through_gige: bool,
                    resume: bool, operator: Operator, settings: Settings,
                    on_instrument: Callable[[Instrument], None] | None) -> pathlib.Path:
    """`acquire` from its checks on, with the session's lock held."""
    from spherejax import atomic_files

    if resume:
        _remove_stale_staging(out)
        if (out / "manifest.json").is_file():
            if _is_work_folder(partial):
                shutil.rmtree(partial, ignore_errors=True)  # a run killed after writing the session
            elif os.path.lexists(partial):
                settings.log(f"{partial}: not an acquisition's work folder (no profile.json): left as it is")
            settings.log(f"{out}: the session is already complete")
            return out
        if not partial.is_dir():
            raise AcquisitionError(f"{partial}: no interrupted acquisition to resume (expected the folder a stopped run leaves)")
        _check_resume(partial, profile)
    else:
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise AcquisitionError(f"{out}: already exists and is not empty (expected a new session folder)")
        if partial.exists():
            raise AcquisitionError(f"{partial}: an interrupted acquisition is there (expected --resume to continue it, or remove it)")
    operator.check_can_prompt()
    config = profile.acquisition
    lamp_file = partial / "lamp.json" if emulate else profile.lamp_state_file
    # The lamp's record is read and checked before anything opens or moves: a damaged one (a
    # time stamp without its time zone, say) is refused in one line (LampStateError) that names
    # the file, not as a stopped acquisition whose "run again with --resume" would not mend it.
    Lamp(lamp_file).is_on

    with contextlib.ExitStack() as stack:
        instrument = connect(profile, stack, emulate=emulate, lamp_state_file=lamp_file, through_gige=through_gige)
        captures = _captures(profile, instrument.camera)  # checked before anything moves
        _layout(profile, instrument.camera)
        partial.mkdir(parents=True, exist_ok=True)
        # Atomic: a kill while writing it must not leave a folder --resume refuses to read.
        atomic_files.write_atomic(partial / "profile.json", json.dumps(_profile_identity(profile), sort_keys=True))
        journal = Journal(partial)
        if emulate:
            # An emulated lamp is switched on when the run starts and needs no waiting.
            config = dataclasses.replace(config, warmup_interval_s=0.0)
        if on_instrument is not None:
            on_instrument(instrument)
        try:
            _run_protocol(instrument, captures, partial, journal, config, operator, settings)
        except AcquisitionError:  # already says why and what was kept (the warm-up's)
            instrument.shutter.make_safe()
            raise
        except (InstrumentError, OSError) as error:  # a device, the lamp's record or the disk
            instrument.shutter.make_safe()
            # A lamp record damaged during the run is not mended by --resume: say what is first.
            remedy = (f"mend or remove the lamp state file {lamp_file}, then run again with --resume"
                      if isinstance(error, LampStateError) else "run again with --resume to complete it")
            raise AcquisitionStopped(
                f"acquisition stopped: {' '.join(str(error).split())}; {len(journal.done_images())} band "
                f"images kept in {partial} ({remedy})"
            ) from None
        except interrupt.Interrupted as stopped:
            # SIGINT or SIGTERM (spherejax.interrupt), seen between band images: the journal and
            # SESSION.partial stay as they are for --resume.
            instrument.shutter.make_safe()
            stopped.done, stopped.total = len(journal.done_images()), len(captures) * len(profile.band_centres_nm)
            stopped.unit = "band images"
            raise
        except BaseException:
            instrument.shutter.make_safe()
            raise
        instrument.shutter.make_safe()
        exposures = {int(k): v for k, v in journal.last("exposures")["exposure_s"].items()}
        _write_session(out, partial, journal, instrument, captures, exposures)
        # The session is complete: move the work folder aside at once, in one rename, so that a
        # kill from here on (closing the devices takes a while) leaves no SESSION.partial. Its
        # hidden name is a staging name, which --resume removes if a kill leaves it
        # (`_remove_stale_staging`).
        from spherejax import io

        finished = io.temp_sibling(out)
        os.rename(partial, finished)
    shutil.rmtree(finished, ignore_errors=True)
    return out


__all__ = ["AcquisitionError", "AcquisitionStopped", "Operator", "Settings", "Instrument", "Journal", "acquire", "choose_exposure", "connect"]
