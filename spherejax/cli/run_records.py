"""The record a run of `evaluate`, `study` or `demo` leaves beside its files (metrics.json,
study.json), and the proof it gives a later run that a file there is spherejax's to replace.

A record's "files" lists the SHA-256 of every file written beside it in the same set
(`with_file_record`). A later run replaces a file at one of its output names only when that very
file's bytes are the bytes the record lists for that name (`not_recorded`): a table the user put
there, or edited since, is the user's, refused and left as it is. Being beside a record, which
once made every output name count as spherejax's, proves nothing about a file.
"""

from __future__ import annotations

import hashlib
import json
import pathlib
from collections.abc import Mapping

#: The key of a record that lists the files written beside it: {name: SHA-256 (hex)}.
FILES_KEY = "files"

#: The largest record read for its list (a run's JSON is a few kilobytes).
_MAX_RECORD_BYTES = 16 << 20


def with_file_record(files: Mapping[str, bytes], record: str) -> dict[str, bytes]:
    """`files` (name -> bytes, one set) with the JSON object `files[record]` extended by
    FILES_KEY: the SHA-256 of every other file of the set. The record is written as the writers
    write it (json.dumps, indent 2), its other fields unchanged."""
    document = json.loads(files[record])
    document[FILES_KEY] = {name: hashlib.sha256(data).hexdigest() for name, data in sorted(files.items()) if name != record}
    return {**files, record: json.dumps(document, indent=2).encode()}


def recorded_files(record: pathlib.Path) -> dict[str, str]:
    """{name: SHA-256} a record lists (`with_file_record`); empty for a record that lists none or
    cannot be read (a link, a FIFO, damaged JSON)."""
    from .. import jsontext
    from ..io.plain_files import read_small

    if record.is_symlink():
        return {}
    try:
        document = jsontext.loads(read_small(record, _MAX_RECORD_BYTES))
    except (OSError, ValueError):
        return {}
    listed = document.get(FILES_KEY) if isinstance(document, dict) else None
    if not isinstance(listed, dict):
        return {}
    return {name: digest for name, digest in listed.items() if isinstance(name, str) and isinstance(digest, str)}


def not_recorded(path: pathlib.Path, recorded: Mapping[str, str], record_name: str) -> str | None:
    """None if the file at `path` holds the bytes `recorded` (`recorded_files`) lists for its
    name, else why it is not spherejax's to replace."""
    from ..io.hashing import sha256_file

    expected = recorded.get(path.name)
    if expected is None:
        return f"a file spherejax did not write (no earlier run's {record_name} beside it records it)"
    try:
        found = sha256_file(path, check=None)
    except OSError as error:
        return f"a file that cannot be read ({error.strerror or error})"
    if found != expected:
        return f"a file spherejax did not write (its bytes are not those the earlier run's {record_name} records)"
    return None


__all__ = ["FILES_KEY", "not_recorded", "recorded_files", "with_file_record"]
