"""The command line's numbers: one argparse type per kind of number an option takes.

Every numeric option of spherejax's commands, by kind (the instrument package's `acquire` has
none):

  integer               --workers (its range, 1..the cores this process may use, depends on the
                        machine: spherejax.cluster.check_workers says it, for the API too)
  positive_integer      --max-steps (at most MAX_STEPS_MAX), --frames (at most FRAMES_MAX)
  non_negative_integer  --seed, at most SEED_MAX
  number_in             --gain (GAIN_MIN..GAIN_MAX), --read-noise (0..READ_NOISE_MAX),
                        --white-reflectance-u (0..1), --response-weight (0..RESPONSE_WEIGHT_MAX)

(--region NAME=r0,r1,c0,c1 and --reference NAME|L,a,b hold numbers too, each a small format of
its own that `spherejax measure` parses in its own words: the region's bounds within the image,
the reference's L*, a*, b* within REFERENCE_L_RANGE and REFERENCE_AB_RANGE.)

Every option's number is bounded, above and below, by what it can mean: a finite number is not
enough, since one of 1e308 is finite and yet overflows the first product it enters (a response
weight of 1e308 made `study`'s objective infinite; a gain of 1e308 is infinite in the float32 a
noise model holds). The bounds are wide enough for any instrument and narrow enough that no
product of them overflows float32 (the noise model's variance, signal / gain + read_noise², is at
most 65535 / 1e-4 + 65536² < 1e10).

A number is finite: "nan", "inf" and "1e400" (inf as a float) are refused, as every numeric check
of spherejax refuses them. A refused value raises `NumberError`, an argparse.ArgumentTypeError
naming the value and what was expected. argparse would make that a usage error ("spherejax
calibrate: error: argument --gain: ..."); the command line's parsers (`cli.parser._OneLineErrors`)
instead report it as the bad input it is, in the line every bad input gets, and `main` returns
exit status 2 (where argparse's usage errors raise SystemExit):

    spherejax: error: --gain '0': expected electrons per count, a finite number > 0
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

#: How a refusal reads: the option, the value as typed (quoted: it may hold spaces, or be empty)
#: and what was expected, as every other bad input of the command line names its value.
VALUE_FIRST = "{option} {value!r}: expected {expected}"
#: `spherejax study`'s layout for its two numbers, older than the types here and kept as it was
#: (scripts and tests quote it): "--max-steps: expected a positive number of BFGS iterations, got 0".
EXPECTED_FIRST = "{option}: expected {expected}, got {value}"

#: The largest seed: JAX's PRNGKey takes a signed 64-bit integer (a larger one raises
#: OverflowError), NumPy's generators a non-negative one.
SEED_MAX = 2**63 - 1
#: The most frames a noise model counts: it holds them as float32 (`spherejax.NoiseModel`), whose
#: integers are exact up to 2**24 (and a 400-digit count would not convert at all: OverflowError).
FRAMES_MAX = 2**24
#: The most BFGS iterations `study` runs: each is a few evaluations of the whole objective, so a
#: larger number is a run of days, never a better fit (the default is 300).
MAX_STEPS_MAX = 100_000
#: A camera's gain in electrons per count: from 1e-4 (a 16-bit count of a ten-thousandth of an
#: electron) to 1e4 (ten thousand electrons a count); no camera lies outside.
GAIN_MIN, GAIN_MAX = 1e-4, 1e4
#: One frame's read noise in counts rms, at most the full scale of a 16-bit frame.
READ_NOISE_MAX = 65536.0
#: `simulate --band-misregistration`: the largest band displacement, frame pixels. 50 moves a
#: band a quarter of the default 192-row frame, far beyond any filter wheel's few pixels.
BAND_MISREGISTRATION_MAX = 50.0
#: The white standard's relative standard uncertainty: 1 is 100 %.
WHITE_REFLECTANCE_U_MAX = 1.0
#: `measure --reference L,a,b`: L* 0..200 and a*, b* -500..500, wider than any surface colour
#: (fluorescent whites reach L* 105, the most saturated a* and b* about 130), narrow enough that
#: CIEDE2000's products (C to the 7th power) stay finite in float32. (1e308,0,0 gave ΔE00 NaN.)
REFERENCE_L_RANGE, REFERENCE_AB_RANGE = (0.0, 200.0), (-500.0, 500.0)
#: `study`'s weight of the response residual beside ΔE00: spherejax.study.RESPONSE_WEIGHT_MAX,
#: which says why (repeated here so that parsing imports no JAX; a test checks they agree).
RESPONSE_WEIGHT_MAX = 1e6


class NumberError(argparse.ArgumentTypeError):
    """A command-line value that is not a number of the kind its option takes.

    Attributes:
      value: the text as given.
      expected: what was expected, in words ("electrons per count, a finite number > 0").
      layout: how `line` lays out the option, the value and the expectation (`VALUE_FIRST`).
    """

    def __init__(self, value: str, expected: str, layout: str = VALUE_FIRST):
        self.value, self.expected, self.layout = value, expected, layout
        # What argparse shows after "argument --gain: " wherever it reports the error itself.
        super().__init__(f"{value!r}: expected {expected}")

    def line(self, option: str) -> str:
        """The refusal of `option`'s value, one line: "--gain '0': expected ..."."""
        return self.layout.format(option=option, value=self.value, expected=self.expected)


class NumberType:
    """An argparse `type`: the text of one kind of number -> the number, or `NumberError`.

    Made by the functions below, one per kind; `what` says what the option's number is
    ("electrons per count") and goes before the kind's text in the refusal.
    """

    def __init__(self, parse: Callable[[str], int | float], accept: Callable, kind: str, what: str | None = None,
                 *, expected: str | None = None, layout: str = VALUE_FIRST):
        """parse: text -> number, ValueError if it is none; accept: number -> bool, the range;
        kind: the kind in words; expected: the whole expected text instead of "what, kind"."""
        self._parse, self._accept, self.kind, self.layout = parse, accept, kind, layout
        self.expected = expected if expected is not None else f"{what}, {kind}" if what else kind

    def __call__(self, text: str) -> int | float:
        try:
            number = self._parse(text)
        except (TypeError, ValueError):  # not a number of this kind at all ("abc", "1.5" for an integer)
            number = None
        if number is None or not self._accept(number):
            raise NumberError(text, self.expected, self.layout)
        return number

    def __repr__(self) -> str:  # argparse names a type by its repr in some of its messages
        return f"<number type: {self.kind}>"


def _finite_float(text: str) -> float:
    number = float(text)  # "1e400" is inf, "nan" nan: both refused as not finite
    if not math.isfinite(number):
        raise ValueError(f"not finite: {text!r}")
    return number


def integer(what: str | None = None, **options) -> NumberType:
    """A whole number of either sign ("7", "-2"; not "7.0"), for an option whose range is checked
    where it is known (--workers: the cores this process may use)."""
    return NumberType(int, lambda n: True, "an integer", what, **options)


def positive_integer(what: str | None = None, *, maximum: int | None = None, **options) -> NumberType:
    """A whole number >= 1 (and <= maximum): a count of things that must happen at least once."""
    kind = "an integer >= 1" if maximum is None else f"an integer 1..{maximum}"
    return NumberType(int, lambda n: 1 <= n and (maximum is None or n <= maximum), kind, what, **options)


def non_negative_integer(what: str | None = None, *, maximum: int | None = None, **options) -> NumberType:
    """A whole number >= 0 (and <= maximum)."""
    kind = "an integer >= 0" if maximum is None else f"an integer 0..{maximum}"
    return NumberType(int, lambda n: 0 <= n and (maximum is None or n <= maximum), kind, what, **options)


def positive_number(what: str | None = None, **options) -> NumberType:
    """A finite number > 0 ("2", "0.5", "1e-3")."""
    return NumberType(_finite_float, lambda x: x > 0, "a finite number > 0", what, **options)


def non_negative_number(what: str | None = None, **options) -> NumberType:
    """A finite number >= 0."""
    return NumberType(_finite_float, lambda x: x >= 0, "a finite number >= 0", what, **options)


def shown(number: float) -> str:
    """A bound as a person writes it: 0.0001, 65536, 1e6 (not format's 1e+06)."""
    return f"{number:g}".replace("e+0", "e").replace("e+", "e")


def number_in(what: str | None = None, *, minimum: float, maximum: float, **options) -> NumberType:
    """A finite number in minimum..maximum, both included: an option whose number means something
    only within bounds (module docstring)."""
    kind = f"a number {shown(minimum)}..{shown(maximum)}"
    return NumberType(_finite_float, lambda x: minimum <= x <= maximum, kind, what, **options)


class BadNumber(SystemExit):
    """Raised by the command line's parsers once they have written a `NumberError`'s line on
    stderr: exit status 2 (a SystemExit, as argparse's own errors, wherever a parser is used on
    its own), which `main` returns."""


__all__ = [
    "VALUE_FIRST", "EXPECTED_FIRST", "SEED_MAX", "FRAMES_MAX", "MAX_STEPS_MAX", "GAIN_MIN", "GAIN_MAX",
    "READ_NOISE_MAX", "BAND_MISREGISTRATION_MAX", "WHITE_REFLECTANCE_U_MAX", "RESPONSE_WEIGHT_MAX", "REFERENCE_L_RANGE", "REFERENCE_AB_RANGE", "NumberError", "NumberType", "BadNumber",
    "integer", "positive_integer", "non_negative_integer", "positive_number", "non_negative_number", "number_in",
    "shown",
]
