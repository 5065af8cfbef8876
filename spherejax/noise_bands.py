"""The one rule for how many bands a noise model's per-band values may have, in words.

A `spherejax.NoiseModel` holds values that are one number for every band or one per band (gain,
read noise, the white standard's uncertainty) and covariances sized by the bands (Stage II's
(B, 4, 4), the estimator's Gram matrix (B + 1, B + 1)). Two places check them against the B bands
of the data: the model in memory (`NoiseModel.check_bands`, spherejax.uncertainty) and its JSON
document (spherejax.noise_document), whose keys name the fields differently. Both take the rule
from here, below them both: the document module is what `NoiseModel.to_json` and `from_json`
import, so it cannot import the model's module, and the model's module does not import the
document's (pydantic) until a model is read or written. Shapes in, a sentence out: no JAX, no
pydantic.
"""

from __future__ import annotations

from collections.abc import Mapping


def band_problem(
    shapes: Mapping[str, tuple[int, ...] | None], bands: int, *, keys: Mapping[str, str] | None = None,
) -> str | None:
    """The first per-band field of a noise model that does not fit `bands` bands, in words, or
    None: the one rule of `NoiseModel.check_bands` (a model in memory) and of its JSON document
    (`spherejax.noise_document`, whose keys differ from the field names by `keys`).

    Args:
      shapes: field -> its shape (None for an absent covariance), for "gain", "read_noise",
        "white_reflectance_u", "coeffs_covariance" and "estimator_covariance.gram".
      bands: the number of bands B.
      keys: field -> the name it goes by where the shapes come from, named beside the field's.
    """
    keys = keys or {}
    for name in ("gain", "read_noise", "white_reflectance_u"):
        shape = tuple(shapes[name])
        if len(shape) == 1 and shape[0] != bands:
            where = f" in {keys[name]}" if name in keys else ""
            return f"{name} has {shape[0]} values{where}, expected one or {bands} (one per band)"
    coeffs = shapes["coeffs_covariance"]
    if coeffs is not None and tuple(coeffs)[0] != bands:
        return f"coeffs_covariance has shape {tuple(coeffs)}, expected ({bands}, 4, 4)"
    gram = shapes["estimator_covariance.gram"]
    if gram is not None and tuple(gram) != (bands + 1, bands + 1):
        return f"estimator_covariance.gram has shape {tuple(gram)}, expected ({bands + 1}, {bands + 1})"
    return None


__all__ = ["band_problem"]
