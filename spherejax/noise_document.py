"""The JSON document of a `spherejax.NoiseModel`, declared once as a pydantic model: what
`NoiseModel.to_json` writes and `NoiseModel.from_json` reads (a calibration file's header
"noise_model", the docstring of spherejax.io).

    {"gain_e_per_count": g, "read_noise_counts": r,            a number, or a list: one per band
     "dark_frames": n, "white_frames": n, "sample_frames": n,   a number >= 1 each (default 1)
     "white_reflectance_u": u,                                  a number or one per band (default 0)
     "coeffs_covariance": [[[...]]] or null,                    (B, 4, 4)
     "estimator_covariance": {"gram": [[...]], "residual": [[...]]} or null}

As every document of spherejax.io (spherejax/io/documents.py): strict types (no bool for a number,
no "1.5" for 1.5), no unknown keys, finite numbers only, frozen. Every number is read as a float64
and written as one (`.tolist()` of a float64 array), so it reads back as the same float64; a
model of float32 values reads back as the same float32 values (a float32's float64 is exact). With
the number of bands (`check(..., bands=B)`, the validation context), the per-band values are also
checked against B, by the rule `NoiseModel.check_bands` applies in memory
(`spherejax.noise_bands.band_problem`).

This is a kernel module (tests/test_layers.py), as is `spherejax.uncertainty`, whose model it
describes, so that a NoiseModel is read and written without spherejax.io. spherejax.io's
`check_document` is therefore out of reach, and `check` has its own short path from a pydantic
error to one line, in the wording `NoiseModel.from_json` has always had (calibration files and
their tests quote it; spherejax.io puts "PATH: header.noise_model is not valid: " before it):

    noise model: expected a JSON object, got list
    noise model: unknown key 'shot_noise'; expected some of [...]
    noise model: missing 'read_noise_counts', expected <what the key holds>
    noise model: read_noise_counts is 'loud', expected <...>        not numbers at all
    noise model: gain_e_per_count expected finite numbers; got inf  numbers, not all finite
    noise model: dark_frames expected <...>; got 0                  numbers out of range or shape
    noise model: gain has 15 values in gain_e_per_count, expected one or 16 (one per band)

`NoiseModel.to_json` and `from_json` import this module when first called, so that
`import spherejax` does not pay for importing pydantic.
"""

from __future__ import annotations

import math
import reprlib
import sys
from collections.abc import Mapping
from typing import Annotated, Any

import numpy as np
import pydantic
from pydantic import AfterValidator, ConfigDict, Field, PlainSerializer, ValidationInfo, model_validator
from pydantic_core import PydanticCustomError

from .noise_bands import band_problem

# validate_default: the defaults (1 frame, 0 uncertainty) become float64 arrays like the values read.
_CONFIG = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False, frozen=True, validate_default=True)


def _float64(values) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    array.setflags(write=False)
    return array


#: A field of numbers holds a read-only float64 array and is written back as JSON numbers.
_AS_FLOAT64 = (AfterValidator(_float64), PlainSerializer(lambda array: array.tolist(), return_type=Any))


def _per_band(expected: str, **bound):
    """A number, or a non-empty list of numbers (one per band), bounded as given -> float64 array."""
    number = Annotated[float, Field(**bound)]
    return Annotated[
        number | Annotated[list[number], Field(min_length=1)],
        Field(union_mode="left_to_right", description=expected), *_AS_FLOAT64,
    ]


def _frames(expected: str):
    return Annotated[float, Field(ge=1, description=expected), *_AS_FLOAT64]


def _square(rows: list[list[float]]) -> list[list[float]]:
    if any(len(row) != len(rows) for row in rows):
        raise ValueError("not a square matrix")
    return rows


_Square = Annotated[list[list[float]], Field(min_length=1), AfterValidator(_square), *_AS_FLOAT64]
_Row4 = Annotated[list[float], Field(min_length=4, max_length=4)]
_Coefficients = Annotated[
    list[Annotated[list[_Row4], Field(min_length=4, max_length=4)]], Field(min_length=1), *_AS_FLOAT64,
]


class EstimatorDocument(pydantic.BaseModel):
    """The reflectance estimator's covariance (`spherejax.EstimatorCovariance`)."""

    model_config = _CONFIG

    gram: Annotated[_Square, Field(
        description="a square matrix of numbers, (B + 1, B + 1): the inverse Gram matrix of the estimator's responses"
    )]
    residual: Annotated[
        _Square, Field(description="a square matrix of numbers: the covariance of the estimator's residuals, 31 x 31")
    ]


class NoiseModelDocument(pydantic.BaseModel):
    """A `spherejax.NoiseModel` as JSON (module docstring). The fields are read-only float64
    arrays (None for an absent covariance); `model_dump()` is the JSON. Declared in the order
    `to_json` has always written the keys, which is the order of its output."""

    model_config = _CONFIG

    gain_e_per_count: _per_band("numbers > 0: the camera gain in electrons per count, one or one per band", gt=0)
    read_noise_counts: _per_band("numbers >= 0: one frame's read noise in counts rms, one or one per band", ge=0)
    dark_frames: _frames("a number >= 1: the frames averaged in the calibration's dark frame") = 1.0
    white_frames: _frames("a number >= 1: the frames averaged in the calibration's white-standard frame") = 1.0
    sample_frames: _frames("a number >= 1: the frames averaged in each sample frame") = 1.0
    white_reflectance_u: _per_band(
        "numbers >= 0: the white standard's relative standard uncertainty, one or one per band", ge=0
    ) = 0.0
    coeffs_covariance: Annotated[
        _Coefficients | None,
        Field(description="shape (B, 4, 4): the covariance of each band's Stage II coefficients c1..c4, or null"),
    ] = None
    estimator_covariance: Annotated[
        EstimatorDocument | None,
        Field(description="an object with 'gram' and 'residual' (the reflectance estimator's covariance), or null"),
    ] = None

    @model_validator(mode="after")
    def _fits_the_bands(self, info: ValidationInfo) -> NoiseModelDocument:
        bands = (info.context or {}).get("bands")
        if bands is None:
            return self
        estimator = self.estimator_covariance
        problem = band_problem(
            {
                "gain": self.gain_e_per_count.shape, "read_noise": self.read_noise_counts.shape,
                "white_reflectance_u": self.white_reflectance_u.shape,
                "coeffs_covariance": None if self.coeffs_covariance is None else self.coeffs_covariance.shape,
                "estimator_covariance.gram": None if estimator is None else estimator.gram.shape,
            },
            bands, keys={"gain": "gain_e_per_count", "read_noise": "read_noise_counts"},
        )
        if problem is not None:
            # The problem goes in the context, not the template, which would format its braces.
            raise PydanticCustomError("noise_model", "{problem}", {"problem": problem})
        return self

    @classmethod
    def of(cls, model) -> NoiseModelDocument:
        """The document of a `NoiseModel` (every field as float64 numbers); ValueError as `check`
        where the model holds what no document does (a non-square estimator matrix)."""

        def plain(value):
            return None if value is None else np.asarray(value, np.float64).tolist()

        estimator = model.estimator_covariance
        return check({
            "gain_e_per_count": plain(model.gain),
            "read_noise_counts": plain(model.read_noise),
            "dark_frames": plain(model.dark_frames),
            "white_frames": plain(model.white_frames),
            "sample_frames": plain(model.sample_frames),
            "white_reflectance_u": plain(model.white_reflectance_u),
            "coeffs_covariance": plain(model.coeffs_covariance),
            "estimator_covariance": None if estimator is None else {
                "gram": plain(estimator.gram), "residual": plain(estimator.residual),
            },
        })


def check(data, *, bands: int | None = None) -> NoiseModelDocument:
    """`data` (parsed JSON) validated as a `NoiseModelDocument`, its per-band values checked
    against `bands` bands when given; ValueError on one line otherwise (module docstring)."""
    if not isinstance(data, Mapping):
        raise ValueError(f"noise model: expected a JSON object, got {type(data).__name__}")
    data = dict(data)
    try:
        return NoiseModelDocument.model_validate(data, context={"bands": bands})
    except pydantic.ValidationError as failure:
        problems = failure.errors(include_url=False)
    raise ValueError("noise model: " + _problem(data, problems))


# ------------------------------------------------------------------------------------------------
# A pydantic error as one line


def _problem(data: dict, problems: list[dict]) -> str:
    """The first problem in words: unknown keys first (a typo may be why a key is missing), then
    a missing key, then the first other problem in the order the fields are declared."""
    unknown = [p for p in problems if p["type"] == "extra_forbidden"]
    if unknown:
        depth = min(len(p["loc"]) for p in unknown)
        first = min((p["loc"] for p in unknown if len(p["loc"]) == depth), key=str)
        allowed = sorted(NoiseModelDocument.model_fields if depth == 1 else EstimatorDocument.model_fields)
        return f"unknown key {'.'.join(map(str, first))!r}; expected some of {allowed}"
    missing = next((p for p in problems if p["type"] == "missing"), None)
    if missing is not None:
        path = _field_path(missing["loc"])
        return f"missing {'.'.join(path)!r}, expected {_expected(path)}"
    first = problems[0]
    if first["type"] == "noise_model":  # _fits_the_bands: the problem in words already
        return first["ctx"]["problem"]
    path = _field_path(first["loc"])
    if not path:  # not expected from this model: every check is on a field or names its own
        return f"is not valid ({first['msg']})"
    name, expected = ".".join(path), _expected(path)
    value = data
    for step in path:
        value = value[step]
    shown = _show(value)
    if path == ["estimator_covariance"]:  # an object, not numbers
        return f"{name} expected {expected}; got {shown}"
    if not _numbers(value):
        return f"{name} is {shown}, expected {expected}"
    digits = _digits_beyond_float(value)
    if digits:
        return f"{name} expected finite numbers; got an int too large for a float64 ({digits} digits)"
    if not _finite(value):
        return f"{name} expected finite numbers; got {shown}"
    return f"{name} expected {expected}; got {shown}"


def _field_path(loc: tuple) -> list[str]:
    """The declared fields along a pydantic location, leaving out what lies between or below
    them (the member of a union, a list index): ["estimator_covariance", "gram"]."""
    model, path = NoiseModelDocument, []
    for step in loc:
        if model is not None and step in model.model_fields:
            path.append(step)
            model = EstimatorDocument if step == "estimator_covariance" else None
    return path


def _expected(path: list[str]) -> str:
    model = EstimatorDocument if len(path) == 2 else NoiseModelDocument
    return model.model_fields[path[-1]].description


def _leaves(value):
    if isinstance(value, list):
        for item in value:
            yield from _leaves(item)
    else:
        yield value


def _numbers(value) -> bool:
    """A number or lists of numbers, however nested or ragged (bool is not a number)."""
    return all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in _leaves(value))


def _digits_beyond_float(value) -> int:
    """The digits of the first integer beyond the float64 range (which JSON allows), else 0.
    Counted by log10, not str(): Python refuses str() of an int of more than 4300 digits."""
    for x in _leaves(value):
        if isinstance(x, int) and abs(x) > _FLOAT_MAX:
            return int(math.log10(abs(x))) + 1
    return 0


def _finite(value) -> bool:
    return all(math.isfinite(x) for x in _leaves(value) if isinstance(x, float))


_FLOAT_MAX = int(sys.float_info.max)

# Python's repr of a value (a string in quotes, lists as lists), each part cut short (a 401-digit
# integer, a list of thousands).
_REPR = reprlib.Repr()
_REPR.maxlist, _REPR.maxlevel, _REPR.maxstring, _REPR.maxlong, _REPR.maxother = 6, 3, 40, 40, 40


def _show(value) -> str:
    """A found value as a message shows it: its repr, at most 80 characters, so that a line
    stays short whatever the file holds."""
    text = _REPR.repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


__all__ = ["NoiseModelDocument", "EstimatorDocument", "check"]
