"""The spectral OpenEXR layout of reflectance outputs: Fichet, Pacanowski, Wilkie, "An OpenEXR
Layout for Spectral Images", Journal of Computer Graphics Techniques 10(3), 2021.

A reflective (non-emissive, unpolarised) spectral image stores one channel per wavelength, named
``T.<value><unit>``: "T" for the reflectance component, the value with "," as its decimal
separator, and the unit "nm" (or "m" / "Hz" with an SI prefix), for example ``T.400nm`` or
``T.412,5nm``; the header holds ``spectralLayoutVersion = "1.0"``. colour-science's
`read_spectral_image_Fichet2021` and spectral EXR viewers read such files. spherejax's own
attributes ("spherejax:...") sit beside it in the same header.

Files written before spherejax followed the layout name their channels ``400nm`` .. ``700nm``;
`wavelengths_of_channels` reads both namings, so they open wherever spherejax reads outputs.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

#: The header attribute that marks the layout, and the version written.
LAYOUT_VERSION_ATTRIBUTE = "spectralLayoutVersion"
LAYOUT_VERSION = "1.0"

#: A reflective channel, as the paper's grammar (and colour-science's pattern) reads it.
_REFLECTIVE = re.compile(
    r"T\.(?P<number>\d*,?\d*(?:[eE][-+]?\d+)?)(?P<prefix>Y|Z|E|P|T|G|M|k|h|da|d|c|m|u|n|p|f|a|z|y)?(?P<unit>m|Hz)"
)
#: The channel names of files written before the layout ("400nm").
_LEGACY = re.compile(r"(?P<number>\d+)nm")
_SI_PREFIX = {
    "Y": 1e24, "Z": 1e21, "E": 1e18, "P": 1e15, "T": 1e12, "G": 1e9, "M": 1e6, "k": 1e3, "h": 1e2,
    "da": 1e1, "": 1.0, "d": 1e-1, "c": 1e-2, "m": 1e-3, "u": 1e-6, "n": 1e-9, "p": 1e-12,
    "f": 1e-15, "a": 1e-18, "z": 1e-21, "y": 1e-24,
}
_SPEED_OF_LIGHT = 299_792_458.0  # m/s: a channel named by frequency


def reflectance_channel_names(wavelengths_nm: Sequence[float]) -> list[str]:
    """Channel names of a reflectance image at `wavelengths_nm`: "T.400nm", "T.412,5nm"."""
    names = []
    for nm in wavelengths_nm:
        text = f"{float(nm):.6f}".rstrip("0").rstrip(".")
        names.append(f"T.{text.replace('.', ',')}nm")
    return names


def _wavelength_nm(match: re.Match) -> float | None:
    """The wavelength a matched name gives, None where it gives none: the grammar admits "T.e5nm"
    (no digits before the exponent: float() refuses it), "T.0Hz" (a zero frequency: a division by
    zero) and numbers that overflow; such a channel is named by no wavelength, not an error."""
    try:
        number = float(match.group("number").replace(",", "."))
    except ValueError:
        return None
    scale = _SI_PREFIX[match.group("prefix") or ""]
    if match.group("unit") == "Hz":
        nm = _SPEED_OF_LIGHT / (number * scale) * 1e9 if number * scale > 0 else math.inf
    else:
        nm = number * (scale / 1e-9)  # exact for nm (1e-9 / 1e-9 == 1.0)
    return nm if math.isfinite(nm) and nm > 0 else None


def reflective_channels(names: Sequence[str]) -> dict[int, float] | None:
    """{channel index: wavelength in nm} of an image's reflectance channels: those named in the
    layout ("T.400nm"), other channels (an RGB preview, which the layout allows beside the
    spectrum) left out; else, when every name is one, the older "400nm" names; else None."""
    found = {}
    for index, name in enumerate(names):
        match = _REFLECTIVE.fullmatch(name)
        if match is not None and match.group("number").strip(",") and (nm := _wavelength_nm(match)) is not None:
            found[index] = nm
    if found:
        return found
    older = wavelengths_of_channels(names)
    return None if older is None else dict(enumerate(older))


def wavelengths_of_channels(names: Sequence[str]) -> list[float] | None:
    """The wavelengths in nm of reflectance channels named in the layout ("T.400nm") or as
    spherejax named them before it ("400nm"); None unless every name is one or the other."""
    if not names:
        return None
    wavelengths = []
    for name in names:
        if (match := _REFLECTIVE.fullmatch(name)) is not None and match.group("number").strip(","):
            if (nm := _wavelength_nm(match)) is None:
                return None
            wavelengths.append(nm)
        elif (match := _LEGACY.fullmatch(name)) is not None:
            wavelengths.append(float(match.group("number")))
        else:
            return None
    return wavelengths


__all__ = [
    "LAYOUT_VERSION",
    "LAYOUT_VERSION_ATTRIBUTE",
    "reflectance_channel_names",
    "reflective_channels",
    "wavelengths_of_channels",
]
