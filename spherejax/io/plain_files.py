"""Files spherejax keeps for itself (OUT's lock and manifest, an acquisition's journal, outputs it
checks on resume), opened so that nothing planted in their place can make it wait or read without
end.

- A FIFO opened for reading waits for a writer, and for writing waits for a reader: `open_regular`
  opens with O_NONBLOCK (it returns at once, or fails with ENXIO), then refuses whatever is not a
  regular file by what it is. O_NOFOLLOW: a symbolic link in the file's place is refused too.
- A manifest truncated up to gigabytes (`truncate -s 3G`: a sparse file of zeros, no newline) was
  read whole into memory: `read_lines` reads in chunks and drops a line longer than any record,
  so memory stays bounded whatever the file holds. It reads only the data a sparse file stores
  (os.SEEK_DATA / os.SEEK_HOLE): a hole reads as NUL bytes, which no record holds, so the line a
  hole falls in is dropped unread and a 3 GB hole costs nothing. A caller whose read may be long
  passes a safe point (`spherejax.interrupt.check`), called between chunks, so that a long file
  never keeps a signal waiting; one reading while it cleans up after a stop passes none.
"""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Callable, Iterator

#: What a file that is neither a regular file nor a folder is, by its stat mode.
SPECIAL_FILES = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)

#: The longest line `read_lines` keeps: a manifest or journal record is a few kilobytes.
MAX_LINE_BYTES = 1 << 20

#: The most bytes `read_small` reads of a document spherejax reads whole (a session's manifest,
#: an instrument profile, the lamp's state): they are kilobytes, a session of ten thousand frames
#: a few megabytes. One of gigabytes (`truncate -s 3G manifest.json`) was read into memory whole.
MAX_DOCUMENT_BYTES = 64 << 20


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


def read_small(path, max_bytes: int = MAX_DOCUMENT_BYTES) -> bytes:
    """The bytes of a regular file read whole, after checking it holds at most `max_bytes`. Opened
    with O_NONBLOCK, so a FIFO or device is refused at once by what it is, never waited on. A
    symbolic link is followed: this is for documents spherejax reads (a profile may well be a
    link), never writes.

    Raises:
      OSError: as os.open does (FileNotFoundError); for a FIFO, socket, device or folder, one
        whose strerror says what it is; for a file over `max_bytes`, EFBIG with "it is N bytes,
        more than such a file holds".
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        found = os.fstat(fd).st_mode
        if not stat.S_ISREG(found):
            raise OSError(errno.EINVAL, f"it is {file_kind(found)}", str(path))
        size = os.fstat(fd).st_size
        if size > max_bytes:
            raise OSError(errno.EFBIG, f"it is {size} bytes, more than such a file holds ({max_bytes} at most)", str(path))
        chunks, total = [], 0
        while chunk := os.read(fd, min(1 << 20, max_bytes + 1 - total)):
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:  # grew while read
                raise OSError(errno.EFBIG, f"it grew past {max_bytes} bytes while read", str(path))
        return b"".join(chunks)
    finally:
        os.close(fd)


def _data_extents(fd: int, size: int, chunk_bytes: int) -> Iterator[tuple[int, int]]:
    """(offset, length) of the chunks of data a file of `size` bytes stores, in order, holes
    left out. A file system without SEEK_DATA gives the whole file as data (its holes then read
    as NUL bytes: the same lines come out, only slower)."""
    offset = 0
    while offset < size:
        try:
            start = os.lseek(fd, offset, os.SEEK_DATA)
            end = min(os.lseek(fd, start, os.SEEK_HOLE), size)
        except OSError as error:
            if error.errno == errno.ENXIO:  # no data after offset: the rest is a hole
                return
            start, end = offset, size  # SEEK_DATA not supported here
        for chunk_start in range(start, end, chunk_bytes):
            yield chunk_start, min(chunk_bytes, end - chunk_start)
        offset = end


def read_lines(path, max_line_bytes: int = MAX_LINE_BYTES, chunk_bytes: int = 1 << 20,
               safe_point: Callable[[], None] | None = None) -> Iterator[bytes]:
    """The lines of a regular file (`open_regular`), without their newlines, read in chunks; a
    line longer than `max_line_bytes` is skipped whole, so memory stays bounded by about
    `max_line_bytes + chunk_bytes` whatever the file holds. Only stored data is read: a line
    that a hole of a sparse file falls in is dropped (module docstring). `safe_point`, if
    given, is called before each chunk (and may raise to stop the read)."""
    fd = open_regular(path, os.O_RDONLY)
    try:
        size = os.fstat(fd).st_size
        pending, skipping, position = b"", False, 0
        for offset, length in _data_extents(fd, size, chunk_bytes):
            if safe_point is not None:
                safe_point()
            if offset != position:  # a hole since the last chunk: its line holds NUL bytes
                pending, skipping = b"", True
            chunk = os.pread(fd, length, offset)
            if not chunk:
                break  # the file shrank while read
            position = offset + len(chunk)
            *lines, pending = (pending + chunk).split(b"\n")
            for line in lines:
                if skipping:  # the end of an overlong line, or of one a hole fell in
                    skipping = False
                elif len(line) <= max_line_bytes:
                    yield line
            if len(pending) > max_line_bytes:
                pending, skipping = b"", True
        if pending and not skipping and position >= size:  # (position < size: a hole ends it)
            yield pending
    finally:
        os.close(fd)


__all__ = ["SPECIAL_FILES", "MAX_LINE_BYTES", "MAX_DOCUMENT_BYTES", "file_kind", "open_regular", "read_lines", "read_small"]
