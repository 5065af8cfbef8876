"""The correction of a calibration with band maps (`Calibration.band_transforms`): the bands
resampled into the reference geometry, then the plan of the registered calibration, whichever
kernel it runs (`spherejax.band_resampling` gives the equations and why every kernel then reads
registered pixels).

    raw (native) --registration_step--> u' (registered), bits
                 --Plan(registered calibration)--> reflectance, Lab, quality, p
                 --merged_quality--> quality with the registration's bits

That is the definition, and what traced frames (under `jax.jit`, `jax.grad`, `jax.vmap`), the GPU
and the jax.numpy path run. Concrete frames on CPU, where the fused kernel corrects them, take a
shorter way with the same outputs to float rounding: the kernel registers each row into a buffer
of its thread's and corrects it from there (`RegisteredPlan._correct_directly`; kernel/call.h,
register_bands_first), so that no registered frame is written to memory or read back. A separate
registration pass made `correct` 2.4-2.7x slower at 1024 x 1024 x 16; inside the loop it costs a
third (benchmarks/README.md, "bench_registration.py").

`registered_calibration` makes the registered calibration once per calibration (kept on it, as its
plans are); `RegisteredPlan` is what `plan_for` returns for a calibration with maps: called as a
`Plan` is, with the same checks, and p (Eq. 14-15) from the registered pixels of the patch's box,
registered from the native pixels around it only (`patch_box_ratio_step`) for concrete frames.
"""

from __future__ import annotations

import dataclasses
import functools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks, band_resampling, equations
from ..calibration import Calibration, compute_dtype, saturation_level
from ..correction_result import CorrectionResult
from . import fused_registration

_lock = threading.Lock()


def _make_registered(calibration: Calibration, dtype) -> Calibration:
    dark = jnp.asarray(calibration.dark).astype(dtype)
    white = jnp.asarray(calibration.white).astype(dtype)
    signal = band_resampling.registered_white(dark, white, calibration.band_transforms)
    # dark 0 and white s': what a kernel computes of (u' - 0) / s' is the registered v'. No
    # saturation level: the registration flags saturated native pixels itself.
    return dataclasses.replace(calibration, dark=jnp.zeros_like(signal), white=signal, saturation=None,
                               band_transforms=None)


def registered_calibration(calibration: Calibration, dtype) -> Calibration:
    """The calibration in the reference geometry (dark 0, white s', no saturation level, no maps;
    `band_resampling`), in `dtype`. Kept on a concrete calibration, one per dtype, so that its plans
    are kept too; made inside the trace for a traced one (its derivative flows through s')."""
    if not all(_checks.is_concrete(x) for x in jax.tree_util.tree_leaves(calibration)):
        return _make_registered(calibration, dtype)
    key = np.dtype(dtype).str
    with _lock:
        kept = calibration.__dict__.setdefault("_registered", {})
        registered = kept.get(key)
    if registered is None:
        with jax.ensure_compile_time_eval():
            registered = jax.jit(_make_registered, static_argnums=1)(calibration, np.dtype(dtype))
        with _lock:
            registered = kept.setdefault(key, registered)
    return registered


@functools.partial(jax.jit, static_argnames=("saturation", "compiled"))
def registration_step(raw, dark, white, inverse, transforms, registered_signal, *, saturation, compiled: bool):
    """`band_resampling.registered_frames` as one program (dark, white in the compute dtype):
    by the compiled loop on CPU where it applies (`compiled`, `fused_registration`; `inverse` its
    1 / (white - dark)), else the definition."""
    if compiled:
        return fused_registration.registered_frames(raw, dark, white, inverse, transforms, registered_signal,
                                                    saturation=saturation)
    return band_resampling.registered_frames(raw, dark, white, transforms, registered_signal, saturation=saturation)


@functools.partial(jax.jit, static_argnames=("offset", "box_shape", "saturation", "compiled"))
def patch_box_ratio_step(native, dark, white, inverse, transforms, registered_signal, patch, *, offset, box_shape,
                         saturation, compiled: bool):
    """p (..., B) from native frames cropped to the patch's read box (`band_resampling.read_box`),
    with the calibration's arrays over that box and the maps in its coordinates: the box
    registered (`registration_step`), then Eq. 14-15 over the patch's box within it, `offset`
    (row, col) from its corner, as the registered calibration's own plan reads it (`patch`: its
    `PatchConstants`; no saturation level: the registration flagged saturated taps)."""
    frames, _ = registration_step(native, dark, white, inverse, transforms, registered_signal,
                                  saturation=saturation, compiled=compiled)
    (row, col), (h, w) = offset, box_shape
    return equations.patch_ratio_of_box(frames[..., row:row + h, col:col + w, :], patch, None)


class RegisteredPlan:
    """The prepared correction of frames of one shape and dtype with a calibration that has band
    maps: the registration step, then the registered calibration's own plan (`Plan`), whose kernel
    and route are chosen as for any float32 frames of that shape.

    Called as a `Plan` is (`plan(raw, p=None, intermediates=False, noise=None, p_u=None)`), and
    `patch_ratio(raw)`, `patch_ratio_u(raw, noise)`. Rows of an image (`Plan.rows`) are refused: a
    strip needs `band_resampling.halo_px` rows of native frames beyond its own
    (`spherejax.stripwise` reads them).
    """

    def __init__(self, calibration: Calibration, shape: tuple[int, ...], dtype, make_plan):
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        raw_type = jax.ShapeDtypeStruct(self.shape, self.dtype)
        self.compute_dtype = np.dtype(compute_dtype(raw_type, calibration))
        self.saturation = saturation_level(raw_type, calibration)
        self.registered = registered_calibration(calibration, self.compute_dtype)
        self.dark = jnp.asarray(calibration.dark).astype(self.compute_dtype)
        self.white = jnp.asarray(calibration.white).astype(self.compute_dtype)
        self.transforms = jnp.asarray(calibration.band_transforms).astype(self.compute_dtype)
        # The compiled registration on CPU where it applies (`fused_registration.applies`), with
        # its 1 / (white - dark) made once here.
        self.compiled = fused_registration.applies(self.dtype, self.compute_dtype, calibration.bands)
        self.inverse = fused_registration.inverse_signal(self.dark, self.white) if self.compiled else None
        # The registered frames are in the compute dtype whatever the raw's.
        self.inner = make_plan(self.registered, self.shape, self.compute_dtype)
        # Concrete frames on CPU go to the fused kernel with their registration inside its loop
        # (`_correct_directly`) where the kernel corrects them and the compiled registration applies.
        self.direct = (self.compiled and self.inner.reads_numpy and self.inner.kernel.mode is not None
                       and self.inner.kernel.direct)
        self._native = None  # the kernel's native arrays, made at the first direct call
        self._patch = None  # the patch's read box and what its registration reads (`_patch_read_box`)

    @property
    def kernel_mode(self):
        return self.inner.kernel_mode

    @property
    def kernel(self):
        return self.inner.kernel

    @property
    def kernel_refusal(self):
        return self.inner.kernel_refusal

    def register(self, raw):
        """(u' (..., H, W, B) registered frames in the compute dtype, their bits (..., H, W) uint8)."""
        _checks.require_plan_frames(raw, self.shape, self.dtype)
        return registration_step(raw, self.dark, self.white, self.inverse, self.transforms, self.registered.white,
                                 saturation=self.saturation, compiled=self.compiled)

    def patch_ratio(self, raw) -> jax.Array:
        """p (..., B) of whole frames from their registered patch. Concrete frames: only the native
        pixels the patch's box is interpolated from (`band_resampling.read_box`) are registered
        (`patch_box_ratio_step`), as a strip's p is read (`spherejax.stripwise.image_patch_ratio`);
        traced ones: from the registered frames."""
        if not _checks.is_concrete(raw) or self.inner.patch is None:
            frames, _ = self.register(raw)
            return self.inner.patch_ratio(frames)
        _checks.require_plan_frames(raw, self.shape, self.dtype)
        if self._patch is None:  # made once (two threads may both make it: the same arrays either way)
            self._patch = self._patch_read_box()
        (r0, r1, c0, c1), offset, arrays = self._patch
        box = raw[..., r0:r1, c0:c1, :]
        if isinstance(box, np.ndarray):
            box = np.ascontiguousarray(box)
        return patch_box_ratio_step(box, *arrays, self.inner.patch, offset=offset, box_shape=self.inner.box_shape,
                                    saturation=self.saturation, compiled=self.compiled)

    def _patch_read_box(self):
        """The patch's read box (row0, row1, col0, col1), the patch's box's origin within it, and the
        registration's arrays over it: dark, white, 1 / (white - dark) (None where the definition
        runs), the maps in the box's own coordinates, s' (the whole frame's, sliced: the box's own
        pixels are interpolated from within it)."""
        (patch_row, patch_col), (h, w) = self.inner.box_origin_host, self.inner.box_shape
        height, width = self.shape[-3:-1]
        maps = np.asarray(self.transforms, np.float64)
        r0, r1, c0, c1 = band_resampling.read_box((patch_row, patch_row + h, patch_col, patch_col + w), maps,
                                                  (height, width))
        local = np.asarray(band_resampling.local_transforms(maps, r0, c0), self.compute_dtype)
        crop = lambda x: None if x is None else jax.device_put(np.asarray(x)[r0:r1, c0:c1])  # noqa: E731
        arrays = (crop(self.dark), crop(self.white), crop(self.inverse), local, crop(self.registered.white))
        return (r0, r1, c0, c1), (int(patch_row - r0), int(patch_col - c0)), arrays

    def patch_ratio_u(self, raw, noise) -> jax.Array:
        frames, _ = self.register(raw)
        return self.inner.patch_ratio_u(frames, noise)

    def __call__(self, raw, *, p=None, intermediates: bool = False, noise=None, p_u=None) -> CorrectionResult:
        if (self.direct and noise is None and not intermediates and _checks.is_concrete(raw)
                and (p is None or _checks.is_concrete(p))):
            return self._correct_directly(raw, p)
        frames, bits = self.register(raw)
        result = self.inner(frames, p=p, intermediates=intermediates, noise=noise, p_u=p_u)
        return dataclasses.replace(result, quality=band_resampling.merged_quality(result.quality, bits))

    def _correct_directly(self, raw, p) -> CorrectionResult:
        """Concrete frames by the fused kernel, each row registered inside its loop
        (`Plan._correct_directly` with `registration`): no registered frame is written or read
        back, which a separate registration pass costs twice the correction's memory traffic
        (benchmarks/bench_registration.py). The same outputs as the registered frames corrected
        by the inner plan, to float rounding (tests/test_registered_kernel.py)."""
        _checks.require_plan_frames(raw, self.shape, self.dtype)
        if p is None:
            p = self.patch_ratio(raw)
        raw = np.ascontiguousarray(raw)  # a CPU jax.Array's view, a NumPy frame itself
        if self._native is None:
            with _lock, jax.ensure_compile_time_eval():
                if self._native is None:
                    pixels, bands = self.shape[-3] * self.shape[-2], self.shape[-1]
                    self._native = (
                        np.asarray(self.dark, np.float32).reshape(pixels, bands),
                        np.asarray(self.inverse, np.float32).reshape(pixels, bands),
                        np.asarray(self.transforms, np.float32), self.saturation,
                    )
        return self.inner._correct_directly(raw, p, registration=self._native)

    def rows(self, raw, row0: int, p) -> CorrectionResult:
        raise ValueError("rows: a calibration with band maps corrects a strip from native rows beyond it "
                         "(band_resampling.halo_px); correct the strip's rows with their halo instead")

    @property
    def calibration(self):
        return self.inner.calibration


__all__ = ["RegisteredPlan", "patch_box_ratio_step", "registered_calibration", "registration_step"]
