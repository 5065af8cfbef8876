"""`Calibration`: everything `correct` needs of an instrument, as a pytree, and what follows
from it alone (its compute dtype, its saturation level, the white patch's bounding box).

Below the engine (`spherejax._engine`) and the public functions (`spherejax.pipeline`), which
both read it. A calibration keeps the plans made for it (`Calibration._plan`), so that every
correction of one input, strip after strip, reuses one plan.
"""

from __future__ import annotations

import dataclasses
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks, band_resampling, colorimetry
from .estimation.kernel_residual import KernelResidual
from .grid import N_WAVELENGTHS

#: The calibration's parameters every pixel goes through: a NaN or infinity in any of them makes
#: every output NaN while the quality flags, which describe pixels, stay 0. Refused when concrete,
#: with every other array that is not a frame (`FRAMES`): the estimator's kernel residual too.
PARAMETERS = ("coeffs", "wiener", "wiener_offset")

#: The fields that hold per-pixel frames: a NaN or a white at or below the dark frame there
#: concerns its own pixels, which every kernel flags one by one (`Quality.WHITE_NOT_ABOVE_DARK`).
#: Every other array of a calibration is a parameter every pixel goes through
#: (`check_parameters`).
FRAMES = ("dark", "white", "patch")


#: Plans a calibration keeps (`Calibration._plan`): the frame shapes of a batch, a stack and its
#: frames, a few strip heights.
_PLANS_KEPT = 8
#: Crops a calibration keeps (`Calibration._part`): the strips of a large image and a few regions.
_PARTS_KEPT = 256
_plans_lock = threading.Lock()


class Calibration(eqx.Module):
    """Everything `correct` needs, as a pytree (its arrays are leaves; the names are static).

    Fields:
      dark: dark frame, (H, W, B), in raw counts.
      white: white-standard frame, (H, W, B), in raw counts, same exposure as the samples.
      patch: the reference white patch (Eq. 14-15), (H, W): a boolean mask, True on the patch
        (the normal case, and the only one a calibration file stores), or floating weights >= 0
        (0 = not in the patch), so that p, and all that follows, can be differentiated with
        respect to the patch: p is the weighted sum of white-standard signals over the weighted
        sum of sample signals. None for rows of a calibration (`rows`): `correct` then needs
        the whole image's p.
      coeffs: Stage II coefficients (B, 4), ordered c1..c4 (Eq. 23).
      wiener: Wiener matrix W (31, B) (`wiener.fit_wiener`): reflectance per unit of the Stage II
        response.
      illuminant: "D65", "A" or "F2" for Lab.
      observer: colour-matching functions for Lab (`colorimetry.OBSERVERS`).
      saturation: raw level at or above which a pixel counts as saturated; None = the full scale
        of an integer raw dtype (65535 for uint16) and no check for float raw.
      wiener_offset: the estimator's offset r0 (31,), reflectance (dimensionless, 400..700 nm
        step 10): the estimate is r = W v_tilde + r0 (`wiener.fit_wiener`). Default zeros, the
        plain linear Wiener estimate r = W v_tilde.
      wiener_residual: the estimator's kernel residual (`estimation.KernelResidual`, from
        `estimation.fit_kernel_estimator`): the estimate is then r = W v_tilde + r0 + A k(v_tilde)
        (E8). None (default): the affine estimator. Every kernel applies it (the kernel
        contract, `spherejax._engine.kernels`).
      band_transforms: (B, 2, 3) or None: each band's 2 x 3 affine map from the reference band's
        geometry to the band's own (x = column, y = row, pixel centres at integers; the session
        manifest's convention), estimated by `calibrate` (`band_registration`). With maps, every
        correction resamples each band's flat-fielded response into the reference geometry first
        (`band_resampling`); None (default, and every calibration made before registration
        existed): the bands are taken as in register, as before.
      wiener_offset, wiener_residual and band_transforms come last among the fields, so that
      positional construction keeps its meaning.
    """

    dark: jax.Array = eqx.field(converter=jnp.asarray)
    white: jax.Array = eqx.field(converter=jnp.asarray)
    patch: jax.Array | None = eqx.field(converter=lambda x: None if x is None else jnp.asarray(x))
    coeffs: jax.Array = eqx.field(converter=jnp.asarray)
    wiener: jax.Array = eqx.field(converter=jnp.asarray)
    illuminant: str = eqx.field(static=True, default="D65")
    observer: str = eqx.field(static=True, default=colorimetry.DEFAULT_OBSERVER)
    saturation: float | None = eqx.field(static=True, default=None)
    # A factory, not an array default: dataclasses refuse unhashable defaults. float32 zeros
    # promote nothing, so a float64 calibration without an offset still computes in float64.
    wiener_offset: jax.Array = eqx.field(
        converter=jnp.asarray, default_factory=lambda: np.zeros(N_WAVELENGTHS, np.float32)
    )
    wiener_residual: KernelResidual | None = None
    band_transforms: jax.Array | None = eqx.field(
        converter=lambda x: None if x is None else jnp.asarray(x), default=None
    )

    def __check_init__(self):
        # Unknown names raise here, at construction, rather than at the first correction.
        colorimetry.tristimulus_weights(self.illuminant, observer=self.observer)
        # jnp.asarray keeps complex values and a later cast drops their imaginary part; the patch
        # has a dtype check of its own (a boolean mask or real weights).
        for name in ("dark", "white", "coeffs", "wiener", "wiener_offset"):
            _checks.require_real(name, getattr(self, name))
        if self.dark.ndim != 3:
            raise ValueError(f"dark: expected shape (H, W, B), got {tuple(self.dark.shape)}")
        height, width, bands = self.dark.shape
        if 0 in self.dark.shape:
            raise ValueError(f"dark: expected at least one pixel and one band, got shape {tuple(self.dark.shape)}")
        _checks.require_shape("white", self.white, self.dark.shape, "the dark frame's (H, W, B)")
        if self.patch is not None:
            _checks.require_mask_or_weights("patch", self.patch, (height, width))
        _checks.require_shape(
            "coeffs", self.coeffs, (bands, 4), f"c1..c4 for each of the {bands} bands"
        )
        _checks.require_shape(
            "wiener", self.wiener, (N_WAVELENGTHS, bands), f"31 wavelengths x the {bands} bands"
        )
        _checks.require_shape(
            "wiener_offset", self.wiener_offset, (N_WAVELENGTHS,), "one reflectance offset r0 per wavelength, 400..700 nm step 10"
        )
        if self.wiener_residual is not None:
            if not isinstance(self.wiener_residual, KernelResidual):
                raise ValueError(f"wiener_residual: expected an estimation.KernelResidual or None, got {type(self.wiener_residual).__name__}")
            if self.wiener_residual.bands != bands:
                raise ValueError(f"wiener_residual: expected a residual of the {bands} bands, got one of {self.wiener_residual.bands}")
        if self.band_transforms is not None:
            band_resampling.check_transforms(self.band_transforms, bands, (height, width))
        if self.saturation is not None and not float(self.saturation) > 0:
            raise ValueError(f"saturation: expected a level > 0 or None, got {self.saturation!r}")
        self.check_values()

    def check_values(self) -> None:
        """Raise ValueError, one line naming the array, unless every parameter (every array but
        the frames) is finite, the sizes are within the documented limits and the estimator maps
        known responses to plausible reflectance (`check_sizes`, `check_parameters`,
        `check_plausible`). Values are checked only
        when concrete: a traced calibration (under jit, grad or vmap) passes.

        Construction runs it; `io.save_calibration` runs it again, since a calibration made by
        `jax.tree_util.tree_map` never went through construction."""
        residual = self.wiener_residual
        points = 0 if residual is None else int(residual.inducing.shape[0])
        itemsize = np.dtype(compute_dtype(self.dark, self)).itemsize
        check_sizes(self.bands, points, itemsize, self.image_shape)
        check_parameters(self, skip=FRAMES)
        if residual is not None and residual.variance is not None:
            check_variance(residual.variance)
        if all(_checks.is_concrete(x) for x in (self.coeffs, self.wiener, self.wiener_offset)):
            check_plausible(self.coeffs, self.wiener, self.wiener_offset, residual)

    @property
    def bands(self) -> int:
        return int(self.dark.shape[-1])

    @property
    def image_shape(self) -> tuple[int, int]:
        return int(self.dark.shape[0]), int(self.dark.shape[1])

    @property
    def patch_box(self) -> tuple[int, int, int, int] | None:
        """(row0, row1, col0, col1) bounding the patch (`patch_bounding_box`); None without a
        patch or when the patch is traced.

        Worked out once per calibration (finding it reads the whole mask, about 0.9 ms a
        megapixel): the patch is an immutable jax.Array, so its box cannot change."""
        if self.patch is None or not _checks.is_concrete(self.patch):
            return None
        known = self.__dict__.get("_patch_box")
        if known is None:
            known = (patch_bounding_box(self.patch),)
            object.__setattr__(self, "_patch_box", known)  # a frozen dataclass: its own memo
        return known[0]

    def _plan(self, key: tuple, make):
        """The plan this calibration keeps under `key` (frames' shape, dtype and kernel mode:
        `spherejax._engine.plan.plan_for`), made with `make()` at first use.

        The plans live and die with the calibration (an attribute of the instance, not a field:
        not part of the pytree, not pickled, not copied by `dataclasses.replace` or tree_map,
        whose new calibration gets plans of its own). The last `_PLANS_KEPT` shapes are kept."""
        with _plans_lock:
            plans = self.__dict__.get("_plans")
            if plans is None:
                plans = {}
                object.__setattr__(self, "_plans", plans)
            plan = plans.get(key)
        if plan is None:
            plan = make()  # outside the lock: it may compile
            with _plans_lock:
                plan = plans.setdefault(key, plan)
                while len(plans) > _PLANS_KEPT:
                    del plans[next(iter(plans))]
        return plan

    def __getstate__(self):
        # A pickled calibration (a dask worker's) carries its arrays, never its plans, which
        # hold compiled programs and device memory.
        return {name: value for name, value in self.__dict__.items() if name not in ("_plans", "_patch_box", "_parts", "_registered")}

    def rows(self, row0: int, row1: int) -> Calibration:
        """This calibration for image rows row0:row1 only, without the patch (None).

        For correcting an image in strips: `correct(raw[row0:row1], calibration.rows(row0, row1),
        p=patch_ratio(raw, calibration))` equals rows row0:row1 of `correct(raw, calibration)`.
        With band maps (`band_transforms`, carried into the rows' own coordinates) a strip's
        registered pixels come from native rows around it too: correct the rows
        `band_resampling.read_box` gives and keep the strip's own (`spherejax.stripwise` does);
        the rows alone leave their first and last rows flagged NOT_COVERED where a map reaches out.
        The same rows give the same object while it is kept (`_part`), and with it its plans.
        """
        height = self.image_shape[0]
        if not 0 <= row0 < row1 <= height:
            raise ValueError(f"rows: expected 0 <= row0 < row1 <= {height}, got {row0}:{row1}")
        return self._part(row0, row1, 0, self.image_shape[1])

    def box(self, row0: int, row1: int, col0: int, col1: int) -> Calibration:
        """This calibration for the pixels [row0:row1, col0:col1] only, without the patch: a region
        corrected with the whole image's p (`spherejax.measure`). Kept as `rows` is."""
        height, width = self.image_shape
        if not (0 <= row0 < row1 <= height and 0 <= col0 < col1 <= width):
            raise ValueError(f"box: expected 0 <= row0 < row1 <= {height} and 0 <= col0 < col1 <= {width}, "
                             f"got {row0}:{row1}, {col0}:{col1}")
        return self._part(row0, row1, col0, col1)

    def _part(self, row0: int, row1: int, col0: int, col1: int) -> Calibration:
        """The patchless crop [row0:row1, col0:col1], kept for a concrete calibration (the last
        `_PARTS_KEPT`: the strips of an image, a few measured regions), so that every input
        corrected by those rows or that region reuses one plan."""
        def crop():
            # dataclasses.replace carries every other field (the Wiener offset included) and runs
            # the checks again.
            # Maps, if any, in the crop's own pixel coordinates.
            transforms = self.band_transforms
            if transforms is not None:
                transforms = band_resampling.local_transforms(transforms, row0, col0)
            return dataclasses.replace(self, dark=self.dark[row0:row1, col0:col1],
                                       white=self.white[row0:row1, col0:col1], patch=None,
                                       band_transforms=transforms)

        if not _checks.is_concrete(self.dark):  # a traced calibration: its crops are traced too
            return crop()
        key = (row0, row1, col0, col1)
        with _plans_lock:
            parts = self.__dict__.setdefault("_parts", {})
            part = parts.get(key)
        if part is None:
            part = crop()
            with _plans_lock:
                part = parts.setdefault(key, part)
                while len(parts) > _PARTS_KEPT:
                    del parts[next(iter(parts))]
        return part


# ---------------------------------------------------------------------------------------------
# What every array of a calibration must hold (`Calibration.check_values`, run where a calibration
# is built, saved and opened: `spherejax.io.calibration_files`). Each check raises ValueError in
# one line naming the array, the value found and what was expected.

#: The most bands a calibration may have: the Stage II coefficients (B, 4), the Wiener matrix
#: (31, B) and the residual's whitening (B, B) grow with B. Multispectral cameras have 4 to 32
#: bands (the paper's 16) and pushbroom hyperspectral ones up to a few hundred; 256 admits them
#: all and keeps every per-pixel matrix of a calibration under 256 kB.
MAX_BANDS = 256

#: The most inducing points m of a kernel residual (`estimation.KernelResidual`, E10). The fit
#: makes at most max(`estimation.kernel_residual.INDUCING_POINT_COUNTS`) (64); applying m points costs every
#: pixel (B + 9) m multiply-adds and, on the jax.numpy path, 8 m bytes of working memory. 1024 is
#: the most the GPU kernel applies (`spherejax._engine.gpu_residual.MAX_INDUCING_POINTS`) and 16
#: times what the fit makes (64): a 192 x 272 frame then takes about a second and 0.5 GB, where 32 768
#: points (a 13 MB file) took 51 s and 11.5 GB.
MAX_INDUCING_POINTS = 1024

#: The most working memory one pixel's correction may need (`correction_bytes_per_pixel`), in
#: bytes. The affine estimator needs about 530 (16 bands, float32); a kernel residual adds 8 m
#: (float32) or 16 m (float64) bytes. 16 KiB admits 1024 inducing points in float32 with up to 64
#: bands, about 18 times the affine correction, and refuses what would make one frame's correction
#: need gigabytes per hundred thousand pixels.
MAX_CORRECTION_BYTES_PER_PIXEL = 16 << 10

#: The largest reflectance magnitude (1 = a perfect diffuser) a calibration may give for the
#: responses whose reflectance is known to be ordinary (`check_plausible`): the white standard's
#: (v = 1 in every band, p = 1), the training responses' mean (a kernel residual's centre), and
#: the residual's own term at its inducing points. Materials stay within 0..1, fluorescent whites
#: reach about 1.5, and a poorly conditioned fit overshoots by a few; 100 leaves room for all of
#: them (and for the random matrices of the tests, up to about 40) while refusing a parameter off
#: by orders of magnitude: Stage II's c1 or the Wiener matrix times 1e30, residual weights of 3e38,
#: which gave reflectance of 1e30 or infinity with quality 0.
PLAUSIBLE_REFLECTANCE = 100.0


def correction_bytes_per_pixel(bands: int, inducing_points: int, itemsize: int) -> int:
    """The working memory, in bytes, of one pixel's correction on the jax.numpy path (the one that
    holds the most intermediates): raw, v, v_tilde and the Stage II input (B each), reflectance and
    the residual's share of it (31 each), XYZ and Lab (3 each), the residual's distances and
    kernel values (m each) in the compute dtype (`itemsize` bytes), and the quality byte."""
    return itemsize * (4 * bands + 2 * N_WAVELENGTHS + 6 + 2 * inducing_points) + 1


def check_sizes(bands: int, inducing_points: int, itemsize: int, image_shape: tuple[int, int]) -> None:
    """Raise ValueError unless the bands and inducing points are within `MAX_BANDS` and
    `MAX_INDUCING_POINTS` and a pixel's correction needs at most `MAX_CORRECTION_BYTES_PER_PIXEL`
    (the message gives the estimate for one frame of `image_shape`). Needs shapes only: a
    calibration file is checked with it before any array is read."""
    if bands > MAX_BANDS:
        raise ValueError(f"dark: {bands} bands; expected at most {MAX_BANDS} (MAX_BANDS)")
    per_pixel = correction_bytes_per_pixel(bands, inducing_points, itemsize)
    frame = per_pixel * int(np.prod(image_shape, dtype=np.int64))
    need = f"about {per_pixel} bytes a pixel, {frame / 1e9:.3g} GB for one {image_shape[0]} x {image_shape[1]} frame"
    if inducing_points > MAX_INDUCING_POINTS:
        raise ValueError(f"wiener_residual.inducing: {inducing_points} inducing points, whose correction would need "
                         f"{need}; expected at most {MAX_INDUCING_POINTS} (MAX_INDUCING_POINTS)")
    if per_pixel > MAX_CORRECTION_BYTES_PER_PIXEL:
        raise ValueError(f"calibration: a correction would need {need} ({bands} bands, {inducing_points} inducing points, "
                         f"{itemsize}-byte floats); expected at most {MAX_CORRECTION_BYTES_PER_PIXEL} bytes a pixel "
                         "(MAX_CORRECTION_BYTES_PER_PIXEL)")


def _leaf_name(path) -> str:
    """`wiener_residual.weights` for the pytree path of a calibration's leaf."""
    return ".".join(str(getattr(key, "name", getattr(key, "key", getattr(key, "idx", key)))) for key in path)


def check_parameters(tree, *, skip: tuple[str, ...] = ()) -> None:
    """Raise ValueError naming the first array of `tree` (a `Calibration`, or any pytree of
    arrays) that holds a NaN or an infinity, its first such value and where; arrays under the
    top-level fields `skip` (the frames) are left out, and traced arrays pass.

    Every array leaf is checked, whatever its name: an estimator that carries new arrays is
    covered without a list to update."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        name = _leaf_name(path)
        if name.split(".")[0] in skip or not hasattr(leaf, "dtype"):
            continue
        _checks.require_finite(name, leaf)


def check_variance(variance) -> None:
    """Raise ValueError, one line naming the array, unless the kernel residual's variance
    (`estimation.ResidualVariance`, E15) has its prior s^2 and noise >= 0: they are variances
    (a negative one would make the propagated uncertainty the square root of a negative number).
    Traced values pass."""
    for name in ("prior", "noise"):
        values = getattr(variance, name)
        if not _checks.is_concrete(values):
            continue
        values = np.asarray(values, np.float64)
        bad = np.flatnonzero(~(values >= 0))
        if bad.size:
            raise ValueError(f"wiener_residual.variance.{name}: {values.flat[bad[0]]:.6g} at index {int(bad[0])}; "
                             "expected variances >= 0")


def _residual_term(inducing, weights, u) -> np.ndarray:
    """A k (n, 31) at whitened responses u (n, B), float64 (E8-E10 with the lengthscale folded)."""
    # |u - z|^2 expanded as `estimation.kernel_features` does: no (n, m, B) temporary.
    squared = (u * u).sum(axis=-1)[:, None] - 2.0 * (u @ inducing.T) + (inducing * inducing).sum(axis=-1)
    return np.exp(-0.5 * np.maximum(squared, 0.0)) @ weights.T


def _plausibility_cases(coeffs, wiener, offset, residual):
    """(what, reflectance (31,) or (n, 31)) the calibration gives for responses of known, ordinary
    reflectance, in float64 (overflow there is an error, not float32's infinity)."""
    white = coeffs.sum(axis=1)  # Eq. 23 at v = 1, p = 1: the white standard, v_tilde = c1 + c2 + c3 + c4
    estimator = "coeffs, wiener, wiener_offset" + ("" if residual is None else " and wiener_residual")
    cases = [(f"{estimator}: the white standard's response (v = 1, p = 1)", white)]
    if residual is not None:
        cases.append(("wiener_residual: the training responses' mean (its centre)", np.asarray(residual.centre, np.float64)))
    out = []
    for what, v_tilde in cases:
        reflectance = wiener @ v_tilde + offset
        if residual is not None:
            centre, whitening, inducing, weights = (np.asarray(x, np.float64) for x in
                                                    (residual.centre, residual.whitening, residual.inducing, residual.weights))
            reflectance = reflectance + _residual_term(inducing, weights, ((v_tilde - centre) @ whitening.T)[None])[0]
        out.append((what, reflectance))
    if residual is not None and not residual.__dict__.get("_plausible_at_inducing"):
        # Depends on the residual alone, which is immutable and shared by every crop of a
        # calibration (`Calibration.rows`): worked out once (m^2 B operations, 16 M for m = 1024).
        inducing, weights = np.asarray(residual.inducing, np.float64), np.asarray(residual.weights, np.float64)
        out.append(("wiener_residual.weights: the residual term A k at its inducing points", _residual_term(inducing, weights, inducing)))
    return out


def check_plausible(coeffs, wiener, offset, residual) -> None:
    """Raise ValueError unless the calibration's Stage II and estimator give reflectance within
    +-`PLAUSIBLE_REFLECTANCE` for the responses of `_plausibility_cases`, in float64.

    Finite parameters can still be absurd: Stage II's c1 times 1e30 makes every reflectance 1e30
    with quality 0, and residual weights of 3e38 overflow float32 to infinity near the training
    responses. A residual whose kernel has been checked once is remembered (it is immutable)."""
    coeffs, wiener, offset = (np.asarray(x, np.float64) for x in (coeffs, wiener, offset))
    if residual is not None and not all(_checks.is_concrete(x) for x in jax.tree_util.tree_leaves(residual)):
        residual = None  # traced: only the affine part can be checked
    with np.errstate(over="ignore", invalid="ignore"):
        cases = _plausibility_cases(coeffs, wiener, offset, residual)
    for what, reflectance in cases:
        bad = ~(np.abs(reflectance) <= PLAUSIBLE_REFLECTANCE)
        if bad.any():
            index = np.unravel_index(int(np.flatnonzero(bad)[0]), reflectance.shape)
            found = float(reflectance[index])
            raise ValueError(
                f"{what} gives reflectance {found:.3g} at {400 + 10 * int(index[-1])} nm; expected reflectance within "
                f"+-{PLAUSIBLE_REFLECTANCE:g} (PLAUSIBLE_REFLECTANCE: a parameter off by orders of magnitude)"
            )
    if residual is not None:
        object.__setattr__(residual, "_plausible_at_inducing", True)  # a frozen dataclass: its own memo


def compute_dtype(raw, calibration: Calibration):
    return _checks.float_dtype(
        raw, calibration.dark, calibration.white, calibration.coeffs, calibration.wiener,
        calibration.wiener_offset,
    )


def saturation_level(raw, calibration: Calibration):
    if calibration.saturation is not None:
        return float(calibration.saturation)
    if jnp.issubdtype(raw.dtype, jnp.integer):
        return float(jnp.iinfo(raw.dtype).max)
    return None


def patch_bounding_box(patch) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1) bounding the patch's nonzero entries (True or weight != 0), or
    None if the patch is traced.

    The white-patch ratio needs only the patch's pixels (0.1 % of the image in the paper's
    layout): slicing to this box keeps the ratio from making three passes over the whole cube.
    Pixels of weight 0 contribute nothing to the ratio's value, so leaving them out is exact.
    Differentiating with respect to the weights makes them tracers, so the ratio is then taken
    over the whole image and a weight of 0 gets its gradient too (which is not 0).
    """
    if not _checks.is_concrete(patch):
        return None
    mask = np.asarray(patch) != 0
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return None if rows.size == 0 else (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)


__all__ = [
    "FRAMES", "MAX_BANDS", "MAX_CORRECTION_BYTES_PER_PIXEL", "MAX_INDUCING_POINTS", "PARAMETERS", "PLAUSIBLE_REFLECTANCE",
    "check_parameters", "check_plausible", "check_variance", "check_sizes", "correction_bytes_per_pixel", "Calibration", "compute_dtype", "saturation_level", "patch_bounding_box"]
