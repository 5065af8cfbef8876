"""Outputs that are not inputs: the check every writing command makes before any work.

spherejax never overwrites a file it was given to read. Comparing the paths as typed is not
enough: `a.tif`, `./a.tif`, `dir/../a.tif`, a symbolic link to it and a hard link to it all name
one file. So each path is compared twice: resolved (`os.path.realpath`: links and `..` undone),
and, where the file exists, by its identity on disk, (st_dev, st_ino), which also catches a hard
link. Two outputs that are one file are refused the same way: the second would replace the first.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping

from .errors import SpherejaxFileError


def _identity(path: pathlib.Path) -> tuple[str, tuple[int, int] | None]:
    """(resolved path, (st_dev, st_ino) or None where nothing is there yet)."""
    resolved = os.path.realpath(path)
    try:
        status = os.stat(resolved)
    except OSError:
        return resolved, None
    return resolved, (status.st_dev, status.st_ino)


def refuse_overlaps(outputs: Mapping[str, os.PathLike | str], inputs: Mapping[str, os.PathLike | str]) -> None:
    """Raise unless every output is a file other than every input and every other output.

    Args:
      outputs: what each output is (e.g. "--cgats FILE") -> the path it will be written to.
      inputs: what each input is (e.g. "the input cube", "the calibration") -> its path.

    Raises:
      SpherejaxFileError: naming the output's path, what else it is, and what was expected.
    """
    seen: list[tuple[str, str, tuple[str, tuple[int, int] | None]]] = [
        (label, str(path), _identity(pathlib.Path(path))) for label, path in inputs.items()
    ]
    for label, path in outputs.items():
        resolved, node = _identity(pathlib.Path(path))
        for other_label, other_path, (other_resolved, other_node) in seen:
            if resolved == other_resolved or (node is not None and node == other_node):
                raise SpherejaxFileError(
                    path, f"{label} is also {other_label} ({other_path})",
                    f"{label} a file of its own, not an input, the calibration or another output",
                )
        seen.append((label, str(path), (resolved, node)))


__all__ = ["refuse_overlaps"]
