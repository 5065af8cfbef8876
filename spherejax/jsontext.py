"""Parsing the JSON of a file (spherejax's own or a user's) into a value or one line of problem.

Every JSON document spherejax and hw/ read back from disk goes through `loads`, because
`json.loads` fails in more ways than its documented `JSONDecodeError`, and a damaged file must end
in the same one-line refusal whichever way it is damaged:

- bytes that are not UTF-8 (`json.loads` would even guess UTF-16 or UTF-32 from them);
- an integer of more than 4300 digits (int() refuses it with a plain ValueError);
- arrays or objects nested thousands deep (the C scanner raises RecursionError);
- NaN and Infinity, which are not JSON, where the caller says so (a checksum over strict JSON
  could not be verified with one in it);
- a key given twice in one object, which `json.loads` takes silently, the last one winning: a
  session manifest with two "frames" or a profile-like document edited by hand would be read as
  something its author did not see. Refused, naming the key (RFC 8259 says names SHOULD be
  unique; every document spherejax writes has unique keys, so a duplicate is always damage or a
  hand edit gone wrong).

Callers wrap the problem in their own error type, naming the file and what was expected
(`spherejax.io`, `hw.lamp`). No file access here: the caller reads the bytes, so it also decides
how a missing or unreadable file is reported.
"""

from __future__ import annotations

import json


class JSONTextError(ValueError):
    """Text that is not JSON spherejax can use.

    Attributes:
      problem: one line that follows a file name, "is not UTF-8 text (byte 3)" or
        "is not valid JSON: Expecting value at line 1 column 1".
      detail: what is wrong without the leading "is not ..." ("byte 3", "Expecting value at line
        1 column 1"), for callers that phrase the problem their own way.
    """

    def __init__(self, problem: str, detail: str):
        self.problem, self.detail = problem, detail
        super().__init__(problem)


def _not_json(constant: str):
    raise ValueError(f"{constant} is not a JSON value")


class _DuplicateKey(ValueError):
    """A key found twice in one JSON object (`_unique_keys`)."""


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """json's object_pairs_hook: the object as a dict, or `_DuplicateKey` naming the key given twice."""
    document = {}
    for key, value in pairs:
        if key in document:
            raise _DuplicateKey(f"the key {key!r} appears twice in one object")
        document[key] = value
    return document


def loads(data: bytes | str, *, allow_nan: bool = True):
    """The JSON value of `data` (bytes are decoded as strict UTF-8).

    Args:
      data: the file's bytes, or text already decoded.
      allow_nan: whether NaN, Infinity and -Infinity are taken (Python's json writes them).

    Raises:
      JSONTextError: not UTF-8, not JSON, beyond the parser's limits (integer digits, nesting
        depth), a key given twice in one object, or a non-finite constant where they are
        refused; never RecursionError.
    """
    if isinstance(data, (bytes, bytearray, memoryview)):
        try:
            data = bytes(data).decode("utf-8")
        except UnicodeDecodeError as error:
            detail = f"byte {error.start}"
            raise JSONTextError(f"is not UTF-8 text ({detail})", detail) from None
    try:
        return json.loads(data, object_pairs_hook=_unique_keys,
                          **({} if allow_nan else {"parse_constant": _not_json}))
    except _DuplicateKey as error:
        detail = str(error)
    except json.JSONDecodeError as error:
        detail = f"{error.msg} at line {error.lineno} column {error.colno}"
    except RecursionError:
        # The nesting depth at which this happens is the interpreter's recursion limit.
        detail = "nested deeper than the JSON parser can follow"
    except ValueError as error:  # an integer of too many digits; a refused constant
        detail = " ".join(str(error).split())
    raise JSONTextError(f"is not valid JSON: {detail}", detail)


__all__ = ["JSONTextError", "loads"]
