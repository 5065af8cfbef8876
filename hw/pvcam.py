"""Teledyne Photometrics / newer QImaging cameras through PVCAM, via PyVCAM.

A thin backend of `hw.camera.Camera`: the interface validates, this module only translates.
PyVCAM (and the PVCAM SDK under it) cannot be installed here, so it is imported inside
`PVCAMCamera.__init__`, never at module level; the camera contract every backend runs
(tests/hw/test_camera_contract.py) runs this one against a fake `pyvcam` that follows PyVCAM's
documented API (tests/hw/fake_pyvcam). The PyVCAM calls used (its `pyvcam.camera.Camera`):

- `pvc.init_pvcam()` / `pvc.uninit_pvcam()`; `Camera.detect_camera()` (generator) or
  `Camera.select_camera(name)`; `open()`, `close()`, `name`;
- `sensor_size` = (serial, parallel) = (W, H) pixels; `bit_depth`; `temp` (°C);
- `exp_res` = 0 selects milliseconds; `exp_time` (int, in `exp_res` units, range-checked by
  PyVCAM against `PARAM_EXPOSURE_TIME`'s min and max);
- `reset_rois()`, `set_roi(s1, p1, w, h)` (s = serial = column, p = parallel = row), then
  `binning = (bx, by)`, which applies to the ROI just set;
- `get_frame()` -> (H, W) numpy array at the current exposure and ROI.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera, CameraError

_MISSING = "PyVCAM is not installed: pip install PyVCAM (Teledyne Photometrics PVCAM SDK required)"

#: PVCAM's exposure resolution index for milliseconds (PARAM_EXP_RES: 0 ms, 1 µs).
_EXP_RES_MS = 0


def _import_pyvcam():
    """(pvc, PyVCAM's Camera class, constants), or CameraError if PyVCAM is absent."""
    try:
        from pyvcam import constants, pvc
        from pyvcam.camera import Camera as PyVCAMCamera
    except ImportError:
        raise CameraError(f"camera 'pvcam': {_MISSING}") from None
    return pvc, PyVCAMCamera, constants


class PVCAMCamera(Camera):
    """A PVCAM camera (the first one found, or the one called `camera_name`).

    Exposures are programmed in whole milliseconds (PVCAM's ms resolution), so `exposure_s`
    reads back the rounded value that the camera uses.
    """

    def __init__(self, *, camera_name: str | None = None, exposure_s: float = 0.05):
        pvc, pyvcam_camera, constants = _import_pyvcam()
        super().__init__(camera_name or "pvcam")
        self._pvc = pvc
        self._initialised = False
        self._cam = None
        try:
            pvc.init_pvcam()
            self._initialised = True
            if camera_name is None:
                cam = next(pyvcam_camera.detect_camera(), None)
                if cam is None:
                    raise CameraError(self._error("PVCAM found no camera"))
            else:
                cam = pyvcam_camera.select_camera(camera_name)
            cam.open()
            self._cam = cam
            self.name = str(cam.name)
            try:
                cam.exp_res = _EXP_RES_MS
            except AttributeError:
                pass  # no PARAM_EXP_RES on this camera: it times exposures in ms already
            width, height = cam.sensor_size
            self._sensor_shape = (int(height), int(width))
            self._bit_depth = int(cam.bit_depth)
            low = cam.get_param(constants.PARAM_EXPOSURE_TIME, constants.ATTR_MIN)
            high = cam.get_param(constants.PARAM_EXPOSURE_TIME, constants.ATTR_MAX)
            # Zero-length exposures are not exposures; 1 ms is the shortest at ms resolution.
            self._limits_s = (max(int(low), 1) / 1000.0, int(high) / 1000.0)
            self.exposure_s = min(max(exposure_s, self._limits_s[0]), self._limits_s[1])
        except CameraError:
            self._release()
            raise
        except (RuntimeError, ValueError, AttributeError) as error:
            self._release()
            raise CameraError(self._error(f"PVCAM failed to open: {' '.join(str(error).split())}")) from None

    def _release(self) -> None:
        try:
            if self._cam is not None:
                self._cam.close()
        finally:
            self._cam = None
            if self._initialised:
                self._initialised = False
                self._pvc.uninit_pvcam()

    def _call(self, what: str, fn, *args):
        """Run a PyVCAM call, turning its RuntimeError / ValueError into a one-line CameraError."""
        try:
            return fn(*args)
        except (RuntimeError, ValueError, AttributeError) as error:
            raise CameraError(self._error(f"{what} failed: {' '.join(str(error).split())}")) from None

    @property
    def sensor_shape(self) -> tuple[int, int]:
        return self._sensor_shape

    @property
    def bit_depth(self) -> int:
        return self._bit_depth

    @property
    def exposure_limits_s(self) -> tuple[float, float]:
        return self._limits_s

    def _set_exposure(self, seconds: float) -> float:
        low_ms, high_ms = (round(v * 1000.0) for v in self._limits_s)
        ms = min(max(int(round(seconds * 1000.0)), low_ms), high_ms)
        self._call("setting the exposure", setattr, self._cam, "exp_time", ms)
        return ms / 1000.0

    def _apply_roi_binning(self, roi, binning) -> None:
        r0, c0, height, width = roi

        def apply():
            self._cam.reset_rois()
            self._cam.set_roi(c0, r0, width, height)
            self._cam.binning = (binning, binning)

        self._call(f"setting ROI {roi} with binning {binning}", apply)

    def _snap(self) -> np.ndarray:
        frame = self._call("get_frame", self._cam.get_frame)
        return np.asarray(frame, dtype=np.uint16)

    def _read_temperature(self) -> float:
        return float(self._call("reading the temperature", getattr, self._cam, "temp"))

    def _close(self) -> None:
        self._call("closing", self._release)


__all__ = ["PVCAMCamera"]
