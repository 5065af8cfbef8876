"""The one error type of every file spherejax reads or writes, and its one-line messages:
"PATH: problem (expected ...)"."""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Iterator


def _one_line(text) -> str:
    # OIIO and numpy errors can span lines; a message must stay one line on stderr.
    return " ".join(str(text).split())


class SpherejaxFileError(ValueError):
    """A file or folder that cannot be read or written: "PATH: problem (expected ...)"."""

    def __init__(self, path, problem: str, expected: str | None = None):
        self.path = str(path)
        self.problem = _one_line(problem)
        self.expected = _one_line(expected) if expected else None
        message = f"{self.path}: {self.problem}"
        if self.expected:
            message += f" (expected {self.expected})"
        super().__init__(message)

    def __reduce__(self):
        # Rebuild from the three parts: dask.distributed ships worker exceptions between processes.
        return type(self), (self.path, self.problem, self.expected)


class SessionError(SpherejaxFileError):
    """A session folder, its manifest or one of its frame files is missing or invalid."""


class CalibrationFileError(SpherejaxFileError):
    """A calibration file is missing, corrupted, of another format or version, or other bands."""


@contextlib.contextmanager
def _reraise_as(error_type: type[SpherejaxFileError]) -> Iterator[None]:
    """Turn a SpherejaxFileError raised inside into `error_type`, same path and message."""
    try:
        yield
    except SpherejaxFileError as error:
        if isinstance(error, error_type):
            raise
        raise error_type(error.path, error.problem, error.expected) from None


def _show(value) -> str:
    """A short one-line rendering of a value found in a file, for error messages.

    Runs of spaces are written as JSON escapes (two spaces: "\\u0020\\u0020"): a message is
    made one line by collapsing its whitespace (`_one_line`), which showed a value of two spaces
    as one (found by the property test of tests/test_io_documents.py). json.dumps escapes every
    other whitespace character already."""
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    text = re.sub(r" {2,}", lambda run: "\\u0020" * len(run.group()), text)
    return text if len(text) <= 80 else text[:77] + "..."
