"""spherejax.io.errors: the file errors, one-line messages that survive a copy."""

import copy

from spherejax.io import CalibrationFileError, SessionError, SpherejaxFileError


def test_errors_are_value_errors_with_one_line_messages():
    error = CalibrationFileError("a/cal.npz", "is\ncorrupted", "a\nfile")
    assert isinstance(error, SpherejaxFileError) and isinstance(error, ValueError)
    assert issubclass(SessionError, SpherejaxFileError)
    assert str(error) == "a/cal.npz: is corrupted (expected a file)"
    assert str(SpherejaxFileError("f.tif", "no such file")) == "f.tif: no such file"


def test_errors_copy_with_their_message():
    # dask.distributed ships exceptions between processes by reducing them like copy does.
    error = SessionError("s/manifest.json", "is not valid JSON", "JSON")
    clone = copy.deepcopy(error)
    assert type(clone) is SessionError and str(clone) == str(error)
    parts = (clone.path, clone.problem, clone.expected)
    assert parts == (error.path, error.problem, error.expected)
