"""Calibration from a session: Stage II coefficients (Section 4) and the Wiener matrix.

Reads a session's captures through `spherejax.io.Session` and measures every annotated region
with the same per-pixel path `correct` runs, so that calibration and correction can never
disagree about v, p or bad pixels:

1. v (Eq. 10) and p (Eq. 14-15) of every training capture, averaged over each region
   (35 x 35 px in the paper); bad pixels are left out of the averages.
2. Section 4's reference-background scheme: for patch i on background j the target is the
   Stage I response of the same patch on the reference background, p^{i,jref} v^{i,jref}
   (Eq. 19). The paper does not say which background it chose; by default this takes the
   background of median brightness (holder-mean Stage I response), so that on average the
   correction is as small as possible, and it is an option.
3. Stage II fitted by `fit_stage2` (the closed form of Eq. 22 by default).
4. The reflectance estimator from the target captures: their Stage II responses against their
   known reflectances (`fit_estimator`: the affine training-based or model-based Wiener
   estimator, or that plus the kernel regression of its residuals where the targets show a real
   gain from it; method and regularisers chosen by cross-validation that holds out whole groups
   of targets, e.g. charts or materials, when a manifest field names them).
0. Bands in register (before all of the above, unless asked not to): each band's map from the
   reference band's geometry (`band_registration.register_bands`) from the session's registration
   target if it holds one (role "registration"), else its target chart; the calibration carries
   the maps (`Calibration.band_transforms`), so every region below is measured on registered
   pixels, as `correct` will read them.
5. The noise model (`spherejax.uncertainty.NoiseModel`) for per-pixel uncertainties, when the
   camera's gain and read noise are known (arguments, or the session's metadata "camera"): the
   frames averaged from the frames' metadata "frames_averaged", the Stage II coefficients'
   covariance from the fit and the estimator's sampling covariance from its targets
   (`estimator_covariance`).
"""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np

from .pipeline import Calibration, correct
from .polynomial import MIN_SAMPLES, STATUS_NAMES, UNDETERMINED, fit_stage2_detailed, identity_coeffs, stage2, why_undetermined
from .uncertainty import NoiseModel
from .estimation import (
    ESTIMATOR_NAMES,
    EstimatorCovariance,
    ResidualKernelEstimator,
    estimator_covariance,
    fit_estimator,
    validate_method,
)
from .calibrate_registration import (
    check_registration_frame,
    register_session_bands,
    registration_frame,
    registration_line,
    registration_summary,
)
from .grid import N_WAVELENGTHS
from .number_text import json_ready


@dataclasses.dataclass
class RegionMeasurement:
    """One annotated region of one capture, averaged: v (B,), p (B,), the holder mean of v (B,)
    and, after Stage II, v_stage2 (B,). `reflectance` is the known one (31,) if annotated."""

    frame_id: str
    set: str | None
    background: str | None
    patch: str
    v: np.ndarray
    p: np.ndarray
    holder_v: np.ndarray
    reflectance: np.ndarray | None


def base_calibration(session) -> Calibration:
    """A Calibration with the session's dark, white standard and patch mask, identity Stage II
    and a zero Wiener matrix: enough to measure v and p with `correct`."""
    bands = len(session.band_centres_nm)
    return Calibration(
        dark=np.asarray(session.dark(), np.float32),
        white=np.asarray(session.white(), np.float32),
        patch=session.white_patch_mask(),
        coeffs=identity_coeffs(bands),
        wiener=np.zeros((N_WAVELENGTHS, bands), np.float32),
        saturation=float(session.saturation),
    )


def _region_mean(cube: np.ndarray, region) -> np.ndarray:
    """nan-mean of an (H, W, C) array over a region's rectangle -> (C,); NaN if nothing usable."""
    r0, r1, c0, c1 = region.region
    block = cube[r0:r1, c0:c1].reshape(-1, cube.shape[-1])
    usable = np.all(np.isfinite(block), axis=-1)
    if not usable.any():
        return np.full(cube.shape[-1], np.nan)
    return block[usable].mean(axis=0)


def _finite_mean(values: np.ndarray) -> np.ndarray:
    """Mean over axis 0 of the finite entries, NaN where there is none: np.nanmean without its
    RuntimeWarning ("Mean of empty slice"), which would print lines beside the one-line error a
    dark capture gets further on (`_check_patch_ratios`)."""
    finite = np.isfinite(values)
    count = finite.sum(axis=0)
    total = np.where(finite, values, 0.0).sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def measure_frames(session, frames, calibration: Calibration) -> list[RegionMeasurement]:
    """Region averages of v and p for `frames` (FrameInfo) of `session`."""
    holder = session.holder_mask()
    measurements = []
    for frame in frames:
        result = correct(session.read(frame), calibration, intermediates=True)
        v = np.asarray(result.v, np.float64)
        p = np.asarray(result.p, np.float64)
        holder_v = _finite_mean(v[holder])
        for region in frame.regions:
            measurements.append(RegionMeasurement(
                frame.id, frame.set, frame.background, region.patch,
                _region_mean(v, region), p, holder_v, region.reflectance,
            ))
    return measurements


#: A white standard with fewer usable pixels than this is refused: a calibration from it would
#: flag, or silently mis-scale, most of every image it corrects.
MIN_USABLE_WHITE_FRACTION = 0.5


def _check_white_standard(session, base: Calibration) -> None:
    """Raise ValueError naming the white frame unless most pixels, and the patch, have a white
    signal that is finite, above dark in every band and below saturation (Eq. 10 needs it)."""
    dark, white = np.asarray(base.dark), np.asarray(base.white)
    signal = white - dark
    usable = np.all(np.isfinite(signal) & (signal > 0) & (white < base.saturation), axis=-1)
    patch = np.asarray(base.patch)
    if usable.mean() < MIN_USABLE_WHITE_FRACTION or not usable[patch].any():
        path = session.frame_path(session.frames_with(role="white")[0])
        raise ValueError(
            f"{path}: the white standard is above the dark frame and below saturation in only "
            f"{100 * usable.mean():.1f} % of pixels and {100 * usable[patch].mean():.1f} % of the "
            f"white patch (expected nearly all: is it the white standard, at the right exposure?)"
        )


def check_frames(session, registration: bool = True) -> None:
    """Raise ValueError, one line naming the file, unless the session's white standard is usable
    (`_check_white_standard`) and, with `registration`, it holds a frame to register the bands by
    (`calibrate_registration.check_registration_frame`): in that order, so that a bad white
    standard is named as such and not as a chart without edges (its flat field has none). Reads
    the dark, white and registration frames; the command line calls it before any other work."""
    _check_white_standard(session, base_calibration(session))
    if registration:
        check_registration_frame(session)


def _check_patch_ratios(session, frames, measurements: list[RegionMeasurement]) -> None:
    """Raise ValueError naming the first training capture whose white-patch ratio (Eq. 15) is
    not finite: its patch reads no signal above dark, so Stage II cannot be fitted from it."""
    bad = {m.frame_id for m in measurements if not np.all(np.isfinite(m.p))}
    for frame in frames:
        if frame.id in bad:
            raise ValueError(
                f"{session.frame_path(frame)}: the white patch reads no usable signal above dark "
                "in some band, so its white-patch ratio is not finite (expected the patch lit, "
                "not saturated)"
            )


def reference_background(measurements: list[RegionMeasurement]) -> str:
    """The background of median brightness: the median over backgrounds of the mean holder
    Stage I response p * holder_v over bands and captures."""
    brightness: dict[str, list[float]] = {}
    for m in measurements:
        brightness.setdefault(m.background, []).append(float(np.mean(m.p * m.holder_v)))
    ordered = sorted(brightness, key=lambda name: np.mean(brightness[name]))
    return ordered[len(ordered) // 2]


def stage2_training_data(measurements: list[RegionMeasurement], reference: str):
    """(v, p, target), each (n, B): Eq. 19 with the reference background `reference`.

    Samples of patches never measured on the reference background are left out.
    """
    backgrounds = {m.background for m in measurements}
    if reference not in backgrounds:
        raise ValueError(
            f"reference background {reference!r} is not among the training backgrounds "
            f"{sorted(backgrounds)}"
        )
    on_reference: dict[str, list[np.ndarray]] = {}
    for m in measurements:
        if m.background == reference:
            on_reference.setdefault(m.patch, []).append(m.p * m.v)
    rows = [m for m in measurements if m.patch in on_reference]
    v = np.stack([m.v for m in rows])
    p = np.stack([m.p for m in rows])
    target = np.stack([np.mean(on_reference[m.patch], axis=0) for m in rows])
    return v, p, target


def check_session(session, reference: str | None = None, wiener_groups: str | None = None) -> None:
    """Raise ValueError naming the manifest unless `session` can be calibrated: training
    captures with regions, a target capture with known reflectances, `reference` (if given)
    among the training backgrounds, and `wiener_groups` (if given) naming at least two groups of
    targets. Cheap: reads no pixels."""
    manifest = session.manifest_path
    training = session.frames_with(role="sample", set="training")
    if not any(frame.regions for frame in training):
        raise ValueError(f"{manifest}: no training capture (role 'sample', set 'training') with patch regions to fit Stage II")
    targets = session.frames_with(role="target")
    known = sum(1 for frame in targets for region in frame.regions if region.reflectance is not None)
    if known < 2:
        raise ValueError(f"{manifest}: the target captures hold {known} regions with known reflectance; the Wiener matrix needs at least 2")
    backgrounds = sorted({frame.background for frame in training})
    samples = [region.patch for frame in training for region in frame.regions]
    if len(samples) < MIN_SAMPLES or len(backgrounds) < 2 or len(set(samples)) < 2:
        raise ValueError(
            f"{manifest}: the training captures hold {len(samples)} patch regions of {len(set(samples))} "
            f"patch(es) on {len(backgrounds)} background(s); Stage II's 4 coefficients per band need at "
            f"least {MIN_SAMPLES} regions, 2 patches and 2 backgrounds (the paper: 9 patches on 10)"
        )
    if reference is not None and reference not in backgrounds:
        raise ValueError(f"{manifest}: no training background named {reference!r} (expected one of {backgrounds})")
    if wiener_groups is not None:
        _check_groups(session, target_groups(session, targets, wiener_groups), wiener_groups)


def _check_groups(session, groups, field: str) -> None:
    if len(set(groups)) < 2:
        raise ValueError(
            f"{session.manifest_path}: every target is in group {groups[0]!r} of field {field!r}; "
            "expected at least 2 groups to hold out in turn (or no --wiener-groups)"
        )


@dataclasses.dataclass
class CalibrationReport:
    """What `calibrate_session` did, for the calibration file's metadata and the log."""

    reference_background: str
    training_samples: int
    training_patches: int
    training_backgrounds: int
    targets: int
    wiener_method: str
    wiener_cross_validation: list[dict]
    stage2_loss: str
    stage2_rms_residual: list[float]
    stage2_status: list[str]
    stage2_dropped_samples: list[int]
    unconverged_bands: list[int]
    #: The calibration's noise model (`spherejax.NoiseModel`), None without gain and read noise.
    noise_model: NoiseModel | None = None
    #: How the noise model was made, or why there is none (one line each).
    noise_notes: list[str] = dataclasses.field(default_factory=list)
    #: How the bands were registered (`registration_summary`), or None when they were not.
    band_registration: dict | None = None

    def as_dict(self) -> dict:
        """Plain JSON: the fields, with the noise model as `noise_model_summary` (its numbers
        and which covariances it holds, not the arrays; the calibration file stores those)."""
        out = dataclasses.asdict(dataclasses.replace(self, noise_model=None))
        out["noise_model"] = noise_model_summary(self.noise_model)
        return out


def _plain(x):
    """A NoiseModel field as JSON: a number (an integral one as int) or a list, each the shortest
    decimal of the field's own precision (`number_text.json_ready`)."""
    value = np.asarray(x)
    if value.ndim == 0:
        number = float(value)
        if number.is_integer() and abs(number) < 2**53:
            return int(number)
    return json_ready(value)


def noise_model_summary(model: NoiseModel | None) -> dict | None:
    """A short JSON summary of a noise model (None for None): gain, read noise, frames averaged,
    the white standard's uncertainty and whether each covariance is present."""
    if model is None:
        return None
    return {
        "gain_e_per_count": _plain(model.gain),
        "read_noise_counts": _plain(model.read_noise),
        "dark_frames": _plain(model.dark_frames),
        "white_frames": _plain(model.white_frames),
        "sample_frames": _plain(model.sample_frames),
        "white_reflectance_u": _plain(model.white_reflectance_u),
        "coeffs_covariance": model.coeffs_covariance is not None,
        "estimator_covariance": model.estimator_covariance is not None,
    }


def noise_model_line(report: CalibrationReport) -> str:
    """One line for the log: the noise model stored, or how to supply one."""
    model = report.noise_model
    if model is None:
        return (
            "noise model: none stored (the camera's gain and read noise are not both known from "
            "the session; give them with --gain E_PER_COUNT --read-noise COUNTS)"
        )

    def shown(x, unit):
        value = np.asarray(x, np.float64)
        if value.ndim == 0:
            return f"{float(value):.4g} {unit}"
        return f"{float(value.mean()):.4g} {unit} (mean of {value.size} bands)"

    covariances = [name for name, present in (
        ("Stage II", model.coeffs_covariance is not None), ("estimator", model.estimator_covariance is not None),
    ) if present]
    frames = f"{_plain(model.dark_frames)} dark / {_plain(model.white_frames)} white / {_plain(model.sample_frames)} sample frames"
    return (
        f"noise model: gain {shown(model.gain, 'e-/count')}, read noise {shown(model.read_noise, 'counts')}, "
        f"{frames}, white standard u {shown(model.white_reflectance_u, '(relative)')}, "
        f"covariances: {', '.join(covariances) or 'none'}"
    )


#: `--wiener-groups` names that are frame fields rather than keys of a frame's metadata.
FRAME_GROUP_FIELDS = ("id", "set", "background")


def target_groups(session, frames, field: str) -> list[str]:
    """The group of each target region of `frames`: the frame's `field` ("id", "set",
    "background") or, for any other name, the value of that key in the frame's metadata.
    Raises ValueError naming the manifest and the first frame that lacks it."""
    groups = []
    for frame in frames:
        if field in FRAME_GROUP_FIELDS:
            value = getattr(frame, field)
        else:
            value = frame.metadata.get(field)
        if value is None or isinstance(value, (dict, list)):
            raise ValueError(
                f"{session.manifest_path}: target frame {frame.id!r} has no {field!r} to group targets by "
                f"(got {value!r}; expected a string or number in the frame's metadata, or one of {FRAME_GROUP_FIELDS})"
            )
        groups.extend([str(value)] * sum(region.reflectance is not None for region in frame.regions))
    return groups


def _refuse_undetermined(session, bands, v, p, target) -> None:
    """Raise ValueError naming the manifest if Stage II cannot be determined in `bands` (indices):
    a calibration with NaN coefficients would flag every pixel it corrects."""
    if len(bands):
        band = int(bands[0])
        raise ValueError(
            f"{session.manifest_path}: Stage II cannot be fitted in {len(bands)} band(s), first "
            f"{int(session.band_centres_nm[band])} nm: its training samples have "
            f"{why_undetermined(v[:, band], p[:, band], target[:, band])} (saturated, dark or flagged "
            "training regions?)"
        )


#: The session metadata "camera" keys of a noise model: (key, argument, what, strictly positive).
_CAMERA_KEYS = (
    ("gain_e_per_count", "gain", "electrons per count", True),
    ("read_noise_counts", "read_noise", "one frame's read noise in counts rms", False),
    ("white_reflectance_u", "white_reflectance_u", "the white standard's relative standard uncertainty", False),
)


def _noise_value(value, bands: int, positive: bool):
    """`value` as float32 (a number or one per band) if it is finite and > 0 (`positive`) or
    >= 0, else None."""
    if isinstance(value, bool) or (isinstance(value, (list, tuple)) and any(isinstance(v, bool) for v in value)):
        return None
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError, OverflowError):
        return None
    if array.dtype != np.float64 or array.ndim > 1 or (array.ndim == 1 and array.shape[0] != bands):
        return None
    if not np.all(np.isfinite(array)) or not np.all(array > 0 if positive else array >= 0):
        return None
    return array.astype(np.float32)


def check_noise_arguments(bands: int, **values) -> None:
    """Raise ValueError (one line, naming the argument) unless each of gain, read_noise and
    white_reflectance_u given is a finite number (or one per band): gain > 0, the others >= 0."""
    for _, name, what, positive in _CAMERA_KEYS:
        value = values.get(name)
        if value is not None and _noise_value(value, bands, positive) is None:
            bound = "> 0" if positive else ">= 0"
            raise ValueError(f"{name}: expected {what}, a finite number {bound} or one per band ({bands}), got {value!r}")


def _frames_of(session, frame) -> float | None:
    """The frame's metadata "frames_averaged" (None when absent); ValueError naming the manifest
    and the frame when it is not a number >= 1."""
    value = frame.metadata.get("frames_averaged")
    if value is None:
        return None
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 1
    if not ok:
        raise ValueError(
            f"{session.manifest_path}: frame {frame.id!r} has metadata frames_averaged {value!r} "
            "(expected the number of frames averaged, >= 1)"
        )
    return value


def _camera_record(session, notes: list[str]) -> dict:
    """The session's metadata "camera" object ({} when absent, or noted when not an object)."""
    record = session.metadata.get("camera")
    if record is None:
        return {}
    if not isinstance(record, dict):
        notes.append(f"session metadata camera is {record!r}, not an object with gain_e_per_count and read_noise_counts: not used")
        return {}
    return record


def build_noise_model(
    session, fit, responses, reflectances, estimator, *, gain=None, read_noise=None, white_reflectance_u=None,
) -> tuple[NoiseModel | None, list[str]]:
    """The calibration's `NoiseModel` (module docstring, step 5) and notes on how it was made.

    Args:
      session: the session (its metadata "camera" and frames' "frames_averaged").
      fit: the Stage II `Stage2Fit` (its covariance).
      responses, reflectances: the estimator's training targets (n, B) and (n, 31).
      estimator: the fitted `WienerEstimator`.
      gain, read_noise, white_reflectance_u: override the session's metadata "camera".

    Returns:
      (model or None when gain or read noise is unknown, notes). All fields float32, like the
      calibration's arrays.

    Raises:
      ValueError: an argument out of range (`check_noise_arguments`), or a session "camera"
        value or frame "frames_averaged" that is used and invalid (naming the manifest).
    """
    bands = session.bands
    check_noise_arguments(bands, gain=gain, read_noise=read_noise, white_reflectance_u=white_reflectance_u)
    notes: list[str] = []
    camera = _camera_record(session, notes)
    given = {"gain": gain, "read_noise": read_noise, "white_reflectance_u": white_reflectance_u}
    values = {}
    for key, name, what, positive in _CAMERA_KEYS:
        if given[name] is not None:
            values[name] = _noise_value(given[name], bands, positive)
        elif key in camera:
            values[name] = _noise_value(camera[key], bands, positive)
            if values[name] is None:
                bound = "> 0" if positive else ">= 0"
                raise ValueError(
                    f"{session.manifest_path}: metadata camera.{key} is {camera[key]!r} (expected {what}, a finite "
                    f"number {bound} or one per band ({bands}); or give {name}= to calibrate_session)"
                )
        else:
            values[name] = None
    if values["gain"] is None or values["read_noise"] is None:
        missing = [name for name in ("gain", "read_noise") if values[name] is None]
        notes.append(
            f"no noise model: {' and '.join(missing)} unknown (the session's metadata camera has no "
            f"{' or '.join(k for k, n, _, _ in _CAMERA_KEYS if n in missing)}); give gain= and read_noise= "
            "(spherejax calibrate --gain E_PER_COUNT --read-noise COUNTS)"
        )
        return None, notes
    if values["white_reflectance_u"] is None:
        values["white_reflectance_u"] = np.float32(0.0)
        notes.append("white standard's certificate uncertainty not given: taken as 0")

    frames = {}
    for role in ("dark", "white"):
        frame = session.frames_with(role=role)[0]
        count = _frames_of(session, frame)
        if count is None:
            notes.append(f"{role} frame {frame.id!r} records no frames_averaged: taken as 1")
            count = 1
        frames[role] = count
    counts = [c for c in (_frames_of(session, f) for f in (*session.frames_with(role="sample"), *session.frames_with(role="target"))) if c is not None]
    if counts:
        tally = collections.Counter(counts)
        most = max(tally.values())
        frames["sample"] = min(c for c, n in tally.items() if n == most)  # a tie: the fewer frames
        if len(tally) > 1:
            notes.append(f"sample and target frames average {sorted(tally)} frames: sample_frames = {frames['sample']}, the most common")
    else:
        frames["sample"] = 1
        notes.append("no sample or target frame records frames_averaged: sample_frames taken as 1")

    coeffs_covariance = np.asarray(fit.covariance, np.float64)
    if not np.all(np.isfinite(coeffs_covariance)):
        bad = np.flatnonzero(~np.all(np.isfinite(coeffs_covariance), axis=(1, 2)))
        notes.append(
            f"Stage II covariance not finite in {len(bad)} band(s), first {int(session.band_centres_nm[bad[0]])} nm "
            "(no degree of freedom left?): coefficients taken as exact"
        )
        coeffs_covariance = None
    else:
        coeffs_covariance = coeffs_covariance.astype(np.float32)
    try:
        covariance = estimator_covariance(responses, reflectances, estimator=estimator)
        estimator_cov = EstimatorCovariance(
            gram=np.asarray(covariance.gram, np.float32), residual=np.asarray(covariance.residual, np.float32)
        )
    except ValueError as error:
        notes.append(f"no estimator covariance: {' '.join(str(error).split())}")
        estimator_cov = None
    model = NoiseModel(
        gain=values["gain"], read_noise=values["read_noise"],
        dark_frames=np.float32(frames["dark"]), white_frames=np.float32(frames["white"]),
        sample_frames=np.float32(frames["sample"]), white_reflectance_u=values["white_reflectance_u"],
        coeffs_covariance=coeffs_covariance, estimator_covariance=estimator_cov,
    )
    return model, notes


def calibrate_session(
    session, *, reference: str | None = None, loss: str = "l2", illuminant: str = "D65",
    wiener_method: str = "auto", wiener_groups: str | None = None,
    gain=None, read_noise=None, white_reflectance_u=None, registration: bool = True,
):
    """Fit Stage II and the reflectance estimator from a session's training and target captures.

    Args:
      session: a `spherejax.io.Session` with training samples (role "sample", set "training",
        regions naming their patch) and target captures (role "target", regions with known
        reflectance).
      reference: the reference background of Section 4; None picks `reference_background`.
      loss: "l2" (closed form, default), "huber", "cauchy" or "tukey" (`fit_stage2_detailed`);
        bands whose fit did not converge are listed in the report, not raised.
      illuminant: stored in the Calibration for Lab.
      wiener_method: "auto" (default: the affine method with the least cross-validated error,
        or the kernel estimator on it where it gains enough, `fit_estimator`), "training" or
        "model" (affine), or "kernel" (the residual kernel estimator whatever its gain).
      wiener_groups: a manifest field naming each target capture's group (`target_groups`):
        cross-validation then holds out one group at a time; None: k folds of alike targets.
      gain: the camera's electrons per count (a number or one per band), overriding the
        session's metadata "camera" "gain_e_per_count".
      read_noise: one frame's read noise in counts rms, overriding "read_noise_counts".
      white_reflectance_u: the white standard's relative standard uncertainty, overriding
        "white_reflectance_u" (default 0).
      registration: estimate each band's map and correct through it (default); False takes the
        bands as in register and stores no maps (`--no-registration`).

    Returns:
      (Calibration, CalibrationReport); report.noise_model is the `NoiseModel` when gain and read
      noise are known (`build_noise_model`), else None, and report.noise_notes says how.
    """
    check_noise_arguments(session.bands, gain=gain, read_noise=read_noise, white_reflectance_u=white_reflectance_u)
    check_session(session, reference, wiener_groups)
    base = base_calibration(session)
    _check_white_standard(session, base)
    registration_record = None
    if registration:
        base, registration_record = register_session_bands(session, base)
    training = session.frames_with(role="sample", set="training")
    targets = session.frames_with(role="target")
    measurements = measure_frames(session, training, base)
    _check_patch_ratios(session, training, measurements)
    reference = reference or reference_background(measurements)
    v, p, target = stage2_training_data(measurements, reference)
    usable = np.sum(np.isfinite(v) & np.isfinite(p) & np.isfinite(target), axis=0)
    _refuse_undetermined(session, np.flatnonzero(usable < MIN_SAMPLES), v, p, target)
    fit = fit_stage2_detailed(v, p, target, loss)
    _refuse_undetermined(session, np.flatnonzero(np.asarray(fit.status) == UNDETERMINED), v, p, target)
    coeffs = np.asarray(fit.coeffs)
    prediction = np.asarray(stage2(v, p, coeffs))
    residual = np.sqrt(np.nanmean((prediction - target) ** 2, axis=0))

    with_stage2 = dataclasses.replace(base, coeffs=coeffs.astype(np.float32))
    validate_method(wiener_method, "wiener method", ESTIMATOR_NAMES)
    groups = None if wiener_groups is None else target_groups(session, targets, wiener_groups)
    target_measurements = [m for m in measure_frames(session, targets, with_stage2) if m.reflectance is not None]
    responses = np.asarray(stage2(np.stack([m.v for m in target_measurements]), np.stack([m.p for m in target_measurements]), coeffs))
    reflectances = np.stack([m.reflectance for m in target_measurements])
    usable = np.all(np.isfinite(responses), axis=1)
    if usable.sum() < 2:
        raise ValueError(
            f"{session.manifest_path}: only {int(usable.sum())} of the {len(usable)} target regions "
            "give a finite response (expected at least 2 for the Wiener matrix: are the target "
            "captures dark or saturated?)"
        )
    if groups is not None:
        groups = [g for g, keep in zip(groups, usable) if keep]
        _check_groups(session, groups, wiener_groups)
    estimator = fit_estimator(responses[usable], reflectances[usable], method=wiener_method, groups=groups)
    kernel_residual = estimator.kernel.astype(np.float32) if isinstance(estimator, ResidualKernelEstimator) else None
    # The estimator covariance (N7) is the affine estimator's (of a kernel estimator, its mean's,
    # whose residuals on the targets are the larger: conservative).
    noise_model, noise_notes = build_noise_model(
        session, fit, responses[usable], reflectances[usable], getattr(estimator, "affine", estimator),
        gain=gain, read_noise=read_noise, white_reflectance_u=white_reflectance_u,
    )

    calibration = Calibration(
        dark=base.dark, white=base.white, patch=base.patch,
        coeffs=coeffs.astype(np.float32), wiener=np.asarray(estimator.matrix, np.float32),
        wiener_offset=np.asarray(estimator.offset, np.float32),
        illuminant=illuminant, saturation=base.saturation, wiener_residual=kernel_residual,
        band_transforms=base.band_transforms,
    )
    report = CalibrationReport(
        reference_background=reference,
        training_samples=int(v.shape[0]),
        training_patches=len({m.patch for m in measurements}),
        training_backgrounds=len({m.background for m in measurements}),
        targets=int(usable.sum()),
        wiener_method=estimator.method,
        wiener_cross_validation=[cv.as_dict() for cv in estimator.cross_validation],
        stage2_loss=loss,
        stage2_rms_residual=json_ready(residual),  # the shortest decimals of its precision
        stage2_status=[STATUS_NAMES[int(x)] for x in np.asarray(fit.status)],
        stage2_dropped_samples=[int(x) for x in np.asarray(fit.dropped)],
        unconverged_bands=sorted(fit.problems()),
        noise_model=noise_model,
        noise_notes=noise_notes,
        band_registration=registration_record,
    )
    return calibration, report


__all__ = [
    "RegionMeasurement",
    "CalibrationReport",
    "base_calibration",
    "check_session",
    "measure_frames",
    "reference_background",
    "stage2_training_data",
    "calibrate_session",
    "target_groups",
    "build_noise_model",
    "check_noise_arguments",
    "noise_model_summary",
    "noise_model_line",
    "registration_frame",
    "check_frames",
    "check_registration_frame",
    "register_session_bands",
    "registration_summary",
    "registration_line",
]
