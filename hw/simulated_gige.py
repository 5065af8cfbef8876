"""The simulated camera's frames served through a fake GigE Vision camera and read by the GenICam
backend: an emulated acquisition that speaks the real camera protocol end to end.

`SimulatorThroughGigE` starts Aravis's in-process fake GigE Vision camera (`Aravis.GvFakeCamera`,
the same code `arv-fake-gv-camera-0.8` runs) on the loopback interface (one a machine: it takes
GVCP's UDP port 3956), makes it fill every frame it streams with what the simulated camera (`hw.simcamera`)
renders for the exposure the frame was programmed with, and opens it with `GenICamCamera`
(`hw.genicam`): discovery, GVCP register access and the GVSP stream all go over loopback as with
a real camera; only the pixels come from the simulator. Everything the acquisition asks of a
camera goes to the GenICam backend (exposure, ROI and binning, snaps), and what only the
simulated camera knows (its scenes and their regions, its noise model, its bit depth) comes
from it.

Why ctypes for the fill callback: PyGObject binds `arv_fake_camera_set_fill_pattern` with a call-
scoped callback, which Aravis keeps and calls from its streaming thread after the binding has
freed it (a segmentation fault on the first frame, Aravis 0.8.26, PyGObject 3.50). The callback
here is a ctypes function kept alive by this object, set on the C object directly; ctypes takes
the GIL when Aravis's thread calls it. In the callback, `arv_buffer_get_data` gives the frame's
memory (its size is not set yet at that point: the frame's size comes from the buffer's image
width and height and the pixel format's bits, `ARV_PIXEL_FORMAT_BIT_PER_PIXEL`).

Frames are Mono16 little-endian words holding the simulator's 14-bit counts; `bit_depth` is the
simulator's, so the exposure search aims at the simulated sensor's full scale.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import itertools
import os
import threading

import numpy as np

from .camera import Camera, CameraError
from .genicam import GenICamCamera, _import_aravis

__all__ = ["SimulatorThroughGigE"]

_FILL_PATTERN = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32,
                                 ctypes.c_uint32)
_serials = itertools.count()

#: Where the fake camera listens (GVCP on UDP port 3956, one camera a machine).
ADDRESS = "127.0.0.1"


def _libaravis():
    """libaravis-0.8 through ctypes, with the three calls used typed."""
    name = ctypes.util.find_library("aravis-0.8") or "libaravis-0.8.so.0"
    lib = ctypes.CDLL(name)
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    for call in (lib.arv_buffer_get_image_width, lib.arv_buffer_get_image_height):
        call.restype = ctypes.c_int
        call.argtypes = [ctypes.c_void_p]
    lib.arv_fake_camera_set_fill_pattern.restype = None
    lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, _FILL_PATTERN, ctypes.c_void_p]
    return lib


def _gobject_pointer(obj) -> int:
    """The C address of a PyGObject object (its __gpointer__ capsule)."""
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype = ctypes.c_void_p
    get.argtypes = [ctypes.py_object, ctypes.c_char_p]
    return get(obj.__gpointer__, None)


class SimulatorThroughGigE(Camera):
    """A `SimulatedCamera`'s frames through a fake GigE Vision camera and `GenICamCamera`.

    Args:
      simulated: the simulated camera whose frames are served (its light path and shutter wired
        as the acquisition wires them); closed with this camera.
      timeout_s: the GenICam backend's frame timeout beyond the exposure, s.
    """

    def __init__(self, simulated, *, timeout_s: float = 5.0):
        super().__init__(f"{simulated.name} through GigE Vision")
        try:
            aravis, _ = _import_aravis()
            self._lib = _libaravis()
        except (ImportError, OSError) as error:
            raise CameraError(self._error(" ".join(str(error).split()))) from None
        self._simulated = simulated
        self._lock = threading.Lock()  # the simulated camera is not called from two threads at once
        self._failure: str | None = None
        serial = f"SJ{os.getpid() % 100000:05d}{next(_serials):03d}"
        self._server = aravis.GvFakeCamera.new(ADDRESS, serial)
        if not self._server.is_running():
            # Its GVCP port (UDP 3956) is taken: another fake camera runs on this machine.
            raise CameraError(self._error(f"Aravis's fake GigE Vision camera did not start on {ADDRESS} "
                                          "(is another one running?)"))
        self._fill = _FILL_PATTERN(self._fill_frame)  # kept: Aravis calls it from its stream thread
        self._lib.arv_fake_camera_set_fill_pattern(_gobject_pointer(self._server.get_fake_camera()), self._fill, None)
        height, width = simulated.sensor_shape
        try:
            # By address, not by its name "Aravis-Fake-<serial>": a name is found by broadcast
            # discovery, whose answer may come back through another interface, which the camera
            # would then stream to (tests/hw/fake_gv_camera.py).
            self._genicam = GenICamCamera(device_id=ADDRESS, pixel_format="Mono16",
                                          roi=(0, 0, height, width), timeout_s=timeout_s)
        except BaseException:
            self._server = None
            raise
        self.exposure_s = simulated.exposure_s if simulated._exposure_s is not None else 0.01

    # --- the frames ---------------------------------------------------------------------------

    def _fill_frame(self, buffer, data, exposure_us, gain, pixel_format) -> None:
        """Aravis's fill pattern: the simulator's frame at the programmed exposure, as Mono16."""
        try:
            width = self._lib.arv_buffer_get_image_width(buffer)
            height = self._lib.arv_buffer_get_image_height(buffer)
            size = ctypes.c_size_t()
            address = self._lib.arv_buffer_get_data(buffer, ctypes.byref(size))
            bits = (pixel_format >> 16) & 0xFF  # ARV_PIXEL_FORMAT_BIT_PER_PIXEL
            if bits != 16:
                raise CameraError(self._error(f"the fake camera streams {bits}-bit pixels, expected Mono16"))
            with self._lock:
                self._simulated.exposure_s = min(max(exposure_us / 1e6, self._simulated.exposure_limits_s[0]),
                                                 self._simulated.exposure_limits_s[1])
                frame = self._simulated.snap()
            if frame.shape != (height, width):
                raise CameraError(self._error(f"the simulator gave a {frame.shape} frame for a {height} x {width} one"))
            words = np.ascontiguousarray(frame, "<u2")
            ctypes.memmove(address, words.ctypes.data, words.nbytes)
        except Exception as error:  # noqa: BLE001 - raised in Aravis's thread: reported by _snap
            self._failure = " ".join(str(error).split())

    # --- the contract: the GenICam backend's device, the simulator's sensor -------------------

    @property
    def sensor_shape(self) -> tuple[int, int]:
        return self._simulated.sensor_shape

    @property
    def bit_depth(self) -> int:
        return self._simulated.bit_depth

    @property
    def exposure_limits_s(self) -> tuple[float, float]:
        low = max(self._simulated.exposure_limits_s[0], self._genicam.exposure_limits_s[0])
        high = min(self._simulated.exposure_limits_s[1], self._genicam.exposure_limits_s[1])
        return low, high

    def _set_exposure(self, seconds: float) -> float:
        self._genicam.exposure_s = seconds
        return self._genicam.exposure_s

    def _apply_roi_binning(self, roi, binning) -> None:
        with self._lock:
            self._simulated.set_roi_binning(roi, binning)
        self._genicam.set_roi_binning(roi, binning)

    def _snap(self) -> np.ndarray:
        self._failure = None
        frame = self._genicam.snap()
        if self._failure is not None:
            raise CameraError(self._error(f"the simulator could not fill the frame: {self._failure}"))
        return frame

    def _read_temperature(self) -> float:
        return self._simulated.temperature_c()

    def _close(self) -> None:
        self._genicam.close()
        self._server = None  # the last reference: Aravis stops the fake camera's threads
        self._simulated.close()

    # --- what only the simulated camera knows --------------------------------------------------

    @property
    def noise_parameters(self) -> dict | None:
        return self._simulated.noise_parameters

    @property
    def band_centres_nm(self) -> list[int]:
        return self._simulated.band_centres_nm

    def set_scene(self, scene: str) -> None:
        with self._lock:
            self._simulated.set_scene(scene)

    def scene_frames(self):
        return self._simulated.scene_frames()

    @property
    def white_patch(self) -> tuple[int, int, int, int]:
        """The white patch in frame pixels (the session's layout where the profile gives none)."""
        return self._simulated.white_patch

    @property
    def holder(self) -> tuple[int, int, int, int]:
        """The sample holder in frame pixels (as `white_patch`)."""
        return self._simulated.holder
