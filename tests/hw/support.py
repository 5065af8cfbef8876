"""Helpers of the hw driver tests: golden transcripts through a scripted port, and the pty
resources an emulated port must give back."""

from __future__ import annotations

import os
import threading

import serial

from hw.emulators import ScriptedPort


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
