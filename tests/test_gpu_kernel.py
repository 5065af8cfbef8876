"""The Pallas prototype of the per-pixel step (spherejax/_engine/gpu_kernel.py) against the
jax.numpy path it would replace on GPUs (`pipeline._pixel_outputs`).

Run in Pallas's interpret mode, so on the CPU, on small frames: the kernel's indexing, masks,
flags and arithmetic are the ones a GPU runs, its compilation by Triton and its speed are not
(benchmarks/bench_gpu_kernel.py checks and times it on a GPU). Quality masks and NaN positions agree
exactly, values to float32 rounding (the projection sums in another order). One test lowers the
kernel to Triton IR for an H100 without a GPU, which checks what the Triton lowering refuses
(block sizes that are not powers of two, operations it has no rule for).
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import pipeline
from spherejax._engine.gpu_kernel import pixel_outputs_pallas
from spherejax.pixel_constants import PixelConstants
from spherejax.polynomial import PAPER_TABLE_2

SATURATION = 16383.0
BANDS = 16


def make_case(height, width, *, raw_dtype, images=(), seed=0):
    """Frames with every kind of bad pixel, their calibration's constants (float32, a non-zero
    Wiener offset) and p, NaN in one band of the last image's p if there are several images."""
    rng = np.random.default_rng(seed)
    bands = BANDS
    dark = rng.uniform(95, 105, (height, width, bands)).astype(np.float32)
    white = (dark + rng.uniform(8000, 12000, (height, width, bands))).astype(np.float32)
    # Reflectances from 0.001 to 1.2: XYZ / white spans both branches of the Lab companding.
    level = np.exp(rng.uniform(np.log(1e-3), np.log(1.2), (*images, height, width, 1)))
    raw = dark + (white - dark) * level * rng.uniform(0.9, 1.1, (*images, height, width, bands))
    raw = np.clip(np.rint(raw), 0, SATURATION - 1)
    first = (0,) * len(images)
    raw[(*first, 3, 4, 5)] = SATURATION  # saturated
    white[10, 11, 2] = dark[10, 11, 2]  # white == dark: no flat field
    white[12, 13, 3] = dark[12, 13, 3] - 5  # white < dark
    raw[(*first, 12, 13, 0)] = SATURATION  # saturated and no flat field: two bits
    dark[2, 21, 1] += 700  # below the dark level by 7 % of the white signal
    raw[(*first, 2, 21, 1)] = 0
    # Below by 0.5 %, which noise allows: not flagged.
    raw[(*first, 0, 22, 2)] = np.floor(dark[0, 22, 2] - 0.005 * (white - dark)[0, 22, 2])
    if raw_dtype == np.float32:
        white[14, 15, 1] = np.nan
        white[16, 17, 0] = np.inf
        raw[(*first, 6, 7, 0)] = np.nan
        raw[(*first, 8, 9, bands - 1)] = -np.inf
        raw[(*first, 18, 19, 0)] = np.inf
        raw[(*first, 1, 20, 0)] = -1000.0  # v about -0.11: below dark
        raw[(*first, 5, 30, 4)] = np.inf  # +inf: non-finite, not saturated
    raw = raw.astype(raw_dtype)
    patch = np.zeros((height, width), bool)
    patch[height // 2 - 4:height // 2 + 4, width // 2 - 5:width // 2 + 5] = True
    calibration = sj.Calibration(
        dark=dark, white=white, patch=patch, coeffs=np.asarray(PAPER_TABLE_2, np.float32),
        wiener=(np.abs(rng.normal(0.0, 1.0, (31, bands))) / bands).astype(np.float32), saturation=SATURATION,
        wiener_offset=rng.uniform(-0.05, 0.05, 31).astype(np.float32),
    )
    p = np.asarray(pipeline.patch_ratio(raw, calibration))
    if images:
        p = p.copy()
        p[(*(n - 1 for n in images), 3)] = np.nan  # the last image's patch is unusable
    return jnp.asarray(raw), jnp.asarray(p), PixelConstants.of(calibration, np.float32)


def assert_agree(got, want):
    reflectance, lab, quality = (np.asarray(x) for x in got)
    want_reflectance, want_lab, want_quality = (np.asarray(x) for x in want)
    assert quality.dtype == np.uint8 and quality.shape == want_quality.shape
    np.testing.assert_array_equal(quality, want_quality)
    bad = want_quality != 0
    for name, value, expected, atol in (
        ("reflectance", reflectance, want_reflectance, 2e-6), ("lab", lab, want_lab, 3e-4),
    ):
        assert value.dtype == np.float32 and value.shape == expected.shape, name
        # NaN in every channel of a flagged pixel and nowhere else.
        np.testing.assert_array_equal(np.isnan(value), np.broadcast_to(bad[..., None], value.shape), err_msg=name)
        np.testing.assert_allclose(value, expected, rtol=2e-5, atol=atol, err_msg=name)


def test_uint16_batch_equals_the_jax_numpy_path():
    """Two 24 x 40 frames of uint16 counts: saturated, no flat field (white == dark and white <
    dark), both at once, below dark and the last frame's patch unusable; 960 pixels in blocks of
    64 (the grid's two axes, no partial block)."""
    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16, images=(2,))
    got = pixel_outputs_pallas(raw, p, constants, saturation=SATURATION, block_pixels=64, interpret=True)
    want = pipeline._pixel_outputs(raw, p, constants, saturation=SATURATION)
    assert_agree(got, want)
    quality = np.asarray(want[2])
    assert quality[0, 3, 4] == sj.QUALITY_SATURATED
    assert quality[0, 10, 11] == quality[0, 12, 13] - sj.QUALITY_SATURATED == sj.QUALITY_WHITE_NOT_ABOVE_DARK
    assert quality[0, 2, 21] == sj.QUALITY_BELOW_DARK and quality[0, 0, 22] == 0
    assert np.all(quality[1] & sj.QUALITY_PATCH_UNUSABLE) and not np.any(quality[0] & sj.QUALITY_PATCH_UNUSABLE)
    assert np.count_nonzero(quality[0]) < 10  # the rest of the first frame is good, and compared


def test_float32_frame_with_the_flat_field_mask_equals_the_jax_numpy_path():
    """One 24 x 40 float32 frame with NaN and infinite raw and white values and a raw value far
    below dark; the (H, W) no-flat-field mask given as the plan gives it; blocks of 128, so that
    the last of the 960 pixels' blocks is partial (masked loads and stores)."""
    raw, p, constants = make_case(24, 40, raw_dtype=np.float32)
    mask = pipeline._no_flat_field(constants.dark, constants.white)
    got = pixel_outputs_pallas(raw, p, constants, saturation=SATURATION, no_flat_field=mask, interpret=True)
    want = pipeline._pixel_outputs(raw, p, constants, saturation=SATURATION, no_flat_field=mask)
    assert_agree(got, want)
    quality = np.asarray(want[2])
    assert quality[6, 7] == quality[8, 9] == quality[18, 19] == quality[5, 30] == sj.QUALITY_NONFINITE
    assert quality[14, 15] == quality[16, 17] == sj.QUALITY_WHITE_NOT_ABOVE_DARK
    assert quality[1, 20] == quality[2, 21] == sj.QUALITY_BELOW_DARK
    assert quality[3, 4] == sj.QUALITY_SATURATED


def test_no_saturation_level():
    """saturation None (float raw without a level): no saturated bit; the saturated count is then
    an ordinary value, as in the jax.numpy path."""
    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16)
    got = pixel_outputs_pallas(raw, p, constants, saturation=None, block_pixels=256, interpret=True)
    want = pipeline._pixel_outputs(raw, p, constants, saturation=None)
    assert_agree(got, want)
    assert not np.any(np.asarray(want[2]) & sj.QUALITY_SATURATED)


@pytest.mark.parametrize(
    ("change", "error"),
    [
        (lambda raw, constants: (raw[..., :8], constants.pixels(constants.dark[..., :8], constants.white[..., :8])),
         NotImplementedError),
        (lambda raw, constants: (raw.astype(jnp.int32), constants), NotImplementedError),
        (lambda raw, constants: (raw[:, :-1], constants), ValueError),
    ],
    ids=["8 bands", "int32 raw", "shape"],
)
def test_refuses_what_it_does_not_take(change, error):
    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16)
    raw, constants = change(raw, constants)
    with pytest.raises(error):
        pixel_outputs_pallas(raw, p[..., :raw.shape[-1]], constants, saturation=SATURATION, interpret=True)


def test_lowers_to_triton_for_an_h100():
    """The kernel as a GPU would compile it (interpret=False), lowered to Triton IR for an
    abstract H100 on this machine: every array the kernel loads or stores has a power-of-two size
    and every operation has a Triton lowering rule. What Triton then makes of the IR (PTX) needs a
    GPU. jax 0.11.2 and 0.12 warn at this lowering that the Pallas Triton backend is deprecated
    (in favour of Mosaic GPU): expected here, not an error."""
    from jax.sharding import AbstractDevice, AbstractMesh

    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16, images=(2,))
    mesh = AbstractMesh(
        (1,), ("x",), abstract_device=AbstractDevice(device_kind="NVIDIA H100 80GB HBM3", num_cores=132, platform="gpu")
    )
    program = jax.jit(lambda raw, p, constants: pixel_outputs_pallas(raw, p, constants, saturation=SATURATION))
    with jax.sharding.use_abstract_mesh(mesh), warnings.catch_warnings():
        warnings.filterwarnings("ignore", "The Pallas Triton backend is deprecated", DeprecationWarning)
        text = program.trace(raw, p, constants).lower(lowering_platforms=("cuda",)).as_text()
    assert "__gpu$xla.gpu.triton" in text
