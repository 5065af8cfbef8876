"""What the viewer shows of one corrected capture, without Qt or napari: a pixel's readout and a
region's measurement.

A `CorrectedCapture` is one output set of `spherejax correct` (N.reflectance.*, N.lab.*,
N.quality.png, N.preview.png), opened lazily through `spherejax.open_corrected`. Optionally it
holds the raw cube the output was corrected from and the calibration it was corrected with
(both checked against the output's attributes: the input's SHA-256 and the calibration's
checksum); with them, and a noise model in the calibration, a pixel's and a region's values come
with their propagated uncertainties (`spherejax.measure`, which sees the raw frames).

Values:
  pixel readout (`pixel`): the reflectance (31,) as the file holds it; L*a*b* (3,) as the Lab
    file holds it under the file's illuminant, else computed from that reflectance under the
    one asked for; the quality bits (an int) and their names; with raw frames, calibration and
    noise model, u_lab (3,) and u_reflectance (31,), standard uncertainties (k = 1) of the
    pixel's values (`measure` of a one-pixel region: the same first-order propagation as
    `correct(..., noise=)`).
  region (`region`): `spherejax.measure`'s `Measurement` of a mask, from the raw frames where
    they are held (covariances with a noise model), else `measurement.measure_reflectances` of
    the file's reflectances (the same mean, Lab and counts for the affine estimators; no
    covariance).
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib

import numpy as np

from .. import colorimetry, io
from ..io.corrected import open_corrected, output_stem, read_preview
from ..io.hashing import sha256_file
from ..measurement import Measurement, delta_e_and_u, measure, measure_reflectances
from ..quality import Quality

#: Chunks of rows (about 32 MB each: `io.corrected.CHUNK_BYTES`) a capture keeps for its readout.
_CACHED_CHUNKS = 4
#: The illuminants a readout can be asked for (`colorimetry.tristimulus_weights`).
ILLUMINANTS = ("D65", "A", "F2")


def quality_names(bits: int) -> list[str]:
    """The names of the quality bits set in `bits` (`spherejax.quality.Quality`), lowest first;
    [] for a good pixel (0). Bits no version of spherejax defines are named "bit N"."""
    names = []
    for bit in range(8):
        if int(bits) & (1 << bit):
            names.append(Quality(1 << bit).name or f"bit {bit}")  # IntFlag: None for 64 and 128
    return names


@dataclasses.dataclass(frozen=True)
class Reference:
    """What ΔE00 is measured against: L*a*b* (3,), its (3, 3) covariance or None (exact), and
    words naming it ("pixel (12, 40)", "region r1", "L*a*b* = (50, 0, 0)")."""

    lab: np.ndarray
    covariance: np.ndarray | None
    label: str

    @classmethod
    def typed(cls, text: str) -> Reference:
        """"L,a,b" as typed -> an exact reference; ValueError naming the text otherwise."""
        parts = [part.strip() for part in str(text).split(",")]
        try:
            lab = np.array([float(part) for part in parts], np.float64)
        except ValueError:
            lab = None
        if lab is None or lab.shape != (3,) or not np.all(np.isfinite(lab)) or not 0 <= lab[0] <= 100:
            raise ValueError(f"reference {text!r}: expected three numbers L,a,b with 0 <= L <= 100")
        return cls(lab, None, "L*a*b* = ({:g}, {:g}, {:g})".format(*lab))

    @classmethod
    def of_pixel(cls, readout: dict) -> Reference:
        """A pixel's readout (`CorrectedCapture.pixel`) as the reference, with its covariance."""
        if not np.all(np.isfinite(readout["lab"])):
            raise ValueError(f"pixel ({readout['row']}, {readout['col']}): has no L*a*b* (flagged: "
                             f"{', '.join(readout['quality_names']) or 'not finite'}); expected a good pixel")
        return cls(np.asarray(readout["lab"], np.float64), readout.get("lab_covariance"),
                   f"pixel ({readout['row']}, {readout['col']})")

    @classmethod
    def of_region(cls, name: str, measurement: Measurement) -> Reference:
        """A region's `Measurement` as the reference, with its covariance."""
        return cls(np.asarray(measurement.lab, np.float64), measurement.lab_covariance, f"region {name}")


class CorrectedCapture:
    """One output set of `spherejax correct`, with the raw cube and calibration where given.

    Args:
      path: any file of the set (N.reflectance.exr, N.reflectance.hdr, N.lab.*, N.quality.png,
        N.preview.png) or N (`spherejax.open_corrected`).
      calibration: the calibration file it was corrected with, or None.
      raw: the raw cube (a TIFF or EXR cube file) it was corrected from, or None; needs
        `calibration`.

    Raises:
      SpherejaxFileError: `path` is not a spherejax output; the calibration's checksum or the
        raw cube's SHA-256 is not the one the output names (one line naming both).
      CalibrationFileError: an unreadable calibration.
    """

    def __init__(self, path, calibration=None, raw=None):
        self.path = pathlib.Path(path)
        self.dataset = open_corrected(self.path)
        self.attributes = dict(self.dataset.attrs)
        self.shape = tuple(int(n) for n in self.dataset["reflectance"].shape[:2])
        self.wavelengths_nm = np.asarray(self.dataset["wavelength"].values, np.float64)
        self.file_illuminant = self.attributes.get("spherejax:illuminant")
        self.stem = output_stem(self.path)
        self.preview_path = self.stem.with_name(self.stem.name + ".preview.png")
        self.calibration = self.noise = self.raw = self.instrument_id = None
        self._chunks: dict[tuple[str, int], np.ndarray] = {}  # `_pixel_values`' cache
        self.observer = colorimetry.DEFAULT_OBSERVER
        self.calibration_path = None if calibration is None else pathlib.Path(calibration)
        self.raw_path = None if raw is None else pathlib.Path(raw)
        if raw is not None and calibration is None:
            raise ValueError(f"{raw}: a raw cube needs the calibration it was corrected with (-c CAL)")
        if calibration is not None:
            self._open_calibration(self.calibration_path)
        if raw is not None:
            self._open_raw(self.raw_path)

    # -- what was given beside the output, checked against it --------------------------------
    def _open_calibration(self, path: pathlib.Path) -> None:
        named = self.attributes.get("spherejax:calibration_checksum")
        calibration_file = io.open_calibration(path)
        try:
            header = calibration_file.header
            checksum = header.get("checksum")
            if named is not None and checksum != named:
                raise io.SpherejaxFileError(
                    path, f"has checksum {checksum}, but {self.reflectance_path} was corrected with a calibration of checksum {named}",
                    "the calibration file the output was corrected with",
                )
            if tuple(calibration_file.image_shape) != self.shape:
                raise io.SpherejaxFileError(
                    path, f"is for {calibration_file.image_shape[0]} x {calibration_file.image_shape[1]} images, "
                    f"but {self.reflectance_path} is {self.shape[0]} x {self.shape[1]}",
                    "the calibration file the output was corrected with",
                )
            self.noise = getattr(calibration_file, "noise_model", None)
            self.band_centres_nm = header["band_centres_nm"]
            self.instrument_id = header.get("instrument_id")
            self.bands = calibration_file.bands
            self.calibration = calibration_file.calibration()
        finally:
            calibration_file.close()
        self.observer = self.calibration.observer

    def _open_raw(self, path: pathlib.Path) -> None:
        named = self.attributes.get("spherejax:input_sha256")
        if named is not None and path.is_file():
            digest = sha256_file(path)
            if digest != named:
                raise io.SpherejaxFileError(
                    path, f"has SHA-256 {digest[:16]}..., but {self.reflectance_path} was corrected from an input "
                    f"with SHA-256 {named[:16]}...", "the raw cube the output was corrected from",
                )
        self.raw = io.read_cube(path, expected_shape=(*self.shape, self.bands), band_centres_nm=self.band_centres_nm)

    @property
    def reflectance_path(self) -> pathlib.Path:
        """The output's reflectance file (the name messages give)."""
        exr = self.stem.with_name(self.stem.name + ".reflectance.exr")
        return exr if exr.is_file() else self.stem.with_name(self.stem.name + ".reflectance.hdr")

    @property
    def has_uncertainty(self) -> bool:
        """True when pixels and regions come with propagated uncertainties."""
        return self.raw is not None and self.noise is not None

    @functools.cached_property
    def quality(self) -> np.ndarray:
        """(H, W) uint8 quality bits; zeros where the output has no quality mask."""
        if "quality" in self.dataset:
            return np.asarray(self.dataset["quality"].values, np.uint8)
        return np.zeros(self.shape, np.uint8)

    @functools.cached_property
    def preview(self) -> np.ndarray | None:
        """(H, W, 3) uint8 sRGB preview (N.preview.png), or None where there is none."""
        if not self.preview_path.is_file():
            return None
        return read_preview(self.preview_path, self.shape)

    # -- a pixel ----------------------------------------------------------------------------
    def _check_pixel(self, row, col) -> tuple[int, int]:
        height, width = self.shape
        if not (0 <= int(row) < height and 0 <= int(col) < width):
            raise ValueError(f"pixel ({row}, {col}): lies outside the {height} x {width} image")
        return int(row), int(col)

    def pixel(self, row: int, col: int, *, illuminant: str | None = None, uncertainty: bool = True,
              reference: Reference | None = None) -> dict:
        """What the viewer shows for one pixel (module docstring), as a dict:

        row, col; wavelength_nm (31,); reflectance (31,) float64 (the file's float32 values);
        lab (3,) and illuminant; quality (int) and quality_names (list of str); and, where the
        capture has raw frames and a noise model and `uncertainty` is True and the pixel is not
        flagged, u_lab (3,), u_reflectance (31,) and lab_covariance (3, 3); with a `reference`,
        delta_e (ΔE00 of the pixel's L*a*b* against it; NaN for a flagged pixel), delta_e_u (its
        standard uncertainty, NaN without the pixel's covariance) and reference (its words).
        """
        row, col = self._check_pixel(row, col)
        illuminant = illuminant or self.file_illuminant or "D65"
        reflectance = self._pixel_values("reflectance", row, col)
        if illuminant == self.file_illuminant and "lab" in self.dataset:
            lab = self._pixel_values("lab", row, col)
        else:
            lab = self._lab(reflectance, illuminant)
        quality = int(self.quality[row, col])
        readout = {
            "row": row, "col": col, "wavelength_nm": self.wavelengths_nm, "reflectance": reflectance,
            "lab": lab, "illuminant": illuminant, "quality": quality, "quality_names": quality_names(quality),
        }
        if uncertainty and self.has_uncertainty and quality == 0:
            mask = np.zeros(self.shape, bool)
            mask[row, col] = True
            try:
                measured = measure(self.raw, self.calibration, mask, self.noise, illuminant=illuminant)
            except ValueError:  # flagged in the raw frames' own correction: no value to propagate
                measured = None
            if measured is not None:
                readout.update(u_lab=measured.lab_u, u_reflectance=measured.reflectance_u,
                               lab_covariance=measured.lab_covariance)
        if reference is not None:
            readout["reference"] = reference.label
            if np.all(np.isfinite(lab)):
                readout["delta_e"], readout["delta_e_u"] = delta_e_and_u(
                    lab, readout.get("lab_covariance"), reference.lab, reference.covariance)
            else:
                readout["delta_e"] = readout["delta_e_u"] = float("nan")
        return readout

    def _pixel_values(self, name: str, row: int, col: int) -> np.ndarray:
        """One pixel of a variable, float64, through a cache of the last chunks of rows read:
        the file is read a chunk of whole rows at a time (`open_corrected`), and the cursor
        passing over an image asks for pixel after pixel of the same few chunks."""
        data = self.dataset[name].data
        bounds = np.cumsum((0, *data.chunks[0]))
        block = int(np.searchsorted(bounds, row, side="right")) - 1
        key = (name, block)
        rows = self._chunks.pop(key, None)
        if rows is None:
            rows = np.asarray(data.blocks[block])
            while len(self._chunks) >= _CACHED_CHUNKS:
                self._chunks.pop(next(iter(self._chunks)))
        self._chunks[key] = rows  # the most recently used last
        return np.asarray(rows[row - bounds[block], col], np.float64)

    def _lab(self, reflectance: np.ndarray, illuminant: str) -> np.ndarray:
        if not np.all(np.isfinite(reflectance)):
            return np.full(3, np.nan)
        import jax.numpy as jnp

        lab = colorimetry.reflectance_to_lab(jnp.asarray(reflectance, jnp.float32), illuminant, observer=self.observer)
        return np.asarray(lab, np.float64)

    # -- a region ---------------------------------------------------------------------------
    def region(self, mask, *, illuminant: str | None = None) -> Measurement:
        """`spherejax.measure`'s `Measurement` of a (H, W) bool mask (module docstring)."""
        illuminant = illuminant or self.file_illuminant or "D65"
        mask = np.asarray(mask, bool)
        if self.raw is not None:
            return measure(self.raw, self.calibration, mask, self.noise, illuminant=illuminant)
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if rows.size == 0:
            raise ValueError("mask: selects no pixel; expected at least one True entry")
        # Only the region's bounding rows are read from the file (whole-row chunks).
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        reflectance = np.asarray(self.dataset["reflectance"][r0:r1, c0:c1].values)
        return measure_reflectances(
            reflectance, mask[r0:r1, c0:c1], self.quality[r0:r1, c0:c1], illuminant=illuminant, observer=self.observer,
        )

    def describe(self) -> str:
        """One line naming the output and what was given beside it."""
        parts = [f"{self.stem.name}: {self.shape[0]} x {self.shape[1]}"]
        if self.calibration_path is not None:
            parts.append(f"calibration {self.calibration_path.name}")
        if self.raw_path is not None:
            parts.append(f"raw {self.raw_path.name}")
        parts.append("with uncertainties" if self.has_uncertainty else "no uncertainties")
        return ", ".join(parts)


__all__ = ["CorrectedCapture", "ILLUMINANTS", "Reference", "quality_names"]
