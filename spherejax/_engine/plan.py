"""A prepared correction: what `correct` works out once per calibration and frame shape.

`Plan(calibration, shape, dtype)` holds, on the device the calibration's arrays are on:

- `constants`: the calibration's arrays cast to the compute dtype (`PixelConstants`), with the
  tristimulus weights of its illuminant and observer;
- `patch` and `box_origin`/`box_shape`: the white patch's bounding box of those arrays
  (`PatchConstants`), the only pixels the white-patch ratio reads;
- `saturation`, `kernel`: the saturation level and the per-pixel kernel, both static: chosen once
  here (`kernels.choose`: the fused CPU kernel's variant on CPU, the Pallas kernel on an NVIDIA GPU,
  compiled when the plan is made and given up for the definition if that fails, else the jax.numpy
  definition), with `kernel_refusal` saying why a faster kernel was not taken;
- `no_flat_field`: the (H, W) mask of pixels without a flat field, read by the jax.numpy path on
  CPU instead of a reduction over both frames on every call;
- the route its whole-frame calls take (`route`) and, for the routes that need it, the compiled
  executable and the NumPy views the fused kernel reads (`_direct`). The route is decided here,
  when the plan is made, and nowhere else: `correct` only checks its arguments.

`correct(raw, calibration)` looks the plan up on the calibration (`plan_for`): a calibration keeps
the plans of the frame shapes it has corrected, and they go with it; nothing is remembered by
object identity in a process-wide table. Strips of an image (rows of a calibration kept by the
calibration file, `io.CalibrationFile.rows`), the archive, the uncertainty and measurement paths,
calibrate, evaluate, study and dask workers all reach the per-pixel step through `correct` and so
through a plan: one per input shape, reused strip after strip and input after input.

A traced calibration (`jax.grad` with respect to it, `jax.vmap` over calibrations) gets a plan
built inside the trace: the same steps, with the casts part of the derivative, nothing compiled
ahead and nothing kept.

Output memory: the pools of `buffers` are keyed by the outputs' shapes, not by plan, so that two
calibrations of one frame size share them (a batch that alternates two instruments keeps two
sets of outputs, not four).
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import weakref

import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks, colorimetry, equations
from ..calibration import Calibration, compute_dtype, saturation_level
from ..correction_result import CorrectionResult
from ..grid import N_WAVELENGTHS
from ..pixel_constants import PatchConstants, PixelConstants
from . import buffers, fused, gpu_kernel, kernels, registered, steps

_log = logging.getLogger(__name__)

#: Routes of whole frames without p, noise or intermediates (`Plan.route`).
DIRECT, RECYCLING, PROGRAM = "direct", "recycling", "program"

#: Bytes of outputs a pixel: reflectance and Lab in float32 and the quality byte.
_OUTPUT_BYTES_PER_PIXEL = 4 * (N_WAVELENGTHS + 3) + 1

#: Executables of `steps.image_step_into`, compiled ahead for a signature (shapes, dtypes, box
#: shape, options: never an object's identity), so that a plan's first recycling call does not
#: compile and a second calibration of the same shapes compiles nothing (tests/test_compilation.py).
#: This is jax.jit's own cache for a program jit cannot compile ahead by itself.
_into_executables: dict = {}
_into_lock = threading.Lock()


def _concrete(calibration) -> bool:
    return all(_checks.is_concrete(x) for x in jax.tree_util.tree_leaves(calibration))


def _device_of(calibration):
    """The one device all of a concrete calibration's arrays are on, or None (several devices,
    or arrays that are not jax.Arrays)."""
    try:
        devices = set().union(*(x.devices() for x in jax.tree_util.tree_leaves(calibration)))
    except AttributeError:
        return None
    return next(iter(devices)) if len(devices) == 1 else None


def _prepare(calibration, dtype, box, with_mask: bool):
    """(PixelConstants, PatchConstants or None, the (H, W) no-flat-field mask or None) of a
    calibration in `dtype`, on the device its arrays are on.

    A calibration on the CPU is prepared in NumPy, which reads its arrays in place: casts,
    slices and the mask are exact operations, so the bits are XLA's, and nothing is compiled (a
    new frame shape then compiles its correction only, tests/test_compilation.py). Elsewhere one
    jitted program does it on the device (`_prepare_on_device`, compiled once per signature),
    rather than reading the frames back to the host. A traced calibration is prepared inside the
    trace, where the casts are part of a derivative.
    """
    if not _concrete(calibration):
        patch = None if box is None else PatchConstants.of(calibration, dtype, box)
        return PixelConstants.of(calibration, dtype), patch, None
    device = _device_of(calibration)
    if device is None or device.platform != "cpu":
        return _prepare_on_device(calibration, np.dtype(dtype), box, with_mask)
    dtype = np.dtype(dtype)
    weights = colorimetry.tristimulus_weights(calibration.illuminant, observer=calibration.observer)

    def cast(x):  # the same jax.Array when it is already in dtype: nothing copied
        return x if x.dtype == dtype else jax.device_put(np.asarray(x).astype(dtype), device)

    def host(x):
        return jax.device_put(np.ascontiguousarray(x), device)

    residual = calibration.wiener_residual
    constants = PixelConstants(
        cast(calibration.dark), cast(calibration.white), cast(calibration.coeffs), cast(calibration.wiener),
        cast(calibration.wiener_offset), host(np.asarray(weights, dtype)),
        None if residual is None else jax.tree_util.tree_map(cast, residual),  # a pytree of arrays
    )
    patch = None
    if box is not None:
        r0, r1, c0, c1 = box
        patch = PatchConstants(*(host(np.asarray(x)[r0:r1, c0:c1].astype(dtype))
                                 for x in (calibration.dark, calibration.white, calibration.patch)))
    mask = None
    if with_mask:
        white_signal = np.asarray(constants.white) - np.asarray(constants.dark)  # as `_no_flat_field`
        mask = host(~(np.min(np.where(np.isfinite(white_signal), white_signal, -1.0), axis=-1) > 0))
    return constants, patch, mask


@functools.partial(jax.jit, static_argnames=("dtype", "box", "with_mask"))
def _prepare_on_device(calibration, dtype, box, with_mask):
    """`_prepare` as one program on the calibration's device (a GPU's)."""
    constants = PixelConstants.of(calibration, dtype)
    patch = None if box is None else PatchConstants.of(calibration, dtype, box)
    mask = equations.flat_field_unusable(constants.dark, constants.white) if with_mask else None
    return constants, patch, mask


class Plan:
    """The prepared correction of frames of one shape and dtype with one calibration.

    Args:
      calibration: a `spherejax.Calibration` (whole, or rows of one: then every call needs p).
      shape: the frames' shape (..., H, W, B) with the calibration's H, W, B.
      dtype: the frames' dtype (uint16 counts, float32 or float64).
      kernel_mode: the kernel asked for (`kernels.choose`): the default fused.AUTO takes the
        fastest that applies; None the jax.numpy definition; a fused variant or a
        `gpu_kernel.MODES` value that kernel where it applies (the tests').

    Call it as `correct` (`plan(raw, p=..., intermediates=..., noise=..., p_u=...)`) with frames
    of that shape and dtype; `spherejax.plan` is the public way to make one. Immutable after
    construction apart from the lazily compiled executable, so threads may share it.
    """

    def __init__(self, calibration: Calibration, shape: tuple[int, ...], dtype, kernel_mode=fused.AUTO):
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        raw_type = jax.ShapeDtypeStruct(self.shape, self.dtype)
        self.compute_dtype = np.dtype(compute_dtype(raw_type, calibration))
        self.saturation = saturation_level(raw_type, calibration)
        self.concrete = _concrete(calibration)
        # A kept plan refers to its calibration weakly: the calibration keeps its plans, and a
        # cycle would hold both frames until a full garbage collection.
        self._calibration = weakref.ref(calibration) if self.concrete else (lambda: calibration)
        self.device = _device_of(calibration) if self.concrete else None
        on_cpu = self.device is not None and self.device.platform == "cpu"
        self.kernel, self.kernel_refusal = kernels.choose(
            kernel_mode, self.dtype, self.compute_dtype, calibration.bands, calibration.wiener_residual,
            self.concrete, self.device,
        )
        if self.kernel_refusal is not None:
            _log.debug("plan for %s %s frames: the jax.numpy path, because %s", self.shape, self.dtype,
                       self.kernel_refusal)
        box = calibration.patch_box if calibration.patch is not None else None
        if calibration.patch is not None and box is None:  # a traced patch: the whole frame
            box = (0, self.shape[-3], 0, self.shape[-2])
        self.box = box
        self.box_shape = None if box is None else (box[1] - box[0], box[3] - box[2])
        # The box's origin is an argument of the programs (patches of one size share one), kept
        # where the computation runs: a NumPy origin would be copied to the device at every call
        # (on a GPU a host-to-device transfer before each program). The host copy is what the
        # direct route slices the frames with.
        self.box_origin_host = None if box is None else np.array([box[0], box[2]], np.int32)
        self.box_origin = self.box_origin_host
        if self.box_origin is not None and self.device is not None:
            self.box_origin = jax.device_put(self.box_origin, self.device)
        # The jax.numpy path reads the (H, W) mask of pixels without a flat field instead of
        # reducing over both frames at every call (on CPU a fifth of its time).
        with_mask = self.concrete and self.kernel.reads_flat_field_mask
        self.constants, self.patch, self.no_flat_field = _prepare(calibration, self.compute_dtype, box, with_mask)
        pixels = int(np.prod(self.shape[:-1], dtype=np.int64))
        large = pixels * _OUTPUT_BYTES_PER_PIXEL >= buffers.MIN_BYTES
        whole = box is not None and self.shape[-3:] == (*calibration.image_shape, calibration.bands)
        self._whole_frames = whole
        # The fused kernel reads NumPy frames where they lie (`fused.correct_arrays`): whole frames
        # (p from the patch's box) and rows of an image given p alike, so that the strips of the
        # command line take the route of the API's whole-frame call.
        self.reads_numpy = on_cpu and self.concrete and self.kernel.direct and self.dtype in fused.RAW_DTYPES
        if not (self.concrete and whole):
            self.route = PROGRAM
        elif self.reads_numpy and large:
            self.route = DIRECT
        elif on_cpu and large:
            self.route = RECYCLING
        else:
            self.route = PROGRAM
        self._direct = None  # the fused kernel's NumPy arrays, made at the first direct call
        # What the kernel derives from the constants (the GPU kernel's padded, folded arrays and its
        # residual's), once here rather than in every call's program.
        self.prepared = jax.jit(self.kernel.prepare)(self.constants) if self.concrete and self.kernel.prepares else None
        self._into = None
        self._lock = threading.Lock()
        if self.kernel == kernels.PallasGpu(gpu_kernel.GPU) and self.concrete:
            self._compile_gpu_kernel()

    def _compile_gpu_kernel(self) -> None:
        """Compile the whole-frame program with the GPU kernel now, by correcting zero frames of
        this plan's shape, and fall back to the jax.numpy definition if that fails:
        a JAX whose Pallas has lost its Triton backend or lowers the kernel differently must not
        fail every `correct`. The compiled program stays in jit's cache for the calls that follow; whatever
        went wrong is logged at DEBUG (the module's logger)."""
        # NumPy zeros, as frames read from files come: a frame committed to a device is another
        # signature of jit's (a second compilation at its first call), a NumPy one is not.
        zeros = np.zeros(self.shape, self.dtype)
        # The Pallas Triton backend's deprecation notice at each lowering (gpu_kernel's docstring)
        # is a DeprecationWarning from JAX's own module, which Python's default filters do not
        # show; where warnings are errors (-W error), the kernel is given up here.
        try:
            jax.block_until_ready(self._whole(zeros) if self._whole_frames else self._pixels(zeros))
        except Exception as error:  # noqa: BLE001 - any failure of a kernel we can do without
            _log.debug("the GPU kernel did not compile for %s frames of %s (%s: %s); using the jax.numpy path",
                       self.shape, self.dtype, type(error).__name__, error)
            self.kernel, self.kernel_refusal = kernels.DEFINITION, f"the GPU kernel did not compile ({error})"
            self.prepared = None
            # The mask the jax.numpy path's plans read (`_prepare`).
            self.no_flat_field = _no_flat_field(self.constants.dark, self.constants.white)
        finally:
            del zeros

    def _pixels(self, raw) -> CorrectionResult:
        """The per-pixel step of frames with p = 1 (a plan without a patch box: `_compile_gpu_kernel`)."""
        p = jnp.ones((*raw.shape[:-3], raw.shape[-1]), self.compute_dtype)
        return steps.pixels_step(raw, p, self.constants, saturation=self.saturation, intermediates=False,
                                 kernel=self.kernel, prepared=self.prepared)

    # ---------------------------------------------------------------------------------------
    # What the routes read

    def _kernel_arrays(self) -> dict:
        """The NumPy arrays the fused kernel reads on the direct route: dark and white (P, B)
        float32 (views of the constants, which are on the CPU), coeffs, projection, bias and
        white_xyz (`fused.kernel_constants`)."""
        c = self.constants
        pixels = self.shape[-3] * self.shape[-2]
        projection, bias, white_xyz = jax.jit(fused.kernel_constants)(c.wiener, c.wiener_offset, c.tristimulus_weights)
        residual = jax.jit(fused.residual_constants, static_argnums=2)(c.wiener_residual, c.tristimulus_weights,
                                                                      c.bands)
        return {
            "dark": np.asarray(c.dark).reshape(pixels, c.bands), "white": np.asarray(c.white).reshape(pixels, c.bands),
            "coeffs": np.asarray(c.coeffs), "projection": np.asarray(projection), "bias": np.asarray(bias),
            "white_xyz": np.asarray(white_xyz), "residual": tuple(np.asarray(x) for x in residual),
        }

    def _into_executable(self):
        """The compiled `steps.image_step_into` of this plan's signature (compiled once)."""
        if self._into is None:
            leaves, structure = jax.tree_util.tree_flatten((self.constants, self.patch, self.no_flat_field))
            signature = (
                self.shape, self.dtype.name, structure, tuple((x.shape, x.dtype.name) for x in leaves),
                self.box_shape, self.saturation, self.kernel,
            )
            outputs = self.shape[:-1]
            with _into_lock:
                executable = _into_executables.get(signature)
                if executable is None:
                    out_types = (
                        jax.ShapeDtypeStruct((*outputs, N_WAVELENGTHS), self.compute_dtype),
                        jax.ShapeDtypeStruct((*outputs, 3), self.compute_dtype),
                        jax.ShapeDtypeStruct(outputs, jnp.uint8),
                    )
                    executable = steps.image_step_into.lower(
                        jax.ShapeDtypeStruct(self.shape, self.dtype), self.constants, self.patch, self.box_origin,
                        *out_types, self.no_flat_field, box_shape=self.box_shape, saturation=self.saturation,
                        kernel=self.kernel,
                    ).compile()
                    _into_executables[signature] = executable
            self._into = executable
        return self._into

    def _statics(self) -> dict:
        return {"box_shape": self.box_shape, "saturation": self.saturation, "kernel": self.kernel}

    @property
    def kernel_mode(self) -> str | None:
        """The kernel's name (`kernels.PixelKernel.mode`): None for the jax.numpy definition."""
        return self.kernel.mode

    # ---------------------------------------------------------------------------------------
    # Calls

    def _check_frames(self, raw, p=None, p_u=None) -> None:
        """Raise ValueError, one line naming the argument, the shape (or dtype) given and the one
        expected, unless raw has this plan's shape and dtype and p and p_u (when given) one value
        per band of each image. `correct` passes only what it checked; a plan called directly
        (`spherejax.plan`) would otherwise fail inside JAX with a message about its internals."""
        _checks.require_plan_frames(raw, self.shape, self.dtype)
        expected = (*self.shape[:-3], self.shape[-1])
        for name, value in (("p", p), ("p_u", p_u)):
            if value is not None and tuple(getattr(value, "shape", np.shape(value))) != expected:
                raise ValueError(f"{name}: expected shape {expected} (one value per band of each image), got "
                                 f"{tuple(getattr(value, 'shape', np.shape(value)))}")

    def patch_ratio(self, raw) -> jax.Array:
        """p (..., B) of whole frames (`spherejax.pipeline.patch_ratio`)."""
        self._check_frames(raw)
        if self.patch is None:
            raise ValueError("raw: this plan's calibration has no patch (rows of a calibration): p needs the whole one")
        return steps.patch_ratio_step(
            raw, self.patch, self.box_origin, box_shape=self.box_shape, saturation=self.saturation
        )

    def patch_ratio_u(self, raw, noise) -> jax.Array:
        """u(p) (..., B) of whole frames under a `NoiseModel` (`spherejax.pipeline.patch_ratio_u`)."""
        self._check_frames(raw)
        if self.patch is None:
            raise ValueError("raw: this plan's calibration has no patch (rows of a calibration): u(p) needs the whole one")
        return steps.patch_ratio_std_step(
            raw, self.patch, noise, self.box_origin, box_shape=self.box_shape, saturation=self.saturation
        )

    def __call__(self, raw, *, p=None, intermediates: bool = False, noise=None, p_u=None) -> CorrectionResult:
        """`correct(raw, calibration, ...)` of frames of this plan's shape and dtype, checked by
        the caller (`spherejax.pipeline.correct`) or here (`_check_frames`) when called directly."""
        self._check_frames(raw, p, p_u)
        if p is None and self.patch is None:
            raise ValueError("p: expected the whole image's white-patch ratio with rows of a calibration "
                             "(patch_ratio of the whole image), got None")
        direct = (self.reads_numpy and noise is None and not intermediates and isinstance(raw, np.ndarray)
                  and raw.flags.c_contiguous)
        if p is not None:
            if direct and _checks.is_concrete(p):  # a traced p (a derivative with respect to it) is XLA's
                return self._correct_directly(raw, p)
            return steps.pixels_step(
                raw, p, self.constants, saturation=self.saturation, intermediates=intermediates,
                kernel=self.kernel, noise=noise, p_u=p_u, prepared=self.prepared,
            )
        if noise is not None or intermediates:
            return steps.image_step(raw, self.constants, self.patch, self.box_origin, intermediates=intermediates,
                                    noise=noise, prepared=self.prepared, **self._statics())
        if self.route == DIRECT and direct:
            return self._correct_directly(raw)
        if isinstance(raw, np.ndarray):
            # into reused, aligned memory (`buffers`), or at least onto the plan's device
            raw = buffers.stage(raw) if buffers.stageable(raw) else jax.device_put(raw, self.device)
        if not _checks.is_concrete(raw):
            return self._correct_mappable(raw)
        if self.route in (DIRECT, RECYCLING) and _on_device(raw, self.device):
            return self._correct_recycling(raw)
        return self._whole(raw)

    def _whole(self, raw, out=None) -> CorrectionResult:
        return steps.image_step(raw, self.constants, self.patch, self.box_origin, intermediates=False,
                                no_flat_field=self.no_flat_field, out=out, prepared=self.prepared, **self._statics())

    def _correct_recycling(self, raw) -> CorrectionResult:
        """Whole frames on CPU, reusing the memory of outputs the caller has dropped
        (`buffers`); the same numbers bit for bit as `_whole` (tested)."""
        executable = self._into_executable()
        key = (self.shape[:-1], self.compute_dtype.name)
        out = buffers.take(key)
        if out is None:
            result = self._whole(raw)
        else:
            result = executable(raw, self.constants, self.patch, self.box_origin, *out, self.no_flat_field)
        buffers.give(key, (result.reflectance, result.lab, result.quality))
        return result

    def rows(self, raw, row0: int, p) -> CorrectionResult:
        """Rows row0:row0 + n of one image, raw (n, W, B), with the whole image's p (B,): what
        `correct(raw, calibration.rows(row0, row0 + n), p=p)` returns, bit for bit, by this plan of
        the whole frame, so that every strip of every input shares it (`spherejax.stripwise`).

        The fused kernel reads NumPy rows where they lie with the rows' dark and white sliced from
        the plan's own arrays (no Calibration, plan or constants made per strip); elsewhere (the
        jax.numpy definition, the GPU) the calibration's rows (`Calibration.rows`, which keeps them)
        go through their own plan."""
        height, width, bands = self.shape[-3:]
        raw_shape = tuple(getattr(raw, "shape", ()))
        if len(raw_shape) != 3 or raw_shape[1:] != (width, bands) or not 0 <= row0 < row0 + raw_shape[0] <= height:
            raise ValueError(f"raw: expected rows (n, {width}, {bands}) of the image from row {row0} within its "
                             f"{height} rows, got shape {raw_shape}")
        row1 = row0 + raw_shape[0]
        if (self.reads_numpy and len(self.shape) == 3 and isinstance(raw, np.ndarray) and raw.flags.c_contiguous
                and raw.dtype == self.dtype and _checks.is_concrete(p)):
            return self._correct_directly(raw, p, rows=(row0, row1))
        calibration = self._calibration()
        if calibration is None:
            raise ValueError("rows: this plan's calibration is gone; make the plan again from the calibration")
        rows = calibration.rows(row0, row1)  # kept by the calibration, with its plan
        return plan_for(rows, raw_shape, raw.dtype)(raw, p=p)

    def _correct_directly(self, raw: np.ndarray, p=None, rows: tuple[int, int] | None = None,
                          registration: tuple | None = None) -> CorrectionResult:
        """NumPy frames by the fused kernel called directly (`fused.correct_arrays`), without
        XLA: the same numbers as `_whole` bit for bit (tested), but the kernel reads the frames
        where they lie, where XLA needs them copied into its own memory first (32 MB a megapixel
        of uint16). The outputs are written into reused NumPy memory (`buffers.take_host`) and
        handed to JAX without a copy. p: given (rows of an image, `correct(rows, calibration_rows,
        p=p)`: the same kernel and constants as `steps.pixels_step`, so the same bits), or None for
        whole frames: from `steps.patch_ratio_step` on the patch's box of the frames (a small
        copy), the program `_whole` traces into its own. rows: (row0, row1) when raw holds only
        those rows of the frame (`rows`): the kernel reads their slice of dark and white.
        registration: (dark (P, B), inverse_signal (P, B), maps (B, 2, 3) float32, the saturation
        level or None) of a calibration with band maps whose registered calibration this plan is
        (`registered.RegisteredPlan`):
        raw is then the native frames, which the kernel registers row by row before correcting
        them (`fused.correct_arrays`); p must be given."""
        if p is None:
            (r0, c0), (h, w) = self.box_origin_host, self.box_shape
            p = steps.patch_ratio_step(
                raw[..., r0:r0 + h, c0:c0 + w, :], self.patch, self.box_origin, box_shape=self.box_shape,
                saturation=self.saturation, raw_is_box=True,
            )
        else:
            p = jax.device_put(np.asarray(p, self.compute_dtype), self.device)
        *batch, height, width, bands = raw.shape
        images, pixels = int(np.prod(batch, dtype=np.int64)), height * width
        pairs = buffers.take_host(
            tuple(raw.shape[:-1]),
            (((*batch, height, width, N_WAVELENGTHS), np.float32), ((*batch, height, width, 3), np.float32),
             ((*batch, height, width), np.uint8)),
        )
        (reflectance, _), (lab, _), (quality, _) = pairs
        if self._direct is None:
            with self._lock, jax.ensure_compile_time_eval():  # concrete even if a trace is running
                if self._direct is None:
                    self._direct = self._kernel_arrays()
        k = self._direct
        dark, white = k["dark"], k["white"]
        if rows is not None:  # row-major pixels: rows row0:row1 are one contiguous slice
            dark, white = (x[rows[0] * width:rows[1] * width] for x in (dark, white))
        saturation = self.saturation
        if registration is not None:  # the native frames' dark and saturation level
            dark, inverse, maps, saturation = registration
            registration = (inverse, maps, height, width)
        fused.correct_arrays(
            raw.reshape(images, pixels, bands), dark, white, np.asarray(p).reshape(images, bands),
            k["coeffs"], k["projection"], k["bias"], k["white_xyz"], saturation, self.kernel.variant,
            (reflectance.reshape(images, pixels, N_WAVELENGTHS), lab.reshape(images, pixels, 3),
             quality.reshape(images, pixels)),
            threads=buffers.cpus(), residual=k["residual"], registration=registration,
        )
        outputs = tuple(jax.device_put(view, self.device, may_alias=True) for view, _ in pairs)
        del reflectance, lab, quality  # only the pool and the jax.Arrays refer to the memory now
        buffers.give(("host", tuple(raw.shape[:-1])), pairs)
        return CorrectionResult(*outputs, p)

    def _correct_mappable(self, raw) -> CorrectionResult:
        """`_whole` of traced frames, so that `jax.vmap` over the frames reuses dropped outputs'
        memory as `correct` on the stack does.

        Why. `jax.vmap(lambda r: sj.correct(r, calibration).lab)(frames)` runs `correct` on
        tracers, so the recycling route cannot apply and every call writes its outputs into
        fresh pages: 3.5 times slower per pixel than `correct(frames, calibration)`
        (benchmarks/bench_batch.py). Here the frames' mapping rule
        (`jax.custom_batching.custom_vmap`) sees the stacked frames and corrects them as one
        stack (`_stack`): without an enclosing `jit` they are concrete and reuse memory; under
        `jit` they are traced and XLA owns the memory.

        Derivatives: `custom_vmap` has no transpose, so the whole sits in a `custom_jvp` whose
        JVP is `_whole`'s: `jax.grad` and `jax.jvp` with respect to raw see the derivative of
        the unmapped program. Without a mapping the value is `_whole`'s, traced as any call is.
        """
        if not self.concrete:  # a traced calibration: nothing to map over one calibration
            return self._whole(raw)

        def image(frames):
            return self._whole(frames)

        @jax.custom_batching.custom_vmap
        def mappable(frames):
            return image(frames)

        @mappable.def_vmap
        def over_frames(axis_size, in_batched, frames):
            del axis_size, in_batched  # the only argument, so mapped, with the mapped axis first
            if buffers.stageable(frames):  # vmap hands NumPy frames on as they are
                frames = buffers.stage(frames)
            result = self._stack(frames)
            return result, jax.tree_util.tree_map(lambda _: True, result)

        @jax.custom_jvp
        def differentiable(frames):
            return mappable(frames)

        @differentiable.defjvp
        def differentiable_jvp(primals, tangents):
            return jax.jvp(image, primals, tangents)

        return differentiable(raw)

    def _stack(self, frames) -> CorrectionResult:
        """Frames mapped with `jax.vmap`, stacked (N, ..., H, W, B): the plan of the stack's shape."""
        calibration = self._calibration()
        if not _checks.is_concrete(frames) or calibration is None:
            return self._whole(frames)
        return plan_for(calibration, frames.shape, frames.dtype)(frames)

    @property
    def calibration(self):
        """The calibration this plan prepares (None once it is gone: the plan still corrects)."""
        return self._calibration()


_no_flat_field = jax.jit(equations.flat_field_unusable)



def _on_device(raw, device) -> bool:
    """True when raw is a jax.Array on exactly `device`."""
    try:
        return raw.devices() == {device}
    except AttributeError:
        return False


def plan_for(calibration: Calibration, shape, dtype) -> Plan:
    """The calibration's plan for frames of `shape` and `dtype`: the one it keeps if it is
    concrete (built at the first call), else a plan built now inside the trace.

    The kept plans are told apart by the kernels' switches as well (SPHEREJAX_FUSED and
    SPHEREJAX_GPU_KERNEL, read at every call): switching a kernel off or the CPU kernel to its
    portable code takes effect at the next call, as it did when the mode was a static argument
    of every call, and a value the switch refuses is refused at every call."""
    shape, dtype = tuple(int(n) for n in shape), np.dtype(dtype)
    # The key holds all a kept plan depends on besides the calibration: the frames' shape and
    # dtype and the kernels' switches as set now (what `fused.mode` and `gpu_kernel.mode` make of
    # them is fixed for a process). Looked up first, before anything is worked out: the work
    # below costs about 0.2 ms a call, a sixth of a megapixel's correction on a GPU.
    key = (shape, dtype.str, os.environ.get(fused.SWITCH), os.environ.get(gpu_kernel.SWITCH))
    kept = calibration.__dict__.get("_plans")  # only a concrete calibration keeps plans
    if kept is not None and (plan := kept.get(key)) is not None:
        return plan
    make = Plan
    if calibration.band_transforms is not None:
        # Bands resampled into the reference geometry first, then the registered calibration's
        # own plan (`registered`).
        make = functools.partial(registered.RegisteredPlan, make_plan=plan_for)
    if not _concrete(calibration):
        return make(calibration, shape, dtype)
    # Made now even while a trace runs (frames mapped with `jax.vmap`, a caller's `jit`): a kept
    # plan holds the calibration's arrays, never that trace's tracers of them.
    with jax.ensure_compile_time_eval():
        return calibration._plan(key, lambda: make(calibration, shape, dtype))
