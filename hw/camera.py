"""The camera interface: exposure, region of interest, binning, snap, average, temperature.

Conventions, stated once:

- exposure in seconds (float); each backend converts to its SDK's unit;
- `roi` = (row0, col0, height, width) in unbinned sensor pixels, `sensor_shape` = (H, W);
- `binning` is square (b x b on-chip summing); frames have shape `frame_shape` =
  (roi height // b, roi width // b);
- frames are (H, W) uint16 with values < 2**bit_depth (a 12-14 bit ADC read as 16-bit words);
  `average` returns float64 so that averaging does not round;
- `temperature_c()` is the sensor temperature in °C, a finite float, or None for a camera that
  does not report one (a GenICam camera without the DeviceTemperature feature): never a made-up
  value, and None is JSON's null in the acquisition's metadata.

As in python-microscope's `microscope/abc.py`, the public methods here validate their arguments
and keep the shared state; each backend implements only small hooks (`_set_exposure`,
`_apply_roi_binning`, `_snap`, `_read_temperature`, `_close`). A backend therefore cannot be
handed an exposure of NaN or a ROI off the sensor, and every backend reports the same errors.

`open_camera("sim" | "pvcam" | "genicam", **options)` picks a backend by name; the backends'
modules are imported lazily, so this module needs neither JAX (simulated camera), PyVCAM (PVCAM)
nor PyGObject and Aravis (GenICam).
`PROFILE_OPTIONS` declares, per backend, the options an instrument profile's `[camera]` table may
pass to it, so that the profile is checked against them when it is read (`hw.profile`), without
importing the backend, instead of failing with a TypeError once the devices are open.
"""

from __future__ import annotations

import abc
import dataclasses
import importlib
import math
import numbers
import operator
from collections.abc import Callable

import numpy as np
from spherejax import interrupt

from .errors import InstrumentError


class CameraError(InstrumentError):
    """A camera failed or cannot do what was asked; the message names the camera and the problem
    on one line."""


class Camera(abc.ABC):
    """A monochrome scientific camera (see the module docstring for units and shapes).

    Subclasses call `Camera.__init__(name)` first, then set up the device, then set an initial
    exposure through the `exposure_s` setter (so that it is validated like any other).
    """

    def __init__(self, name: str):
        self.name = str(name)
        self._closed = False
        self._exposure_s: float | None = None
        self._roi: tuple[int, int, int, int] | None = None  # None: the full sensor
        self._binning = 1

    # --- what a backend provides ---------------------------------------------------------------

    @property
    @abc.abstractmethod
    def sensor_shape(self) -> tuple[int, int]:
        """(H, W) of the full sensor in unbinned pixels."""

    @property
    @abc.abstractmethod
    def bit_depth(self) -> int:
        """ADC bits; frames hold values 0 .. 2**bit_depth - 1."""

    @property
    @abc.abstractmethod
    def exposure_limits_s(self) -> tuple[float, float]:
        """(shortest, longest) exposure the camera accepts, s."""

    @abc.abstractmethod
    def _set_exposure(self, seconds: float) -> float:
        """Apply a validated exposure; return the exposure the device actually uses (s), which
        may differ by the device's time resolution."""

    @abc.abstractmethod
    def _apply_roi_binning(self, roi: tuple[int, int, int, int], binning: int) -> None:
        """Apply a validated ROI (row0, col0, height, width) and binning."""

    @abc.abstractmethod
    def _snap(self) -> np.ndarray:
        """Expose and read one frame, (H, W) uint16 of `frame_shape`."""

    @abc.abstractmethod
    def _read_temperature(self) -> float | None:
        """Sensor temperature, °C, or None if the camera has no temperature sensor."""

    def _close(self) -> None:
        """Release the device (called once)."""

    # --- public interface ----------------------------------------------------------------------

    def _count(self, value, problem: str) -> int:
        """`value` as an integer >= 1 (bools refused), else ValueError(`problem`)."""
        try:
            if isinstance(value, bool):
                raise TypeError
            count = operator.index(value)
        except TypeError:
            raise ValueError(self._error(problem)) from None
        if count < 1:
            raise ValueError(self._error(problem))
        return count

    def _error(self, problem: str) -> str:
        return f"camera {self.name!r}: {problem}"

    def _check_open(self) -> None:
        if self._closed:
            raise CameraError(self._error("is closed"))

    @property
    def noise_parameters(self) -> dict | None:
        """{"gain_e_per_count": e- per count, "read_noise_counts": one frame's read noise in
        counts rms} when the camera knows them (the simulated camera: its model's values), else
        None (a real camera: the profile's [noise] gives them). Recorded in the session for
        calibrate's noise model."""
        return None

    @property
    def saturation_dn(self) -> int:
        """The largest value a frame pixel can hold, 2**bit_depth - 1 (a saturated pixel)."""
        return 2 ** int(self.bit_depth) - 1

    @property
    def exposure_s(self) -> float:
        """Exposure time, s: what the device uses, after the setter's validation and rounding."""
        if self._exposure_s is None:
            raise CameraError(self._error("has no exposure set"))
        return self._exposure_s

    @exposure_s.setter
    def exposure_s(self, seconds: float) -> None:
        self._check_open()
        low, high = self.exposure_limits_s
        # Strings and booleans are refused even though float() would take them: an exposure
        # typed as "0.5" or True is a caller's bug, not a value.
        if isinstance(seconds, bool) or not isinstance(seconds, numbers.Real):
            raise ValueError(self._error(f"exposure {seconds!r} is not a number of seconds"))
        value = float(seconds)
        if not math.isfinite(value) or not low <= value <= high:
            raise ValueError(
                self._error(f"exposure {seconds!r} s is outside the camera's limits [{low:g}, {high:g}] s")
            )
        self._exposure_s = float(self._set_exposure(value))

    @property
    def roi(self) -> tuple[int, int, int, int]:
        """(row0, col0, height, width) in unbinned sensor pixels; set None for the full sensor."""
        if self._roi is None:
            height, width = self.sensor_shape
            return (0, 0, int(height), int(width))
        return self._roi

    @roi.setter
    def roi(self, roi: tuple[int, int, int, int] | None) -> None:
        self.set_roi_binning(roi, self._binning)

    @property
    def binning(self) -> int:
        """On-chip binning b >= 1 (b x b pixels summed into one); it must divide the ROI."""
        return self._binning

    @binning.setter
    def binning(self, binning: int) -> None:
        self.set_roi_binning(self._roi, binning)

    def set_roi_binning(self, roi: tuple[int, int, int, int] | None, binning: int) -> None:
        """Set ROI and binning together (a ROI the old binning does not divide, with a binning
        that does). Raises ValueError, naming the value, if the ROI leaves the sensor or the
        binning does not divide its height and width."""
        self._check_open()
        sensor_h, sensor_w = (int(v) for v in self.sensor_shape)
        if roi is None:
            roi = (0, 0, sensor_h, sensor_w)
        try:
            r0, c0, height, width = (operator.index(v) for v in roi)
        except (TypeError, ValueError):
            raise ValueError(
                self._error(f"ROI {roi!r} is not four integers (row0, col0, height, width)")
            ) from None
        if r0 < 0 or c0 < 0 or height < 1 or width < 1 or r0 + height > sensor_h or c0 + width > sensor_w:
            raise ValueError(
                self._error(
                    f"ROI (row0, col0, height, width) = {(r0, c0, height, width)} is not inside "
                    f"the {sensor_h} x {sensor_w} sensor"
                )
            )
        b = self._count(binning, f"binning {binning!r} is not an integer >= 1")
        if height % b or width % b:
            raise ValueError(
                self._error(f"binning {b} does not divide the ROI's height {height} and width {width}")
            )
        full = (r0, c0, height, width) == (0, 0, sensor_h, sensor_w)
        self._apply_roi_binning((r0, c0, height, width), b)
        self._roi = None if full else (r0, c0, height, width)
        self._binning = b

    @property
    def frame_shape(self) -> tuple[int, int]:
        """(H, W) of the frames `snap` returns: the ROI's size // binning."""
        _, _, height, width = self.roi
        return height // self._binning, width // self._binning

    def snap(self) -> np.ndarray:
        """Expose and read one frame at `exposure_s`: (H, W) uint16 of `frame_shape`."""
        self._check_open()
        if self._exposure_s is None:
            raise CameraError(self._error("has no exposure set"))
        frame = self._snap()
        if not isinstance(frame, np.ndarray) or frame.dtype != np.uint16 or frame.shape != self.frame_shape:
            got = f"{getattr(frame, 'dtype', type(frame).__name__)} {getattr(frame, 'shape', '')}"
            raise CameraError(self._error(f"returned a {got} frame, expected uint16 {self.frame_shape}"))
        return frame

    def average(self, n: int) -> np.ndarray:
        """Mean of `n` >= 1 consecutive snaps, (H, W) float64 (DN): averaging shrinks shot and
        read noise as 1 / sqrt(n)."""
        count = self._count(n, f"average needs an integer number of frames >= 1, got {n!r}")
        total = np.zeros(self.frame_shape, np.float64)
        for _ in range(count):
            # A safe point between frames: an exposure runs inside the camera's SDK and cannot be
            # cut, but a stop need not wait for all `n` of them.
            interrupt.check()
            total += self.snap()
        return total / np.float64(count)

    def temperature_c(self) -> float | None:
        """Sensor temperature, °C (recorded with every frame), or None when the camera does not
        report one. A NaN or infinite reading is a CameraError: it would not be valid JSON."""
        self._check_open()
        reading = self._read_temperature()
        if reading is None:
            return None
        value = float(reading)
        if not math.isfinite(value):
            raise CameraError(self._error(f"reported a sensor temperature of {reading!r} °C"))
        return value

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Release the camera; closing twice is harmless."""
        if not self._closed:
            self._closed = True
            self._close()

    def __enter__(self) -> "Camera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"roi={self.roi}, binning={self._binning}, exposure_s={self._exposure_s}"
        return f"<{type(self).__name__} {self.name!r} {state}>"


#: Backend name -> (module, relative to this package, class): imported only when chosen (PyVCAM or
#: JAX are heavy or absent).
BACKENDS = {
    "genicam": (".genicam", "GenICamCamera"),
    "pvcam": (".pvcam", "PVCAMCamera"),
    "sim": (".simcamera", "SimulatedCamera"),
}


def open_camera(backend: str, **options) -> Camera:
    """Open a camera by backend name: "sim" -> `SimulatedCamera(**options)`, "pvcam" ->
    `PVCAMCamera(**options)`, "genicam" -> `GenICamCamera(**options)`. An unknown name raises
    ValueError naming it and the choices."""
    if backend not in BACKENDS:
        choices = ", ".join(repr(name) for name in sorted(BACKENDS))
        raise ValueError(f"unknown camera backend {backend!r}: choose one of {choices}")
    module, cls = BACKENDS[backend]
    return getattr(importlib.import_module(module, __package__), cls)(**options)


@dataclasses.dataclass(frozen=True)
class ProfileOption:
    """A constructor keyword of a backend that a profile's `[camera]` table may set: its TOML
    type(s), what to say it should be, and a check of the value (all one-line error material)."""

    kinds: type | tuple[type, ...]
    expected: str
    check: Callable[[object], bool] | None = None


#: The largest sensor side, in pixels, a profile may give the simulated camera (16384: far beyond
#: any scientific sensor's, yet a frame of it stays within memory), and the longest exposure or
#: frame timeout it may give any backend, s: finite, so that no wait a profile sets is without end.
MAX_SIDE_PX = 16384
MAX_PROFILE_SECONDS = 3600.0


def _is_shape(value) -> bool:
    return len(value) == 2 and all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_SIDE_PX for v in value)


def _is_seconds(value) -> bool:
    return 0 < value <= MAX_PROFILE_SECONDS


def _is_roi(value) -> bool:
    return (
        len(value) == 4
        and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
        and value[0] >= 0 and value[1] >= 0 and value[2] >= 1 and value[3] >= 1
    )


#: Backend name -> {keyword: ProfileOption}: what a profile may pass to each backend's constructor.
#: Only values TOML can spell: the simulated camera's callables, InstrumentModel and
#: ExperimentDesign are the acquisition's to pass. tests/hw/test_camera.py checks every name here
#: against the backend's signature, so the table cannot drift from the constructors.
PROFILE_OPTIONS: dict[str, dict[str, ProfileOption]] = {
    "sim": {
        # Both numpy's and JAX's generators take 0 .. 2**32 - 1 whatever JAX's x64 setting.
        "seed": ProfileOption(int, "an integer 0..4294967295", lambda v: 0 <= v <= 2**32 - 1),
        "image_shape": ProfileOption(list, f"[height, width] in pixels, two integers >= 1 and <= {MAX_SIDE_PX}", _is_shape),
        "name": ProfileOption(str, "a non-empty string", bool),
    },
    "pvcam": {
        "camera_name": ProfileOption(str, "a PVCAM camera name, a non-empty string", bool),
        "exposure_s": ProfileOption((int, float), "an initial exposure in seconds > 0 and <= 3600", _is_seconds),
    },
    # hw.genicam.GenICamCamera; pixel formats as hw.genicam.MONO_FORMATS (not imported: that
    # module is the backend, loaded only when chosen).
    "genicam": {
        "device_id": ProfileOption(str, "an Aravis device id as arv-tool-0.8 lists it, or an IP address", bool),
        "exposure_s": ProfileOption((int, float), "an initial exposure in seconds > 0 and <= 3600", _is_seconds),
        "gain": ProfileOption((int, float), "a gain >= 0 and <= 1000 in the camera's unit (dB on most)",
                              lambda v: 0 <= v <= 1000),
        "pixel_format": ProfileOption(
            str, 'one of "Mono8", "Mono10", "Mono12", "Mono14", "Mono16"',
            lambda v: v in ("Mono8", "Mono10", "Mono12", "Mono14", "Mono16"),
        ),
        "roi": ProfileOption(list, "[row0, col0, height, width] in unbinned sensor pixels", _is_roi),
        "binning": ProfileOption(int, "a square binning, an integer >= 1 and <= 64", lambda v: 1 <= v <= 64),
        "timeout_s": ProfileOption((int, float), "seconds > 0 and <= 3600 a frame may take beyond its exposure",
                                   _is_seconds),
    },
}


__all__ = ["BACKENDS", "PROFILE_OPTIONS", "Camera", "CameraError", "ProfileOption", "open_camera"]
