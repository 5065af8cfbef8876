"""Writing files so that a reader, a crash or a kill sees the old file or the new one, never half.

Every writer in spherejax and hw/ goes through here, the engine's cache of kernel timings
(`_engine.variant_cache`) included: this module imports nothing of spherejax, so that it stands
below every layer (io is above the engine, which may not import it). One rule for temporary names:
``.<target name>.<12 hex digits>.tmp`` in the target's own folder (`temp_sibling`), which
`is_temp_sibling` recognises, so that whatever a killed run leaves is found and removed by the
next one (`spherejax.archive`'s resume, `hw.acquire`'s).

The steps of one write (`atomic_file`):

1. the temporary name is created with O_EXCL: never an existing file, nor a link to one
   elsewhere; with mode 0666 less the umask, the mode a file created at the target's name would
   get (`tempfile.mkstemp` would give 0600, which the rename would carry into the target);
2. the contents are written, flushed and fsynced: on disk before the rename makes them the file;
3. `os.replace` puts it at the target's name, atomically (same folder, same file system);
4. the folder is fsynced, so that the rename itself survives a power cut (POSIX).

On any failure before the rename the temporary file is removed and the target is as it was.

A set of files that belong together (a command's tables and figures, a measurement's CSV and
JSON) goes through `write_together`: every temporary file written first, then the renames, so a
full disk leaves none of them changed.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import re
import uuid
from collections.abc import Iterator, Mapping
from typing import IO

#: Mode bits a new file is created with, before the umask (as `open(path, "w")` creates it).
NEW_FILE_MODE = 0o666


def temp_sibling(path: os.PathLike | str) -> pathlib.Path:
    """An unused hidden name beside `path`, ``.<name>.<12 hex>.tmp``: same folder, so os.replace /
    os.rename onto `path` is atomic. For files and folders (`io.write_session` stages a session
    folder under one)."""
    path = pathlib.Path(path)
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")


def is_temp_sibling(name: str, of: str | None = None) -> bool:
    """True if `name` is one `temp_sibling` makes (".<name>.<12 hex>.tmp"), of a file or folder
    named `of` if given: what a killed run leaves, and cleans up after."""
    stem = re.escape(of) if of is not None else ".+"
    return re.fullmatch(rf"\.{stem}\.[0-9a-f]{{12}}\.tmp", name) is not None


def open_exclusive(path: os.PathLike | str, mode: str = "wb", *, encoding: str | None = None) -> IO:
    """Create `path` with O_EXCL (OSError if it exists, a link included) and `NEW_FILE_MODE` less
    the umask, open for writing: mode "wb", "w+b" (readable too) or "w" (text, UTF-8 unless
    `encoding` says otherwise). Step 1 of every write here."""
    if mode not in ("wb", "w+b", "w"):
        raise ValueError(f"mode: expected 'wb', 'w+b' or 'w', got {mode!r}")
    access = os.O_RDWR if "+" in mode else os.O_WRONLY
    descriptor = os.open(path, access | os.O_CREAT | os.O_EXCL, NEW_FILE_MODE)
    text = {"encoding": encoding or "utf-8"} if mode == "w" else {}
    return os.fdopen(descriptor, mode, **text)  # owns the descriptor from here


def create_exclusive(path: os.PathLike | str) -> None:
    """Create `path` empty with O_EXCL and `NEW_FILE_MODE` less the umask (OSError if it exists)."""
    open_exclusive(path).close()


def fsync_folder(folder: os.PathLike | str) -> None:
    """fsync a folder, so that a rename into it is on disk (POSIX; elsewhere nothing to do)."""
    if os.name != "posix":
        return
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


@contextlib.contextmanager
def atomic_file(path: os.PathLike | str, mode: str = "wb", *, encoding: str | None = None) -> Iterator[IO]:
    """Open a new temporary file beside `path` for writing; on leaving the block without an
    error it becomes `path` (the steps in the module docstring), on an error it is removed.

    Args:
      path: the file to write.
      mode: "wb" (bytes), "w+b" (bytes, readable too: h5py's file-object driver reads back
        what it wrote) or "w" (text).
      encoding: for text, default UTF-8.

    Raises:
      OSError: from creating, writing or renaming (the caller words it for its file kind).
    """
    path = pathlib.Path(path)
    temporary = temp_sibling(path)
    try:
        handle = open_exclusive(temporary, mode, encoding=encoding)
    except OSError:
        raise  # nothing created (a name already there is not ours to remove)
    except BaseException:
        # A stop raised at once (spherejax.interrupt.at_once) just as the file was created: it is
        # ours (its name is new and random), and must not outlive the stop.
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        raise
    try:
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        raise
    fsync_folder(path.parent)


def create_whole(path: os.PathLike | str, data: bytes, *, direct_without_links: bool = False) -> bool:
    """Create `path` holding `data`, never seen empty or torn and never over a file already there:
    written and fsynced under a temporary sibling, then linked into place (link(2) never replaces
    a file). Return whether this call created it (False: something was there already).

    On a file system without hard links the link's OSError is raised, unless
    `direct_without_links`: then `path` is created directly with O_EXCL and written (seen empty
    for that moment; a log may be, a lock file may not)."""
    temporary = temp_sibling(path)
    try:
        with open_exclusive(temporary) as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        try:
            os.link(temporary, path)
        except FileExistsError:
            return False
        except OSError:
            if not direct_without_links:
                raise
            try:
                with open_exclusive(path) as handle:
                    handle.write(data)
                    handle.flush()
                    os.fsync(handle.fileno())
            except FileExistsError:
                return False
        return True
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)


def write_atomic(path: os.PathLike | str, data: bytes | str) -> None:
    """Write `data` (bytes, or str as UTF-8) to `path` through `atomic_file`."""
    with atomic_file(path, "w" if isinstance(data, str) else "wb") as handle:
        handle.write(data)


def write_together(files: Mapping[os.PathLike | str, bytes]) -> None:
    """Write every path -> bytes as one set: each to a temporary sibling (created, written and
    fsynced as in `atomic_file`) first, then each renamed into place, then their folders fsynced.

    A failure while writing the temporaries (a full disk, the usual one) leaves every target as it
    was. On a failure among the renames (which need no space), the targets this call created are
    removed; one it replaced stays replaced. The temporaries never outlive the call.

    Raises:
      OSError: from creating, writing or renaming, with `filename` the target it was for (the
        caller words it for its file kind).
    """
    temporaries: dict[pathlib.Path, pathlib.Path] = {}
    added: list[pathlib.Path] = []
    try:
        for path, payload in files.items():
            path = pathlib.Path(path)
            temporaries[path] = temp_sibling(path)
            try:
                with open_exclusive(temporaries[path]) as handle:
                    handle.write(payload)
                    handle.flush()
                    os.fsync(handle.fileno())
            except OSError as error:
                error.filename = str(path)  # the file the user asked for, not its temporary name
                raise
        for path, temporary in temporaries.items():
            new = not os.path.lexists(path)
            try:
                os.replace(temporary, path)
            except OSError as error:
                error.filename = str(path)
                raise
            if new:
                added.append(path)
        for folder in {path.parent for path in temporaries}:
            fsync_folder(folder)
    except BaseException:
        for path in added:
            path.unlink(missing_ok=True)
        raise
    finally:
        for temporary in temporaries.values():
            temporary.unlink(missing_ok=True)
