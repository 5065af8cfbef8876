"""The kernel contract: what a per-pixel kernel computes, what each one supports, and which one a
plan runs.

Every kernel computes the same function of one pixel (`spherejax.equations.pixel_outputs`): the
quality bits (`spherejax.quality.Quality`), the flat field (Eq. 10), Stage I and II (Eq. 16-17,
23), the reflectance estimate of the whole estimator family (the affine estimator W v + r0 of
every method, and the kernel residual A k(v) of E8-E10 where the calibration has one) and Lab.
Three implementations:

    JaxNumpy    the definition in jax.numpy (`spherejax.equations`): every platform, every dtype,
                traced calibrations; on CPU in cache-sized blocks (`cpu_blocks.pixel_outputs_in_blocks`).
                What the others are tested against (tests/test_fused.py, tests/test_gpu_kernel.py).
    FusedCpu    the fused C++ kernel (`fused`, sources in kernel/): float32, uint16 or float32
                raw, up to `fused.MAX_BANDS` bands, the kernel residual at the rank the extension
                declares (`fused.capabilities`); instruction-set variants as policies of one
                template (generic, AVX2, AVX-512).
    PallasGpu   the Pallas (Triton) kernel on NVIDIA GPUs (`gpu_kernel`): float32, uint16 or
                float32 raw, a power-of-two number of bands >= 16, the kernel residual as
                `gpu_kernel.applies_residual` declares.

Each kernel says itself what it refuses (`refusal`: None, or why not, in words) and how it runs
(`pixel_outputs`). `choose` is the one place that picks a kernel, once, when a plan is made
(`spherejax._engine.plan.Plan`); nothing downstream decides a route of its own. Kernels are
frozen dataclasses: hashable, so that a jitted step takes its kernel as a static argument and
compiles once per kernel.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np

from .. import equations
from ..pixel_constants import PixelConstants
from . import fused, gpu_kernel
from .cpu_blocks import pixel_outputs_in_blocks


class PixelKernel:
    """A per-pixel kernel (the module docstring). Subclasses are frozen dataclasses.

    Attributes:
      mode: the kernel's name as the plan reports it (`Plan.kernel_mode`): None for the jax.numpy
        definition, a variant of `fused.VARIANTS`, or one of `gpu_kernel.MODES`.
      direct: True if it also corrects NumPy frames without XLA (`fused.correct_arrays`).
      reads_flat_field_mask: True if it reads the plan's (H, W) mask of pixels without a flat
        field (`equations.flat_field_unusable`) instead of working it out from dark and white.
      prepares: True if `prepare` derives constants the plan should make once.
    """

    mode: str | None = None
    direct: bool = False
    reads_flat_field_mask: bool = False
    prepares: bool = False

    def refusal(self, raw_dtype, compute_dtype, bands: int, residual, concrete: bool) -> str | None:
        """None if this kernel computes frames of `raw_dtype` in `compute_dtype` with `bands`
        bands and the estimator's kernel residual `residual` (None: affine), else why not.
        concrete: the calibration's arrays are concrete (not traced)."""
        raise NotImplementedError

    def prepare(self, constants: PixelConstants):
        """What this kernel derives from the calibration's arrays once (a pytree of arrays, made by
        the plan with `jax.jit` and passed to every `pixel_outputs`), or None for nothing."""
        return None

    def pixel_outputs(self, raw, p, constants: PixelConstants, *, saturation, out=None, no_flat_field=None,
                      prepared=None):
        """(reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W) uint8) of raw
        (..., H, W, B) with the white-patch ratio p (..., B), traced inside a jitted step.

        out: None, or donated arrays of the outputs' shapes whose memory the outputs may take
        (`steps.image_step_into`). no_flat_field: None, or the plan's (H, W) mask. prepared:
        `prepare(constants)` made once by the plan, or None (made in the call's program)."""
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class JaxNumpy(PixelKernel):
    """The definition (`equations.pixel_outputs`), on CPU in blocks that stay in cache."""

    reads_flat_field_mask = True

    def refusal(self, raw_dtype, compute_dtype, bands, residual, concrete):
        return None

    def pixel_outputs(self, raw, p, constants, *, saturation, out=None, no_flat_field=None, prepared=None):
        def plain(raw, p, constants):
            return equations.pixel_outputs(raw, p, constants, saturation=saturation, no_flat_field=no_flat_field)

        def on_cpu(raw, p, constants):
            return pixel_outputs_in_blocks(raw, p, constants, saturation=saturation, out=out,
                                           no_flat_field=no_flat_field)

        # The same equations either way: blocks only on CPU, where XLA does not fuse the
        # projection with the elementwise steps (`cpu_blocks.pixel_outputs_in_blocks`).
        return jax.lax.platform_dependent(raw, p, constants, cpu=on_cpu, default=plain)


@dataclasses.dataclass(frozen=True)
class FusedCpu(PixelKernel):
    """The fused C++ kernel, running `variant` (one of `fused.VARIANTS`)."""

    variant: str = fused.GENERIC
    direct = True

    @property
    def mode(self) -> str:
        return self.variant

    def refusal(self, raw_dtype, compute_dtype, bands, residual, concrete):
        # What the compiled kernel declares it supports (module.cc, `capabilities`).
        declared = fused.capabilities()
        if np.dtype(compute_dtype) != np.float32:
            return f"the fused kernel computes in float32, not {np.dtype(compute_dtype)}"
        if np.dtype(raw_dtype).name not in declared.get("raw_dtypes", ()):
            return f"the fused kernel reads {' or '.join(declared.get('raw_dtypes', ()))} raw, not {np.dtype(raw_dtype)}"
        if not 1 <= bands <= declared.get("max_bands", 0):
            return f"the fused kernel takes 1 to {declared.get('max_bands', 0)} bands, not {bands}"
        if residual is not None:
            if self.variant not in declared.get("residual_variants", ()):
                return f"the fused kernel's {self.variant} code does not apply a kernel residual"
            if not concrete:
                return "a traced kernel residual: its rank cannot be checked against the kernel's"
            if not fused.residual_fits(residual):
                return (f"the kernel residual's weights have rank above the {fused.RESIDUAL_RANK} the fused kernel "
                        "applies (a file not made by spherejax's fit)")
        return None

    def pixel_outputs(self, raw, p, constants, *, saturation, out=None, no_flat_field=None, prepared=None):
        c = constants
        return fused.correct_pixels(
            _positional_definition(saturation), raw, c.dark, c.white, p, c.coeffs, c.wiener, c.wiener_offset,
            c.tristimulus_weights, saturation=saturation, kernel_mode=self.variant, residual=c.wiener_residual,
        )


@dataclasses.dataclass(frozen=True)
class PallasGpu(PixelKernel):
    """The Pallas kernel: compiled by Triton (`gpu_kernel.GPU`) or interpreted (`INTERPRET`, any
    backend: the tests')."""

    pallas_mode: str = gpu_kernel.GPU
    prepares = True

    @property
    def mode(self) -> str:
        return self.pallas_mode

    def refusal(self, raw_dtype, compute_dtype, bands, residual, concrete):
        if not gpu_kernel.supports(raw_dtype, compute_dtype, bands):
            return (f"the GPU kernel takes uint16 or float32 raw of a power-of-two number of bands >= 16 in float32, "
                    f"not {np.dtype(raw_dtype)} of {bands} bands in {np.dtype(compute_dtype)}")
        if residual is not None and not gpu_kernel.applies_residual(residual):
            return "the GPU kernel does not apply this kernel residual (`gpu_kernel.applies_residual`)"
        return None

    def prepare(self, constants):
        return gpu_kernel.prepare(constants)

    def pixel_outputs(self, raw, p, constants, *, saturation, out=None, no_flat_field=None, prepared=None):
        return gpu_kernel.pixel_outputs(raw, p, constants, saturation=saturation, kernel_mode=self.pallas_mode,
                                        prepared=prepared)


def _positional_definition(saturation):
    """`equations.pixel_outputs` in the positional form `fused.correct_pixels` calls its
    definition with (raw, dark, white, p, coeffs, wiener, wiener_offset, tristimulus weights,
    kernel residual): its JVP, and what runs off the CPU."""
    def plain(raw, dark, white, p, coeffs, wiener, wiener_offset, weights, residual):
        constants = PixelConstants(dark, white, coeffs, wiener, wiener_offset, weights, residual)
        return equations.pixel_outputs(raw, p, constants, saturation=saturation)

    return plain


#: The jax.numpy definition: the kernel wherever no other applies.
DEFINITION = JaxNumpy()


@functools.lru_cache(maxsize=None)
def of_mode(mode: str | None) -> PixelKernel:
    """The kernel whose `mode` is `mode` (None: the definition; a fused variant, or AUTO / PORTABLE
    for the process's measured one; a `gpu_kernel.MODES` value)."""
    if mode is None:
        return DEFINITION
    if mode in gpu_kernel.MODES:
        return PallasGpu(mode)
    return FusedCpu(fused.resolve(mode, fused.VARIANT_BANDS) if mode in (fused.AUTO, "1", fused.PORTABLE) else mode)


def choose(asked, raw_dtype, compute_dtype, bands: int, residual, concrete: bool, device) -> tuple[PixelKernel, str | None]:
    """The kernel a plan runs, and why a faster one was not taken (None when nothing was refused).

    Args:
      asked: None (the definition), fused.AUTO (the fastest that applies on the calibration's
        device, as the switches SPHEREJAX_FUSED and SPHEREJAX_GPU_KERNEL allow), or a mode to
        take where it applies (a fused variant; `gpu_kernel.INTERPRET` in the tests).
      raw_dtype, compute_dtype, bands: the frames'.
      residual: the calibration's kernel residual or None; concrete: whether its arrays are.
      device: the calibration's device, or None (traced, or on several devices).
    """
    if asked is None:
        return DEFINITION, None
    if asked in gpu_kernel.MODES:
        candidate = PallasGpu(asked)
    elif device is not None and device.platform != "cpu":
        # The fused kernel runs on CPU only. Its switch is still read, so that a mistyped value is
        # refused here as on the CPU (tests/test_gpu_kernel.py).
        fused.switch()
        if gpu_kernel.mode(raw_dtype, compute_dtype, bands, device) is None:
            return DEFINITION, None
        candidate = PallasGpu(gpu_kernel.GPU)
    else:
        variant = fused.mode(raw_dtype, compute_dtype, bands)
        if variant is None:
            return DEFINITION, fused.unavailable_reason()
        candidate = FusedCpu(variant if asked == fused.AUTO else asked)
    reason = candidate.refusal(raw_dtype, compute_dtype, bands, residual, concrete)
    return (DEFINITION, reason) if reason is not None else (candidate, None)


__all__ = ["PixelKernel", "JaxNumpy", "FusedCpu", "PallasGpu", "DEFINITION", "of_mode", "choose"]
