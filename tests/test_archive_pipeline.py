"""The in-process batch's pipeline (`spherejax.archive.batch._in_process`): inputs under way in
threads at once, results in input order, a stop with inputs under way, a consumer that stops
early; and the per-stage times the benchmark reads (`spherejax.archive.stage_times`)."""

from __future__ import annotations

import pathlib
import threading
import time

import numpy as np
import pytest

from spherejax import archive, interrupt, io
from spherejax.archive import batch, outputs, stage_times

from .batch_support import NAMES, frame, manifest_records, outputs_of, run


@pytest.fixture
def rng():
    return np.random.default_rng(5)


def inputs_in(folder, rng, count):
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(count):
        io.write_frame(folder / f"f{k}.tif", frame(rng), channel_names=NAMES)
    return folder


class Recorder:
    """Stands in for `correct_input`: records how many inputs were under way at once, takes
    `delays[name]` seconds (the first input slowest, so that order must be restored), and
    returns the result of the real `correct_input`."""

    def __init__(self, real, delays):
        self.real, self.delays = real, delays
        self.lock = threading.Lock()
        self.running = 0
        self.most = 0
        self.threads = set()

    def __call__(self, spec, *args, **kwargs):
        with self.lock:
            self.running += 1
            self.most = max(self.most, self.running)
            self.threads.add(threading.current_thread().name)
        try:
            time.sleep(self.delays.get(spec.name, 0.0))
            return self.real(spec, *args, **kwargs)
        finally:
            with self.lock:
                self.running -= 1


def test_two_inputs_are_under_way_at_once_and_results_keep_input_order(cal, tmp_path, rng, monkeypatch, capsys):
    """With the first input slowest, the second is corrected meanwhile (two at once, in threads)
    and the manifest still lists the inputs in order; the outputs are those of one at a time."""
    source = inputs_in(tmp_path / "in", rng, 4)
    recorder = Recorder(batch.correct_input, {"in/f0": 0.6})
    monkeypatch.setattr(batch, "correct_input", recorder)
    status, _, err = run(["correct", "-c", str(cal), str(source), "-o", str(tmp_path / "out")], capsys)
    assert status == 0, err
    assert recorder.most == batch.INPUTS_IN_FLIGHT == 2
    assert all(name.startswith("spherejax-input") for name in recorder.threads)
    assert [record["name"] for record in manifest_records(tmp_path / "out")] == ["in/f0", "in/f1", "in/f2", "in/f3"]
    monkeypatch.setattr(batch, "INPUTS_IN_FLIGHT", 1)
    monkeypatch.setattr(batch, "correct_input", recorder.real)
    status, _, err = run(["correct", "-c", str(cal), str(source), "-o", str(tmp_path / "one")], capsys)
    assert status == 0, err
    assert outputs_of(tmp_path / "out") == outputs_of(tmp_path / "one")


def test_a_stop_with_two_inputs_under_way_records_the_one_that_finished(cal, tmp_path, rng, monkeypatch):
    """A stop asked for while f0 is being written and f1 is done: f1 (finished) is yielded and
    recorded, f0 stops at its next safe point leaving nothing, no later input starts, and the
    stop is raised only once no thread is still working."""
    source = inputs_in(tmp_path / "in", rng, 4)
    out = tmp_path / "out"
    real = batch.correct_input
    f1_done = threading.Event()
    started = []

    def slow_first(spec, *args, **kwargs):
        started.append(spec.name)
        if spec.name == "in/f0":
            f1_done.wait(10)
            interrupt._pending = 15  # SIGTERM arrives while f0 is under way (as the handler records it)
        result = real(spec, *args, **kwargs)
        if spec.name == "in/f1":
            f1_done.set()
        return result

    monkeypatch.setattr(batch, "correct_input", slow_first)
    monkeypatch.setattr(interrupt, "_active", True)
    try:
        with pytest.raises(interrupt.Interrupted) as stopped:
            archive.run_batch([source], out, cal)
    finally:
        interrupt._pending = None
    assert started == ["in/f0", "in/f1"]
    assert stopped.value.done == 1 and stopped.value.total == 4
    assert [record["name"] for record in manifest_records(out)] == ["in/f1"]
    assert sorted(p.name for p in out.rglob("f*")) == sorted(f"f1.{kind}" for kind in archive.OUTPUT_KINDS)
    assert not [t for t in threading.enumerate() if t.name.startswith("spherejax-input")]


def test_a_consumer_that_stops_early_waits_for_the_inputs_under_way(cal, tmp_path, rng, monkeypatch):
    """Closing the results early (an error in the code that writes the manifest) returns only
    once the inputs under way are finished: no thread writes into OUT after the lock is gone."""
    source = inputs_in(tmp_path / "in", rng, 3)
    specs = archive.discover_inputs([source], tmp_path / "out")
    (tmp_path / "out").mkdir()
    finished = []
    real = batch.correct_input

    def slow(spec, *args, **kwargs):
        time.sleep(0.3 if spec.name == "in/f1" else 0.0)
        result = real(spec, *args, **kwargs)
        finished.append(spec.name)
        return result

    monkeypatch.setattr(batch, "correct_input", slow)
    results = batch._in_process(specs, tmp_path / "out", cal, {})
    first, _ = next(results)
    assert first.name == "in/f0"
    results.close()  # f1 was under way
    assert "in/f1" in finished
    assert not [t for t in threading.enumerate() if t.name.startswith("spherejax-input")]


def test_a_folder_made_meanwhile_by_another_input_is_used_not_refused(tmp_path, monkeypatch):
    """Two inputs of one folder started at once both found OUT/in missing and both made it: the
    second failed, "OUT/in: cannot be created: File exists" (the clean-clone CI run, with two
    inputs under way). A folder made between the look and the mkdir is used as found, and is not
    this input's to remove."""
    out = tmp_path / "out"
    out.mkdir()
    real_exists = pathlib.Path.exists
    raced = []

    def exists_then_made_by_another(path):
        if path == out.resolve() / "in" and not raced:
            raced.append(path)
            path.mkdir()  # the other input makes it right after this one looked
            return False
        return real_exists(path)

    monkeypatch.setattr(pathlib.Path, "exists", exists_then_made_by_another)
    folder, created = outputs.output_folder(out, "in/a")
    assert raced and folder == out.resolve() / "in" and created == []
    outputs.release_folder(out, "in/a")


def test_a_failed_input_leaves_a_folder_another_input_is_using(tmp_path):
    """The folder an input made is removed when it fails only while no other input under way
    uses it: the other has not written into it yet and would find it gone."""
    out = tmp_path / "out"
    out.mkdir()
    _, made_by_a = outputs.output_folder(out, "in/a")
    _, made_by_b = outputs.output_folder(out, "in/b")
    assert made_by_a == [out.resolve() / "in"] and made_by_b == []
    outputs.release_folder(out, "in/a")  # a fails
    outputs.remove_empty_folders(made_by_a)
    assert (out / "in").is_dir()  # b is still under way
    outputs.release_folder(out, "in/b")  # b fails too
    outputs.remove_empty_folders(made_by_a)
    assert not (out / "in").exists()


def test_stage_times_add_up_and_name_every_stage(cal, tmp_path, rng):
    """Each input's record names the stages of the package docstring, every one positive, and
    they add up to no more than the input's own time (stages are exclusive)."""
    source = inputs_in(tmp_path / "in", rng, 2)
    with stage_times.collecting() as records:
        archive.run_batch([source], tmp_path / "out", cal)
    assert sorted(record["name"] for record in records) == ["in/f0", "in/f1"]
    expected = {"hash", "read", "correct", "preview"} | {
        f"{step} {kind}" for step in ("encode", "commit") for kind in archive.OUTPUT_KINDS
    }
    for record in records:
        assert set(record["stages"]) == expected
        assert all(seconds > 0 for seconds in record["stages"].values())
        assert sum(record["stages"].values()) <= record["seconds"]


def test_stage_times_cost_nothing_outside_collecting():
    """Outside `collecting`, a stage records nothing anywhere."""
    with stage_times.input_record("x"), stage_times.stage("read"):
        pass
    with stage_times.collecting() as records:
        pass
    assert records == []
