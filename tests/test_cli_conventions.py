"""The command line's conventions, as a new user meets them: help, version, `python -m`, global
options in either position, -o/--out everywhere (old spellings still working), messages through
logging with a log file spherejax owns, progress, honest reruns of `demo`, `calibrate --force`.
"""

import argparse
import io as text_io
import json
import logging
import os
import pathlib
import shutil
import subprocess
import sys
import threading
import time

import pytest

import spherejax
from spherejax import cli, console, io, simulate
from tests.helpers import SMALL

COMMANDS = ("demo", "simulate", "twin", "calibrate", "evaluate", "study", "correct", "acquire", "measure")


def run(argv, capsys):
    status = cli.main(argv)
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def one_error_line(status, err, *fragments):
    assert status == cli.EXIT_BAD_INPUT
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def snapshot(folder: pathlib.Path) -> dict:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def subcommand_parsers() -> dict[str, argparse.ArgumentParser]:
    parser = cli.build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


class TestTheEntryPoints:
    def test_version(self):
        result = subprocess.run([sys.executable, "-m", "spherejax", "--version"], capture_output=True, text=True, timeout=120)
        assert result.returncode == 0 and result.stderr == ""
        words = result.stdout.split()
        assert words[:2] == ["spherejax", spherejax.__version__]
        assert "jax" in result.stdout and "Python" in result.stdout

    def test_python_dash_m_runs_a_command_with_one_line_errors(self, tmp_path):
        result = subprocess.run(
            [sys.executable, "-m", "spherejax", "calibrate", str(tmp_path / "nowhere"), "-o", str(tmp_path / "c.h5")],
            capture_output=True, text=True, timeout=120,
        )
        assert result.returncode == 2
        assert result.stderr.startswith("spherejax: error: ") and len(result.stderr.splitlines()) == 1
        assert "nowhere" in result.stderr and not (tmp_path / "c.h5").exists()

    def test_a_bare_spherejax_prints_help(self, capsys):
        status, out, err = run([], capsys)
        assert status == 0 and err == ""
        assert out.startswith("usage: spherejax")
        for command in COMMANDS:
            assert f"\n    {command} " in out, command

    def test_usage_errors_are_one_line(self, capsys):
        with pytest.raises(SystemExit) as stopped:
            cli.main(["correct", "-c", "cal.h5"])
        assert stopped.value.code == cli.EXIT_BAD_INPUT
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1, err
        assert err.startswith("spherejax correct: error: ") and "INPUT" in err and "--help" in err

    def test_an_unknown_command_is_one_line(self, capsys):
        with pytest.raises(SystemExit) as stopped:
            cli.main(["corect"])
        assert stopped.value.code == cli.EXIT_BAD_INPUT
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "'corect'" in err


class TestHelp:
    def test_every_command_has_a_description_examples_and_help_for_every_argument(self):
        parsers = subcommand_parsers()
        assert set(COMMANDS) <= set(parsers)
        for name, parser in parsers.items():
            assert parser.description and len(parser.description) > 120, name
            assert parser.epilog and parser.epilog.startswith("examples:") and f"spherejax {name}" in parser.epilog, name
            for action in parser._actions:
                assert action.help and action.help != argparse.SUPPRESS, (name, action.dest)

    def test_every_command_names_its_output_with_dash_o_and_dash_dash_out(self):
        for name, parser in subcommand_parsers().items():
            if name == "measure" or name in COMMANDS:
                options = {s for a in parser._actions for s in a.option_strings}
                assert {"-o", "--out"} <= options, name

    def test_old_spellings_are_marked_deprecated_in_help(self):
        parsers = subcommand_parsers()
        for name in ("calibrate", "correct", "measure", "acquire"):
            text = parsers[name].format_help()
            assert "--output" in text and "deprecated" in text, name
        assert "OUT" in parsers["simulate"].format_help() and "deprecated" in parsers["simulate"].format_help()

    def test_the_estimator_choices_are_the_librarys(self):
        from spherejax.estimation import ESTIMATOR_NAMES

        assert cli.WIENER_METHODS == ESTIMATOR_NAMES
        action = next(a for a in subcommand_parsers()["calibrate"]._actions if a.dest == "wiener_method")
        assert tuple(action.choices) == ESTIMATOR_NAMES

    def test_global_options_are_listed_on_every_command(self):
        for name, parser in subcommand_parsers().items():
            text = parser.format_help()
            for option in ("-q, --quiet", "-v, --verbose", "--log-file FILE"):
                assert option in text, (name, option)


class TestGlobalOptionsInEitherPosition:
    @pytest.mark.parametrize("argv", [
        ["-q", "calibrate", "S", "-o", "C"], ["calibrate", "S", "-o", "C", "-q"], ["calibrate", "-q", "S", "-o", "C"],
    ])
    def test_quiet(self, argv):
        assert cli.build_parser().parse_args(argv).quiet is True

    @pytest.mark.parametrize("argv", [["-v", "correct", "-c", "C", "I", "-o", "O"], ["correct", "-c", "C", "I", "-o", "O", "-v"]])
    def test_verbose(self, argv):
        assert cli.build_parser().parse_args(argv).verbose == 1

    @pytest.mark.parametrize("argv", [["--log-file", "L", "simulate", "-o", "S"], ["simulate", "-o", "S", "--log-file", "L"]])
    def test_log_file(self, argv):
        assert cli.build_parser().parse_args(argv).log_file == "L"

    def test_defaults_when_absent(self):
        args = cli.build_parser().parse_args(["simulate", "-o", "S"])
        assert (args.quiet, args.verbose, args.log_file) == (False, 0, None)

    def test_quiet_after_the_command_silences_progress(self, workspace, tmp_path, capsys):
        status, out, err = run(["calibrate", str(workspace / "session"), "-o", str(tmp_path / "c.h5"), "-q"], capsys)
        assert status == 0 and out == "" and err == ""
        status, out, err = run(["calibrate", str(workspace / "session"), "-o", str(tmp_path / "d.h5")], capsys)
        assert status == 0 and "[1/1] calibrating" in err and "reflectance estimator" in out

    def test_verbose_after_the_command_shows_debug_lines(self, workspace, tmp_path, capsys):
        status, _, err = run(["calibrate", str(workspace / "session"), "-o", str(tmp_path / "c.h5"), "-v"], capsys)
        assert status == 0
        assert f"spherejax {spherejax.__version__} (Python" in err and "command line: spherejax calibrate" in err


class TestOutputSpellings:
    def test_simulate_with_dash_o_and_with_the_old_positional(self, tmp_path, capsys, monkeypatch):
        monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)
        assert run(["-q", "simulate", "-o", str(tmp_path / "a"), "--seed", "3"], capsys)[0] == 0
        status, _, err = run(["simulate", str(tmp_path / "b"), "--seed", "3"], capsys)
        assert status == 0 and "deprecated" not in err  # the old spelling works, quietly
        a, b = io.load_session(tmp_path / "a"), io.load_session(tmp_path / "b")
        assert [f.id for f in a.frames] == [f.id for f in b.frames]

    def test_simulate_refuses_two_folders_and_none(self, tmp_path, capsys):
        one_error_line(*run(["simulate", str(tmp_path / "a"), "-o", str(tmp_path / "b")], capsys)[::2], "given twice")
        one_error_line(*run(["simulate"], capsys)[::2], "-o/--out")
        assert list(tmp_path.iterdir()) == []

    def test_the_old_spelling_is_said_at_debug_level(self, workspace, tmp_path, capsys):
        status, _, err = run(["-v", "calibrate", str(workspace / "session"), "--output", str(tmp_path / "c.h5")], capsys)
        assert status == 0 and "--output is the old spelling of -o/--out" in err
        assert io.open_calibration(tmp_path / "c.h5") is not None

    def test_evaluate_takes_dash_o(self, workspace, tmp_path, capsys):
        out = tmp_path / "e"
        status, _, _ = run(["-q", "evaluate", str(workspace / "session"), "-c", str(workspace / "cal.h5"), "-o", str(out)], capsys)
        assert status == 0 and (out / "metrics.json").exists()


class TestLogFile:
    def test_written_appended_and_timestamped(self, workspace, tmp_path, capsys):
        log = tmp_path / "run.log"
        argv = ["calibrate", str(workspace / "session"), "-o", str(tmp_path / "c.h5"), "--log-file", str(log)]
        assert run(argv, capsys)[0] == 0
        first = log.read_text().splitlines()
        assert console.not_a_log(log) is None
        assert any("INFO spherejax.cli: [1/1] calibrating" in line for line in first)
        assert any("DEBUG spherejax.cli: spherejax" in line for line in first)  # debug lines go to the file
        # an error goes there too, and the second run appends
        status, _, err = run(["--log-file", str(log), "calibrate", str(tmp_path / "nowhere"), "-o", str(tmp_path / "d.h5")], capsys)
        one_error_line(status, err, "nowhere")
        second = log.read_text().splitlines()
        assert second[:len(first)] == first
        assert any(line.endswith(err.strip()) and " ERROR spherejax.cli: " in line for line in second[len(first):])

    def test_a_file_of_the_users_is_refused_and_left_as_it_was(self, tmp_path, capsys):
        notes = tmp_path / "notes.txt"
        notes.write_text("my lab notes\n")
        before = snapshot(tmp_path)
        status, _, err = run(["simulate", "-o", str(tmp_path / "s"), "--log-file", str(notes)], capsys)
        one_error_line(status, err, str(notes), "not a spherejax log")
        assert snapshot(tmp_path) == before

    def test_a_folder_a_link_and_a_missing_folder_are_refused(self, tmp_path, capsys):
        (tmp_path / "folder").mkdir()
        (tmp_path / "target.log").write_text("")
        (tmp_path / "link.log").symlink_to(tmp_path / "target.log")
        for path, fragment in ((tmp_path / "folder", "folder"), (tmp_path / "link.log", "link"),
                               (tmp_path / "no" / "run.log", "does not exist")):
            before = snapshot(tmp_path)
            status, _, err = run(["simulate", "-o", str(tmp_path / "s"), "--log-file", str(path)], capsys)
            one_error_line(status, err, str(path), fragment)
            assert snapshot(tmp_path) == before

    def test_a_fifo_is_refused_without_waiting(self, tmp_path, capsys):
        fifo = tmp_path / "pipe.log"
        os.mkfifo(fifo)
        result = {}
        worker = threading.Thread(target=lambda: result.update(
            status=cli.main(["simulate", "-o", str(tmp_path / "s"), "--log-file", str(fifo)])))
        worker.start()
        worker.join(60)
        assert not worker.is_alive() and result["status"] == cli.EXIT_BAD_INPUT
        assert "FIFO" in capsys.readouterr().err
        assert not (tmp_path / "s").exists()


class TestMessages:
    def test_another_modules_records_say_whose_and_what(self, capsys):
        with console.configured():
            logging.getLogger("spherejax._engine.fused").warning("the fused kernel is not built")
            logging.getLogger("spherejax_hw.shutter").info("closed")
            logging.getLogger("spherejax_hw.serialline").debug("hidden at the default level")
            console.say("spherejax: [1/2] a line of the command line's own")
        err = capsys.readouterr().err.splitlines()
        assert err == ["spherejax: warning: the fused kernel is not built", "spherejax: closed",
                       "spherejax: [1/2] a line of the command line's own"]

    def test_quiet_keeps_warnings_and_errors_only(self, capsys):
        with console.configured(quiet=True):
            console.say("progress")
            console.warn("a warning")
            console.say("spherejax: error: an error", logging.ERROR)
        assert capsys.readouterr().err.splitlines() == ["spherejax: warning: a warning", "spherejax: error: an error"]

    def test_handlers_are_removed_afterwards(self, capsys):
        with console.configured():
            pass
        console.say("after the command")
        assert "after the command" not in capsys.readouterr().err
        assert all(not logging.getLogger(name).handlers for name in console.LOGGER_NAMES)


class TestProgress:
    def test_plain_lines_off_a_terminal(self, capsys):
        with console.configured(), console.Steps(2) as steps:
            steps.start("first")
            steps.done("detail")
            steps.start("second")
            steps.done()
        err = capsys.readouterr().err.splitlines()
        assert err[0] == "[1/2] first ..." and err[1].startswith("      done in ") and err[1].endswith("s (detail)")
        assert err[2] == "[2/2] second ..."

    def test_steps_without_lines_log_at_debug_only(self, capsys):
        with console.configured(), console.Steps(1, lines=False) as steps:
            steps.start("measuring")
            steps.done()
        assert capsys.readouterr().err == ""
        with console.configured(verbose=1), console.Steps(1, lines=False) as steps:
            steps.start("measuring")
            steps.done()
        assert capsys.readouterr().err.splitlines()[0] == "[1/1] measuring ..."

    def test_announced_steps_must_all_run(self):
        with pytest.raises(RuntimeError, match="announced 3 steps, ran 2"):
            with console.Steps(3, quiet=True) as steps:
                steps.start("one")
                steps.start("two")

    def test_a_bar_that_moves_on_a_terminal(self, monkeypatch):
        """A step of one long call shows its elapsed time while it runs, redrawn from a thread."""
        screen = text_io.StringIO()
        monkeypatch.setattr(console, "on_terminal", lambda: True)
        monkeypatch.setattr(sys, "stderr", screen)
        with console.configured(), console.Steps(1) as steps:
            steps.start("a long call")
            time.sleep(1.6)
            steps.done()
        text = screen.getvalue()
        assert "[1/1] a long call ..." in text and "done in 1." in text
        redraws = [part for part in text.split("\r") if part.startswith("[1/1] 00:0")]
        assert len(redraws) >= 3, text  # drawn at the start and ticked while the call ran
        assert "[1/1] 00:01" in text

    def test_study_announces_every_step_it_runs(self, workspace, tmp_path, capsys):
        status, _, err = run(["study", str(workspace / "session"), "-c", str(workspace / "cal.h5"), "-o",
                              str(tmp_path / "s"), "--max-steps", "2"], capsys)
        assert status == 0
        announced = [line.split("]")[0] + "]" for line in err.splitlines() if line.startswith("[")]
        assert announced == ["[1/3]", "[2/3]", "[3/3]"], err


class TestHonestReruns:
    def test_demo_refuses_a_session_of_another_seed(self, workspace, tmp_path, capsys, monkeypatch):
        monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)
        shutil.copytree(workspace / "session", tmp_path / "demo" / "session")  # seed 5
        before = snapshot(tmp_path)
        status, out, err = run(["demo", "-o", str(tmp_path / "demo"), "--seed", "6"], capsys)
        one_error_line(status, err, str(tmp_path / "demo" / "session"), "seed 5", "seed 6")
        assert out == "" and snapshot(tmp_path) == before

    def test_demo_refuses_another_design_and_another_version(self, workspace, tmp_path, capsys, monkeypatch):
        shutil.copytree(workspace / "session", tmp_path / "demo" / "session")
        session = io.load_session(tmp_path / "demo" / "session")
        assert "design" in cli.demo_session_differs(session, 5)  # the SMALL design is not the default
        monkeypatch.setattr(simulate, "ExperimentDesign", lambda: SMALL)
        assert cli.demo_session_differs(session, 5) is None
        monkeypatch.setattr(spherejax, "__version__", "99.0")
        assert "spherejax 99.0" in cli.demo_session_differs(session, 5)

    def test_demo_refuses_a_session_that_was_not_simulated(self, workspace, tmp_path, capsys):
        target = tmp_path / "demo" / "session"
        shutil.copytree(workspace / "session", target)
        manifest = json.loads((target / "manifest.json").read_text())
        del manifest["metadata"]["simulator"]
        (target / "manifest.json").write_text(json.dumps(manifest))
        status, _, err = run(["demo", "-o", str(tmp_path / "demo"), "--seed", "5"], capsys)
        one_error_line(status, err, "not a simulated session")

    def test_calibrate_replaces_a_calibration_only_with_force(self, workspace, tmp_path, capsys):
        cal = tmp_path / "c.h5"
        shutil.copy(workspace / "cal.h5", cal)
        before = cal.read_bytes()
        status, _, err = run(["calibrate", str(workspace / "session"), "-o", str(cal)], capsys)
        one_error_line(status, err, str(cal), "--force")
        assert cal.read_bytes() == before
        status, _, _ = run(["-q", "calibrate", str(workspace / "session"), "-o", str(cal), "--force"], capsys)
        assert status == 0 and cal.read_bytes() != before
        io.open_calibration(cal).close()

    def test_force_never_replaces_a_file_that_is_not_a_calibration(self, workspace, tmp_path, capsys):
        notes = tmp_path / "notes.h5"
        notes.write_bytes(b"not a calibration")
        status, _, err = run(["calibrate", str(workspace / "session"), "-o", str(notes), "--force"], capsys)
        one_error_line(status, err, str(notes), "not a spherejax calibration")
        assert notes.read_bytes() == b"not a calibration"


def test_a_torn_compilation_cache_entry_says_nothing_on_stderr(capsys):
    """JAX's warning about a torn persistent-cache entry (left by a process killed mid-write;
    it recompiles) is not printed: in a clean-clone CI run it broke `correct`'s one-line stop
    message. Any other warning still reaches the suite's warnings-as-errors filter."""
    import argparse
    import warnings

    from spherejax.cli import run

    def command(args):
        warnings.warn("Error reading persistent compilation cache entry for 'jit_stage': error: Error -5 while "
                      "decompressing data: incomplete or truncated stream", UserWarning)
        return 0

    assert run._run(argparse.Namespace(run=command)) == 0
    assert capsys.readouterr().err == ""

    def other(args):
        warnings.warn("something else", UserWarning)
        return 0

    with pytest.raises(UserWarning, match="something else"):
        run._run(argparse.Namespace(run=other))
