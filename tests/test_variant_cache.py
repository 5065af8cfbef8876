"""The fused kernel's variant timings kept once per machine (spherejax/_engine/variant_cache.py):
every process reads the same timings, so every run on a machine runs the same variant and gives
the same bits."""

import json
import os
import threading
import time

import pytest

from spherejax._engine import fused, fused_variants, variant_cache

SUPPORTED = ("avx512", "avx2", "generic")


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv(variant_cache.CACHE_DIR, str(tmp_path / "cache"))
    return tmp_path / "cache"


def counting(times):
    calls = []

    def measure():
        calls.append(1)
        return dict(times)

    return measure, calls


def test_measured_once_and_read_after(folder):
    measure, calls = counting({"avx512": 2e-3, "avx2": 1.5e-3, "generic": 3e-3})
    first = variant_cache.timings("machine A", SUPPORTED, measure)
    again = variant_cache.timings("machine A", SUPPORTED, lambda: pytest.fail("measured twice"))
    assert first == again == {"avx512": 2e-3, "avx2": 1.5e-3, "generic": 3e-3} and calls == [1]
    stored = json.loads((folder / variant_cache.FILE_NAME).read_text())
    assert stored["format"] == variant_cache.FORMAT and stored["machines"]["machine A"] == first
    # another machine key (another CPU, another build) measures anew and keeps both
    other = variant_cache.timings("machine B", ("avx2", "generic"), lambda: {"avx2": 1.0, "generic": 2.0})
    assert other == {"avx2": 1.0, "generic": 2.0}
    assert set(json.loads((folder / variant_cache.FILE_NAME).read_text())["machines"]) == {"machine A", "machine B"}
    assert [p.name for p in folder.iterdir() if p.name.endswith(".tmp")] == []


def test_processes_starting_together_wait_for_one_measurement(folder):
    calls, results = [], []

    def slow():
        calls.append(1)
        time.sleep(0.3)
        return {"avx512": 1.0 + len(calls), "avx2": 5.0, "generic": 9.0}  # another answer each time

    threads = [threading.Thread(target=lambda: results.append(variant_cache.timings("m", SUPPORTED, slow)))
               for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert calls == [1] and all(r == results[0] for r in results)


@pytest.mark.parametrize("what", ["foreign file", "link", "folder", "not json"])
def test_a_file_spherejax_did_not_write_is_left_alone(folder, tmp_path, what):
    folder.mkdir(parents=True)
    path = folder / variant_cache.FILE_NAME
    target = tmp_path / "theirs.json"
    target.write_text('{"format": "someone else"}')
    if what == "foreign file":
        path.write_text('{"format": "someone else", "machines": {}}')
    elif what == "link":
        path.symlink_to(target)
    elif what == "folder":
        path.mkdir()
    else:
        path.write_text("not json")
    before = path.read_bytes() if path.is_file() else None
    assert variant_cache.timings("m", SUPPORTED, lambda: pytest.fail("measured")) is None
    assert target.read_text() == '{"format": "someone else"}'
    if before is not None:
        assert path.read_bytes() == before


def test_an_unusable_folder_measures_nothing(tmp_path, monkeypatch):
    blocked = tmp_path / "file"
    blocked.write_text("x")
    monkeypatch.setenv(variant_cache.CACHE_DIR, str(blocked / "cache"))  # a file where a folder must be
    assert variant_cache.timings("m", SUPPORTED, lambda: pytest.fail("measured")) is None


def test_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv(variant_cache.CACHE_DIR, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert variant_cache.cache_folder() == tmp_path / "spherejax"
    monkeypatch.setenv(variant_cache.CACHE_DIR, str(tmp_path / "x"))
    assert variant_cache.cache_folder() == tmp_path / "x"


def test_the_machine_key_names_the_cpu_the_variants_and_the_version():
    key = variant_cache.machine_key(("avx2", "generic"), "1.2.3")
    assert key.endswith("| runs avx2,generic | spherejax 1.2.3")
    with open("/proc/cpuinfo") as cpuinfo:
        model = next(line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name"))
    assert model in key


@pytest.mark.skipif(not fused.built(), reason="the fused kernel was not built here")
def test_the_kernel_reads_the_kept_timings_in_a_new_process(folder, monkeypatch):
    """Every process of a machine chooses from the same timings: a fresh process's choice is
    the one the kept timings give, without measuring."""
    import subprocess
    import sys

    kept = {name: 1.0 for name in fused.supported_variants()}
    kept["generic"] = 0.5  # clearly fastest: chosen wherever it is kept
    key = variant_cache.machine_key(fused.supported_variants(), fused_variants._spherejax_version())
    folder.mkdir(parents=True)
    (folder / variant_cache.FILE_NAME).write_text(json.dumps({"format": variant_cache.FORMAT, "machines": {key: kept}}))
    code = ("from spherejax._engine import fused\n"
            "fused.measure_variants = lambda *a, **k: (_ for _ in ()).throw(AssertionError('measured'))\n"
            "print(fused.measurement().auto)")
    env = {**os.environ, variant_cache.CACHE_DIR: str(folder)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "generic"
