"""The one state machine of every image writer: rows into temporary files, put in place by `commit`.

The OpenImageIO image writer (`frames.AtomicImageWriter`), the images spherejax encodes itself
(`streamed_writer.StreamedImageWriter`: the quality PNG and the uncompressed EXR) and the ENVI
writer (`envi.EnviWriter`, two files) share it, and with it the rules of `spherejax.atomic_files`:

- open: each target file gets a temporary name beside it (`temp_sibling`), created with O_EXCL
  (never an existing file, nor a link to one elsewhere); a name that could not be created is not
  the writer's, and is never removed by it;
- writing: rows come in order, top to bottom (`write_rows`); a subclass writes them (`_write_rows`),
  into a file it opened itself or into the one stream this class keeps (`_open_stream`,
  `_write`: written past the page cache where the system allows it, `io.direct_io`, and hashed
  as written, so that `commit` returns the digest without reading the file back);
- commit: only once every row is written, the subclass finishes its files, fsynced and closed
  (`_complete`, which returns the digest(s) `commit` returns); then each temporary file is renamed
  onto its target in the order the targets were given (the ENVI header last, so that a reader
  that finds it finds the data), and the folder is fsynced so that the renames survive a power cut;
- closed, after `commit` or `abort` (leaving the `with` block, or any failure): the temporary
  files are removed, every target is as it was unless `commit` renamed it, and every further
  `write_rows` or `commit` is refused.

A failure is one `SpherejaxFileError` naming the file the caller asked for (`path`), never a
temporary name: "could not be written: <why>", where `_why` gives the system's reason (a subclass
may say more: `StreamedImageWriter` names a full disk or the file-size limit).
"""

from __future__ import annotations

import abc
import contextlib
import hashlib
import os
import pathlib
from collections.abc import Sequence
from typing import IO

from ..atomic_files import create_exclusive, fsync_folder, open_exclusive, temp_sibling
from .direct_io import DirectFile
from .errors import SpherejaxFileError


class AtomicWriter(abc.ABC):
    """An image of `height` rows written into temporary files beside its targets and put in
    place by `commit` (module docstring).

    Args:
      path: the file errors name; the only target unless `targets` is given.
      height: rows in the image.
      targets: every file written, in the order `commit` renames them into place (the folder of
        `path`: renames within one folder are atomic).

    A subclass creates its temporary files in `_open` (with `_create` or `_open_stream`), writes
    rows in `_write_rows`, finishes its files in `_complete`, and closes what it holds in
    `_release`.
    """

    def __init__(self, path, height: int, *, targets: Sequence[os.PathLike | str] | None = None):
        self.path = pathlib.Path(path)
        self.height = int(height)
        self._next_row = 0
        #: target -> its temporary name; renamed in this order.
        self._temps = {pathlib.Path(t): temp_sibling(t) for t in (targets if targets is not None else [self.path])}
        self._created: list[pathlib.Path] = []  # the temporary files this writer made: only those it removes
        self._is_open = True
        self._file: IO | None = None  # the stream's file object, its own buffer unused
        self._direct: DirectFile | None = None
        self._digest = None
        self._stream_target: pathlib.Path | None = None
        self._finished: tuple | None = None  # (the digest(s),) once `finish` has run
        try:
            self._open()
        except OSError as error:
            raise self._failed(error, self.path) from None

    @property
    def _temp(self) -> pathlib.Path:
        """The temporary name of `path`."""
        return self._temps[self.path]

    # -- what a subclass provides

    @abc.abstractmethod
    def _open(self) -> None:
        """Create the temporary files (`_create`, `_open_stream`); an OSError is reported as the
        writer's failure, after `abort`."""

    @abc.abstractmethod
    def _write_rows(self, row0: int, pixels) -> None:
        """Write rows row0:row0 + len(pixels), the next ones (the subclass's format)."""

    @abc.abstractmethod
    def _complete(self):
        """Finish every file: the last bytes written, fsynced and closed. Returns what `commit`
        returns (the digest(s))."""

    def _release(self) -> None:
        """Close whatever the writer holds open, without raising (called by `abort`, also after
        a failure); a subclass that holds more closes that too, then calls this."""
        file, self._file = self._file, None
        if self._direct is not None:
            self._direct.release()
        if file is not None:
            with contextlib.suppress(OSError):
                file.close()

    def _why(self, error: OSError) -> str:
        """Why a write failed, in the system's words (never the temporary name)."""
        return error.strerror or str(error)

    # -- the tools a subclass writes with

    def _create(self, target: pathlib.Path) -> pathlib.Path:
        """Create `target`'s temporary file empty with O_EXCL, for a library that rewrites it by
        name (OpenImageIO, Spectral Python); return the name."""
        temporary = self._temps[target]
        create_exclusive(temporary)  # OSError: nothing created, and a name already there is not ours
        self._created.append(temporary)
        return temporary

    def _open_stream(self, target: pathlib.Path) -> None:
        """Open `target`'s temporary file (O_EXCL) as the stream `_write` appends to."""
        temporary = self._temps[target]
        self._file = open_exclusive(temporary)
        self._created.append(temporary)
        self._stream_target = target
        self._digest = hashlib.sha256()
        # Every byte goes through `_direct`; the file object's own buffer stays empty.
        self._direct = DirectFile(self._file.fileno())

    def _write(self, data) -> None:
        """Append `data` (bytes-like) to the stream and to its digest."""
        block = memoryview(data).cast("B")
        try:
            self._direct.write(block)
        except OSError as error:
            raise self._failed(error, self._stream_target) from None
        self._digest.update(block)

    def _close_stream(self) -> str:
        """The stream's last bytes written and fsynced, its file closed; return its SHA-256 (hex)."""
        self._direct.finish()  # fsynced: on disk before the rename makes it the file
        file, self._file = self._file, None
        file.close()
        return self._digest.hexdigest()

    def _failed(self, error: OSError, path: pathlib.Path) -> SpherejaxFileError:
        """Abort, and the error to raise for `error`, naming `path`."""
        self.abort()
        return SpherejaxFileError(path, f"could not be written: {self._why(error)}")

    def _check_open(self) -> None:
        if not self._is_open:
            raise SpherejaxFileError(self.path, "is no longer open for writing")

    # -- the interface

    def write_rows(self, row0: int, pixels) -> None:
        """Write rows row0:row0 + len(pixels), the next rows of the image."""
        self._check_open()
        if self._finished is not None:
            raise SpherejaxFileError(self.path, "is finished: no row can be written after `finish`")
        if row0 != self._next_row:
            raise ValueError(f"rows: expected the next row {self._next_row}, got {row0}")
        self._write_rows(row0, pixels)
        self._next_row = row0 + len(pixels)

    def finish(self):
        """Finish the files, fsynced and closed, without putting them in place; return the
        digest(s) (`_complete`). A caller that must record what it is about to put in place (the
        batch's claims: `archive.lock.record_made`) calls this, records, then `commit`s; `commit`
        alone finishes first. No row can be written after it."""
        self._check_open()
        if self._finished is None:
            if self._next_row != self.height:
                self.abort()
                raise SpherejaxFileError(self.path, f"has {self._next_row} of its {self.height} rows", "every row written")
            try:
                self._finished = (self._complete(),)
            except OSError as error:
                why = self._why(error)  # before `abort`: the reason may lie in the temporary (its size)
                self.abort()
                raise SpherejaxFileError(self.path, f"could not be written: {why}") from None
            except BaseException:
                self.abort()
                raise
        return self._finished[0]

    def commit(self):
        """Finish the files (`finish`, unless done), rename them into place; return the digest(s)."""
        digest = self.finish()
        try:
            for target, temporary in self._temps.items():
                os.replace(temporary, target)
            for folder in dict.fromkeys(target.parent for target in self._temps):
                fsync_folder(folder)  # and the renames on disk too
        except OSError as error:
            raise SpherejaxFileError(self.path, f"could not be written: {self._why(error)}") from None
        finally:
            self.abort()
        return digest

    def abort(self) -> None:
        """Drop what was written: the temporary files go, the targets are untouched."""
        self._is_open = False
        self._release()
        for temporary in self._created:
            # Best effort: the folder itself may be what failed (gone, or a file in its place).
            with contextlib.suppress(OSError):
                temporary.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.abort()


__all__ = ["AtomicWriter"]
