"""spherejax.jsontext: every way json.loads fails becomes one JSONTextError line."""

from __future__ import annotations

import pytest

from spherejax import jsontext


@pytest.mark.parametrize(
    "data, problem",
    [
        (b"", "is not valid JSON: Expecting value at line 1 column 1"),
        (b'{"a": 1,\n "b": }', "is not valid JSON: Expecting value at line 2 column 7"),
        (b"[" * 100_000 + b"]" * 100_000, "is not valid JSON: nested deeper than the JSON parser can follow"),
        (b"9" * 5000, "is not valid JSON: Exceeds the limit (4300 digits)"),
        (b'"caf\xe9"', "is not UTF-8 text (byte 4)"),
        ('{"a": 1}'.encode("utf-16"), "is not UTF-8 text (byte 0)"),
    ],
    ids=["empty", "syntax", "deep", "digits", "latin-1", "utf-16"],
)
def test_damaged_text_is_one_line(data, problem):
    with pytest.raises(jsontext.JSONTextError) as error:
        jsontext.loads(data)
    assert isinstance(error.value, ValueError)
    assert str(error.value).startswith(problem) and error.value.problem == str(error.value)
    assert "\n" not in str(error.value) and error.value.detail in error.value.problem
    # No chained traceback behind the one line (a RecursionError's would be thousands of frames).
    assert error.value.__cause__ is None and (error.value.__suppress_context__ or error.value.__context__ is None)


def test_values_and_constants():
    assert jsontext.loads(b'{"a": [1, 2.5, "\xc3\xa9"]}') == {"a": [1, 2.5, "é"]}
    assert jsontext.loads('{"x": null}') == {"x": None}
    assert jsontext.loads(b"NaN") != jsontext.loads(b"NaN")  # Python's json writes NaN; taken by default
    with pytest.raises(jsontext.JSONTextError, match="^is not valid JSON: Infinity is not a JSON value$"):
        jsontext.loads(b"[Infinity]", allow_nan=False)
