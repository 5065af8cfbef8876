"""Files spherejax keeps for itself (OUT's lock and manifest, an acquisition's journal, outputs it
checks on resume), opened so that nothing planted in their place can make it wait or read without
end.

- A FIFO opened for reading waits for a writer, and for writing waits for a reader: `open_regular`
  opens with O_NONBLOCK (it returns at once, or fails with ENXIO), then refuses whatever is not a
  regular file by what it is. O_NOFOLLOW: a symbolic link in the file's place is refused too.
- A manifest truncated up to gigabytes (`truncate -s 3G`: a sparse file of zeros, no newline) was
  read whole into memory: `read_lines` reads in chunks and drops a line longer than any record,
  so memory stays bounded whatever the file holds.
"""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Iterator

#: What a file that is neither a regular file nor a folder is, by its stat mode.
SPECIAL_FILES = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)

#: The longest line `read_lines` keeps: a manifest or journal record is a few kilobytes.
MAX_LINE_BYTES = 1 << 20


def file_kind(mode: int) -> str:
    """What a file that is not a regular file is: "a FIFO", "a socket", ..., "a folder"."""
    for is_kind, what in SPECIAL_FILES:
        if is_kind(mode):
            return what
    return "a folder" if stat.S_ISDIR(mode) else "not a regular file"


def open_regular(path, flags: int, mode: int = 0o666) -> int:
    """os.open(path, flags | O_NONBLOCK | O_NOFOLLOW, mode), refusing anything but a regular file.

    Raises:
      OSError: as os.open does (ELOOP for a symbolic link); for a FIFO, socket, device or folder,
        an OSError whose strerror is "it is a FIFO" (and the like), without having blocked.
    """
    try:
        fd = os.open(path, flags | os.O_NONBLOCK | os.O_NOFOLLOW, mode)
    except OSError as error:
        if error.errno != errno.ENXIO:  # ENXIO: a FIFO or socket opened for writing, no reader
            raise
        try:
            kind = file_kind(os.lstat(path).st_mode)
        except OSError:
            kind = "a FIFO or socket"
        raise OSError(errno.ENXIO, f"it is {kind}", str(path)) from None
    found = os.fstat(fd).st_mode
    if not stat.S_ISREG(found):
        os.close(fd)
        raise OSError(errno.EINVAL, f"it is {file_kind(found)}", str(path))
    return fd


def read_lines(path, max_line_bytes: int = MAX_LINE_BYTES, chunk_bytes: int = 1 << 20) -> Iterator[bytes]:
    """The lines of a regular file (`open_regular`), without their newlines, read in chunks; a
    line longer than `max_line_bytes` is skipped whole, so memory stays bounded by about
    `max_line_bytes + chunk_bytes` whatever the file holds."""
    with open(open_regular(path, os.O_RDONLY), "rb") as handle:
        pending, skipping = b"", False
        while chunk := handle.read(chunk_bytes):
            *lines, pending = (pending + chunk).split(b"\n")
            for line in lines:
                if skipping:  # the end of an overlong line
                    skipping = False
                elif len(line) <= max_line_bytes:
                    yield line
            if len(pending) > max_line_bytes:
                pending, skipping = b"", True
        if pending and not skipping:
            yield pending


__all__ = ["SPECIAL_FILES", "MAX_LINE_BYTES", "file_kind", "open_regular", "read_lines"]
