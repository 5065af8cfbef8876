"""OUT/.spherejax.lock, the lock of one run on OUT and the outputs it claims (`OutputLock`), and the
check before any work that no output can touch a file spherejax does not own (`claim_outputs`):
the package docstring, "Safety"."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import pathlib
import re
import socket
from collections.abc import Iterable

from .. import io
from .discovery import InputSpec, identity
from .errors import BatchError, link_or
from .manifest import MANIFEST_NAME
from .outputs import ALL_OUTPUT_KINDS, OUTPUT_KINDS_BY_FORMAT, written_for

LOCK_NAME = ".spherejax.lock"


class OutputLock:
    """An exclusive lock on OUT for one run (package docstring): flock on OUT/.spherejax.lock.

    The lock file is one JSON object: the holder's "pid" and "host", then "claims", every output
    path (relative to OUT) the run set out to write, written and fsynced before any of them is
    (`claim`). A run that ends removes the file; one killed (or failed) leaves it,
    and the run that takes it over reads its claims (`claimed`): outputs put in place and never
    recorded in the manifest (a kill between the two) are known as spherejax's, not taken for a
    user's files in the way. They live here, not in a file of their own, because the lock file is
    the one file a killed run is known to leave in OUT.
    """

    def __init__(self, out_root: pathlib.Path):
        self.path = out_root / LOCK_NAME
        self.fd: int | None = None
        self.taken_over: str | None = None  # the previous holder, when its lock file was left
        self.claimed: set[str] = set()  # output paths claimed by runs that left the lock file
        self.holds_claims = False  # the file holds claims (this run's or carried over)

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
                holder = _describe_holder(os.read(fd, 4096))
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
            left = os.read(fd, 4096)
            if left:
                self.taken_over = _describe_holder(left)
                self.claimed = _read_claims(fd)
            self.fd = fd
            self._claims: list[str] = []
            self._write()
            self.claim(sorted(self.claimed))  # carried over until a run ends
            return

    def _write(self) -> None:
        """The lock file's one JSON object, written over what was there (it only grows)."""
        record = {"pid": os.getpid(), "host": socket.gethostname(), "claims": self._claims}
        data = (json.dumps(record, ensure_ascii=False) + "\n").encode("utf-8", errors="backslashreplace")
        if os.fstat(self.fd).st_size > len(data):  # only when taking over a longer file
            os.ftruncate(self.fd, len(data))
        os.pwrite(self.fd, data, 0)

    def claim(self, outputs: Iterable[str]) -> None:
        """Record, before writing them, the output paths (relative to OUT) this run may write."""
        new = [name for name in outputs if name not in self._claims]
        if new and self.fd is not None:
            self._claims.extend(new)
            self._write()
            os.fsync(self.fd)
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


#: The most of a left lock file read for its claims: 10,000 inputs' claims take about 3 MB.
_MAX_LOCK_BYTES = 64 << 20


def _read_claims(fd: int) -> set[str]:
    """The output paths a lock file left by an earlier run claims (`OutputLock`); none from a file
    that is not such an object (torn by a kill mid-write, or not spherejax's)."""
    size = os.fstat(fd).st_size
    if size > _MAX_LOCK_BYTES:
        return set()
    try:
        record = json.loads(os.pread(fd, size, 0))
    except (ValueError, RecursionError):
        return set()
    claims = record.get("claims") if isinstance(record, dict) else None
    return {name for name in claims if isinstance(name, str)} if isinstance(claims, list) else set()


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


def claim_outputs(specs: list[InputSpec], out_root: pathlib.Path, calibration_path: pathlib.Path,
                   output_format: str, owned: set[str]) -> list[InputSpec]:
    """Check, before any work, that no output can touch a file spherejax does not own, and give
    each input the files of OUT it may remove (`InputSpec.owned`).

    Refused (BatchError, one line naming the file):
    - an output that is an input of the batch or the calibration, however named (resolved path,
      or (st_dev, st_ino) where it exists: `OUT` being the inputs' folder made a.tif's Lab output
      replace the input a.lab.exr);
    - an output name where a file already is that neither OUT's manifest nor the claims of a
      killed run record (`owned`, `OutputLock.claimed`): a file spherejax did not write is the user's, never replaced
      and never removed. One exception, for a manifest whose last record was torn by a kill
      (which leaves the outputs in place unrecorded): in an OUT that holds a manifest, the
      outputs of an input whose reflectance output names that very input as its source
      (spherejax:source, `written_for`) are taken as spherejax's.
    Files of the other format at an input's names are left alone unless the manifest records them.
    """
    has_manifest = os.path.lexists(out_root / MANIFEST_NAME)
    owned = set(owned)
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
    for spec in specs:
        if spec.problem is None:
            for kind in OUTPUT_KINDS_BY_FORMAT[output_format]:
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
                if os.path.lexists(path) and relative not in owned:
                    if not (has_manifest and written_for(out_root, spec)):
                        in_the_way.append(path)
                    else:
                        owned.add(relative)
        mine = tuple(f"{spec.name}.{kind}" for kind in ALL_OUTPUT_KINDS if f"{spec.name}.{kind}" in owned)
        claimed.append(dataclasses.replace(spec, owned=mine) if mine else spec)
    if in_the_way:
        more = f" (and {len(in_the_way) - 1} more)" if len(in_the_way) > 1 else ""
        raise BatchError(
            in_the_way[0],
            f"is in the way of an output{more}: OUT's manifest does not record it as written by spherejax, "
            "so it is not replaced",
            "no file at an output's name but spherejax's own: move it, or choose another OUT",
        )
    return claimed


__all__ = ["LOCK_NAME", "OutputLock", "claim_outputs"]
