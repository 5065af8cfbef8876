"""The errors that refuse a batch before it starts."""

from __future__ import annotations

import errno

from .. import io


class BatchError(io.SpherejaxFileError):
    """The batch cannot start: OUT locked, already holding a batch, or not writable."""


class NoInputError(BatchError):
    """The inputs given hold no cube, band files or session to correct (`run_batch`, before OUT
    is created): "IN1, IN2: no cube found: searched ... (expected at least one ...)"."""


def link_or(error: OSError) -> str:
    """The reason an os.open with O_NOFOLLOW failed, in words: ELOOP means a symbolic link."""
    return "it is a symbolic link" if error.errno == errno.ELOOP else str(error.strerror)


__all__ = ["BatchError", "NoInputError", "link_or"]
