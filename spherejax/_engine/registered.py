"""The correction of a calibration with band maps (`Calibration.band_transforms`): the bands
resampled into the reference geometry, then the plan of the registered calibration, whichever
kernel it runs (`spherejax.band_resampling` gives the equations and why every kernel then reads
registered pixels).

    raw (native) --registration_step--> u' (registered), bits
                 --Plan(registered calibration)--> reflectance, Lab, quality, p
                 --merged_quality--> quality with the registration's bits

`registered_calibration` makes the registered calibration once per calibration (kept on it, as its
plans are); `RegisteredPlan` is what `plan_for` returns for a calibration with maps: called as a
`Plan` is, with the same checks, and p (Eq. 14-15) from the registered frames' patch box.
"""

from __future__ import annotations

import dataclasses
import functools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks, band_resampling
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
        frames, _ = self.register(raw)
        return self.inner.patch_ratio(frames)

    def patch_ratio_u(self, raw, noise) -> jax.Array:
        frames, _ = self.register(raw)
        return self.inner.patch_ratio_u(frames, noise)

    def __call__(self, raw, *, p=None, intermediates: bool = False, noise=None, p_u=None) -> CorrectionResult:
        frames, bits = self.register(raw)
        result = self.inner(frames, p=p, intermediates=intermediates, noise=noise, p_u=p_u)
        return dataclasses.replace(result, quality=band_resampling.merged_quality(result.quality, bits))

    def rows(self, raw, row0: int, p) -> CorrectionResult:
        raise ValueError("rows: a calibration with band maps corrects a strip from native rows beyond it "
                         "(band_resampling.halo_px); correct the strip's rows with their halo instead")

    @property
    def calibration(self):
        return self.inner.calibration


__all__ = ["RegisteredPlan", "registered_calibration", "registration_step"]
