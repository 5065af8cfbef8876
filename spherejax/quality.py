"""The quality bits of `CorrectionResult.quality`: why a pixel's outputs are NaN.

One `enum.IntFlag`, `Quality`, whose members are plain ints where files and arrays hold them
(uint8 masks, the quality PNG's palette, JSON and CSV counts): `Quality.SATURATED == 1`. 0 is a
good pixel. Every kernel (the jax.numpy definition `spherejax.equations.pixel_outputs`, the fused
CPU kernel `spherejax/_engine/kernel/fused_correct.h`, the Pallas GPU kernel) sets the same bits.
"""

from __future__ import annotations

import enum


class Quality(enum.IntFlag):
    """Bits of the (..., H, W) uint8 quality mask; a pixel with any bit set has NaN outputs."""

    #: raw at or above the saturation level in some band
    SATURATED = 1
    #: raw NaN or infinite in some band (float input), or an output (reflectance or Lab) NaN or
    #: infinite though the inputs were finite: an estimate that overflows float32, e.g. a raw of
    #: 1e38 over a white signal of one count (`equations.flag_nonfinite_outputs`). One bit for
    #: both: either way a value was not finite, and files keep their bits (no new bit needed).
    NONFINITE = 2
    #: white <= dark (or not finite) in some band: no flat field
    WHITE_NOT_ABOVE_DARK = 4
    #: the white-patch ratio of some band is not finite: the whole image is bad
    PATCH_UNUSABLE = 8
    #: raw below the dark level by more than noise allows in some band (`BELOW_DARK_LIMIT`)
    BELOW_DARK = 16
    #: some band's image does not cover the pixel: bands registered into the reference band's
    #: geometry (`band_resampling`) and this pixel maps outside some band's frame
    NOT_COVERED = 32


# The names the public API has always exported, as plain ints: JAX takes an int subclass in
# arithmetic only through int(), and files store the values, never the names.
QUALITY_SATURATED = int(Quality.SATURATED)
QUALITY_NONFINITE = int(Quality.NONFINITE)
QUALITY_WHITE_NOT_ABOVE_DARK = int(Quality.WHITE_NOT_ABOVE_DARK)
QUALITY_PATCH_UNUSABLE = int(Quality.PATCH_UNUSABLE)
QUALITY_BELOW_DARK = int(Quality.BELOW_DARK)
QUALITY_NOT_COVERED = int(Quality.NOT_COVERED)

#: The flat-fielded response (Eq. 10) below which a band's raw value is taken as below the dark
#: level by more than noise allows (`QUALITY_BELOW_DARK`): v < -BELOW_DARK_LIMIT, i.e. raw more
#: than 2 % of the white standard's signal (white - dark) below the dark frame. A pixel at the dark
#: level varies by its read and dark-current noise, a few counts, against a white signal of
#: thousands of counts in any usable exposure: 2 % is tens of standard deviations away, so noise
#: alone never reaches it, while a raw value of -1000 counts (a float input gone wrong, a dark
#: frame taken under other conditions than the captures) does, and would otherwise come out as a
#: reflectance far below 0 with quality 0. The fused CPU kernel (kernel/fused_correct.h,
#: kBelowDarkLimit) uses the same number.
BELOW_DARK_LIMIT = 0.02


__all__ = [
    "Quality", "QUALITY_SATURATED", "QUALITY_NONFINITE", "QUALITY_WHITE_NOT_ABOVE_DARK", "QUALITY_PATCH_UNUSABLE",
    "QUALITY_BELOW_DARK", "QUALITY_NOT_COVERED", "BELOW_DARK_LIMIT",
]
