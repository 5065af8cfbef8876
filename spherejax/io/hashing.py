"""The SHA-256 of a file, the one way spherejax and hw/ hash what they read back or wrote.

`sha256_file` reads in blocks of `BLOCK_BYTES` with a safe point (`spherejax.interrupt.check`)
before each block, so hashing gigabytes never keeps a signal waiting (`hashlib.file_digest`
cannot be interrupted). Where hashing must not stop (a writer's `commit`, after the last safe
point; clean-up after a stop, when a stop is already pending) the caller passes `check=None`.

A path is opened with `plain_files.open_regular`: a symbolic link in the file's place is refused
(ELOOP), and a FIFO is refused at once by what it is instead of waiting for a writer. An open
binary handle is hashed from where it stands to its end.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable

from .. import interrupt
from .plain_files import open_regular

#: The bytes read per block, each block preceded by the safe point.
BLOCK_BYTES = 1 << 20


def sha256_file(source, *, into=None, check: Callable[[], None] | None = interrupt.check) -> str:
    """The SHA-256 (hex) of a file's bytes.

    Args:
      source: a path (opened with `open_regular`, read from its start) or a binary handle open
        for reading (read from its position to its end, left open).
      into: a hashlib object to feed instead of a fresh SHA-256 (several files hashed as one);
        its hexdigest is returned.
      check: called before each block (a safe point; it may raise to stop); None for none.

    Raises:
      OSError: the path cannot be opened (FileNotFoundError, ELOOP for a link, "it is a FIFO"
        and the like) or read.
    """
    digest = hashlib.sha256() if into is None else into
    if isinstance(source, (str, bytes, os.PathLike)):
        with open(open_regular(source, os.O_RDONLY), "rb") as handle:
            _feed(handle, digest, check)
    else:
        _feed(source, digest, check)
    return digest.hexdigest()


def _feed(handle, digest, check: Callable[[], None] | None) -> None:
    while block := handle.read(BLOCK_BYTES):
        if check is not None:
            check()
        digest.update(block)


__all__ = ["BLOCK_BYTES", "sha256_file"]
