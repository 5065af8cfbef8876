"""The command line's numbers (spherejax.cli.number_types): one argparse type per kind of number,
each refusing what is not a finite number of its kind with a message naming the value and what
was expected; through `spherejax`, one line on stderr naming the option too, exit status 2, no
traceback, nothing written; and every numeric option of every command uses one."""

from __future__ import annotations

import argparse
import math
import subprocess
import sys

import pytest

from spherejax import cli
from spherejax.cli import number_types as numbers

NON_NUMBERS = ["", " ", "abc", "1,5", "0x10", "--1", "1e", "nan", "NaN", "inf", "-inf", "Infinity", "1e400", "-1e400"]


def refused(kind: numbers.NumberType, text: str) -> numbers.NumberError:
    with pytest.raises(numbers.NumberError) as caught:
        kind(text)
    assert isinstance(caught.value, argparse.ArgumentTypeError)
    assert caught.value.value == text and caught.value.expected == kind.expected
    return caught.value


# ------------------------------------------------------------------------------------- the kinds


class TestKinds:
    def test_integer(self):
        kind = numbers.integer("the count")
        assert [kind(t) for t in ("7", "-2", "0", " 12 ", "+3", str(10**30))] == [7, -2, 0, 12, 3, 10**30]
        assert type(kind("7")) is int
        for text in [*NON_NUMBERS, "1.5", "7.0", "1e3"]:
            refused(kind, text)
        assert kind.expected == "the count, an integer"

    def test_positive_integer(self):
        kind = numbers.positive_integer("the frames")
        assert kind("1") == 1 and kind("300") == 300 and type(kind("4")) is int
        for text in [*NON_NUMBERS, "0", "-1", "1.5", "2.0"]:
            refused(kind, text)
        assert refused(kind, "0").line("--frames") == "--frames '0': expected the frames, an integer >= 1"
        bounded = numbers.positive_integer("the frames", maximum=numbers.FRAMES_MAX)
        assert bounded(str(2**24)) == 2**24
        for text in ("0", str(2**24 + 1), "9" * 400):
            refused(bounded, text)
        assert bounded.expected == "the frames, an integer 1..16777216"

    def test_non_negative_integer_with_a_maximum(self):
        kind = numbers.non_negative_integer("the seed", maximum=numbers.SEED_MAX)
        assert kind("0") == 0 and kind(str(numbers.SEED_MAX)) == 2**63 - 1
        for text in [*NON_NUMBERS, "-1", str(numbers.SEED_MAX + 1), "1.0", "9" * 5000]:
            refused(kind, text)
        assert kind.expected == "the seed, an integer 0..9223372036854775807"
        assert numbers.non_negative_integer()("5") == 5 and numbers.non_negative_integer().expected == "an integer >= 0"

    def test_positive_number(self):
        kind = numbers.positive_number("electrons per count")
        assert [kind(t) for t in ("2", "0.5", "1e-3", "5e-324", "1.7976931348623157e308")] == [
            2.0, 0.5, 1e-3, 5e-324, 1.7976931348623157e308]
        assert type(kind("2")) is float
        for text in [*NON_NUMBERS, "0", "-0.0", "-1"]:
            refused(kind, text)
        assert refused(kind, "nan").line("--gain") == "--gain 'nan': expected electrons per count, a finite number > 0"

    def test_non_negative_number(self):
        kind = numbers.non_negative_number()
        assert kind("0") == 0.0 and kind("-0.0") == 0.0 and kind("3.25") == 3.25
        for text in [*NON_NUMBERS, "-1", "-1e-300"]:
            refused(kind, text)
        assert kind.expected == "a finite number >= 0"

    def test_every_value_a_kind_accepts_is_finite(self):
        for kind in (numbers.positive_number(), numbers.non_negative_number()):
            for text in ("1e308", "1e-320", "0.1"):
                assert math.isfinite(kind(text))

    def test_the_other_layout_keeps_study_s_wording(self):
        kind = numbers.positive_integer(expected="a positive number of BFGS iterations", layout=numbers.EXPECTED_FIRST)
        assert refused(kind, "0").line("--max-steps") == "--max-steps: expected a positive number of BFGS iterations, got 0"

    def test_a_plain_argparse_parser_reports_it_as_a_usage_error(self, capsys):
        """Outside spherejax's parsers, a NumberError is an ordinary ArgumentTypeError."""
        parser = argparse.ArgumentParser(prog="tool")
        parser.add_argument("--gain", type=numbers.positive_number("electrons per count"))
        assert parser.parse_args(["--gain", "2"]).gain == 2.0
        with pytest.raises(SystemExit) as stopped:
            parser.parse_args(["--gain", "-2"])
        assert stopped.value.code == 2
        assert "tool: error: argument --gain: '-2': expected electrons per count, a finite number > 0" in capsys.readouterr().err


# --------------------------------------------------------------------------- the command line


def subcommand_parsers() -> dict[str, argparse.ArgumentParser]:
    parser = cli.build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


#: Every numeric option of every command -> its kind's text.
NUMERIC_OPTIONS = {
    ("demo", "--seed"): "an integer 0..9223372036854775807",
    ("simulate", "--seed"): "an integer 0..9223372036854775807",
    ("simulate", "--band-misregistration"): "a number 0..50",
    ("calibrate", "--gain"): "a number 0.0001..10000",
    ("calibrate", "--read-noise"): "a number 0..65536",
    ("calibrate", "--white-reflectance-u"): "a number 0..1",
    ("study", "--response-weight"): "a number 0..1e6",
    ("study", "--max-steps"): "an integer 1..100000",
    ("correct", "--workers"): "an integer",
    ("measure", "--gain"): "a number 0.0001..10000",
    ("measure", "--read-noise"): "a number 0..65536",
    ("measure", "--frames"): "an integer 1..16777216",
}


def test_every_numeric_option_has_a_number_type():
    found = {}
    for name, parser in subcommand_parsers().items():
        for action in parser._actions:
            assert action.type not in (int, float), (name, action.option_strings)
            if isinstance(action.type, numbers.NumberType):
                found[(name, action.option_strings[-1])] = action.type.kind
    assert found == NUMERIC_OPTIONS


def test_parsed_values_are_numbers_of_their_kind():
    parser = cli.build_parser()
    args = parser.parse_args(["calibrate", "s", "-o", "c.h5", "--gain", "2.5", "--read-noise", "0", "--white-reflectance-u", "3e-3"])
    assert (args.gain, args.read_noise, args.white_reflectance_u) == (2.5, 0.0, 0.003)
    args = parser.parse_args(["measure", "-c", "c.h5", "i.tif", "--region", "a=0,1,0,1", "--frames", "4"])
    assert args.frames == 4 and type(args.frames) is int and args.gain is None
    args = parser.parse_args(["study", "s"])
    assert (args.response_weight, args.max_steps) == (0.01, 300)  # the defaults, not parsed
    assert parser.parse_args(["simulate", "-o", "s", "--seed", "12"]).seed == 12


def run(argv, capsys):
    status = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def assert_one_line(status, out, err, expected_line):
    assert status == cli.EXIT_BAD_INPUT
    assert out == "" and "Traceback" not in err
    assert err.splitlines() == [expected_line], err


#: One bad value per kind through `spherejax`, and the whole line it gets.
BY_KIND = [
    ("integer", ["correct", "-c", "{t}/cal.h5", "{t}/in", "-o", "{t}/out", "--workers", "two"],
     ("spherejax: error: --workers 'two': expected the number of worker processes (1..the cores this process may use), "
      "an integer")),
    ("positive-integer", ["measure", "-c", "{t}/cal.h5", "{t}/in.tif", "--region", "a=0,1,0,1", "--frames", "0"],
     "spherejax: error: --frames '0': expected the sample frames averaged, an integer 1..16777216"),
    ("non-negative-integer", ["simulate", "-o", "{t}/session", "--seed", "-7"],
     "spherejax: error: --seed '-7': expected the simulation's seed, an integer 0..9223372036854775807"),
    ("positive-number", ["calibrate", "{t}/session", "-o", "{t}/cal.h5", "--gain", "inf"],
     "spherejax: error: --gain 'inf': expected electrons per count, a number 0.0001..10000"),
    ("non-negative-number", ["calibrate", "{t}/session", "-o", "{t}/cal.h5", "--read-noise", "-0.5"],
     "spherejax: error: --read-noise '-0.5': expected one frame's read noise in counts rms, a number 0..65536"),
    ("study-layout", ["study", "{t}/session", "--response-weight", "nan"],
     "spherejax: error: --response-weight: expected a value 0..1e6, got nan"),
]


@pytest.mark.parametrize(("argv", "line"), [case[1:] for case in BY_KIND], ids=[case[0] for case in BY_KIND])
def test_a_bad_number_is_one_line_and_exit_status_2(tmp_path, capsys, argv, line):
    """Refused by the parser, before any file is looked at: nothing in tmp_path is read or made."""
    argv = [part.format(t=tmp_path) for part in argv]
    assert_one_line(*run(argv, capsys), line)
    assert list(tmp_path.iterdir()) == []


def test_the_option_may_come_with_an_equals_sign_and_global_options(tmp_path, capsys):
    argv = ["-q", "calibrate", tmp_path / "session", "-o", tmp_path / "cal.h5", "--gain=", "-v"]
    assert_one_line(*run(argv, capsys), "spherejax: error: --gain '': expected electrons per count, a number 0.0001..10000")


def test_a_control_character_in_the_value_stays_on_the_line(tmp_path, capsys):
    argv = ["study", tmp_path / "session", "--max-steps", "1\n2"]
    assert_one_line(*run(argv, capsys), "spherejax: error: --max-steps: expected a positive number of BFGS iterations, at most 100000, got 1\\n2")


def test_usage_errors_stay_argparse_s(capsys):
    """Only numbers change: a missing argument is still a usage error (SystemExit, its prefix)."""
    with pytest.raises(SystemExit) as stopped:
        cli.main(["calibrate", "--gain", "2"])
    assert stopped.value.code == cli.EXIT_BAD_INPUT
    assert capsys.readouterr().err.startswith("spherejax calibrate: error: the following arguments are required")


def test_the_parser_alone_exits_with_status_2(capsys):
    """`build_parser().parse_args` used without `main` (scripts, the layers test) still exits 2
    after the one line, as argparse does."""
    with pytest.raises(SystemExit) as stopped:
        cli.build_parser().parse_args(["study", "s", "--max-steps", "-3"])
    assert stopped.value.code == 2 and isinstance(stopped.value, numbers.BadNumber)
    assert capsys.readouterr().err == "spherejax: error: --max-steps: expected a positive number of BFGS iterations, at most 100000, got -3\n"


def test_python_dash_m_spherejax_refuses_a_bad_number_in_one_line(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "spherejax", "measure", "-c", str(tmp_path / "cal.h5"), str(tmp_path / "in.tif"),
         "--region", "a=0,1,0,1", "--gain", "1e400"],
        capture_output=True, text=True, timeout=180,
    )
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr == "spherejax: error: --gain '1e400': expected electrons per count, a number 0.0001..10000\n"


def test_number_in_bounds_both_ends():
    kind = numbers.number_in("electrons per count", minimum=numbers.GAIN_MIN, maximum=numbers.GAIN_MAX)
    assert kind("0.0001") == 1e-4 and kind("10000") == 1e4 and kind("2.5") == 2.5
    for text in [*NON_NUMBERS, "0", "-1", "9.9e-5", "10000.01", "1e308"]:
        refused(kind, text)
    assert kind.expected == "electrons per count, a number 0.0001..10000"
    assert numbers.shown(1e6) == "1e6" and numbers.shown(65536.0) == "65536" and numbers.shown(1e-4) == "0.0001"
