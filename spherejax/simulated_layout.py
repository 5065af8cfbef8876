"""The paper's experiment laid out, before anything is rendered (Zou et al. 2019, Sections 4-5):
the materials, and what lies on the holder in each capture.

- `Material`: a surface, its reflectance (L,) on `simulated_instrument.FINE_WAVELENGTHS_NM`, its
  first-bounce coupling (1 = Lambertian) and fluorescence. All reflectances are measured spectra
  shipped with colour-science (`spherejax.spectra`), none used twice.
- `ExperimentDesign`: the layout's sizes, in pixels, and how many patches, backgrounds and targets.
- `experiment_layout` -> `ExperimentLayout`: grey patches on uniform backgrounds at several
  positions (training), coloured patches on patterned backgrounds (test), a chart of targets of
  known reflectance (Wiener training), and the white standard. Each capture is a `Scene`: a
  material index map (holder H, holder W) int32 over the holder, its material table, and the
  session-manifest fields, among them the averaging regions [r0, r1, c0, c1] in image pixels,
  each with its reflectance (31,) at 400..700 nm step 10.
- `sensor_map`: a scene over the whole image (H, W) = (holder H, holder W + strip): the holder at
  the top left, beside it the strip, a black mount holding the reference white patch, in every
  frame (Fig. 2); `fixed_materials`: the white standard, that patch and the mount.

numpy only; deterministic for a seed, instrument and design. `spherejax.simulate` renders the
layout (`spherejax.simulated_rendering`); `hw.simcamera` (spherejax_hw) renders it frame by frame.
"""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np

from . import kubelka_munk, spectra
from .grid import WAVELENGTHS_NM
from .simulated_instrument import FINE_WAVELENGTHS_NM, InstrumentModel

#: Indices of FINE_WAVELENGTHS_NM at 400..700 nm step 10, the spectrophotometer's samples.
_FINE_AT_31 = np.searchsorted(FINE_WAVELENGTHS_NM, WAVELENGTHS_NM.astype(float))


@dataclasses.dataclass(frozen=True)
class ExperimentDesign:
    """Layout of the simulated experiment (Zou et al. Sections 4-5), in pixels.

    pixels_per_cm: 24 -- the 10 x 8 cm holder images to 240 x 192 px (the paper's camera has far
      more pixels; this keeps a session near 70 MB).
    patch_px: 12 -- the paper's small patches, 0.5 cm (Section 4). Their size matters: the veiling
      glare a patch's centre gets from its background falls as the patch grows (for this PSF,
      the share of it from beyond a radius R is 1 / sqrt(1 + (R / core)^2)), so a larger patch
      than the paper's understates what Stage I leaves (1.75 cm patches, as here until this was
      found, left 0.0020 in Table 1 where 0.5 cm patches leave 0.0047).
    region_px: 4 -- the paper's averaging region, 35 x 35 of its camera's pixels in the patch's
      centre: its QImaging QI695 (2750 x 2200 px) imaging the 10 x 8 cm holder and the white
      patch beside it samples about 230-270 px/cm, so the region spans ~0.14 cm, 28 % of the
      patch's width, 4 px here. Its mean has ~9x the noise of the paper's 1225-pixel mean: on
      seed 0 Table 1's Stage II is 0.0011 with noise and 0.0008 without (docs/results.md).
    white_patch_px: 24, strip_px: 32 -- the reference white patch on a black mount beside the
      holder, in every frame (Fig. 2).
    training_patches: 9, training_backgrounds: 10 -- Section 4's n_p and n_b.
    patches_per_capture: 3 -- three small patches at a time, rotating through three positions
      from background to background ("at different positions").
    test_patches: 6, test_backgrounds: 6 -- coloured patches on patterned backgrounds (Fig. 4).
    targets: 144, target_px: 16, target_region_px: 10 -- a 12 x 12 chart of known reflectances.
    fluorescent_training_backgrounds: 2, fluorescent_test_backgrounds: 1 -- the brightest
      backgrounds carry whitening agents, as white-ish textiles do.
    """

    pixels_per_cm: float = 24.0
    patch_px: int = 12
    region_px: int = 4
    white_patch_px: int = 24
    strip_px: int = 32
    training_patches: int = 9
    training_backgrounds: int = 10
    patches_per_capture: int = 3
    test_patches: int = 6
    test_backgrounds: int = 6
    targets: int = 144
    target_px: int = 16
    target_region_px: int = 10
    fluorescent_training_backgrounds: int = 2
    fluorescent_test_backgrounds: int = 1

    def holder_shape(self, instrument: InstrumentModel) -> tuple[int, int]:
        return (
            int(round(instrument.holder_height_m * 100 * self.pixels_per_cm)),
            int(round(instrument.holder_width_m * 100 * self.pixels_per_cm)),
        )

    def image_shape(self, instrument: InstrumentModel) -> tuple[int, int]:
        height, width = self.holder_shape(instrument)
        return height, width + self.strip_px

    def white_patch(self, instrument: InstrumentModel) -> tuple[int, int, int, int]:
        _, width = self.holder_shape(instrument)
        c0 = width + (self.strip_px - self.white_patch_px) // 2
        return 8, 8 + self.white_patch_px, c0, c0 + self.white_patch_px


# ---------------------------------------------------------------------------------------------
# Materials


@dataclasses.dataclass(frozen=True)
class Material:
    """A surface on the holder: its name, source, reflectance on FINE_WAVELENGTHS_NM (L,), its
    first-bounce coupling (1 = Lambertian) and its fluorescence (0..1 of full strength)."""

    name: str
    source: str
    reflectance: np.ndarray
    coupling: float = 1.0
    fluorescence: float = 0.0

    def at_31(self) -> np.ndarray:
        """The spectrophotometer's view: reflectance at 400..700 nm step 10 (no fluorescence)."""
        return self.reflectance[_FINE_AT_31]


def _stable_unit(name: str, seed: int) -> float:
    """A number in [-1, 1) fixed by a material's name and the seed (same material, same value)."""
    return np.random.default_rng([zlib.crc32(name.encode()), seed]).uniform(-1.0, 1.0)


def _material(name, source, reflectance, instrument, seed, lambertian=False, fluorescence=0.0):
    coupling = 1.0 if lambertian else 1.0 + instrument.non_lambertian_spread * _stable_unit(name, seed)
    return Material(name, source, np.asarray(reflectance, float), coupling, fluorescence)


def _flat(value: float) -> np.ndarray:
    return np.full(FINE_WAVELENGTHS_NM.shape, value)


class _Library:
    """The measured spectra the experiment draws from, split so that no spectrum is used twice."""

    def __init__(self):
        self.sets = spectra.reflectance_sets(FINE_WAVELENGTHS_NM)
        self.names = spectra.reflectance_names(FINE_WAVELENGTHS_NM)

    def take(self, set_name: str, predicate=lambda name: True) -> list[tuple[str, np.ndarray]]:
        return [(n, r) for n, r in zip(self.names[set_name], self.sets[set_name]) if predicate(n)]


def _spread_by_brightness(items, count):
    """`count` items spread evenly from darkest to brightest (mean reflectance)."""
    order = sorted(items, key=lambda item: float(np.mean(item[1])))
    picks = np.round(np.linspace(0, len(order) - 1, count)).astype(int)
    return [order[i] for i in picks]


def _lay_over(layer: Material, beneath: np.ndarray, table: list, instrument: InstrumentModel) -> np.ndarray:
    """Lay a single layer of `layer` over the materials `beneath` (an index map into `table`):
    appends to `table` one material per material beneath, the layer as it reads over that one
    (`kubelka_munk.layer_over_background`, the layer's scattering power
    `instrument.sample_layer_scattering_power`; its coupling and fluorescence stay the layer's),
    and returns the index map of the layer's pixels. A scattering power of 0 lays an opaque layer:
    one material, the layer itself."""
    if instrument.sample_layer_scattering_power == 0.0:
        table.append(layer)
        return np.full(beneath.shape, len(table) - 1, np.int32)
    out = np.empty(beneath.shape, np.int32)
    for index in np.unique(beneath):
        under = table[int(index)]
        seen = kubelka_munk.layer_over_background(
            layer.reflectance, instrument.sample_layer_scattering_power, under.reflectance
        )
        table.append(dataclasses.replace(layer, reflectance=seen))
        out[beneath == index] = len(table) - 1
    return out


# ---------------------------------------------------------------------------------------------
# Scenes


def _centred_region(r0, c0, size, region):
    offset = (size - region) // 2
    return [r0 + offset, r0 + offset + region, c0 + offset, c0 + offset + region]


def _patch_slots(holder_shape, patch_px, count):
    """`count` positions (row, col) of small patches on the holder, spread over the field."""
    height, width = holder_shape
    rows = np.linspace(0.22, 0.78, count) * height - patch_px / 2
    cols = np.linspace(0.2, 0.8, count) * width - patch_px / 2
    # Alternate rows so the positions cover the field's corners and centre.
    rows = np.concatenate([rows[::2], rows[1::2]])
    return [(int(r), int(c)) for r, c in zip(rows, cols)]


def _pattern(kind: int, holder_shape, n_materials: int, rng) -> np.ndarray:
    """Index map (H, W) of a patterned background made of `n_materials` stripes or checks."""
    height, width = holder_shape
    y, x = np.mgrid[0:height, 0:width]
    period = int(rng.integers(28, 64))
    if kind % 4 == 0:
        cells = x // period
    elif kind % 4 == 1:
        cells = y // period
    elif kind % 4 == 2:
        cells = (x // period) + (y // period)
    else:
        cells = (x + y) // period
    return (cells % n_materials).astype(np.int32)


@dataclasses.dataclass(frozen=True)
class Scene:
    """What lies on the holder for one capture: a material index map over the holder and its
    material table, plus the session-manifest fields (regions in image pixels)."""

    name: str
    role: str  # "white", "sample" or "target"
    holder_map: np.ndarray  # (holder H, holder W) int32, indices into `table`
    table: tuple  # Material, ...
    regions: tuple = ()  # {"name", "patch", "region": [r0, r1, c0, c1], "reflectance": 31}
    set: str | None = None
    background: str | None = None


@dataclasses.dataclass
class ExperimentLayout:
    """The paper's experiment before rendering: materials and where everything lies.

    `scenes` holds the sample and target captures in capture order; `white` the white standard.
    `sensor_map` adds what surrounds the holder in every frame (the black mount and the white
    reference patch).
    """

    instrument: InstrumentModel
    design: ExperimentDesign
    seed: int
    image_shape: tuple[int, int]
    holder_shape: tuple[int, int]
    white_patch: tuple[int, int, int, int]
    standard: Material
    white_tile: Material
    mount: Material
    white: Scene
    scenes: dict[str, Scene]
    materials: dict[str, Material]

    def sensor_map(self, scene: Scene) -> tuple[np.ndarray, list[Material]]:
        """`sensor_map` of a scene of this experiment."""
        return sensor_map(scene, self.image_shape, self.white_patch, self.mount, self.white_tile)


def sensor_map(scene: Scene, image_shape, white_patch, mount: Material, white_tile: Material) -> tuple[np.ndarray, list[Material]]:
    """(material index map (H, W) over the whole image, material table) of a scene: the
    holder's content at the top left plus the strip beside it, black mount with the white
    reference patch at `white_patch` (r0, r1, c0, c1)."""
    table = list(scene.table) + [mount, white_tile]
    full = np.full(tuple(image_shape), len(table) - 2, np.int32)
    height, width = scene.holder_map.shape
    full[:height, :width] = scene.holder_map
    r0, r1, c0, c1 = white_patch
    full[r0:r1, c0:c1] = len(table) - 1
    return full, table


def fixed_materials(instrument: InstrumentModel, seed: int) -> tuple[Material, Material, Material]:
    """(white standard, white reference tile, black mount): in every experiment."""
    standard = _material("white standard", "PTFE board", _flat(instrument.white_standard_reflectance), instrument, seed, lambertian=True)
    white_tile = _material("white patch", "ceramic tile", _flat(instrument.white_patch_reflectance), instrument, seed, lambertian=True)
    mount = _material("mount", "black anodised", _flat(instrument.mount_reflectance), instrument, seed, lambertian=True)
    return standard, white_tile, mount


def experiment_layout(seed: int = 0, instrument: InstrumentModel | None = None, design: ExperimentDesign | None = None) -> ExperimentLayout:
    """The materials and scenes of the paper's experiment (Section 4), without rendering:
    9 grey patches on 10 uniform backgrounds (training), coloured patches on patterned
    backgrounds (test), a chart of colour targets. Deterministic for a seed, instrument, design.
    `spherejax.simulate.simulate_experiment` renders it; `hw.simcamera` renders it frame by frame."""
    instrument = instrument or InstrumentModel()
    design = design or ExperimentDesign()
    library = _Library()
    holder_shape = design.holder_shape(instrument)

    def material(name, source, reflectance, lambertian=False, fluorescence=0.0):
        return _material(name, source, reflectance, instrument, seed, lambertian, fluorescence)

    standard, white_tile, mount = fixed_materials(instrument, seed)

    # Greys for training: the neutral rows of the ColorCheckers, spread light to dark.
    neutrals = []
    for set_name in ("ColorChecker: BabelColor Average", "ColorChecker: ColorChecker N Ohta", "ColorChecker: ISO 17321-1"):
        neutrals += [(f"{set_name} / {n}", r) for n, r in library.take(set_name, lambda n: n.startswith(("white", "neutral", "black")))]
    greys = [material(n, "colour-science", r) for n, r in _spread_by_brightness(neutrals, design.training_patches)]

    # Backgrounds: TM-30 CES spectra, uniform for training and in patterns for test, disjoint.
    ces = library.take("CES (TM-30)")
    training_picks = _spread_by_brightness(ces, design.training_backgrounds)  # darkest first
    training_names = {n for n, _ in training_picks}
    fluorescent = {n for n, _ in training_picks[-design.fluorescent_training_backgrounds :]} if design.fluorescent_training_backgrounds else set()
    backgrounds = [
        material(f"CES / {n}", "colour-science", r, fluorescence=1.0 if n in fluorescent else 0.0)
        for n, r in training_picks
    ]
    remaining = [item for item in ces if item[0] not in training_names]
    remaining += [(f"CQS 9.0 / {n}", r) for n, r in library.take("VS: NIST CQS 9.0")]

    # Coloured test patches: chromatic ColorChecker patches (BabelColor), spread in hue.
    chromatic = library.take("ColorChecker: BabelColor Average", lambda n: not n.startswith(("white", "neutral", "black")))
    chosen = [chromatic[int(i)] for i in np.round(np.linspace(0, len(chromatic) - 1, design.test_patches))]
    test_patches = [material(f"BabelColor / {n}", "colour-science", r) for n, r in chosen]

    # Targets: the RAW to ACES training patches, spread over the set.
    aces = library.take("RAW to ACES training")
    target_idx = np.round(np.linspace(0, len(aces) - 1, design.targets)).astype(int)
    targets = [material(f"ACES / {aces[i][0]}", "colour-science", aces[i][1]) for i in target_idx]
    chart_surround = greys[len(greys) // 2]

    materials = {m.name: m for m in [standard, white_tile, mount, *greys, *backgrounds, *test_patches, *targets]}
    scenes: dict[str, Scene] = {}
    slots = _patch_slots(holder_shape, design.patch_px, design.patches_per_capture)

    def patch_scene(frame_id, set_name, background_name, holder_map, table, patches, shift):
        """Place `patches` on a background at rotated slots."""
        beneath = holder_map
        holder_map = holder_map.copy()
        table = list(table)
        regions = []
        for k, patch in enumerate(patches):
            r, c = slots[(k + shift) % len(slots)]
            window = (slice(r, r + design.patch_px), slice(c, c + design.patch_px))
            holder_map[window] = _lay_over(patch, beneath[window], table, instrument)
            regions.append({
                "name": patch.name, "patch": patch.name,
                "region": _centred_region(r, c, design.patch_px, design.region_px),
                "reflectance": patch.at_31().tolist(),
            })
        scenes[frame_id] = Scene(frame_id, "sample", holder_map, tuple(table), tuple(regions), set_name, background_name)

    groups = [greys[i : i + design.patches_per_capture] for i in range(0, len(greys), design.patches_per_capture)]
    for j, background in enumerate(backgrounds):
        for g, group in enumerate(groups):
            patch_scene(
                f"train-bg{j:02d}-g{g}", "training", background.name,
                np.zeros(holder_shape, np.int32), [background], group, shift=j + g,
            )

    test_groups = [test_patches[i : i + design.patches_per_capture] for i in range(0, len(test_patches), design.patches_per_capture)]
    pattern_rng = np.random.default_rng([seed, 7])
    test_fluorescent = design.fluorescent_test_backgrounds
    for j in range(design.test_backgrounds):
        n_materials = 2 + j % 3
        picks = [remaining[int(i)] for i in pattern_rng.choice(len(remaining), n_materials, replace=False)]
        table = [
            material(n if n.startswith("CQS") else f"CES / {n}", "colour-science", r,
                     fluorescence=1.0 if (j < test_fluorescent and k == 0) else 0.0)
            for k, (n, r) in enumerate(picks)
        ]
        for m in table:
            materials[m.name] = m
        holder_map = _pattern(j, holder_shape, n_materials, pattern_rng)
        name = "pattern-" + "+".join(m.name.split(" / ")[-1] for m in table)
        for g, group in enumerate(test_groups):
            patch_scene(f"test-bg{j:02d}-g{g}", "test", name, holder_map, table, group, shift=j + g)

    # The target chart: 12 x 12 targets on a mid-grey surround, centred on the holder.
    per_row = int(np.ceil(np.sqrt(design.targets)))
    chart = np.zeros(holder_shape, np.int32)
    table = [chart_surround]
    regions = []
    top = (holder_shape[0] - per_row * design.target_px) // 2
    left = (holder_shape[1] - per_row * design.target_px) // 2
    for k, target in enumerate(targets):
        r = top + (k // per_row) * design.target_px
        c = left + (k % per_row) * design.target_px
        window = (slice(r, r + design.target_px), slice(c, c + design.target_px))
        chart[window] = _lay_over(target, np.zeros((design.target_px, design.target_px), np.int32), table, instrument)
        regions.append({
            "name": f"t{k:03d}", "patch": target.name,
            "region": _centred_region(r, c, design.target_px, design.target_region_px),
            "reflectance": target.at_31().tolist(),
        })
    scenes["targets"] = Scene("targets", "target", chart, tuple(table), tuple(regions))

    return ExperimentLayout(
        instrument=instrument, design=design, seed=seed, image_shape=design.image_shape(instrument),
        holder_shape=holder_shape, white_patch=design.white_patch(instrument), standard=standard,
        white_tile=white_tile, mount=mount,
        white=Scene("white", "white", np.zeros(holder_shape, np.int32), (standard,)),
        scenes=scenes, materials=materials,
    )


__all__ = [
    "Material",
    "ExperimentDesign",
    "Scene",
    "ExperimentLayout",
    "experiment_layout",
    "fixed_materials",
    "sensor_map",
]
