"""A simulated camera: frames rendered by spherejax's physical sphere simulator.

`SimulatedCamera` implements `hw.camera.Camera` over `spherejax.simulate`: the same renderer
(`spherejax.simulated_rendering._Renderer.rates`: multi-bounce sphere, vignetting, filter
gradients, glare, non-Lambertian coupling, fluorescence), the same flux calibration
(`_Renderer.calibrate_exposures` on the white standard), the same exposure model (`_expose`:
shot noise, read noise, dark current, gain, bias, 14-bit ADC, saturation) and the same xenon
lamp (slow drift, frame-to-frame flicker). What it adds is what a camera in the instrument sees
from moment to moment:

- the band whose filter is in the light path, asked of `light_path()` at every snap (0..15 for
  400..700 nm, None when no single band filter is in the path: two crossed narrow-band filters
  pass almost nothing, so the frame is dark plus a leak of `FILTER_LEAK` of the mean band signal);
- the shutter, asked of `shutter_open()` at every snap (closed: a dark frame, bias plus dark
  current times exposure plus read noise, the same for every band);
- optionally the lamp, asked of `lamp_on_s()` (seconds since switch-on, None when off): an arc
  settles over minutes after ignition (`WARMUP_DEFICIT`, `WARMUP_TAU_S`), which the simulator,
  whose lamp is always warmed up, does not model;
- the scene on the holder (`set_scene`): "white" (the white standard), "empty" (the bare black
  holder), or one of the simulated experiment's sample captures (`scenes()`), laid out exactly as
  `spherejax.simulate.simulate_experiment` lays them out for the same seed and design, so that a
  session acquired through `hw` with this camera matches a simulated session;
- ROI and on-chip binning (b x b electrons summed before the read: signal and dark current add,
  read noise is paid once per binned pixel).

Shapes: the sensor is the simulator's image, (H, W) = design.image_shape (192 x 272 px by
default); the rate cube of a scene is (16, H, W) e-/s, rendered once per scene and cached; a snap
crops, bins and exposes one band plane, a few ms per frame.

Units: exposure s; rates e-/s; frames DN (uint16, < 2**adc_bits).
"""

from __future__ import annotations

import collections
import dataclasses
import math
import operator
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from spherejax import simulate, simulated_rendering
from spherejax.grid import BAND_CENTRES_NM

from .camera import Camera, CameraError

#: Exposure range of the simulated camera, s: 10 µs to 20 min, as cooled CCD cameras of the
#: QImaging / Photometrics class allow.
EXPOSURE_LIMITS_S = (1.0e-5, 1200.0)

#: Sensor temperature, °C: a TE-cooled CCD regulated at its set point.
SENSOR_TEMPERATURE_C = -25.0

#: Fraction of the mean band signal that two crossed narrow-band filters let through (each blocks
#: out of band at about OD 4, and their passbands do not overlap).
FILTER_LEAK = 1.0e-4

#: Lamp output just after ignition is short of its settled value by this fraction, relaxing with
#: time constant WARMUP_TAU_S (s): a short-arc lamp settles over minutes (docs/instrument.md, acquisition step 1).
WARMUP_DEFICIT = 0.05
WARMUP_TAU_S = 300.0

#: The starting exposure, s: of the order of the simulator's calibrated exposures (tens of ms).
DEFAULT_EXPOSURE_S = 0.05

#: Rate cubes kept (16 x H x W float32 each, 3.3 MB at the default size).
_CACHED_SCENES = 8


def _design_for_shape(design: simulate.ExperimentDesign, instrument: simulate.InstrumentModel, image_shape) -> simulate.ExperimentDesign:
    """The design rescaled so that its image is `image_shape` (H, W): pixels per cm from H, the
    strip beside the holder takes the remaining width, patch and region sizes scale with it."""
    height, width = (operator.index(v) for v in image_shape)
    if (height, width) == design.image_shape(instrument):
        return design
    pixels_per_cm = height / (instrument.holder_height_m * 100.0)
    scale = pixels_per_cm / design.pixels_per_cm

    def px(value: int) -> int:
        # Floor, so that the 12 x 12 target chart still fits the holder after rounding.
        return max(1, int(value * scale))

    scaled = dataclasses.replace(
        design, pixels_per_cm=pixels_per_cm, patch_px=px(design.patch_px), region_px=px(design.region_px),
        white_patch_px=px(design.white_patch_px), target_px=px(design.target_px),
        target_region_px=px(design.target_region_px),
    )
    holder_width = scaled.holder_shape(instrument)[1]
    strip = width - holder_width
    r0, r1, _, _ = scaled.white_patch(instrument)
    if strip < scaled.white_patch_px + 2 or r1 > height:
        raise ValueError(
            f"image_shape {tuple(image_shape)}: a {height}-row image needs a width of at least "
            f"{holder_width + scaled.white_patch_px + 2} (holder {holder_width} px plus the white patch strip)"
        )
    return dataclasses.replace(scaled, strip_px=strip)


class SimulatedCamera(Camera):
    """Renders frames from spherejax's physical simulator for the band currently in the light path.

    Args (keyword-only):
      light_path: () -> index 0..15 of the band whose filter is in the path (400 + 20 i nm), or
        None when no single band filter is (then only a leak of FILTER_LEAK reaches the sensor).
      shutter_open: () -> bool; False gives a dark frame.
      seed: the simulator's seed (optics, material couplings, layouts, noise).
      instrument, design: the simulator's `InstrumentModel` and `ExperimentDesign` (defaults).
      image_shape: sensor (H, W); default the design's image (192 x 272); another shape rescales
        the design (pixels per cm from H, the white-patch strip takes the rest of W).
      lamp_on_s: () -> seconds since the lamp was switched on, or None when it is off (no light);
        default: a lamp warmed up since the camera was made.
      clock: () -> seconds (monotonic), for the lamp's drift when `lamp_on_s` is not given.
      name: the camera's name in messages.
    """

    def __init__(
        self,
        *,
        light_path: Callable[[], int | None],
        shutter_open: Callable[[], bool],
        seed: int = 0,
        instrument: simulate.InstrumentModel | None = None,
        design: simulate.ExperimentDesign | None = None,
        image_shape: tuple[int, int] | None = None,
        lamp_on_s: Callable[[], float | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        name: str = "sim",
    ):
        super().__init__(name)
        self._light_path = light_path
        self._shutter_open = shutter_open
        self._lamp_on_s = lamp_on_s
        self._clock = clock
        self._start_s = float(clock())
        self.seed = int(seed)
        self.instrument = instrument or simulate.InstrumentModel()
        design = design or simulate.ExperimentDesign()
        self.design = design if image_shape is None else _design_for_shape(design, self.instrument, image_shape)
        self._image_shape = tuple(int(v) for v in self.design.image_shape(self.instrument))
        self._holder_shape = tuple(int(v) for v in self.design.holder_shape(self.instrument))
        self._renderer = simulated_rendering._Renderer(self.instrument, self._image_shape, self._holder_shape, self.seed)
        self._standard, self._tile, self._mount = simulate.fixed_materials(self.instrument, self.seed)
        self._fixed = {
            "white": simulate.Scene("white", "white", np.zeros(self._holder_shape, np.int32), (self._standard,)),
            "empty": simulate.Scene("empty", "empty", np.zeros(self._holder_shape, np.int32), (self._mount,)),
        }
        # The experiment's scenes, laid out by the simulator on first use (that loads the spectra).
        self._samples: dict[str, simulate.Scene] | None = None
        self._cache: collections.OrderedDict[str, tuple[np.ndarray, np.ndarray]] = collections.OrderedDict()
        self._scene = "white"
        self.exposure_s = DEFAULT_EXPOSURE_S

    # --- Camera ------------------------------------------------------------------------------------

    @property
    def sensor_shape(self) -> tuple[int, int]:
        return self._image_shape

    @property
    def bit_depth(self) -> int:
        return int(self.instrument.adc_bits)

    @property
    def exposure_limits_s(self) -> tuple[float, float]:
        return EXPOSURE_LIMITS_S

    def _set_exposure(self, seconds: float) -> float:
        return seconds

    def _apply_roi_binning(self, roi, binning) -> None:
        """Nothing to program: `_snap` crops and bins the rendered plane."""

    def _read_temperature(self) -> float:
        return SENSOR_TEMPERATURE_C

    @property
    def noise_parameters(self) -> dict | None:
        """The simulator's true gain (e-/count) and read noise (counts rms), as `_snap` exposes
        frames: binning sums electrons before the one read, so neither depends on it. None when
        the model's noise is switched off (frames without noise)."""
        inst = self.instrument
        if not inst.noise:
            return None
        gain = float(inst.gain_e_per_dn)
        return {"gain_e_per_count": gain, "read_noise_counts": float(inst.read_noise_e) / gain}

    def _close(self) -> None:
        self._cache.clear()

    def _snap(self) -> np.ndarray:
        r0, c0, height, width = self.roi
        b = self.binning
        lamp = self._lamp_output() if self._shutter_open() else 0.0
        if lamp > 0.0:
            band = self._band()
            cube, leak = self._rates(self._scene)
            plane = leak if band is None else cube[band]
            plane = plane[r0 : r0 + height, c0 : c0 + width]
            if b > 1:
                plane = plane.reshape(height // b, b, width // b, b).sum(axis=(1, 3), dtype=np.float32)
        else:
            plane = np.zeros((height // b, width // b), np.float32)
        inst = self.instrument
        self._renderer.key, key = jax.random.split(self._renderer.key)
        frame = simulated_rendering._expose(
            jnp.asarray(plane[None], jnp.float32),
            jnp.asarray([self.exposure_s], jnp.float32),
            jnp.asarray([lamp], jnp.float32),
            key,
            *(np.float32(x) for x in (
                # Binning sums the dark current of b x b pixels; the read happens once.
                inst.read_noise_e, inst.dark_current_e_per_s * b * b, inst.gain_e_per_dn, inst.bias_dn,
                inst.saturation_dn, 1, 1.0 if inst.noise else 0.0,
            )),
        )
        return np.ascontiguousarray(np.asarray(frame)[..., 0])

    # --- the light reaching the sensor -----------------------------------------------------------

    def _band(self) -> int | None:
        band = self._light_path()
        if band is None:
            return None
        try:
            index = operator.index(band)
        except TypeError:
            index = -1
        if not 0 <= index < len(BAND_CENTRES_NM):
            raise CameraError(self._error(f"light path reports band {band!r}, expected 0..{len(BAND_CENTRES_NM) - 1} or None"))
        return index

    def _lamp_output(self) -> float:
        """Relative lamp output for one frame: warm-up x slow drift x flicker (0 when off)."""
        inst = self.instrument
        if self._lamp_on_s is not None:
            on_s = self._lamp_on_s()
            if on_s is None:
                return 0.0
            elapsed = max(float(on_s), 0.0)
            warm = 1.0 - WARMUP_DEFICIT * math.exp(-elapsed / WARMUP_TAU_S)
        else:
            elapsed = float(self._clock()) - self._start_s
            warm = 1.0
        # The simulator's lamp: a linear drift per hour and per-frame flicker (`_Renderer.capture`).
        drift = 1.0 + inst.lamp_drift_per_hour * elapsed / 3600.0
        flicker = 1.0 + inst.lamp_fluctuation * float(self._renderer.rng.standard_normal())
        return max(warm * drift * flicker, 0.0)

    def _flux_scale(self) -> float:
        """e-/s per unit of the renderer's rates, fixed by the white standard as the simulator
        fixes it (its brightest band's brightest pixel at `peak_rate_e_per_s`)."""
        if self._renderer.flux_scale is None:
            white = self._render(self._fixed["white"])
            self._renderer.calibrate_exposures(white)
        return self._renderer.flux_scale

    def _full_map(self, scene: simulate.Scene) -> tuple[np.ndarray, list]:
        """The sensor's material map: holder content plus the black strip with the white patch."""
        white_patch = self.design.white_patch(self.instrument)
        return simulate.sensor_map(scene, self._image_shape, white_patch, self._mount, self._tile)

    def _render(self, scene: simulate.Scene) -> jax.Array:
        return self._renderer.rates(*self._full_map(scene))

    def _rates(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(cube (16, H, W), leak (H, W)) in e-/s for a scene, rendered once and cached."""
        if name in self._cache:
            self._cache.move_to_end(name)
            return self._cache[name]
        scale = np.float32(self._flux_scale())
        cube = np.asarray(self._render(self._scene_by_name(name)), np.float32) * scale
        leak = np.float32(FILTER_LEAK) * cube.mean(axis=0, dtype=np.float32)
        self._cache[name] = (cube, leak)
        while len(self._cache) > _CACHED_SCENES:
            self._cache.popitem(last=False)
        return cube, leak

    # --- scenes -------------------------------------------------------------------------------------

    def _sample_scenes(self) -> dict[str, simulate.Scene]:
        if self._samples is None:
            self._samples = simulate.experiment_layout(self.seed, self.instrument, self.design).scenes
        return self._samples

    def _scene_by_name(self, name: str) -> simulate.Scene:
        return self._fixed[name] if name in self._fixed else self._sample_scenes()[name]

    def scenes(self) -> list[str]:
        """Scene names: "white", "empty", then the simulated experiment's capture ids
        ("train-bg00-g0", ..., "test-bg00-g0", ..., "targets")."""
        return [*self._fixed, *self._sample_scenes()]

    def set_scene(self, scene: str) -> None:
        """Put something on the holder (the operator's job): a name from `scenes()`."""
        if scene not in self._fixed and scene not in self._sample_scenes():
            names = list(self._sample_scenes())
            raise ValueError(
                self._error(f"unknown scene {scene!r}: expected 'white', 'empty' or one of the {len(names)} "
                            f"sample scenes of scenes() ({names[0]!r} ... {names[-1]!r})")
            )
        self._scene = scene

    @property
    def scene(self) -> str:
        """The scene on the holder now."""
        return self._scene

    def scene_frames(self) -> list[dict]:
        """The simulated experiment's sample and target captures, in order, as session-manifest
        fields: {"id", "role", "set", "background", "regions"} ("set" and "background" for samples
        only), regions in frame pixels of the current ROI and binning (those the ROI cuts are
        left out)."""
        frames = []
        for scene in self._sample_scenes().values():
            fields = {"id": scene.name, "role": scene.role}
            if scene.role == "sample":
                fields.update(set=scene.set, background=scene.background)
            fields["regions"] = self._frame_regions(scene)
            frames.append(fields)
        return frames

    @property
    def regions(self) -> list[dict]:
        """Averaging regions of the current scene with their known reflectance (31,), in frame
        pixels [r0, r1, c0, c1]; empty for "white" and "empty"."""
        return self._frame_regions(self._scene_by_name(self._scene))

    def _frame_regions(self, scene: simulate.Scene) -> list[dict]:
        out = []
        for region in scene.regions:
            box = self._to_frame(region["region"], whole=True)
            if box is not None:
                out.append(dict(region, region=list(box)))
        return out

    def _to_frame(self, box, *, whole: bool = False) -> tuple[int, int, int, int] | None:
        """A sensor-pixel box [r0, r1) x [c0, c1) in frame pixels: the binned pixels wholly
        inside it and inside the ROI; None if none are (or, with `whole`, if the ROI cuts it)."""
        r0, r1, c0, c1 = box
        roi_r, roi_c, height, width = self.roi
        b = self.binning
        if whole and (r0 < roi_r or c0 < roi_c or r1 > roi_r + height or c1 > roi_c + width):
            return None
        fr0 = min(max(-(-(r0 - roi_r) // b), 0), height // b)
        fr1 = min(max((r1 - roi_r) // b, 0), height // b)
        fc0 = min(max(-(-(c0 - roi_c) // b), 0), width // b)
        fc1 = min(max((c1 - roi_c) // b, 0), width // b)
        if fr1 <= fr0 or fc1 <= fc0:
            return None
        return fr0, fr1, fc0, fc1

    def _frame_box(self, box, what: str) -> tuple[int, int, int, int]:
        frame_box = self._to_frame(box)
        if frame_box is None:
            raise CameraError(self._error(f"the {what} {tuple(box)} lies outside the ROI {self.roi}"))
        return frame_box

    @property
    def white_patch(self) -> tuple[int, int, int, int]:
        """(r0, r1, c0, c1) of the white reference patch in frame pixels (the simulator's
        `design.white_patch` at full frame and binning 1)."""
        return self._frame_box(self.design.white_patch(self.instrument), "white patch")

    @property
    def holder(self) -> tuple[int, int, int, int]:
        """(r0, r1, c0, c1) of the sample holder in frame pixels."""
        return self._frame_box((0, self._holder_shape[0], 0, self._holder_shape[1]), "holder")

    @property
    def band_centres_nm(self) -> list[int]:
        """Centres of the 16 bands, nm (400, 420, ..., 700): index i of `light_path()`."""
        return [int(b) for b in BAND_CENTRES_NM]

    @property
    def calibrated_exposures_s(self) -> np.ndarray:
        """(16,) s: the exposures the simulator's own protocol picks (white standard's brightest
        pixel at `exposure_fill` of full well), a reference for exposure searches."""
        self._flux_scale()
        return np.array(self._renderer.exposure, np.float64)

    @property
    def white_standard_reflectance(self) -> np.ndarray:
        """(31,) reflectance of the simulated white standard at 400..700 nm step 10 (its certificate)."""
        return self._standard.at_31().astype(np.float64)


__all__ = ["SimulatedCamera", "EXPOSURE_LIMITS_S", "FILTER_LEAK", "SENSOR_TEMPERATURE_C", "WARMUP_DEFICIT", "WARMUP_TAU_S"]
