"""An image file that spherejax encodes itself, written strip by strip: what every such writer shares.

The quality PNG (`quality_png`) and the uncompressed EXR (`exr_uncompressed`) are encoded here, not
by OpenImageIO; like `frames.AtomicImageWriter` they are `atomic_writer.AtomicWriter`s, with its
rules (those of `spherejax.atomic_files`):

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
`_write_rows` and writes what follows the last row in `_finish`.
"""

from __future__ import annotations

from .atomic_writer import AtomicWriter
from .library_messages import write_limit


class StreamedImageWriter(AtomicWriter):
    """An image of `height` rows written strip by strip into a temporary file beside `path`
    (module docstring); `commit` puts it in place and returns its SHA-256 (hex)."""

    def _open(self) -> None:
        self._open_stream(self.path)

    def _why(self, error: OSError) -> str:
        """Why a write failed: `library_messages.write_limit`'s words where the file-size limit or
        a full disk explains it, else the system's reason, never the temporary name."""
        return write_limit(self._temp) or super()._why(error)

    def _finish(self) -> None:
        """`_write` what follows the last row (the subclass's format; nothing by default)."""

    def _complete(self) -> str:
        self._finish()
        return self._close_stream()


__all__ = ["StreamedImageWriter"]
