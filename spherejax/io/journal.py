"""Append-only journals of JSON objects, one a line, each appended with one write and fsync.

The one format behind a batch's OUT/manifest.jsonl (`spherejax.archive.manifest`) and an
acquisition's SESSION.partial/journal.jsonl (`spherejax_hw.acquire`):

- Appending: the file is opened with `plain_files.open_regular` (O_NOFOLLOW: a symbolic link
  planted in its place must not make us append to the file it points at; O_NONBLOCK: a FIFO there
  is refused at once rather than waited on) and O_APPEND. Each record is one `os.write` (never
  interleaved with another writer's) followed by fsync: once `append` returns, the line is on disk.
- A kill mid-write may leave a last line without its newline. Opening for appending looks at the
  last byte: the first record appended then starts with a newline, in the same write, so it is on
  a line of its own and the torn line stays a line that reads as nothing.
- Encoding: `json.dumps(sort_keys=True, ensure_ascii=False, allow_nan=False)` as UTF-8. A file name
  that is not UTF-8 reaches Python as lone surrogates (os.fsdecode), which UTF-8 cannot encode;
  backslashreplace writes each as the JSON escape "\\udcXX", which reads back as the same name.
  NaN and Infinity are not JSON: a record holding one is refused (ValueError) before any write.
- Reading (`Journal.records`): streamed by `plain_files.read_lines` (a journal truncated up to
  gigabytes, sparse and without a newline, is never read whole; a line a hole falls in is
  dropped), each line parsed by `spherejax.jsontext.loads` (bytes that are not UTF-8, nesting
  thousands deep, integers past int()'s limit: the line is skipped, never an exception). Only JSON
  objects whose `key` field is a string are records; every other line (torn, damaged, another
  writer's) is left out. The journal's `safe_point`, if any, is called between chunks.
"""

from __future__ import annotations

import json
import os
import pathlib
from collections.abc import Callable, Iterator

from .. import jsontext
from .plain_files import open_regular, read_lines


def encode(record: dict) -> bytes:
    """One journal line: the record's JSON (module docstring) and its newline, as UTF-8."""
    line = json.dumps(record, sort_keys=True, ensure_ascii=False, allow_nan=False) + "\n"
    return line.encode("utf-8", errors="backslashreplace")


class Journal:
    """A journal file (module docstring): `records` reads it, `open` (or `append`) adds to it.

    Args:
      path: the file.
      key: the field every record holds as a string ("name" for a batch's manifest, "event" for
        an acquisition's journal); lines without it are not records.
      safe_point: called between the chunks `records` reads (`spherejax.interrupt.check`), or None.
    """

    def __init__(self, path, *, key: str, safe_point: Callable[[], None] | None = None):
        self.path = pathlib.Path(path)
        self.key = key
        self.safe_point = safe_point

    def records(self) -> Iterator[dict]:
        """Every record, in order; nothing when the file is not there.

        Raises:
          OSError: the file cannot be read (a symbolic link in its place: ELOOP).
        """
        if not self.path.is_file():
            return
        for line in read_lines(self.path, safe_point=self.safe_point):
            try:
                record = jsontext.loads(line)
            except jsontext.JSONTextError:
                continue  # torn by a kill, or damaged: not a record
            if isinstance(record, dict) and isinstance(record.get(self.key), str):
                yield record

    def open(self) -> JournalWriter:
        """The journal opened for appending (created if missing); close it, or use it in `with`.

        Raises:
          OSError: as `open_regular` (ELOOP for a symbolic link, "it is a FIFO", ...).
        """
        return JournalWriter(self.path)

    def append(self, record: dict) -> None:
        """Open, append one record (on disk when this returns) and close."""
        with self.open() as writer:
            writer.append(record)


class JournalWriter:
    """A journal open for appending: one `os.write` and fsync per record (module docstring)."""

    def __init__(self, path: pathlib.Path):
        self.path = path
        self.fd: int | None = open_regular(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
        try:
            self._prefix = b"" if _ends_a_line(self.fd, path) else b"\n"
        except BaseException:
            self.close()
            raise

    def append(self, record: dict) -> None:
        """Append `record` as one line, on disk (fsync) when this returns.

        Raises:
          ValueError: a record JSON cannot hold (NaN, a value of no JSON type): nothing written.
          OSError: the write or the fsync failed.
        """
        data = memoryview(self._prefix + encode(record))
        try:
            while data:  # one write on O_APPEND (never interleaved) unless the disk fills mid-line:
                data = data[os.write(self.fd, data):]  # then the next write says why (ENOSPC)
            os.fsync(self.fd)
        except BaseException:
            self._prefix = b"\n"  # a line left torn here: the next record starts on a line of its own
            raise
        self._prefix = b""

    def close(self) -> None:
        fd, self.fd = self.fd, None
        if fd is not None:
            os.close(fd)

    def __enter__(self) -> JournalWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _ends_a_line(fd: int, path: pathlib.Path) -> bool:
    """Whether the journal open as `fd` is empty or ends in a newline (else a kill cut its last
    line). The last byte is read through a second open of the same name (`fd` is write-only)."""
    size = os.fstat(fd).st_size
    if not size:
        return True
    reader = open_regular(path, os.O_RDONLY)
    try:
        return os.pread(reader, 1, size - 1) == b"\n"
    finally:
        os.close(reader)


__all__ = ["Journal", "JournalWriter", "encode"]
