"""OUT/.spherejax.lock, the lock of one run on OUT and what it claims (`OutputLock`,
`record_made`), and the check before any work that no output can touch a file spherejax does not
own (`claim_outputs`): the package docstring, "Safety".

Ownership is proved, never inferred. A file at an output's name is spherejax's only when its bytes
are bytes spherejax recorded putting at that very name: the SHA-256 a record of OUT's manifest
lists for it, or the SHA-256 a run wrote into its lock file (`record_made`) after finishing the
file and before renaming it into place. Neither a name alone (a claim, a record of another file
since replaced) nor a neighbour (an EXR whose spherejax:source matches) proves anything about the
file found there.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import pathlib
import re
import socket
from collections.abc import Collection, Iterable, Mapping, Sequence

from .. import io
from ..io.exclusive_lock import is_lock_file
from ..io.hashing import sha256_file
from .discovery import InputSpec, identity
from .errors import BatchError, link_or
from .manifest import manifest_records
from .outputs import ALL_OUTPUT_KINDS, OUTPUT_KINDS_BY_FORMAT

LOCK_NAME = ".spherejax.lock"

#: A SHA-256 as the lock file and the manifest write it: 64 lowercase hex digits.
_SHA256 = re.compile(r"[0-9a-f]{64}")


class OutputLock:
    """An exclusive lock on OUT for one run (package docstring): flock on OUT/.spherejax.lock.

    The lock file is a journal of JSON lines, each fsynced:
    - the first, {"pid", "host"} padded to `HOLDER_BYTES`: the holder, named in the message that
      refuses a second run; a run that takes the file over writes its own in its place;
    - {"claims": [...]}: output paths (relative to OUT) the run set out to write (`claim`), before
      any is written;
    - {"made": {path: SHA-256}}: the files of one input, finished under their temporary names,
      appended just before they are renamed into place (`record_made`, by whichever process
      corrects the input: this one's threads or a dask worker).
    A run that ends removes the file; one killed (or failed) leaves it, and the run that takes it
    over carries its claims and made records on (`claimed`, `made`): an output put in place and
    never recorded in the manifest (a kill between the two) is known as spherejax's by its bytes,
    while a file the user put at a name the dead run claimed but never wrote, or over a file it
    did write, is not. They live here, not in a file of their own, because the lock file is the
    one file a killed run is known to leave in OUT.
    """

    def __init__(self, out_root: pathlib.Path):
        self.path = out_root / LOCK_NAME
        self.fd: int | None = None
        self.taken_over: str | None = None  # the previous holder, when its lock file was left
        self.claimed: set[str] = set()  # output paths claimed by runs that left the lock file
        self.made: dict[str, set[str]] = {}  # output path -> SHA-256s runs that left the file put there
        self.holds_claims = False  # the file holds claims or made records (this run's or carried over)

    def acquire(self) -> None:
        while True:
            try:
                # O_NOFOLLOW: the lock is written (the holder's pid); a symbolic link planted in
                # its place must not redirect that write to a file outside OUT.
                # open_regular: a FIFO in the lock's place made `correct` wait forever on its read.
                fd = io.open_regular(self.path, os.O_RDWR | os.O_CREAT)
            except OSError as error:
                raise BatchError(self.path, f"cannot be created: {link_or(error)}", "a regular file in a writable OUT") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _describe_holder(os.pread(fd, 4096, 0))
                os.close(fd)
                raise BatchError(
                    self.path, f"is held by {holder}: another spherejax correct is writing to this OUT",
                    "one run per OUT; wait for it or use another OUT",
                ) from None
            # The previous holder may have removed the file between our open and flock: then we
            # hold a lock on a file nobody else will see. Start again on the file now there.
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            left = os.pread(fd, 4096, 0)
            if left and not is_lock_file(left):
                # A file at the lock's name that no spherejax run wrote (a user's notes, a log):
                # not ours to write over, nor to remove at the end. An empty file holds nothing to
                # lose (a run killed between its create and its first write leaves one).
                os.close(fd)
                raise BatchError(
                    self.path, 'is in the way: a file that is not a spherejax lock (it does not begin with '
                    '{"pid": N, "host": ...})', "OUT's lock file, or nothing, at this name",
                ) from None
            if left:
                self.taken_over = _describe_holder(left)
                self.claimed, self.made = _read_left(fd)
            if left[HOLDER_BYTES - 1:HOLDER_BYTES] == b"\n" and b"\n" not in left[:HOLDER_BYTES - 1]:
                # The holder's line, replaced in place: one write of one block, which a kill cannot
                # tear; the lines after it (the claims and made records carried over) stay as
                # they are, never rewritten.
                os.pwrite(fd, _holder_line(), 0)
            else:
                # Empty, another version's file, or anything else: written afresh, with what
                # `_read_left` found in it.
                carried = [{"claims": sorted(self.claimed)}] if self.claimed else []
                carried += [{"made": {name: digest}} for name, digests in sorted(self.made.items())
                            for digest in sorted(digests)]
                os.ftruncate(fd, 0)
                os.pwrite(fd, _holder_line() + _lines(carried), 0)
            os.fsync(fd)
            self.fd = fd
            self._claims: list[str] = sorted(self.claimed)
            self.holds_claims = bool(self.claimed or self.made)
            return

    def claim(self, outputs: Iterable[str]) -> None:
        """Record, before writing them, the output paths (relative to OUT) this run may write. A
        claim names what the run means to write; it proves nothing about a file found there
        later (`record_made` does)."""
        new = [name for name in outputs if name not in self._claims]
        if new and self.fd is not None:
            self._claims.extend(new)
            _append_lines(self.fd, [{"claims": new}])
            self.holds_claims = True

    def release(self, keep_claims: bool = False) -> None:
        """Give up the lock; the file goes unless `keep_claims` (a run that did not end) and it
        holds claims."""
        if self.fd is not None:
            # Unlink while still holding the lock, so nobody locks a file that is about to go.
            if not (keep_claims and self.holds_claims):
                self.path.unlink(missing_ok=True)
            os.close(self.fd)
            self.fd = None


#: The size of the lock file's first line, the holder's (padded with spaces): rewritten in place by
#: the run that takes the file over, in one write that a kill cannot tear.
HOLDER_BYTES = 512


def _holder_line() -> bytes:
    """{"pid": ..., "host": ...} padded to `HOLDER_BYTES` with its newline (a host name too long is cut)."""
    host = socket.gethostname()
    while True:
        data = json.dumps({"pid": os.getpid(), "host": host}, ensure_ascii=False).encode("utf-8", errors="backslashreplace")
        if len(data) < HOLDER_BYTES:
            return data.ljust(HOLDER_BYTES - 1) + b"\n"
        host = host[: len(host) // 2]


def _lines(records: list[dict]) -> bytes:
    """`records` as JSON lines."""
    data = "".join(json.dumps(record, ensure_ascii=False) + "\n" for record in records)
    return data.encode("utf-8", errors="backslashreplace")


def _append_lines(fd: int, records: list[dict]) -> None:
    """`records` as JSON lines at the end of the lock file, in one write, fsynced. Only one writer
    appends at a time: the holder before any input starts (`OutputLock.claim`), then the inputs'
    `record_made`, each with a file of its own opened O_APPEND (atomic appends, also across
    processes)."""
    os.lseek(fd, 0, os.SEEK_END)
    block = memoryview(_lines(records))
    while block:
        block = block[os.write(fd, block):]
    os.fsync(fd)


def record_made(out_root, digests: Mapping[os.PathLike | str, str]) -> None:
    """Append to OUT's lock file the SHA-256 of each file about to be put in place (`digests`:
    path -> SHA-256, the files finished under their temporary names), fsynced, so that a run killed
    after the renames and before the manifest's line leaves them proved spherejax's by their
    bytes (`OutputLock`). Called by `outputs.correct_into` in whatever process corrects the input.

    Without a lock file (`correct_input` called on its own, no run holding OUT) there is nothing
    to record into, and nothing is created.

    Raises:
      SpherejaxFileError: the lock file cannot be appended to (the input fails: its outputs would
        be put in place unproved).
    """
    root = pathlib.Path(out_root).resolve()
    path = root / LOCK_NAME
    made = {pathlib.Path(file).resolve().relative_to(root).as_posix(): digest for file, digest in digests.items()}
    try:
        fd = io.open_regular(path, os.O_WRONLY | os.O_APPEND)
    except FileNotFoundError:
        return
    except OSError as error:
        raise io.SpherejaxFileError(path, f"cannot be written: {link_or(error)}", "OUT's lock file, a regular file") from None
    try:
        _append_lines(fd, [{"made": made}])
    except OSError as error:
        raise io.SpherejaxFileError(path, f"cannot be written: {error.strerror}", "room in OUT for its lock file") from None
    finally:
        os.close(fd)


#: The most of a left lock file read for its claims: 10,000 inputs' claims take about 3 MB.
_MAX_LOCK_BYTES = 64 << 20


def _read_left(fd: int) -> tuple[set[str], dict[str, set[str]]]:
    """What a lock file left by an earlier run holds (`OutputLock`): (the output paths claimed,
    output path -> the SHA-256s made there). Lines that are not such objects (torn by a kill
    mid-write, or not spherejax's) are skipped; a file over `_MAX_LOCK_BYTES` gives nothing."""
    claims: set[str] = set()
    made: dict[str, set[str]] = {}
    size = os.fstat(fd).st_size
    if size > _MAX_LOCK_BYTES:
        return claims, made
    for line in os.pread(fd, size, 0).split(b"\n"):
        try:
            record = json.loads(line)
        except (ValueError, RecursionError):
            continue
        if not isinstance(record, dict):
            continue
        if isinstance(record.get("claims"), list):
            claims.update(name for name in record["claims"] if isinstance(name, str))
        if isinstance(record.get("made"), dict):
            for name, digest in record["made"].items():
                if isinstance(digest, str) and _SHA256.fullmatch(digest):
                    made.setdefault(name, set()).add(digest)
    return claims, made


def _describe_holder(content: bytes) -> str:
    """The holder a lock file names, in one line (it goes into messages); never raises: the file
    may hold anything."""
    # The holder's pid and host open the object; the claims after them may run past what was read.
    match = re.match(rb'\{"pid": (\d+), "host": ("(?:[^"\\]|\\.)*")', content)
    try:
        holder = {"pid": int(match[1]), "host": json.loads(match[2])} if match else json.loads(content)
        return " ".join(f"pid {holder['pid']} on {holder['host']}".split())
    except (ValueError, TypeError, KeyError, RecursionError):
        return "another process"


def written_by_spherejax(out_root: pathlib.Path, lock: OutputLock) -> dict[str, set[str]]:
    """Output path (relative to OUT) -> every SHA-256 spherejax recorded putting there: the
    outputs of every record of OUT's manifest, and the made records of runs that left the lock
    file (`OutputLock.made`). What `claim_outputs` proves a file found at an output's name by."""
    written: dict[str, set[str]] = {name: set(digests) for name, digests in lock.made.items()}
    for record in manifest_records(out_root):
        outputs = record.get("outputs")
        if isinstance(outputs, dict):
            for name, digest in outputs.items():
                if isinstance(name, str) and isinstance(digest, str):
                    written.setdefault(name, set()).add(digest)
    return written


def _proved(path: pathlib.Path, digests: Collection[str] | None) -> bool:
    """Whether the file at `path` holds bytes spherejax recorded putting there (`digests`): a
    regular file (never a link, a FIFO or a folder) whose SHA-256 is one of them."""
    if not digests:
        return False
    try:
        return sha256_file(path) in digests
    except OSError:
        return False


def claim_outputs(specs: list[InputSpec], out_root: pathlib.Path, calibration_path: pathlib.Path,
                  output_format: str, written: Mapping[str, Collection[str]],
                  verified: Sequence[bool] | None = None) -> list[InputSpec]:
    """Check, before any work, that no output can touch a file spherejax does not own, and give
    each input the files of OUT it may replace or remove (`InputSpec.owned`).

    Args:
      specs: the batch's inputs.
      written: output path (relative to OUT) -> the SHA-256s spherejax recorded putting there
        (`written_by_spherejax`).
      verified: per input of `specs`, True when --resume verified it done (its record's outputs
        there with their recorded SHA-256s, `manifest.is_done`): nothing of it is written or
        removed, so its files are not hashed again.

    Refused (BatchError, one line naming the file):
    - an output that is an input of the batch or the calibration, however named (resolved path,
      or (st_dev, st_ino) where it exists: `OUT` being the inputs' folder made a.tif's Lab output
      replace the input a.lab.exr);
    - an output name of an input to correct where a file already is that is not proved
      spherejax's on its own (module docstring): its SHA-256 is none that `written` records at
      that very name. A file spherejax did not write is the user's, never replaced and never
      removed, whatever lies beside it.
    Files of the other format at an input's names are left alone unless so proved.
    """
    protected: dict = {}
    for spec in specs:
        for file in spec.files:
            protected[os.path.realpath(file)] = spec.source
            with contextlib.suppress(OSError):
                protected[identity(os.stat(file))] = spec.source
    protected[os.path.realpath(calibration_path)] = f"the calibration ({calibration_path})"
    with contextlib.suppress(OSError):
        protected[identity(os.stat(calibration_path))] = f"the calibration ({calibration_path})"
    in_the_way = []
    claimed = []
    for index, spec in enumerate(specs):
        if spec.problem is not None:
            claimed.append(spec)  # it fails without writing: its names are not its to touch
            continue
        kinds = OUTPUT_KINDS_BY_FORMAT[output_format]
        for kind in kinds:
            relative = f"{spec.name}.{kind}"
            path = out_root / relative
            other = protected.get(os.path.realpath(path))
            if other is None:
                with contextlib.suppress(OSError):
                    other = protected.get(identity(os.stat(path)))
            if other is not None:
                raise BatchError(
                    path, f"is the output {relative} of {spec.source}, and also the input {other}",
                    "an OUT whose outputs are no inputs: choose another OUT",
                )
        if verified is not None and verified[index]:
            claimed.append(spec)  # skipped: nothing of it is touched
            continue
        mine = []
        for kind in kinds + tuple(kind for kind in ALL_OUTPUT_KINDS if kind not in kinds):
            relative = f"{spec.name}.{kind}"
            path = out_root / relative
            if not os.path.lexists(path):
                continue
            if _proved(path, written.get(relative)):
                mine.append(relative)
            elif kind in kinds:
                in_the_way.append(path)
        claimed.append(dataclasses.replace(spec, owned=tuple(mine)) if mine else spec)
    if in_the_way:
        more = f" (and {len(in_the_way) - 1} more)" if len(in_the_way) > 1 else ""
        raise BatchError(
            in_the_way[0],
            f"is in the way of an output{more}: OUT's manifest does not record it as written by spherejax "
            "(these bytes at this name), nor does the lock file of a run that was stopped, so it is not replaced",
            "no file at an output's name but spherejax's own: move it, or choose another OUT",
        )
    return claimed


__all__ = ["LOCK_NAME", "OutputLock", "claim_outputs", "record_made", "written_by_spherejax"]
