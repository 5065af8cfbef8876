"""Helpers of the hw driver tests: golden transcripts through a scripted port, the pty
resources an emulated port must give back, and an instrument profile and emulated acquisition
(tests/hw/test_acquire.py, tests/robustness/)."""

from __future__ import annotations

import os
import pathlib
import threading

import serial

from spherejax_hw import acquire
from spherejax_hw.emulators import ScriptedPort


def scripted(monkeypatch, script, url: str) -> ScriptedPort:
    """Make `serial.serial_for_url` open a ScriptedPort that plays `script` ((write, reply) pairs)."""
    port = ScriptedPort(script, url=url)
    monkeypatch.setattr(serial, "serial_for_url", port.serial_for_url)
    return port


def transcript(script):
    """The expected ScriptedPort transcript for a script: each write followed by its whole reply."""
    out = []
    for written, answered in script:
        out.append(("write", written))
        if answered:
            out.append(("read", answered))
    return out


def pty_resources() -> tuple[set[str], set[str]]:
    """Open pseudo-terminal fds of this process and running EmulatedPort server threads."""
    fds = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:  # closed between listdir and readlink
            continue
        if target.startswith(("/dev/pts/", "/dev/ptmx")):
            fds.add(f"{fd}->{target}")
    threads = {t.name for t in threading.enumerate() if t.name.startswith("EmulatedPort")}
    return fds, threads


# --- an emulated acquisition (tests/hw/test_acquire.py, tests/robustness/) ---------------------

BANDS = list(range(400, 701, 20))
SAMPLES = ("train-bg00-g0", "test-bg01-g1")


def write_profile(folder: pathlib.Path, *, samples=SAMPLES, extra: str = "", move_timeout_s: float = 3.0) -> pathlib.Path:
    lines = ["[instrument]", 'id = "sphere-1"']
    for name, port in (("a", "/dev/ttyUSB0"), ("b", "/dev/ttyUSB1")):
        lines += [f"[wheels.{name}]", f'port = "{port}"', 'model = "FW212C"', "open_slot = 12", f"move_timeout_s = {move_timeout_s}"]
    lines += ["[shutter]", 'port = "/dev/ttyUSB2"', 'model = "SC10"', "[camera]", 'backend = "sim"', "[bands]"]
    lines += [f'{nm} = ["{"a" if i < 8 else "b"}", {i % 8 + 1}]' for i, nm in enumerate(BANDS)]
    lines += ["[acquisition]", "frames_averaged = 2", "dark_frames = 2", "warmup_checks = 2"]
    for sample in samples:
        set_name = "training" if sample.startswith("train") else "test"
        lines += ["[[samples]]", f'id = "{sample}"', f'set = "{set_name}"', 'background = "bg"']
    path = folder / "sphere.toml"
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


def quiet_settings(progress=None):
    return acquire.Settings(log=lambda line: None, progress=progress)


def run_acquire(profile, out, **kwargs):
    with open(os.devnull, "w") as devnull:
        operator = acquire.Operator(yes=True, stream=devnull)
        return acquire.acquire(profile, out, emulate=True, operator=operator, settings=quiet_settings(), **kwargs)
