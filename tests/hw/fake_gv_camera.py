"""Aravis's fake GigE Vision camera (`arv-fake-gv-camera-0.8`, Debian package aravis-tools) on
loopback, for the GenICam backend's tests (tests/hw/test_genicam.py, test_camera_contract.py).

Facts these tests rely on (Aravis 0.8.26, src/arvfakecamera.c and what was seen here):

- the fake answers GVCP on UDP port 3956 of the address given with -i, and also binds the
  broadcast address's port 3956, so only one fake can run on a machine at a time: `running`
  holds a lock file while its fake runs, and pytest-xdist's other worker waits for it;
- it is opened by IP address ("127.0.0.1"), not by its name "Aravis-Fake-GV01": opening by name
  goes through broadcast discovery, and on a machine with a second network interface the answer
  may come back through that one; Aravis then asks the fake to stream to that interface's
  address, and no frame ever arrives (seen here: "Interface address = 192.0.2.2");
- its frames are a diagonal ramp scaled by s = 1 + GainRaw + log10(exposure_us / 10 000)
  (arv_fake_camera_diagonal_ramp in src/arvfakecamera.c): pixel (x, y) of frame number f is
  ((x + y + f) mod 255) * s in Mono8, and (256 (x + y + f) mod 65535) * s in Mono16 (measured
  here: tests/hw/test_genicam.py checks both), truncated and clipped to the format's range.
  So the level is logarithmic in the exposure (zero at 1 ms without gain, full scale near
  10 ms), the ramp moves one step a frame (f counts every frame sent), and a frame's
  99.5th percentile is about 0.995 s of full scale.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import os
import pathlib
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator

import pytest

FAKE = "arv-fake-gv-camera-0.8"
ADDRESS = "127.0.0.1"
GVCP_PORT = 3956
_LOCK = pathlib.Path(tempfile.gettempdir()) / "spherejax-arv-fake-gv-camera.lock"


def require_aravis() -> None:
    """Skip the calling test (module) unless PyGObject and the Aravis 0.8 typelib import; CI
    installs both (.ci/run, pyproject's genicam extra), so there this never skips."""
    from spherejax_hw.genicam import unavailable_reason

    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(f"GenICam tests need PyGObject and Aravis 0.8: {reason}")


@dataclasses.dataclass
class FakeCamera:
    """A running fake camera: its device id for `open_camera("genicam", device_id=...)`."""

    process: subprocess.Popen
    device_id: str = ADDRESS

    def kill(self) -> None:
        """SIGKILL, as a camera that loses power or its cable: no goodbye on the network."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=10)


def _listening(address: str, port: int) -> bool:
    """Whether a UDP socket is bound to address:port (/proc/net/udp: little-endian hex)."""
    want = "".join(f"{int(part):02X}" for part in reversed(address.split("."))) + f":{port:04X}"
    with open("/proc/net/udp") as table:
        return any(line.split()[1] == want for line in table.readlines()[1:])


@contextlib.contextmanager
def exclusive() -> Iterator[None]:
    """Hold the machine's GigE Vision loopback: no other test process (the other xdist worker,
    another pytest run) starts a fake or opens 127.0.0.1 until this ends. A test that expects
    no camera there must hold it too, or it may find, and take control of, another's fake."""
    with open(_LOCK, "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


@contextlib.contextmanager
def running(timeout_s: float = 10.0) -> Iterator[FakeCamera]:
    """Start the fake on loopback (waiting for any other test process's fake to end first),
    wait until it listens, yield it, and kill it on the way out, whatever happened."""
    if shutil.which(FAKE) is None:
        pytest.fail(f"{FAKE} is not installed: apt-get install aravis-tools")
    with exclusive():
        process = subprocess.Popen([FAKE, "-i", ADDRESS], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   env={**os.environ, "LC_ALL": "C"})
        camera = FakeCamera(process)
        try:
            deadline = time.monotonic() + timeout_s
            while not _listening(ADDRESS, GVCP_PORT):
                if process.poll() is not None:
                    output = process.stdout.read().decode(errors="replace").strip()
                    pytest.fail(f"{FAKE} -i {ADDRESS} exited with {process.returncode}: {output!r} (is another one running?)")
                if time.monotonic() > deadline:
                    pytest.fail(f"{FAKE} -i {ADDRESS} did not listen on UDP port {GVCP_PORT} within {timeout_s} s")
                time.sleep(0.02)
            yield camera
        finally:
            camera.kill()
            process.stdout.close()
