"""One run at a time on something spherejax writes: an exclusive `fcntl.flock` on a lock file.

The primitive `correct`'s lock on OUT uses (`spherejax.archive.lock.OutputLock`), for a lock
file in a folder spherejax does not own, such as the one beside an acquisition's session
(`spherejax_hw.acquisition_journal`):

- the kernel drops a flock when its process dies, so a killed run never leaves the lock held: the
  next run takes the file over (`HeldLock.taken_over` names the dead holder);
- the lock file is never seen empty or torn: it is created holding its record, written to a
  temporary sibling and linked into place (link(2) never replaces a file), so its first bytes,
  `{"pid": N, "host": "..."`, are the signature by which a file at the lock's name is known as a
  spherejax lock (OutputLock's records begin the same way). A file there without it (a user's
  notes named SESSION.lock) is refused and left as it is, never written over or removed;
- it is opened with O_NOFOLLOW and O_NONBLOCK (`plain_files.open_regular`): a symbolic link, a
  FIFO or a folder planted at its name is refused without following or waiting on it;
- the holder removes it while still holding the lock (`HeldLock.release`), so nobody locks a file
  that is about to go.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import json
import os
import pathlib
import re
import socket

from .. import atomic_files
from .errors import SpherejaxFileError

#: The start of every spherejax lock file: the holder's pid, then its host.
_SIGNATURE = re.compile(rb'\{"pid": (\d+), "host": ("(?:[^"\\]|\\.)*")')

#: The most of a lock file read to say who holds it.
_HOLDER_BYTES = 4096


def describe_holder(content: bytes) -> str:
    """The holder a lock file's first bytes name, in one line ("pid 12 on lab-pc"); never raises."""
    match = _SIGNATURE.match(content)
    try:
        return " ".join(f"pid {int(match[1])} on {json.loads(match[2])}".split()) if match else "another process"
    except ValueError:
        return "another process"


def is_lock_file(content: bytes) -> bool:
    """Whether a file's first bytes carry the signature of a spherejax lock file (this module's
    and `correct`'s OUT lock, in every format they have had)."""
    return _SIGNATURE.match(content) is not None


@dataclasses.dataclass
class HeldLock:
    """A lock file held by this process (`take`).

    Fields:
      path: the lock file. fd: its descriptor, which holds the flock.
      taken_over: the holder named by a lock file a killed run left (None for a new file).
    """

    path: pathlib.Path
    fd: int | None
    taken_over: str | None = None

    def release(self) -> None:
        """Remove the lock file (while still holding it, and only if the name still leads to it)
        and give up the lock. Idempotent."""
        if self.fd is None:
            return
        try:
            with contextlib.suppress(OSError):
                here = os.lstat(self.path)
                held = os.fstat(self.fd)
                if (here.st_dev, here.st_ino) == (held.st_dev, held.st_ino):
                    os.unlink(self.path)
        finally:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> HeldLock:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _record(extra: dict) -> bytes:
    record = {"pid": os.getpid(), "host": socket.gethostname(), **extra}
    return (json.dumps(record, ensure_ascii=False) + "\n").encode("utf-8", errors="backslashreplace")


def take(path: os.PathLike | str, *, busy: str, expected: str, record: dict | None = None) -> HeldLock:
    """Take the exclusive lock on `path` (module docstring), or raise without touching anything.

    Args:
      path: the lock file; its folder must exist.
      busy: what a held lock means, for the refusal ("another spherejax acquire is writing this
        session").
      expected: the refusal's "expected" text ("one acquisition per session: ...").
      record: more fields of the JSON object the lock file holds, after "pid" and "host".

    Returns:
      The `HeldLock`, holding the file's record of this process.

    Raises:
      SpherejaxFileError: one line naming the lock file: held by a running process (naming it),
        something other than a spherejax lock there (a user's file, a link, a FIFO, a folder), or
        a folder where it cannot be created.
    """
    from .plain_files import open_regular

    path = pathlib.Path(path)
    ours = _record(record or {})
    while True:
        try:
            fd = open_regular(path, os.O_RDWR)
        except FileNotFoundError:
            try:
                atomic_files.create_whole(path, ours)
            except OSError as error:
                raise SpherejaxFileError(path, f"cannot be created: {error.strerror or error}", expected) from None
            continue
        except OSError as error:
            why = "a symbolic link" if error.errno == errno.ELOOP else error.strerror or str(error)
            raise SpherejaxFileError(path, f"is in the way: {why}, not a spherejax lock", expected) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = describe_holder(os.pread(fd, _HOLDER_BYTES, 0))
            os.close(fd)
            raise SpherejaxFileError(path, f"is held by {holder}: {busy}", expected) from None
        # The holder may have removed the file between our open and flock: then this lock is on a
        # file nobody else will see. Start again on whatever is there now.
        try:
            here = os.lstat(path)
            same = (here.st_dev, here.st_ino) == (os.fstat(fd).st_dev, os.fstat(fd).st_ino)
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        found = os.pread(fd, _HOLDER_BYTES, 0)
        if not is_lock_file(found):
            os.close(fd)
            raise SpherejaxFileError(
                path, "is in the way: a file that is not a spherejax lock (it does not begin with "
                '{"pid": N, "host": ...})', expected,
            )
        taken_over = None if found.startswith(ours) else describe_holder(found)
        # Written over the start, then cut to length: a kill between the two leaves a file that
        # still begins with a signature, never an empty one.
        os.pwrite(fd, ours, 0)
        os.ftruncate(fd, len(ours))
        os.fsync(fd)
        return HeldLock(path, fd, taken_over)


__all__ = ["HeldLock", "describe_holder", "is_lock_file", "take"]
