"""JSON documents of the file formats: canonical and readable JSON, and `_Fields`, the checks of
a document's keys and values that give the one-line messages of `errors`."""

from __future__ import annotations

import datetime
import json
import math
import pathlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from .errors import SpherejaxFileError, _show


def _json_value(path, value, error_type: type[SpherejaxFileError], what: str):
    """`value` as it reads back from JSON (numpy values, tuples and non-string keys normalised).

    Checksums and round trips compare what is written with what is read, so both start from this.
    """

    def default(obj):
        if isinstance(obj, (np.ndarray, np.generic)):
            return obj.tolist()
        if callable(getattr(obj, "to_json", None)):  # a session's `Region` (not imported: sessions uses this)
            return obj.to_json()
        raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")

    try:
        return json.loads(json.dumps(value, default=default, allow_nan=False))
    except (TypeError, ValueError) as error:
        raise error_type(path, f"{what} cannot be stored as JSON: {error}", "JSON values") from None


def _canonical_json(value) -> bytes:
    return json.dumps(
        value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    ).encode("utf-8")


def _readable_json(value, indent: str = "") -> str:
    """JSON for people: one field per line, but a list of numbers or strings on one line.

    json.dumps(indent=2) would put each of a target's 31 reflectances on a line of its own.
    """
    inner = indent + "  "
    if isinstance(value, dict) and value:
        fields = [f"{inner}{json.dumps(k)}: {_readable_json(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(fields) + "\n" + indent + "}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        items = [inner + _readable_json(v, inner) for v in value]
        return "[\n" + ",\n".join(items) + "\n" + indent + "]"
    return json.dumps(value, allow_nan=False)


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # a JSON integer beyond float range (JSON puts no limit on digits)
        return False


def _is_timestamp(value) -> bool:
    if not isinstance(value, str):
        return False
    try:
        datetime.datetime.fromisoformat(value)
    except ValueError:
        return False
    return True


def _is_rect(value, image_shape: tuple[int, int]) -> bool:
    if not (isinstance(value, list) and len(value) == 4 and all(_is_int(v) for v in value)):
        return False
    r0, r1, c0, c1 = value
    return 0 <= r0 < r1 <= image_shape[0] and 0 <= c0 < c1 <= image_shape[1]


def _rect_expected(image_shape: tuple[int, int]) -> str:
    height, width = image_shape
    return (
        f"[r0, r1, c0, c1] with 0 <= r0 < r1 <= {height} and 0 <= c0 < c1 <= {width}: "
        f"a non-empty rectangle inside the {height} x {width} image"
    )


def _describe_bands(bands: Sequence[int]) -> str:
    """Band centres for a message: like 400..700 nm step 20 (16 bands), or the list."""
    bands = [int(b) for b in bands]
    steps = {b - a for a, b in zip(bands, bands[1:])}
    if len(bands) > 2 and len(steps) == 1:
        return f"{bands[0]}..{bands[-1]} nm step {steps.pop()} ({len(bands)} bands)"
    return f"{bands} nm"


_REQUIRED = object()


class _Fields:
    """One JSON object of a file, read one checked field at a time.

    Every problem raises `error(file, "<where>.<key> is <value found>", expected)`, so each message
    names the file, the field, the value and what was expected.
    """

    def __init__(self, obj: Mapping, *, file, error: type[SpherejaxFileError], where: str = ""):
        self.obj, self.file, self.error, self.where = obj, file, error, where

    def name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def fail(self, key: str, problem: str, expected: str):
        raise self.error(self.file, f"{self.name(key)} {problem}", expected)

    def value(self, key: str, expected: str, check: Callable[[Any], bool], default=_REQUIRED):
        """The value of `key` if `check` accepts it; `default` when absent, unless required."""
        if key not in self.obj:
            if default is _REQUIRED:
                self.fail(key, "is missing", expected)
            return default
        value = self.obj[key]
        if not check(value):
            self.fail(key, f"is {_show(value)}", expected)
        return value

    def only(self, allowed: frozenset[str]) -> None:
        unknown = sorted(set(self.obj) - allowed)
        if unknown:
            where = self.where or "the top level"
            raise self.error(
                self.file, f"{where} has unknown fields {unknown}", f"only {sorted(allowed)}"
            )

    def string(self, key: str, *, choices: Sequence[str] | None = None, default=_REQUIRED):
        if choices is None:
            expected = "a non-empty string"
        else:
            expected = " or ".join(json.dumps(c) for c in choices)
        return self.value(
            key,
            expected,
            lambda v: isinstance(v, str) and v != "" and (choices is None or v in choices),
            default,
        )

    def integer(self, key: str, *, minimum: int) -> int:
        return self.value(key, f"an integer >= {minimum}", lambda v: _is_int(v) and v >= minimum)

    def number(self, key: str, *, allow_null: bool = False, default=_REQUIRED):
        expected = "a number > 0" + (" or null" if allow_null else "")
        return self.value(
            key,
            expected,
            lambda v: (allow_null and v is None) or (_is_number(v) and v > 0),
            default,
        )

    def increasing_ints(self, key: str, expected: str, *, maximum: int = 2**31 - 1) -> list[int]:
        # The maximum keeps the values inside int64 arithmetic (JSON puts no limit on digits).
        def check(v):
            if not (isinstance(v, list) and v and all(_is_int(x) and 0 < x <= maximum for x in v)):
                return False
            return all(a < b for a, b in zip(v, v[1:]))

        return self.value(key, expected, check)

    def numbers(self, key: str, length: int, expected: str, *, positive=False, default=_REQUIRED):
        def check(v):
            if not (isinstance(v, list) and len(v) == length and all(_is_number(x) for x in v)):
                return False
            return not positive or all(x > 0 for x in v)

        values = self.value(key, expected, check, default)
        return values if values is None else np.asarray(values, dtype=np.float64)

    def shape(self, key: str, ndim: int, expected: str) -> tuple[int, ...]:
        def check(v):  # the bound as in increasing_ints: sizes stay inside int64 arithmetic
            return isinstance(v, list) and len(v) == ndim and all(_is_int(x) and 0 < x < 2**31 for x in v)

        return tuple(self.value(key, expected, check))

    def rect(self, key: str, image_shape: tuple[int, int]) -> tuple[int, int, int, int]:
        rect = self.value(key, _rect_expected(image_shape), lambda v: _is_rect(v, image_shape))
        return tuple(rect)

    def timestamp(self, key: str, default=_REQUIRED) -> str:
        return self.value(key, "an ISO 8601 date and time", _is_timestamp, default)

    def mapping(self, key: str, expected: str = "a JSON object", default=_REQUIRED) -> dict:
        return self.value(key, expected, lambda v: isinstance(v, dict), default)

    def child(self, key: str, expected: str) -> _Fields:
        """The object `key`, as a `_Fields` named after it."""
        obj = self.mapping(key, expected)
        return _Fields(obj, file=self.file, error=self.error, where=self.name(key))

    def children(self, key: str, what: str, default=_REQUIRED) -> list[_Fields]:
        """The objects of the list `key`, each a `_Fields` named "key[i]"."""
        items = self.value(key, f"a list of {what}", lambda v: isinstance(v, list), default)
        children = []
        for index, item in enumerate(items):
            where = f"{key}[{index}]"
            if not isinstance(item, dict):
                self.fail(where, f"is {_show(item)}", f"one of the {what}, an object")
            children.append(_Fields(item, file=self.file, error=self.error, where=self.name(where)))
        return children

    def relative_path(self, key: str) -> str:
        """A path relative to the file's folder, with no "..": it cannot name a file outside."""

        def check(value):
            # A NUL byte cannot be in a file name: os calls on one raise ValueError.
            if not isinstance(value, str) or value in ("", ".") or "\0" in value:
                return False
            # Both readings: a manifest written on Windows may use "\\" and drive letters.
            posix, native = pathlib.PurePosixPath(value), pathlib.PurePath(value)
            escapes = ".." in posix.parts or ".." in native.parts
            return not (posix.is_absolute() or native.is_absolute() or native.drive or escapes)

        return self.value(key, 'a relative path inside the folder (not absolute, no "..")', check)


def _check_format(fields: _Fields, name: str, version: int) -> None:
    """Refuse a document of another format, or of a newer version than this software reads."""
    from .. import __version__

    found = fields.obj.get("format", _REQUIRED)
    if found != name:
        shown = "missing" if found is _REQUIRED else _show(found)
        problem = f"is not a {name} file: format is {shown}"
        raise fields.error(fields.file, problem, f'format "{name}"')
    found_version = fields.integer("format_version", minimum=1)
    if found_version > version:
        raise fields.error(
            fields.file,
            f"is {name} format version {found_version}, newer than spherejax {__version__} reads",
            f"format version {version} or older; upgrade spherejax to read it",
        )
