"""SESSION.partial, an acquisition's work folder, and what lets a stopped run resume from it.

    SESSION.partial/profile.json     the profile's identity (instrument id, bands, samples,
                                     camera backend): --resume refuses another profile
    SESSION.partial/journal.jsonl    one fsynced JSON line per finished step (`Journal`): the
                                     warm-up, the exposures, every band image with its SHA-256
    SESSION.partial/captures/...     the band images (`acquisition_protocol`)
    SESSION.partial/lamp.json        with --emulate, the emulated lamp's state (`hw.lamp`)

Here: the journal, the checks before a run creates, resumes or removes the work folder
(`_check_ownership`, `_check_resume`, `_is_work_folder`), the lock that lets one acquisition at a
time work on a session (`_lock_session`, SESSION.lock beside it) and the cleanup of the staging
folders a run killed while it wrote the session leaves (`_remove_stale_staging`). `acquire.acquire`
decides when each is called. Every refusal is one AcquisitionError line.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import os
import pathlib
import shutil

from spherejax import jsontext
from spherejax.io.plain_files import read_small

from .errors import AcquisitionError
from .profile import Profile

JOURNAL_NAME = "journal.jsonl"
PARTIAL_SUFFIX = ".partial"
#: SESSION.lock beside SESSION: one acquisition per session at a time (`_lock_session`).
LOCK_SUFFIX = ".lock"


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _sha256(path: pathlib.Path) -> str | None:
    """The SHA-256 (hex) of a band image, or None when it cannot be read as a regular file. No
    safe point: it is called while a stop is handled, to count what was kept."""
    from spherejax.io.hashing import sha256_file

    try:
        return sha256_file(path, check=None)
    except OSError:
        return None


class Journal:
    """SESSION.partial/journal.jsonl: one fsynced JSON line per finished step (`spherejax.io.journal`,
    the format of a batch's manifest too); a line cut by a kill is ignored on reading."""

    def __init__(self, folder: pathlib.Path):
        from spherejax.io.journal import Journal as JsonLines

        self.folder = folder
        self.path = folder / JOURNAL_NAME
        # No safe point: read while a stop is handled (`acquire`), to say what was kept.
        self._lines = JsonLines(self.path, key="event")

    def records(self) -> list[dict]:
        return list(self._lines.records())

    def append(self, record: dict) -> None:
        # Opened for each record: a symbolic link in the journal's place must not redirect the
        # append (O_NOFOLLOW), and a FIFO there must not make the acquisition wait for a reader.
        self._lines.append(record)

    def last(self, event: str) -> dict | None:
        found = [r for r in self.records() if r["event"] == event]
        return found[-1] if found else None

    def done_images(self) -> dict[tuple[str, int], dict]:
        """(capture id, band) -> record of every band image whose file is there, unchanged."""
        done = {}
        for record in self.records():
            if record["event"] != "image":
                continue
            file = self.folder / record["file"]
            if _sha256(file) == record.get("sha256"):
                done[(record["capture"], int(record["band_nm"]))] = record
        return done


# --------------------------------------------------------------------------------- work folder


def _profile_identity(profile: Profile) -> dict:
    identity = {
        "instrument_id": profile.instrument_id,
        "bands": {str(k): list(v) for k, v in profile.bands.items()},
        "samples": [_plan_identity(s) for s in profile.samples],
        "camera": profile.camera.backend,
    }
    if profile.tunable_filter is not None:  # only then: a wheel profile's identity stays as it was
        identity["tunable_filter"] = {"model": profile.tunable_filter.model, "bands": list(profile.band_centres_nm)}
    return identity


def _plan_identity(plan) -> dict:
    """A [[samples]] entry in the profile's identity: its fields, "role" only for the registration
    target, so that a plan without one is identified as it was before there were roles."""
    fields = dataclasses.asdict(plan)
    if fields["role"] == "sample":
        del fields["role"]
    return fields


def _check_resume(partial: pathlib.Path, profile: Profile) -> None:
    """Refuse, in one AcquisitionError line, to resume `partial` unless it is the work folder of
    an acquisition of this same profile (its profile.json, `_profile_identity`), or one a kill
    left before its profile.json was in place."""
    saved = partial / "profile.json"
    if not saved.is_file():
        # A run killed between creating the folder and renaming profile.json into place left
        # nothing to keep (at most the temporary, half written): the resumed run starts afresh.
        if _is_work_folder(partial):
            return
        raise AcquisitionError(f"{partial}: holds no profile.json: not an acquisition spherejax can resume")
    try:
        before = jsontext.loads(read_small(saved, 1 << 20))
    except jsontext.JSONTextError as error:
        raise AcquisitionError(f"{saved}: {error.problem}: not an acquisition spherejax can resume") from None
    except OSError as error:
        raise AcquisitionError(f"{saved}: cannot be read: {error.strerror}: not an acquisition spherejax can resume") from None
    now = _profile_identity(profile)
    if before != now:
        changed = sorted(k for k in now if before.get(k) != now[k])
        raise AcquisitionError(
            f"{profile.path}: differs from the interrupted acquisition's profile in {changed} "
            f"(expected the same instrument, bands and samples to resume)"
        )


def _remove_stale_staging(out: pathlib.Path) -> None:
    """Remove the staging folders a run killed while writing the session left beside it.

    io.write_session writes the session into a hidden sibling (`io.temp_sibling`) and renames it
    into place; a kill before the rename leaves that folder, which the run that completes the
    session would otherwise leave there for good. The finished SESSION.partial is moved to such
    a name too before it is deleted (`acquire`).
    Called on --resume only, when the run that made it is over.
    """
    from spherejax import io

    with contextlib.suppress(OSError):
        for entry in out.parent.iterdir():
            if io.is_temp_sibling(entry.name, out.name) and entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)


def _check_ownership(profile: Profile, out: pathlib.Path, partial: pathlib.Path, *, emulate: bool) -> None:
    """Before anything is opened or removed: SESSION and SESSION.partial, the folders `acquire`
    creates and removes whole, are not links (the session is renamed into place, which would
    replace a link; the work folder would be written through one), and neither is, nor holds at
    any depth, the profile or the lamp state file it reads and updates (io.ownership.refuse_holding,
    by resolved path and (st_dev, st_ino)); SESSION.lock is neither of those files either
    (io.ownership.refuse_overlaps). AcquisitionError, one line naming the folder or file."""
    from spherejax.io import SpherejaxFileError, ownership

    inputs = {"the profile (--profile)": profile.path}
    if not emulate:  # emulated, the lamp state lives in SESSION.partial, spherejax's own
        inputs["the profile's lamp state file"] = profile.lamp_state_file
    folders = {"-o SESSION": out, "SESSION.partial": partial}
    try:
        for label, folder in folders.items():
            if folder.is_symlink():
                raise SpherejaxFileError(
                    folder, f"{label} is a symbolic link (to {os.readlink(folder)})",
                    f"{label} a folder spherejax makes, not a link",
                )
        ownership.refuse_holding(folders, inputs)
        ownership.refuse_overlaps({"SESSION.lock": session_lock_path(out)}, inputs)
    except SpherejaxFileError as error:
        raise AcquisitionError(str(error)) from None


def session_lock_path(out: pathlib.Path) -> pathlib.Path:
    """SESSION.lock, beside SESSION and SESSION.partial."""
    return out.with_name(out.name + LOCK_SUFFIX)


def _lock_session(out: pathlib.Path):
    """The exclusive lock of one acquisition on the session `out` (`spherejax.io.exclusive_lock`,
    the primitive of `correct`'s lock on OUT): taken before any device opens and before
    SESSION.partial is created, resumed or removed, and held until the run ends, so that a second
    `acquire` on the same session (with --resume or not) is refused in one line, touching nothing:
    two runs once drove the instrument at once and the loser left a full SESSION.partial. A run
    killed leaves SESSION.lock, unlocked; the next run takes it over and removes it at its end.

    Returns:
      The `spherejax.io.exclusive_lock.HeldLock` (release it, or use it as a context manager).

    Raises:
      AcquisitionError: one line naming SESSION.lock: held by a running acquisition (its pid and
        host), or something else at that name (a user's file, a link, a folder).
    """
    from spherejax.io import SpherejaxFileError, exclusive_lock

    try:
        return exclusive_lock.take(
            session_lock_path(out), record={"acquiring": out.name},
            busy=f"another spherejax acquire is writing the session {out.name}",
            expected="one acquisition per session: wait for it to finish, or choose another -o SESSION",
        )
    except SpherejaxFileError as error:
        raise AcquisitionError(str(error)) from None


def _is_work_folder(partial: pathlib.Path) -> bool:
    """True if `partial` is a folder an acquisition made (it holds its profile.json, or only the
    temporary name of one): what `acquire` may remove."""
    from spherejax import atomic_files

    if partial.is_symlink() or not partial.is_dir():
        return False
    if (partial / "profile.json").is_file():
        return True
    return all(atomic_files.is_temp_sibling(entry.name, "profile.json") for entry in partial.iterdir())


__all__ = ["JOURNAL_NAME", "LOCK_SUFFIX", "PARTIAL_SUFFIX", "Journal", "session_lock_path"]
