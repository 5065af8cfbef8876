"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis 0.8, via PyGObject.

A thin backend of `hw.camera.Camera`: the interface validates, this module only translates.
Aravis is reached through GObject introspection (`gi.require_version("Aravis", "0.8")`), imported
inside `GenICamCamera.__init__`, never at module level: spherejax installs and runs without it,
and a missing library is one CameraError line saying what to install (`unavailable_reason`).

The Aravis calls used (`Aravis.Camera`, Aravis 0.8 API; every one raises `GLib.Error` on failure,
which becomes a one-line CameraError naming the camera):

- `Aravis.Camera.new(device_id)`: `device_id` as `arv-tool-0.8` lists it ("Aravis-Fake-GV01"),
  or the camera's IP address; None opens the first camera found;
- `get_sensor_size()` -> (width, height) in unbinned pixels;
- `dup_available_pixel_formats_as_strings()`, `set_pixel_format_from_string()`,
  `get_pixel_format_as_string()`: PFNC names; only the unpacked monochrome formats are used
  (Mono8: one byte a pixel; Mono10/12/14/16: one little-endian 16-bit word a pixel);
- `get_exposure_time_bounds()`, `set_exposure_time()`, `get_exposure_time()`: microseconds;
  `set_exposure_time_auto(Aravis.Auto.OFF)` / `set_gain_auto(Aravis.Auto.OFF)` where available;
- `get_gain_bounds()`, `set_gain()`, `get_gain()`: the device's own gain unit (the SFNC `Gain`
  feature, in dB on most cameras, or the older integer `GainRaw`);
- `is_binning_available()`, `set_binning(dx, dy)`; `set_region(x, y, width, height)`: x = column
  offset, y = row offset, both and the sizes in *binned* pixels (SFNC: OffsetX/Y, Width and Height
  count pixels after binning), so a contract ROI (row0, col0, height, width) with binning b becomes
  `set_region(col0 // b, row0 // b, width // b, height // b)` after `set_binning(b, b)`;
  `set_region` itself zeroes the offsets before changing the size (Aravis 0.8 source), and we zero
  them before changing the binning, so no intermediate state leaves the sensor;
- `acquisition(timeout_us)`: one frame in single-frame mode at the current settings; returns an
  `Aravis.Buffer` (`get_status()`, `get_image_width()`, `get_image_height()`, `get_data()`), or
  None when no frame came within the timeout;
- `get_device().get_feature("DeviceTemperature")` (None when the device has no such feature) and
  `get_device().get_float_feature_value("DeviceTemperature")`: °C (SFNC).

Checked against Aravis 0.8.26's fake GigE Vision camera (`arv-fake-gv-camera-0.8`, Debian 12;
tests/hw/test_genicam.py): discovery and opening by name and by IP address; the 2048 x 2048
sensor; Mono8 and Mono16 (the fake offers no Mono10/12/14) and their byte layout; exposure
bounds 10 µs .. 10 s and exact read-back; gain bounds 0 .. 10 (GainRaw); region offsets and
sizes; a vanished camera raising `GLib.Error` from `acquisition` within about 2.5 s, and from
register access within 5 s (Aravis's GigE Vision control timeout); no DeviceTemperature.
Assumed from the SFNC and Aravis documentation, not verified (the fake ignores binning when it
fills a frame and has no temperature): that a real camera's Width/Height/Offset are in binned
pixels, that Mono10/12/14 come unpacked in 16-bit words with the value in the low bits, and that
DeviceTemperature reads the sensor (a DeviceTemperatureSelector is set to "Sensor" where the
camera has one).

Mono8 cameras: frames are still (H, W) uint16, with `bit_depth` 8 (values 0..255), so that the
saturation level and the exposure search follow the true depth; by default the deepest unpacked
monochrome format the camera offers is used. A camera without DeviceTemperature reports None
from `temperature_c()` (the contract allows it; the acquisition records null).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from .camera import Camera, CameraError

log = logging.getLogger(__name__)

#: Snaps of one frame before an incomplete frame is an error (`GenICamCamera._snap`).
FRAME_ATTEMPTS = 3

#: Unpacked PFNC monochrome formats -> bits of each value (the words are 8 or 16 bits wide).
MONO_FORMATS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}

_INSTALL = (
    "apt-get install gir1.2-aravis-0.8 (and, to build PyGObject, libgirepository1.0-dev libcairo2-dev "
    "gcc pkg-config), then pip install 'spherejax[genicam]'"
)


def _import_aravis():
    """(Aravis, GLib) through PyGObject; ImportError (one line, saying what to install) if absent."""
    try:
        import gi
    except ImportError:
        raise ImportError(f"PyGObject is not installed: {_INSTALL}") from None
    try:
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ValueError, ImportError) as error:  # ValueError: "Namespace Aravis not available"
        raise ImportError(f"Aravis 0.8 is not available to PyGObject ({' '.join(str(error).split())}): {_INSTALL}") from None
    return Aravis, GLib


def unavailable_reason() -> str | None:
    """None when PyGObject and the Aravis 0.8 typelib can be imported, else why not (one line)."""
    try:
        _import_aravis()
    except ImportError as error:
        return str(error)
    return None


class GenICamCamera(Camera):
    """A GenICam camera through Aravis (module docstring: the calls, units and what was verified).

    Args:
        device_id: the Aravis device id (`arv-tool-0.8` lists them), or the camera's IP address;
            None opens the first camera Aravis finds.
        exposure_s: initial exposure, s (clipped into the camera's limits).
        gain: gain in the device's unit (Aravis `set_gain`: dB on SFNC cameras), None to leave it.
        pixel_format: one of `MONO_FORMATS`; None picks the deepest one the camera offers.
        roi: initial (row0, col0, height, width) in unbinned pixels; None for the full sensor.
        binning: initial square binning b >= 1.
        timeout_s: how long a snap may take beyond the exposure before the camera is declared
            gone, s (GigE Vision cameras stream over UDP: a lost frame never arrives).
    """

    def __init__(
        self,
        *,
        device_id: str | None = None,
        exposure_s: float = 0.01,
        gain: float | None = None,
        pixel_format: str | None = None,
        roi: list[int] | tuple[int, int, int, int] | None = None,
        binning: int = 1,
        timeout_s: float = 5.0,
    ):
        super().__init__(device_id or "genicam")
        try:
            self._aravis, self._glib = _import_aravis()
        except ImportError as error:
            raise CameraError(self._error(str(error))) from None
        if not (isinstance(timeout_s, (int, float)) and not isinstance(timeout_s, bool) and math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(self._error(f"timeout_s {timeout_s!r} is not a number of seconds > 0"))
        self._timeout_s = float(timeout_s)
        self._cam = None
        self._temperature_feature: bool | None = None
        self._device_binning: int | None = None  # unknown until we set it: a last user may have left any
        try:
            self._cam = self._call("opening", self._aravis.Camera.new, device_id)
            width, height = self._call("reading the sensor size", self._cam.get_sensor_size)
            self._sensor_shape = (int(height), int(width))
            self._pixel_format, self._bit_depth = self._choose_pixel_format(pixel_format)
            self._switch_off_auto()
            low_us, high_us = self._call("reading the exposure limits", self._cam.get_exposure_time_bounds)
            # An exposure of 0 µs is not an exposure: 1 µs is the shortest we ask for.
            self._limits_s = (max(float(low_us), 1.0) / 1e6, float(high_us) / 1e6)
            self._gain = None
            if gain is not None:
                self.gain = gain
            self.set_roi_binning(None if roi is None else tuple(roi), binning)
            self.exposure_s = min(max(float(exposure_s), self._limits_s[0]), self._limits_s[1])
        except BaseException:
            self._cam = None  # dropping the last reference closes Aravis's control channel
            raise

    # --- translation helpers --------------------------------------------------------------------

    def _call(self, what: str, fn, *args):
        """Run an Aravis call, turning its GLib.Error into a one-line CameraError."""
        try:
            return fn(*args)
        except self._glib.Error as error:
            problem = f"{what} failed: {' '.join(str(error.message).split())}"
        # Raised outside the handler with `fn` dropped: a traceback kept by the caller would
        # otherwise hold the bound method, and with it the Aravis camera (and its heartbeat
        # thread, still claiming the device) after `close`.
        fn = args = None
        raise CameraError(self._error(problem))

    def _choose_pixel_format(self, asked: str | None) -> tuple[str, int]:
        offered = list(self._call("listing the pixel formats", self._cam.dup_available_pixel_formats_as_strings) or [])
        usable = [name for name in MONO_FORMATS if name in offered]
        if asked is not None:
            if asked not in MONO_FORMATS:
                raise ValueError(self._error(f"pixel format {asked!r} is not one of {list(MONO_FORMATS)}"))
            if asked not in offered:
                raise CameraError(self._error(f"does not offer pixel format {asked!r} (it offers {offered})"))
            chosen = asked
        elif usable:
            chosen = max(usable, key=MONO_FORMATS.__getitem__)
        else:
            raise CameraError(self._error(f"offers no unpacked monochrome pixel format {list(MONO_FORMATS)} (it offers {offered})"))
        self._call(f"setting pixel format {chosen}", self._cam.set_pixel_format_from_string, chosen)
        now = self._call("reading the pixel format", self._cam.get_pixel_format_as_string)
        if now != chosen:
            raise CameraError(self._error(f"asked for pixel format {chosen}, the camera uses {now}"))
        return chosen, MONO_FORMATS[chosen]

    def _switch_off_auto(self) -> None:
        """Automatic exposure or gain would change the signal behind the acquisition's back."""
        auto_off = self._aravis.Auto.OFF
        if self._call("checking for automatic exposure", self._cam.is_exposure_auto_available):
            self._call("switching automatic exposure off", self._cam.set_exposure_time_auto, auto_off)
        if self._call("checking for automatic gain", self._cam.is_gain_auto_available):
            self._call("switching automatic gain off", self._cam.set_gain_auto, auto_off)

    # --- the contract's properties and hooks ------------------------------------------------------

    @property
    def sensor_shape(self) -> tuple[int, int]:
        return self._sensor_shape

    @property
    def bit_depth(self) -> int:
        return self._bit_depth

    @property
    def pixel_format(self) -> str:
        """The PFNC pixel format frames are read in ("Mono16", ...)."""
        return self._pixel_format

    @property
    def exposure_limits_s(self) -> tuple[float, float]:
        return self._limits_s

    @property
    def gain(self) -> float | None:
        """The gain the device reports (its unit: dB on SFNC cameras), None if never set here."""
        return self._gain

    @gain.setter
    def gain(self, value: float) -> None:
        self._check_open()
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(self._error(f"gain {value!r} is not a number"))
        if not self._call("checking for gain", self._cam.is_gain_available):
            raise CameraError(self._error("has no gain control"))
        low, high = self._call("reading the gain limits", self._cam.get_gain_bounds)
        if not low <= value <= high:
            raise ValueError(self._error(f"gain {value!r} is outside the camera's limits [{low:g}, {high:g}]"))
        self._call(f"setting gain {value!r}", self._cam.set_gain, float(value))
        self._gain = float(self._call("reading the gain", self._cam.get_gain))

    def _set_exposure(self, seconds: float) -> float:
        self._call("setting the exposure", self._cam.set_exposure_time, seconds * 1e6)
        return float(self._call("reading the exposure", self._cam.get_exposure_time)) / 1e6

    def _apply_roi_binning(self, roi, binning) -> None:
        r0, c0, height, width = roi
        b = binning
        if r0 % b or c0 % b:
            # GenICam offsets count binned pixels: an offset the binning does not divide cannot
            # be programmed. Refused before anything is sent, so the device keeps its settings.
            raise CameraError(self._error(f"ROI {roi} with binning {b}: a GenICam camera needs row0 and col0 divisible by the binning"))
        if b != self._device_binning:
            if not self._call("checking for binning", self._cam.is_binning_available):
                if b > 1:
                    raise CameraError(self._error(f"cannot bin {b} x {b}: the camera has no binning"))
            else:
                self._call("moving the region to the origin", self._cam.set_region, 0, 0, 0, 0)
                self._call(f"setting binning {b}", self._cam.set_binning, b, b)
            self._device_binning = b
        self._call(f"setting ROI {roi}", self._cam.set_region, c0 // b, r0 // b, width // b, height // b)

    def _snap(self) -> np.ndarray:
        timeout_s = self.exposure_s + self._timeout_s
        # A GigE Vision frame travels as UDP packets: one can arrive incomplete (packets lost, or
        # the buffer cleared, as seen under load on loopback: ARV_BUFFER_STATUS_CLEARED) from a
        # camera that is fine. Such a frame is taken again, FRAME_ATTEMPTS times in all; no frame
        # at all (the camera gone) is not retried.
        for attempt in range(1, FRAME_ATTEMPTS + 1):
            buffer = self._call("acquiring a frame", self._cam.acquisition, int(timeout_s * 1e6))
            if buffer is None:
                raise CameraError(self._error(f"no frame within {timeout_s:.3g} s (camera gone, or frames lost on the network)"))
            status = buffer.get_status()
            if status == self._aravis.BufferStatus.SUCCESS:
                break
            log.debug("%s: frame %d of %d not received whole (%s)", self.name, attempt, FRAME_ATTEMPTS, status.value_nick)
        else:
            raise CameraError(self._error(f"frame not received whole ({status.value_nick}) in {FRAME_ATTEMPTS} attempts"))
        height, width = buffer.get_image_height(), buffer.get_image_width()
        if (height, width) != self.frame_shape:
            raise CameraError(self._error(f"sent a {height} x {width} frame, expected {self.frame_shape[0]} x {self.frame_shape[1]}"))
        data = buffer.get_data()
        dtype = np.dtype(np.uint8) if self._bit_depth == 8 else np.dtype("<u2")
        if len(data) < height * width * dtype.itemsize:
            raise CameraError(self._error(f"sent {len(data)} bytes for a {height} x {width} {self._pixel_format} frame"))
        return np.frombuffer(data, dtype, count=height * width).reshape(height, width).astype(np.uint16)

    def _read_temperature(self) -> float | None:
        device = self._cam.get_device()
        if self._temperature_feature is None:
            self._temperature_feature = device.get_feature("DeviceTemperature") is not None
            selector = device.get_feature("DeviceTemperatureSelector")
            if self._temperature_feature and selector is not None:
                self._call("selecting the sensor temperature", device.set_string_feature_value, "DeviceTemperatureSelector", "Sensor")
        if not self._temperature_feature:
            return None
        return float(self._call("reading the temperature", device.get_float_feature_value, "DeviceTemperature"))

    def _close(self) -> None:
        # Aravis 0.8 has no close call: releasing the last reference to the camera closes its
        # control channel (and with it the GigE Vision heartbeat). `acquisition` stops its own
        # stream, so no acquisition is left running.
        self._cam = None


__all__ = ["FRAME_ATTEMPTS", "GenICamCamera", "MONO_FORMATS", "unavailable_reason"]
