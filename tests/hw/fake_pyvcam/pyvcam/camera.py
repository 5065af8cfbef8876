"""Fake `pyvcam.camera.Camera`: the calls hw/pvcam.py makes, checked as PyVCAM checks them."""

import numpy as np

from . import constants, pvc


class Camera:
    def __init__(self, name):
        self.name = name
        self.is_open = False
        self._properties = pvc.CAMERAS[name]
        self._exp_res = None
        self._exp_time = 0
        self._roi = None  # (s1, p1, width, height)
        self._binning = (1, 1)
        self._frames = 0

    @classmethod
    def detect_camera(cls):
        for index in range(pvc.get_cam_total()):
            yield cls(pvc.get_cam_name(index))

    @classmethod
    def select_camera(cls, name):
        for index in range(pvc.get_cam_total()):
            if pvc.get_cam_name(index) == name:
                return cls(name)
        raise RuntimeError("Failed to create a detected camera. Invalid name")

    def open(self):
        pvc.open_camera(self.name)
        self.is_open = True
        self.reset_rois()

    def close(self):
        pvc.close_camera(self.name)
        self.is_open = False

    def _require_open(self):
        if not self.is_open:
            raise RuntimeError(f"{self.name}: camera not open")

    def get_param(self, param_id, param_attr=constants.ATTR_CURRENT):
        self._require_open()
        if param_id == constants.PARAM_EXPOSURE_TIME:
            low, high = self._properties["exposure_ms"]
            return {constants.ATTR_MIN: low, constants.ATTR_MAX: high, constants.ATTR_CURRENT: self._exp_time}[param_attr]
        height, width = self._properties["sensor"]
        values = {constants.PARAM_SER_SIZE: width, constants.PARAM_PAR_SIZE: height,
                  constants.PARAM_BIT_DEPTH: self._properties["bit_depth"]}
        if param_id not in values:
            raise AttributeError(f"{self.name}: parameter {param_id} not available")
        return values[param_id]

    @property
    def sensor_size(self):
        """(serial, parallel) = (width, height) pixels."""
        return self.get_param(constants.PARAM_SER_SIZE), self.get_param(constants.PARAM_PAR_SIZE)

    @property
    def bit_depth(self):
        return self.get_param(constants.PARAM_BIT_DEPTH)

    @property
    def temp(self):
        self._require_open()
        return self._properties["temperature_c"]

    @property
    def exp_res(self):
        return self._exp_res

    @exp_res.setter
    def exp_res(self, index):
        self._require_open()
        if index not in (0, 1):
            raise ValueError(f"{self.name}: invalid exposure resolution index {index}")
        self._exp_res = index

    @property
    def exp_time(self):
        return self._exp_time

    @exp_time.setter
    def exp_time(self, value):
        self._require_open()
        low, high = self._properties["exposure_ms"]
        if not isinstance(value, int) or not low <= value <= high:
            raise ValueError(f"{self.name}: invalid exposure time {value!r}: expected an int in [{low}, {high}]")
        self._exp_time = value

    def reset_rois(self):
        self._require_open()
        width, height = self.sensor_size
        self._roi = (0, 0, width, height)

    def set_roi(self, s1, p1, width, height):
        self._require_open()
        sensor_w, sensor_h = self.sensor_size
        if s1 < 0 or p1 < 0 or width < 1 or height < 1 or s1 + width > sensor_w or p1 + height > sensor_h:
            raise ValueError(f"{self.name}: invalid ROI {(s1, p1, width, height)}")
        self._roi = (s1, p1, width, height)

    @property
    def binning(self):
        return self._binning

    @binning.setter
    def binning(self, value):
        self._require_open()
        sbin, pbin = (value, value) if isinstance(value, int) else value
        _, _, width, height = self._roi
        if width % sbin or height % pbin:
            raise ValueError(f"{self.name}: binning {value} does not divide the ROI")
        self._binning = (sbin, pbin)

    def get_frame(self, exp_time=None, timeout_ms=-1):
        self._require_open()
        if self._exp_time < 1 and exp_time is None:
            raise RuntimeError(f"{self.name}: no exposure set")
        s1, p1, width, height = self._roi
        sbin, pbin = self._binning
        self._frames += 1
        rng = np.random.default_rng(self._frames)
        full = 2 ** self._properties["bit_depth"] - 1
        # A dark level plus light proportional to the exposure, summed over the binned pixels.
        level = min(100 + 2 * (exp_time or self._exp_time) * sbin * pbin, full)
        frame = rng.poisson(level, (height // pbin, width // sbin))
        return np.minimum(frame, full).astype(np.uint16)
