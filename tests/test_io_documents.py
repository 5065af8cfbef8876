"""The shared declaration and checking of documents (spherejax.io.documents): what each reusable
type accepts and refuses, and the one-line message `check_document` makes of a problem."""

from __future__ import annotations

import math
import typing
from typing import Annotated

import pydantic
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from spherejax.io import documents as d
from spherejax.io.errors import SessionError

FILE = "doc.json"
CONTEXT = {"image_shape": (10, 20), "height": 10, "width": 20, "bands": 3}


def error_of(model, data, **options) -> str:
    """The one-line message of the document's refusal."""
    with pytest.raises(SessionError) as caught:
        d.check_document(model, data, error=d.located(SessionError, FILE), **options)
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"{FILE}: "), message
    return message


def valid(model, data, **options):
    return d.check_document(model, data, error=d.located(SessionError, FILE), **options)


# One field of each reusable type, checked on its own.
FIELD_TYPES = {
    "FiniteNumber": d.FiniteNumber,
    "PositiveNumber": d.PositiveNumber,
    "NonNegativeNumber": d.NonNegativeNumber,
    "integer1": d.integer(1),
    "integer0to9": d.integer(0, 9),
    "choice": d.choice("a", "b"),
    "NonEmptyStr": d.NonEmptyStr,
    "Timestamp": d.Timestamp,
    "AwareTime": d.AwareTime,
    "IncreasingInts": d.IncreasingInts,
    "BandCentres": d.BandCentres,
    "Rectangle": d.Rectangle,
    "ImageRectangle": d.ImageRectangle,
    "RelativePath": d.RelativePath,
    "Sha256": d.Sha256,
    "Checksum": d.Checksum,
    "JsonObject": d.JsonObject,
    "shape2": d.shape(2, "[H, W]"),
    "numbers3": d.numbers(3, "three numbers"),
    "numbers_bands": d.numbers("bands", "{bands} numbers > 0", positive=True),
}
MODELS = {
    name: pydantic.create_model(f"_One_{name}", __base__=d.Document, value=(annotation, ...))
    for name, annotation in FIELD_TYPES.items()
}
SHA = "0123456789abcdef" * 4

ACCEPTS = [
    ("FiniteNumber", 0), ("FiniteNumber", -1.5), ("FiniteNumber", 10**300),
    ("PositiveNumber", 1), ("PositiveNumber", 1e-300),
    ("NonNegativeNumber", 0), ("NonNegativeNumber", 0.0),
    ("integer1", 1), ("integer1", 2**70), ("integer0to9", 9),
    ("choice", "a"), ("NonEmptyStr", "x"),
    ("Timestamp", "2026-01-05"), ("Timestamp", "2026-01-05T09:00:00"), ("AwareTime", "2026-01-05T09:00:00+01:00"),
    ("IncreasingInts", [1, 2, 5]), ("BandCentres", [400, 420]),
    ("Rectangle", [0, 1, 0, 1]), ("Rectangle", [5, 10, 5, 20]), ("ImageRectangle", [0, 10, 0, 20]),
    ("RelativePath", "frames/a.tif"), ("RelativePath", "a..b/c"), ("RelativePath", "./a"),
    ("Sha256", SHA), ("Checksum", "sha256:" + SHA), ("JsonObject", {}), ("JsonObject", {"a": [1, None]}),
    ("shape2", [3, 4]), ("numbers3", [0, -1.5, 2]), ("numbers_bands", [1, 2, 3.5]),
]
REFUSES = [
    ("FiniteNumber", True), ("FiniteNumber", "1"), ("FiniteNumber", math.nan), ("FiniteNumber", math.inf),
    ("FiniteNumber", 10**400), ("FiniteNumber", None), ("FiniteNumber", [1]),
    ("PositiveNumber", 0), ("PositiveNumber", -1), ("PositiveNumber", -math.inf), ("PositiveNumber", False),
    ("NonNegativeNumber", -1e-300),
    ("integer1", 0), ("integer1", True), ("integer1", 1.0), ("integer1", "1"), ("integer0to9", 10),
    ("choice", "c"), ("choice", "A"), ("choice", 1),
    ("NonEmptyStr", ""), ("NonEmptyStr", 1), ("NonEmptyStr", None),
    ("Timestamp", "yesterday"), ("Timestamp", 20260105), ("AwareTime", "2026-01-05T09:00:00"),
    ("IncreasingInts", []), ("IncreasingInts", [2, 2]), ("IncreasingInts", [3, 1]), ("IncreasingInts", [0, 1]),
    ("IncreasingInts", [1, True]), ("IncreasingInts", [2**31]), ("IncreasingInts", (1, 2)),
    ("BandCentres", [100_001]),
    ("Rectangle", [1, 1, 0, 1]), ("Rectangle", [0, 1, 2, 1]), ("Rectangle", [-1, 1, 0, 1]), ("Rectangle", [0, 1, 0]),
    ("Rectangle", [0, 1.0, 0, 1]), ("Rectangle", [0, True, 0, 1]), ("ImageRectangle", [0, 11, 0, 20]),
    ("ImageRectangle", [0, 10, 0, 21]),
    ("RelativePath", "../a"), ("RelativePath", "a/../../b"), ("RelativePath", "/etc/passwd"), ("RelativePath", ""),
    ("RelativePath", "."), ("RelativePath", "a\0b"), ("RelativePath", 1),
    ("Sha256", SHA.upper()), ("Sha256", SHA[:-1]), ("Sha256", SHA + "\n"), ("Checksum", SHA), ("Checksum", "sha256:" + SHA + "0"),
    ("JsonObject", []), ("JsonObject", None),
    ("shape2", [3]), ("shape2", [3, 0]), ("shape2", [3, 4, 5]), ("shape2", [3, 2**31]),
    ("numbers3", [1, 2]), ("numbers3", [1, 2, math.nan]), ("numbers3", [1, 2, "3"]),
    ("numbers_bands", [1, 2]), ("numbers_bands", [1, 2, 0]),
]


@pytest.mark.parametrize(("name", "value"), ACCEPTS, ids=[f"{n}-{v!r}"[:60] for n, v in ACCEPTS])
def test_reusable_type_accepts(name, value):
    valid(MODELS[name], {"value": value}, context=CONTEXT)


@pytest.mark.parametrize(("name", "value"), REFUSES, ids=[f"{n}-{v!r}"[:60] for n, v in REFUSES])
def test_reusable_type_refuses_naming_field_value_and_expected_text(name, value):
    message = error_of(MODELS[name], {"value": value}, context=CONTEXT)
    expected = [m for m in typing.get_args(FIELD_TYPES[name]) if isinstance(m, d.Expect)][-1].render(CONTEXT)
    assert message == f"{FILE}: value is {d._show(value)} (expected {expected})"


def test_values_come_back_as_their_type():
    assert valid(MODELS["PositiveNumber"], {"value": 16383}).value == 16383
    assert type(valid(MODELS["PositiveNumber"], {"value": 16383}).value) is int  # not turned into 16383.0
    assert valid(MODELS["Rectangle"], {"value": [0, 1, 2, 3]}).value == (0, 1, 2, 3)
    assert valid(MODELS["shape2"], {"value": [3, 4]}).value == (3, 4)
    array = valid(MODELS["numbers3"], {"value": [1, 2, 3]}).value
    assert array.dtype == "float64" and not array.flags.writeable
    assert valid(MODELS["AwareTime"], {"value": "2026-01-05T10:00:00+01:00"}).value.isoformat() == "2026-01-05T09:00:00+00:00"


def test_a_rectangle_without_an_image_is_only_checked_for_order():
    valid(MODELS["Rectangle"], {"value": [0, 10**6, 0, 10**6]})


class _Item(d.Document):
    band: d.integer(1)
    rect: d.ImageRectangle = (0, 1, 0, 1)


class _Doc(d.Document):
    count: d.integer(1)
    items: Annotated[list[Annotated[_Item, d.Expect("an item, an object")]], d.Expect("a list of items")] = []
    table: Annotated[dict[str, Annotated[_Item, d.Expect("an item")]], d.Expect("a table of items")] = {}

    @pydantic.model_validator(mode="after")
    def _first_band_is_one(self):
        if self.items and self.items[0].band != 1:
            raise d.refuse(f"is band {self.items[0].band}", "band 1 first", ("items", 0, "band"))
        return self


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({}, "count is missing (expected an integer >= 1)"),
        ({"count": True}, "count is true (expected an integer >= 1)"),
        ({"count": 1, "items": [{"band": 1}, {"band": 1}, {"band": "2"}]}, 'items[2].band is "2" (expected an integer >= 1)'),
        ({"count": 1, "items": [{"band": 1}, {}]}, "items[1].band is missing (expected an integer >= 1)"),
        ({"count": 1, "items": [{"band": 1}, 7]}, "items[1] is 7 (expected an item, an object)"),
        ({"count": 1, "items": {"band": 1}}, 'items is {"band": 1} (expected a list of items)'),
        ({"count": 1, "table": {"x": {"band": 0}}}, "table.x.band is 0 (expected an integer >= 1)"),
        ({"count": 1, "items": [{"band": 1, "rect": [0, 2, 0, 30]}]},
         "items[0].rect is [0, 2, 0, 30] (expected [r0, r1, c0, c1] with 0 <= r0 < r1 <= 10 and 0 <= c0 < c1 <= 20: "
         "a non-empty rectangle inside the 10 x 20 image)"),
        ({"count": 1, "items": [{"band": 2}]}, "items[0].band is band 2 (expected band 1 first)"),
        # unknown fields first, all of them, before the other problems of their object
        ({"count": 0, "zz": 1, "aa": 2}, "the top level has unknown fields ['aa', 'zz'] (expected only ['count', 'items', 'table'])"),
        ({"count": 1, "items": [{"band": 0, "bnad": 1}]}, "items[0] has unknown fields ['bnad'] (expected only ['band', 'rect'])"),
        # but not before a problem of an object outside theirs that comes first
        ({"count": 0, "items": [{"band": 1, "bnad": 1}]}, "count is 0 (expected an integer >= 1)"),
    ],
)
def test_message_names_file_location_value_and_expected_text(data, message):
    assert error_of(_Doc, data, context=CONTEXT) == f"{FILE}: {message}"


def test_where_prefix_and_unknown_keys_one_at_a_time():
    assert error_of(_Doc, {"count": 0}, where="header") == f"{FILE}: header.count is 0 (expected an integer >= 1)"
    assert error_of(_Doc, {"count": 1, "b": 1, "a": 1}, where="header", unknown="key") == (
        f"{FILE}: header.a is not a known key (expected one of ['count', 'items', 'table'])"
    )
    assert error_of(_Doc, {"count": 1, "a": 1}, unknown="key", unknown_expected="nothing else") == (
        f"{FILE}: a is not a known key (expected nothing else)"
    )


def test_a_long_value_is_cut_to_one_short_line():
    message = error_of(_Doc, {"count": list(range(1000))})
    assert "..." in message and message.endswith("(expected an integer >= 1)")
    assert len(message) < 200


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({}, "is not a spherejax-session file: format is missing (expected format \"spherejax-session\")"),
        ({"format": "other", "format_version": "x"}, 'is not a spherejax-session file: format is "other"'),
        # a newer version is refused before anything else it holds is looked at
        ({"format": "spherejax-session", "format_version": 2, "anything": [1]}, "is spherejax-session format version 2, newer than"),
        ({"format": "spherejax-session", "format_version": 1.0}, "header.format_version is 1.0 (expected an integer >= 1)"),
        ({"format": "spherejax-session"}, "header.format_version is missing (expected an integer >= 1)"),
    ],
)
def test_check_format_comes_first(data, message):
    with pytest.raises(SessionError) as caught:
        d._check_format(data, "spherejax-session", 1, error=d.located(SessionError, FILE), where="header")
    assert str(caught.value).startswith(f"{FILE}: {message}")


def test_check_format_returns_the_version():
    doc = {"format": "spherejax-session", "format_version": 1}
    assert d._check_format(doc, "spherejax-session", 1, error=d.located(SessionError, FILE)) == 1


def _document_models():
    from spherejax_hw import lamp, profile
    from spherejax.archive import manifest
    from spherejax.io import calibration_files, sessions

    return [
        sessions._Manifest, sessions._Frame, sessions._Region, calibration_files._CalibrationHeader,
        calibration_files._CalibrationHeaderV1, calibration_files._ArrayEntry, manifest._Record, lamp._State,
        lamp._Warmup, profile._Profile, profile._Wheel, profile._Acquisition, profile._Noise, profile._Sample,
        *profile._CAMERA_TABLES.values(),
    ]


def test_every_field_of_every_document_says_what_it_expects():
    """A field without an Expect would make a message without its expected text."""
    missing = []
    for model in _document_models():
        for name in model.model_fields:
            depth, expect = d._expect_at(model, (name,))
            if expect is None and name not in ("format", "format_version", "noise_model", "camera"):
                missing.append(f"{model.__name__}.{name}")
    assert missing == []


_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=8,
)


@settings(max_examples=300, deadline=None)
@given(_JSON)
@example("  ")  # shown as " " once the message was made one line (a clean-clone CI run)
@example(["a  b", {"c   ": 1}])
def test_any_json_value_in_a_strict_int_field_is_that_int_or_one_line(value):
    model = MODELS["integer1"]
    try:
        checked = valid(model, {"value": value})
    except SessionError as error:
        message = str(error)
        assert "\n" not in message and "Traceback" not in message
        assert message == f"{FILE}: value is {d._show(value)} (expected an integer >= 1)"
        assert not (type(value) is int and value >= 1)
    else:
        assert type(value) is int and checked.value == value >= 1
