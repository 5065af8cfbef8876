"""An image file that spherejax encodes itself, written strip by strip: what every such writer shares.

The quality PNG (`quality_png`) and the uncompressed EXR (`exr_uncompressed`) are encoded here, not
by OpenImageIO, and both follow the rules of `atomic_files` as `frames.AtomicImageWriter` does:

- the file is written under a temporary name beside `path`, created with O_EXCL (never an
  existing file, nor a link to one elsewhere);
- its bytes go past the page cache where the file system allows it (`io.direct_io`: they are
  fsynced before the rename anyway) and are hashed as they are written, so that `commit` returns
  the file's SHA-256 without reading it back;
- rows come in order, top to bottom, and `commit` renames the file into place only once every row
  is written, then fsyncs the folder; leaving the `with` block uncommitted, a failed write or
  `abort` removes the temporary file and leaves `path` untouched;
- a failed write is reported as one `SpherejaxFileError` naming `path` (never the temporary name),
  in the words of `library_messages.write_limit` where the file-size limit or a full disk
  explains it.

A subclass writes its header in `__init__` (after this class's) with `_write`, encodes rows in
`_encode_rows` and writes what follows the last row in `_finish`.
"""

from __future__ import annotations

import abc
import contextlib
import hashlib
import os
import pathlib

from ..atomic_files import fsync_folder, open_exclusive, temp_sibling
from .direct_io import DirectFile
from .errors import SpherejaxFileError
from .library_messages import write_limit


class StreamedImageWriter(abc.ABC):
    """An image of `height` rows written strip by strip into a temporary file beside `path`
    (module docstring); `commit` puts it in place and returns its SHA-256 (hex)."""

    def __init__(self, path, height: int):
        self.path = pathlib.Path(path)
        self.height = int(height)
        self._next_row = 0
        self._digest = hashlib.sha256()
        self._temp = temp_sibling(self.path)
        self._file = None
        self._direct: DirectFile | None = None
        try:
            self._file = open_exclusive(self._temp)  # `spherejax.atomic_files`: the rules every writer follows
            # Every byte goes through `_direct`; the file object's own buffer stays empty.
            self._direct = DirectFile(self._file.fileno())
        except OSError as error:
            self.abort()
            raise SpherejaxFileError(self.path, f"could not be written: {self._why(error)}") from None

    def _why(self, error: OSError) -> str:
        """Why a write failed: `library_messages.write_limit`'s words where the file-size limit or
        a full disk explains it, else the system's reason, never the temporary name."""
        return write_limit(self._temp) or error.strerror or " ".join(str(error).split())

    def _write(self, data) -> None:
        """Append `data` (bytes-like) to the file and to its digest."""
        block = memoryview(data).cast("B")
        try:
            self._direct.write(block)
        except OSError as error:
            self.abort()
            raise SpherejaxFileError(self.path, f"could not be written: {self._why(error)}") from None
        self._digest.update(block)

    @abc.abstractmethod
    def _encode_rows(self, row0: int, pixels) -> None:
        """Encode and `_write` rows row0:row0 + len(pixels) (the subclass's format)."""

    def _finish(self) -> None:
        """`_write` what follows the last row (the subclass's format; nothing by default)."""

    def write_rows(self, row0: int, pixels) -> None:
        """Write rows row0:row0 + len(pixels), the next rows of the image."""
        if self._file is None:
            raise SpherejaxFileError(self.path, "is no longer open for writing")
        if row0 != self._next_row:
            raise ValueError(f"rows: expected the next row {self._next_row}, got {row0}")
        self._encode_rows(row0, pixels)
        self._next_row = row0 + len(pixels)

    def commit(self) -> str:
        """Finish the file, fsync it, rename it into place; return its SHA-256 (hex)."""
        if self._file is None:
            raise SpherejaxFileError(self.path, "is no longer open for writing")
        if self._next_row != self.height:
            self.abort()
            raise SpherejaxFileError(self.path, f"has {self._next_row} of its {self.height} rows", "every row written")
        try:
            self._finish()
            self._direct.finish()  # the last bytes, fsynced: on disk before the rename makes it the file
            file, self._file = self._file, None
            file.close()
            os.replace(self._temp, self.path)
            fsync_folder(self.path.parent)  # and the rename on disk too
        except OSError as error:
            raise SpherejaxFileError(self.path, f"could not be written: {self._why(error)}") from None
        finally:
            self.abort()
        return self._digest.hexdigest()

    def abort(self) -> None:
        """Drop what was written: the temporary file goes, `path` is untouched."""
        file, self._file = self._file, None
        if self._direct is not None:
            self._direct.release()
        if file is not None:
            with contextlib.suppress(OSError):
                file.close()
        with contextlib.suppress(OSError):
            self._temp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.abort()


__all__ = ["StreamedImageWriter"]
