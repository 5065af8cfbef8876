"""JSON and TOML documents of the file formats: canonical and readable JSON, and the one way a
document is declared and checked.

A document (a session manifest, a calibration header, a batch manifest record, an instrument
profile, a lamp state) is a pydantic model deriving from `Document`: strict types (no bool for an
integer, no "1" for 1, no 1.0 for 1), no unknown fields, finite numbers only, frozen. Each field
says in words what it expects with `Expect` in its annotation, e.g.
`Annotated[int, Field(ge=1), Expect("an integer >= 1")]`; the types that recur (`integer`,
`number`, `NonEmptyStr`, `Timestamp`, `IncreasingInts`, `Rectangle`, `RelativePath`, `Sha256`,
...) carry theirs. `check_document` validates a mapping against a model and turns the first
problem into the document's own one-line error: the file, the field's location (`frames[3].role`,
`header.arrays.dark`), the value found (`errors._show`) and the expected text, or "is missing",
or the unknown fields.

Why pydantic (v2) rather than msgspec: a pydantic ValidationError gives each problem structured,
the location tuple, the input value and the error type, which map directly onto these one-line
messages, where msgspec gives only a formatted string without the value. Pydantic also has strict
types, extra="forbid", allow_inf_nan=False, and a validation context for checks that depend on
the file (a rectangle inside the image shape the manifest declares).

Checks across fields (a sample frame needs a set; a band names a wheel of the profile) are model
validators that raise `refuse(...)`, which names the field at fault and what it expected.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import pathlib
import sys
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Annotated, Any, Literal

import numpy as np
import pydantic
from pydantic import AfterValidator, ConfigDict, Field, ValidationInfo
from pydantic_core import PydanticCustomError

from ..number_text import json_ready
from .errors import SpherejaxFileError, _show
from .library_messages import library_text


def _json_value(path, value, error_type: type[SpherejaxFileError], what: str):
    """`value` as it reads back from JSON (numpy values, tuples and non-string keys normalised;
    a NumPy float32 as the shortest decimal of its float32, `number_text.json_ready`, not the
    float64 digits `.tolist()` shows).

    Checksums and round trips compare what is written with what is read, so both start from this.
    """

    def default(obj):
        if isinstance(obj, (np.ndarray, np.generic)):
            return json_ready(obj)
        if callable(getattr(obj, "to_json", None)):  # a session's `Region` (not imported: sessions uses this)
            return obj.to_json()
        raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")

    try:
        return _without_surrogates(json.loads(json.dumps(value, default=default, allow_nan=False)))
    except (TypeError, ValueError) as error:
        raise error_type(path, f"{what} cannot be stored as JSON: {error}", "JSON values") from None


def _without_surrogates(value):
    """`value` (as JSON reads back) with every string and key through `library_text`: a path
    recorded under a non-UTF-8 locale (a calibration's session, say) holds lone surrogates, which
    the UTF-8 of the file cannot encode ("'utf-8' codec can't encode characters ...")."""
    if isinstance(value, str):
        return library_text(value)
    if isinstance(value, list):
        return [_without_surrogates(v) for v in value]
    if isinstance(value, dict):
        return {library_text(k): _without_surrogates(v) for k, v in value.items()}
    return value


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


def _describe_bands(bands: Sequence[int]) -> str:
    """Band centres for a message: like 400..700 nm step 20 (16 bands), or the list."""
    bands = [int(b) for b in bands]
    steps = {b - a for a, b in zip(bands, bands[1:])}
    if len(bands) > 2 and len(steps) == 1:
        return f"{bands[0]}..{bands[-1]} nm step {steps.pop()} ({len(bands)} bands)"
    return f"{bands} nm"


# ------------------------------------------------------------------------------------------------
# Declaring a document


@dataclasses.dataclass(frozen=True)
class Expect:
    """What a field expects, in words, for its error messages: `Annotated[T, Expect("...")]`.

    The text may name values of the validation context in braces, e.g. "{bands} exposure times"
    (`check_document`'s context). The outermost `Expect` of a field wins, so a field may word a
    reusable type's expectation its own way.
    """

    text: str

    def render(self, context: Mapping | None) -> str:
        return self.text.format_map(context) if context else self.text


class Document(pydantic.BaseModel):
    """Base of every document model: strict, no unknown fields, finite numbers, frozen.

    Fields are validated in the order they are declared, and `check_document` reports the first
    problem, so declare them in the order their problems should be reported.
    """

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False, frozen=True)


def refuse(problem: str, expected: str | None = None, at: tuple = ()) -> PydanticCustomError:
    """The error a model validator raises for a check across fields.

    Args:
      problem: what is wrong, as it follows the location ("is missing", "lists 2 regions").
      expected: what was expected; None takes the `Expect` of the field at `at`.
      at: the location of the field at fault below the model (("regions", 0, "reflectance")).
    """
    # The problem goes in the context, not the template: a value shown in it may hold braces.
    return PydanticCustomError("document", "refused", {"problem": problem, "expected": expected, "at": at})


# The largest float: a JSON or TOML integer beyond it has no float value (json.dumps and NumPy
# would overflow), so a number field refuses it as the finite-number checks always did.
_FLOAT_MAX = int(sys.float_info.max)


def number(*, gt=None, ge=None, lt=None, le=None):
    """A finite number (int or float, never bool), bounded as given; ints stay ints.

    One Python type per member (no int -> float conversion): a saturation of 16383 reads back as
    16383, as it was written.
    """
    low = -_FLOAT_MAX if gt is None and ge is None else None
    high = _FLOAT_MAX if lt is None and le is None else None
    as_int = Annotated[int, Field(gt=gt, ge=ge if low is None else low, lt=lt, le=le if high is None else high)]
    return Annotated[as_int | Annotated[float, Field(gt=gt, ge=ge, lt=lt, le=le)], Field(union_mode="left_to_right")]


def integer(minimum: int, maximum: int | None = None):
    """An integer >= minimum (and <= maximum), never a bool or a float."""
    text = f"an integer >= {minimum}" if maximum is None else f"an integer {minimum}..{maximum}"
    return Annotated[int, Field(ge=minimum, le=maximum), Expect(text)]


def choice(*values: str):
    """One of the given strings."""
    return Annotated[Literal[values], Expect(" or ".join(json.dumps(v) for v in values))]


def _timestamp(value: str) -> str:
    datetime.datetime.fromisoformat(value)  # ValueError: not ISO 8601
    return value


def _aware_time(value: str) -> datetime.datetime:
    parsed = datetime.datetime.fromisoformat(value)
    if parsed.tzinfo is None or parsed.utcoffset() is None:
        raise ValueError("no UTC offset")
    return parsed.astimezone(datetime.timezone.utc)


def _increasing(values: list[int]) -> list[int]:
    if any(a >= b for a, b in zip(values, values[1:])):
        raise ValueError("not increasing")
    return values


def _rectangle(rect: list[int], info: ValidationInfo) -> tuple[int, int, int, int]:
    r0, r1, c0, c1 = rect
    height, width = (info.context or {}).get("image_shape", (None, None))
    if not (r0 < r1 and c0 < c1) or (height is not None and (r1 > height or c1 > width)):
        raise ValueError("not a non-empty rectangle inside the image")
    return r0, r1, c0, c1


_POSIX_PATHS = type(pathlib.PurePath()) is pathlib.PurePosixPath


def _relative_path(value: str) -> str:
    # A NUL byte cannot be in a file name: os calls on one raise ValueError.
    if value in ("", ".") or "\0" in value:
        raise ValueError("not a file name")
    # The POSIX reading by splitting, as PurePosixPath would (a manifest lists thousands of
    # files, and pathlib takes some 15 us a path); where this system's paths are not POSIX, its
    # own reading too: a file written on Windows may use "\\" and drive letters.
    if value.startswith("/") or ".." in value.split("/"):
        raise ValueError("not inside the folder")
    if not _POSIX_PATHS:
        native = pathlib.PurePath(value)
        if native.is_absolute() or native.drive or ".." in native.parts:
            raise ValueError("not inside the folder")
    return value


def _length_of(key: str):
    """An after-validator: the list is as long as the validation context's `key` says."""

    def check(values: list, info: ValidationInfo) -> list:
        if info.context is not None and len(values) != info.context[key]:
            raise ValueError(f"not {key} long")
        return values

    return AfterValidator(check)


# The types that recur. Sizes and band centres stay below 2**31: inside int64 arithmetic (JSON
# and TOML put no limit on an integer's digits).
FiniteNumber = Annotated[number(), Expect("a finite number")]
PositiveNumber = Annotated[number(gt=0), Expect("a number > 0")]
NonNegativeNumber = Annotated[number(ge=0), Expect("a number >= 0")]
NonEmptyStr = Annotated[str, Field(min_length=1), Expect("a non-empty string")]
Timestamp = Annotated[str, AfterValidator(_timestamp), Expect("an ISO 8601 date and time")]
#: An ISO 8601 time with a UTC offset, read as a timezone-aware datetime in UTC.
AwareTime = Annotated[str, AfterValidator(_aware_time), Expect("an ISO 8601 time with a UTC offset")]
IncreasingInts = Annotated[
    list[Annotated[int, Field(gt=0, lt=2**31)]], Field(min_length=1), AfterValidator(_increasing),
    Expect("increasing integers > 0"),
]
BandCentres = Annotated[
    list[Annotated[int, Field(gt=0, le=100_000)]], Field(min_length=1), AfterValidator(_increasing),
    Expect("band centres in nm: integers from 1 to 100000, increasing"),
]
#: [r0, r1, c0, c1] -> (r0, r1, c0, c1): rows r0:r1 and columns c0:c1, non-empty, and inside
#: the validation context's "image_shape" (H, W) when it gives one.
Rectangle = Annotated[
    list[Annotated[int, Field(ge=0)]], Field(min_length=4, max_length=4), AfterValidator(_rectangle),
    Expect("[r0, r1, c0, c1], integers >= 0 with r0 < r1 and c0 < c1"),
]
#: A rectangle inside the context's image; its expected text names the context's height and width.
ImageRectangle = Annotated[
    Rectangle,
    Expect(
        "[r0, r1, c0, c1] with 0 <= r0 < r1 <= {height} and 0 <= c0 < c1 <= {width}: "
        "a non-empty rectangle inside the {height} x {width} image"
    ),
]
#: A path relative to the document's folder that cannot name a file outside it.
RelativePath = Annotated[str, AfterValidator(_relative_path), Expect('a relative path inside the folder (not absolute, no "..")')]
Sha256 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$"), Expect("a SHA-256: 64 lowercase hex digits")]
Checksum = Annotated[str, Field(pattern=r"^sha256:[0-9a-f]{64}$"), Expect('"sha256:" and 64 hex digits')]
JsonObject = Annotated[dict[str, Any], Expect("a JSON object")]


def shape(ndim: int, expected: str):
    """A list of `ndim` sizes > 0 -> tuple."""
    return Annotated[
        list[Annotated[int, Field(gt=0, lt=2**31)]], Field(min_length=ndim, max_length=ndim),
        AfterValidator(tuple), Expect(expected),
    ]


def numbers(length: int | str, expected: str, *, positive: bool = False):
    """A list of finite numbers (> 0 if positive) -> float64 array, read-only, of a fixed length
    or of the length the validation context gives under that name."""
    item = number(gt=0) if positive else number()
    sized = [Field(min_length=length, max_length=length)] if isinstance(length, int) else [_length_of(length)]
    return Annotated[list[item], *sized, AfterValidator(_readonly_float64), Expect(expected)]


def _affine_maps(values: list) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    determinant = array[:, 0, 0] * array[:, 1, 1] - array[:, 0, 1] * array[:, 1, 0]
    if np.any(determinant <= 0.0):
        raise ValueError("a map that collapses or mirrors the image")
    array.setflags(write=False)
    return array


#: One 2 x 3 affine map per band (the context's "bands"), each from the reference geometry's
#: pixel coordinates (x = column, y = row, pixel centres at integers) to the band's -> (B, 2, 3)
#: float64, read-only; each invertible and not mirrored.
BandTransforms = Annotated[
    list[Annotated[list[Annotated[list[number()], Field(min_length=3, max_length=3)]], Field(min_length=2, max_length=2)]],
    _length_of("bands"), AfterValidator(_affine_maps),
    Expect("{bands} 2 x 3 affine maps [[a, b, c], [d, e, f]], one per band, from the reference geometry's pixel "
           "coordinates (x = column, y = row) to the band's, each with a e - b d > 0"),
]


def _readonly_float64(values: list) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    array.setflags(write=False)
    return array


# ------------------------------------------------------------------------------------------------
# Checking a document

#: error(location, problem, expected) -> the exception a document raises: location is dotted
#: ("frames[3].role", "" for the document itself), problem follows it ("is 3", "is missing").
DocumentError = Callable[[str, str, "str | None"], Exception]


def located(error_type: type[SpherejaxFileError], path) -> DocumentError:
    """The `DocumentError` of a file: error_type(path, "<location> <problem>", expected)."""

    def make(location: str, problem: str, expected: str | None) -> Exception:
        return error_type(path, f"{location} {problem}" if location else problem, expected)

    return make


def check_document(
    model: type[Document],
    data,
    *,
    error: DocumentError,
    where: str = "",
    context: dict | None = None,
    unknown: Literal["fields", "key"] = "fields",
    unknown_expected: str | None = None,
):
    """`data` validated as `model`, or the first problem raised as `error(...)`.

    Args:
      model: the document's model.
      data: the parsed document (JSON or TOML: dicts, lists, str, int, float, bool, None).
      error: makes the document's exception (`located` for a spherejax file).
      where: the location of `data` in its file ("header"), put before each field's.
      context: the validation context: values of the file other checks depend on ("image_shape",
        "bands"); the `Expect` texts may name them.
      unknown: how unknown fields are reported: "fields", "<where> has unknown fields [...]"
        (expected "only [the fields]"); "key", "<first unknown> is not a known key" (expected
        "one of [the fields]", or `unknown_expected`).

    Raises:
      The exception `error` makes, for the first problem in the order the fields are declared;
      unknown fields of an object come before the other problems inside it.
    """
    try:
        return model.model_validate(data, context=context)
    except pydantic.ValidationError as failure:
        problems = failure.errors(include_url=False)
    first = _first(problems)
    if first["type"] == "extra_forbidden":
        parent = first["loc"][:-1]
        names = sorted(str(p["loc"][-1]) for p in problems if p["type"] == "extra_forbidden" and p["loc"][:-1] == parent)
        allowed = sorted(_fields_at(model, parent))
        if unknown == "fields":
            raise error(_dotted(where, parent) or "the top level", f"has unknown fields {names}", f"only {allowed}")
        raise error(_dotted(where, (*parent, names[0])), "is not a known key", unknown_expected or f"one of {allowed}")
    loc, problem, expected = first["loc"], None, None
    if first["type"] == "document":  # refuse(): a check across fields names its own location
        ctx = first["ctx"]
        loc, problem, expected = (*loc, *ctx["at"]), ctx["problem"], ctx["expected"]
    depth, expect = _expect_at(model, loc)
    if expected is None and expect is not None:
        expected = expect.render(context)
    if problem is None:
        # Shown whole: the field that declares what it expects, not the item inside it that failed.
        loc = loc[:depth] if expect is not None else loc
        value = _value_at(data, loc)
        problem = "is missing" if value is _MISSING else f"is {_show(value)}"
    raise error(_dotted(where, loc), problem, expected)


def _first(problems: list[dict]) -> dict:
    """The problem to report: pydantic's first, unless an object around it has unknown fields
    (those come first, as a typo may be why a field is missing)."""
    first = problems[0]
    for depth in range(len(first["loc"]) + 1):
        for problem in problems:
            if problem["type"] == "extra_forbidden" and problem["loc"][:-1] == first["loc"][:depth]:
                return problem
    return first


_MISSING = object()


def _value_at(data, loc: tuple):
    for step in loc:
        try:
            data = data[step]
        except (KeyError, IndexError, TypeError):
            return _MISSING
    return data


def _dotted(where: str, loc: tuple) -> str:
    text = where
    for step in loc:
        if isinstance(step, int):
            text += f"[{step}]"
        else:
            text += f".{step}" if text else str(step)
    return text


def _unwrap(annotation) -> tuple[Any, list]:
    """(the type under Annotated and Optional, the metadata found on the way)."""
    metadata = []
    while True:
        if typing.get_origin(annotation) is Annotated:
            metadata = [*annotation.__metadata__, *metadata]  # the outer Annotated's come last
            annotation = annotation.__origin__
        elif typing.get_origin(annotation) in (typing.Union, types.UnionType) and type(None) in typing.get_args(annotation):
            members = [a for a in typing.get_args(annotation) if a is not type(None)]
            if len(members) != 1:
                return annotation, metadata
            annotation = members[0]
        else:
            return annotation, metadata


def _step(annotation, step):
    """The annotation of `step` (a field name, list index or dict key) inside `annotation`, or
    None where the location leaves the declared types (inside a union's member, say)."""
    annotation, _ = _unwrap(annotation)
    if isinstance(annotation, type) and issubclass(annotation, pydantic.BaseModel):
        field = annotation.model_fields.get(step) if isinstance(step, str) else None
        return None if field is None else Annotated[(field.annotation, *field.metadata)] if field.metadata else field.annotation
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is list and isinstance(step, int) and args:
        return args[0]
    if origin is dict and isinstance(step, str) and len(args) == 2:
        return args[1]
    return None


def _expect_at(model, loc: tuple) -> tuple[int, Expect | None]:
    """(how many steps of loc lead to the deepest field declaring an `Expect`, that Expect)."""
    annotation, found = model, (0, None)
    for depth, step in enumerate(loc, start=1):
        annotation = _step(annotation, step)
        if annotation is None:
            break
        expects = [m for m in _unwrap(annotation)[1] if isinstance(m, Expect)]
        if expects:
            found = (depth, expects[-1])
    return found


def _fields_at(model, loc: tuple) -> list[str]:
    annotation = model
    for step in loc:
        annotation = _step(annotation, step)
    annotation, _ = _unwrap(annotation)
    return list(annotation.model_fields)


class _FormatVersion(Document):
    format_version: integer(1)


def _check_format(data: Mapping, name: str, version: int, *, error: DocumentError, where: str = "") -> int:
    """Refuse a document of another format, or of a newer version than this software reads,
    before anything else is checked (a newer version may differ in the rest). Returns the
    document's format version."""
    from .. import __version__

    found = data.get("format", _MISSING)
    if found != name:
        shown = "missing" if found is _MISSING else _show(found)
        raise error("", f"is not a {name} file: format is {shown}", f'format "{name}"')
    present = {"format_version": data["format_version"]} if "format_version" in data else {}
    found_version = check_document(_FormatVersion, present, error=error, where=where).format_version
    if found_version > version:
        raise error(
            "",
            f"is {name} format version {found_version}, newer than spherejax {__version__} reads",
            f"format version {version} or older; upgrade spherejax to read it",
        )
    return found_version
