"""The integrating sphere as surface elements exchanging flux (radiosity), per band.

Zou et al. (2019) model the sphere by three port fractions and one wall reflectance (Eqs. 1-9):
every point of the holder, and the white patch beside it, sees the same irradiance, scaled by
k(λ) = α_ww + α_wsp α_spw ρ̄(λ). That is exact only for an ideal sphere with every surface on it:
light leaving a diffuse point of a sphere lands on any region in proportion to the region's
area. A real sphere breaks it where the paper says Stage I fails (Section 4: "the imperfections
of the sphere such as lack of symmetry"): the holder and the white patch lie in a flat port, not
on the sphere; a baffle hides the entrance port's diffuser from them and shadows parts of the
wall differently for each point; the ports are holes. This module resolves where the light goes:

    elements    wall: a Fibonacci lattice of equal-area points on the sphere (the entrance and
                detector ports' points are holes, reflectance 0); the sample plane: the holder
                and the strip beside it (mount, white patch) in square cells; the baffle: a disc,
                both faces
    H = H0 + F diag(ρ) H                                           irradiance, W m^-2 per band
    F_ij = V_ij cos θ_i cos θ_j A_j / (π d_ij² + (A_i + A_j) / 2)  form factor, i receiving
                                                                   from j (the point form, the
                                                                   areas in the denominator so
                                                                   that near pairs stay below
                                                                   one and A_i F_ij = A_j F_ji)
    H0_i = V_i,port cos θ_port cos θ_i A_port / (π d² + A_port)     the diffuser at the entrance
                                                                   port, a Lambertian disc of
                                                                   unit exitance

For two points on a sphere the point form is exact (cos θ_i = cos θ_j = d / 2R: F_ij =
A_j / 4πR²), so without baffle and with the plane's cells shrunk onto the sphere this reduces to
Eq. 9. V is 0 where the segment between two points crosses the baffle (or passes below the
sample plane).

The wall block does not depend on the scene: `SphereTransport` eliminates it once per wall
reflectance (Schur complement), leaving a system in the plane's cells and the baffle that each
scene solves in a few milliseconds. Irradiance at the plane's pixels comes from the cells'
(bilinear). Lengths m; the plane's frame: x along the image's columns, y along its rows, z up
towards the detector port; the sphere's centre is the origin and the sample plane lies at
z = -sqrt(R² - r_port²), r_port the port's half-diagonal.

Geometry defaults are the paper's sphere (Section 5: 50 cm, ports 6 and 5 cm, holder 10 x 8 cm);
the baffle's size and place follow the sphere design rule the paper cites (Labsphere, "A Guide
to Integrating Sphere Theory and Applications", 2017: a baffle between the entrance port and the
sample port, about 1.5 times the port's size, at a third of the way from the entrance port).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

_HIGHEST = jax.lax.Precision.HIGHEST


@dataclasses.dataclass(frozen=True)
class SphereGeometry:
    """Where the sphere's surfaces are, m (docstring of the module for the sources).

    radius_m: 0.25 -- the paper's 50 cm sphere.
    entrance_port_radius_m: 0.03, detector_port_radius_m: 0.025 -- its 6 and 5 cm ports; the
      detector port at the top, over the sample plane; the entrance port on the equator (+x).
    plane_size_m: (0.08, 0.1133) -- the sample port (rows, columns): the 8 x 10 cm holder and
      the 1.33 cm strip beside it that holds the white patch on its mount (`simulated_layout`).
    cell_m: 0.0067 -- the sample plane's cells (16 pixels at 24 px/cm).
    wall_points: 600 -- wall elements (7 cm² each); the paper's port fraction to 1 %.
    baffle_radius_m: 0.045, baffle_position: 0.35 -- a disc 1.5 times the entrance port,
      centred a third of the way from the entrance port to the sample plane's centre, facing
      along that line: no point of the sample plane sees the diffuser.
    """

    radius_m: float = 0.25
    entrance_port_radius_m: float = 0.03
    detector_port_radius_m: float = 0.025
    plane_size_m: tuple[float, float] = (0.08, 0.11333)
    cell_m: float = 0.00667
    wall_points: int = 600
    baffle_radius_m: float = 0.045
    baffle_position: float = 0.35

    @property
    def plane_z(self) -> float:
        half_diagonal = 0.5 * float(np.hypot(*self.plane_size_m))
        return -float(np.sqrt(self.radius_m**2 - half_diagonal**2))

    @property
    def plane_cells(self) -> tuple[int, int]:
        return tuple(max(1, int(round(s / self.cell_m))) for s in self.plane_size_m)

    @property
    def entrance_port_centre(self) -> np.ndarray:
        return np.array([self.radius_m, 0.0, 0.0])

    @property
    def detector_port_centre(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.radius_m])

    def baffle(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre (3,), unit normal (3,) pointing towards the entrance port)."""
        start = self.entrance_port_centre
        end = np.array([0.0, 0.0, self.plane_z])
        centre = start + self.baffle_position * (end - start)
        normal = (start - end) / np.linalg.norm(start - end)
        return centre, normal


@dataclasses.dataclass(frozen=True)
class Elements:
    """The sphere's surface elements: centres (N, 3), unit normals into the sphere (N, 3), areas
    (N,) m², and which part each is: kind (N,) int8, one of WALL, ENTRANCE, DETECTOR, PLANE,
    BAFFLE; plane cells first, in row-major order of `SphereGeometry.plane_cells`."""

    centres: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    kind: np.ndarray


PLANE, WALL, ENTRANCE, DETECTOR, BAFFLE = 0, 1, 2, 3, 4


def _fibonacci_sphere(count: int) -> np.ndarray:
    """count unit vectors spread evenly over the sphere (equal areas to O(1/count))."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _baffle_points(geometry: SphereGeometry, rings: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Points of the baffle disc (one face) and their areas: a centre and `rings` rings."""
    centre, normal = geometry.baffle()
    helper = np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    radius = geometry.baffle_radius_m
    points, areas = [centre], [np.pi * (radius / (2 * rings + 1)) ** 2]
    for ring in range(1, rings + 1):
        inner, outer = (2 * ring - 1) * radius / (2 * rings + 1), (2 * ring + 1) * radius / (2 * rings + 1)
        count = 6 * ring
        angles = 2 * np.pi * (np.arange(count) + 0.5 * ring) / count
        middle = 0.5 * (inner + outer)
        for a in angles:
            points.append(centre + middle * (np.cos(a) * u + np.sin(a) * v))
            areas.append(np.pi * (outer**2 - inner**2) / count)
    return np.array(points), np.array(areas)


def sphere_elements(geometry: SphereGeometry) -> Elements:
    """The elements of `geometry` (see `Elements`)."""
    R = geometry.radius_m
    rows, cols = geometry.plane_cells
    height, width = geometry.plane_size_m
    y = (np.arange(rows) + 0.5) / rows * height - height / 2
    x = (np.arange(cols) + 0.5) / cols * width - width / 2
    plane = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.full((rows, cols), geometry.plane_z)), axis=-1).reshape(-1, 3)
    plane_normals = np.tile([0.0, 0.0, 1.0], (len(plane), 1))
    plane_areas = np.full(len(plane), height * width / (rows * cols))

    directions = _fibonacci_sphere(geometry.wall_points)
    wall = R * directions
    # The sample port: the wall inside the plane's footprint is replaced by the plane.
    in_port = (np.abs(wall[:, 0]) <= width / 2) & (np.abs(wall[:, 1]) <= height / 2) & (wall[:, 2] < 0)
    wall, directions = wall[~in_port], directions[~in_port]
    kind = np.full(len(wall), WALL, np.int8)
    areas = np.zeros(len(wall))
    # The other ports: holes, as elements of reflectance 0 whose areas add up to the ports' own
    # (a lattice point stands for 4 pi R^2 / count; a port holds a whole number of them).
    rest = 4 * np.pi * R**2 - height * width
    for centre, radius, label in ((geometry.entrance_port_centre, geometry.entrance_port_radius_m, ENTRANCE),
                                  (geometry.detector_port_centre, geometry.detector_port_radius_m, DETECTOR)):
        inside = np.linalg.norm(wall - centre, axis=1) < radius
        if not inside.any():  # a port smaller than the lattice's spacing: its nearest point
            inside = np.arange(len(wall)) == np.argmin(np.linalg.norm(wall - centre, axis=1))
        kind[inside] = label
        areas[inside] = np.pi * radius**2 / inside.sum()
        rest -= np.pi * radius**2
    areas[kind == WALL] = rest / np.sum(kind == WALL)

    baffle_points, baffle_areas = _baffle_points(geometry)
    _, baffle_normal = geometry.baffle()
    centres = np.concatenate([plane, wall, baffle_points, baffle_points])
    normals = np.concatenate([plane_normals, -directions, np.tile(baffle_normal, (len(baffle_points), 1)),
                              np.tile(-baffle_normal, (len(baffle_points), 1))])
    areas = np.concatenate([plane_areas, areas, baffle_areas, baffle_areas])
    kinds = np.concatenate([np.full(len(plane), PLANE, np.int8), kind, np.full(2 * len(baffle_points), BAFFLE, np.int8)])
    return Elements(centres, normals, areas, kinds)


def _blocked_by_baffle(starts: np.ndarray, ends: np.ndarray, geometry: SphereGeometry) -> np.ndarray:
    """(P, Q) bool: the segment from starts[p] to ends[q] crosses the baffle disc (strictly
    between its ends)."""
    centre, normal = geometry.baffle()
    a = (starts - centre) @ normal  # signed heights (P,)
    b = (ends - centre) @ normal  # (Q,)
    denominator = a[:, None] - b[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(np.abs(denominator) > 1e-15, a[:, None] / denominator, -1.0)
    crossing = (t > 1e-9) & (t < 1 - 1e-9)
    hit = starts[:, None, :] + t[..., None] * (ends[None, :, :] - starts[:, None, :])
    return crossing & (np.linalg.norm(hit - centre, axis=-1) < geometry.baffle_radius_m)


def form_factors(elements: Elements, geometry: SphereGeometry) -> np.ndarray:
    """F (N, N): the fraction of what element j emits (diffusely) that element i receives,
    divided by A_i / A_j, i.e. the point-form form factor from i to j (module docstring);
    H_i = sum_j F_ij B_j for exitances B. float64."""
    d = elements.centres[None, :, :] - elements.centres[:, None, :]  # i -> j
    distance2 = np.sum(d * d, axis=-1)
    distance = np.sqrt(np.maximum(distance2, 1e-30))
    cos_i = np.sum(elements.normals[:, None, :] * d, axis=-1) / distance
    cos_j = -np.sum(elements.normals[None, :, :] * d, axis=-1) / distance
    # (A_i + A_j) / 2 in the denominator, not A_j: A_i F_ij = A_j F_ji (reciprocity) holds exactly.
    softening = 0.5 * (elements.areas[:, None] + elements.areas[None, :])
    F = np.clip(cos_i, 0, None) * np.clip(cos_j, 0, None) * elements.areas[None, :] / (np.pi * distance2 + softening)
    # Between two points of the sphere the exact value: A_j / 4 pi R^2 (the point form with its
    # softening would lose 5-8 % to the nearest neighbours, which the wall's many bounces
    # multiply into a sphere several times too dark).
    on_sphere = elements.kind != PLANE
    on_sphere &= elements.kind != BAFFLE
    sphere_pairs = on_sphere[:, None] & on_sphere[None, :]
    F = np.where(sphere_pairs, elements.areas[None, :] / (4 * np.pi * geometry.radius_m**2), F)
    np.fill_diagonal(F, 0.0)
    F *= ~_blocked_by_baffle(elements.centres, elements.centres, geometry)
    # The enclosure is closed (ports are elements): all an element emits lands on some element.
    # The point form leaves the plane's and the baffle's sums short by the discretisation
    # (0.5 %); spreading that over the row keeps the energy balance exact.
    return F / np.sum(F, axis=1, keepdims=True)


def diffuser_irradiance(elements: Elements, geometry: SphereGeometry) -> np.ndarray:
    """H0 (N,): irradiance from the entrance port's diffuser, a Lambertian disc of unit exitance
    facing into the sphere (blocked by the baffle where the segment crosses it)."""
    port = geometry.entrance_port_centre
    area = np.pi * geometry.entrance_port_radius_m**2
    d = port[None, :] - elements.centres
    distance2 = np.sum(d * d, axis=-1)
    distance = np.sqrt(distance2)
    cos_i = np.sum(elements.normals * d, axis=-1) / distance
    cos_port = np.sum(-port / np.linalg.norm(port) * -d, axis=-1) / distance
    H0 = np.clip(cos_i, 0, None) * np.clip(cos_port, 0, None) * area / (np.pi * distance2 + area)
    H0 *= ~_blocked_by_baffle(elements.centres, port[None, :], geometry)[:, 0]
    H0[elements.kind == ENTRANCE] = 0.0
    return H0


@dataclasses.dataclass(frozen=True)
class SphereTransport:
    """The sphere's light transport for one geometry, with the wall eliminated.

    Build with `sphere_transport(geometry)`; `plane_irradiance(transport, wall, cells, baffle)`
    then gives the sample plane's irradiance per band for any scene.
    """

    geometry: SphereGeometry
    elements: Elements
    F: np.ndarray  # (N, N)
    H0: np.ndarray  # (N,)


def sphere_transport(geometry: SphereGeometry | None = None) -> SphereTransport:
    geometry = geometry or SphereGeometry()
    elements = sphere_elements(geometry)
    return SphereTransport(geometry, elements, form_factors(elements, geometry), diffuser_irradiance(elements, geometry))


def _reflectances(transport: SphereTransport, wall, cells, baffle):
    """ρ (K, N) per band: cells (K, C) on the plane, wall (K,) on the wall and the baffle (or
    `baffle` (K,)), 0 in the ports."""
    kind = transport.elements.kind
    K = cells.shape[0]
    wall_part = jnp.where(jnp.asarray(kind == WALL)[None, :], wall[:, None], 0.0)
    baffle_part = jnp.where(jnp.asarray(kind == BAFFLE)[None, :], baffle[:, None], 0.0)
    plane_count = int(np.sum(kind == PLANE))
    rho = wall_part + baffle_part
    return rho.at[:, :plane_count].set(cells.reshape(K, plane_count))


def irradiance(transport: SphereTransport, wall, cells, baffle=None):
    """H (K, N), irradiance of every element per band for unit diffuser exitance: the solution
    of H = H0 + F diag(ρ) H (module docstring), ρ from `_reflectances`.

    wall: (K,) the wall's reflectance per band; cells: (K, rows, cols) the plane cells' mean
    reflectance per band; baffle: (K,), the baffle's (None: the wall's). Differentiable in all
    three. One solve of all N unknowns per band: the reference `plane_transport` is checked
    against; for many scenes, `plane_transport` once and `plane_irradiance` per scene.
    """
    wall = jnp.asarray(wall)
    baffle = wall if baffle is None else jnp.asarray(baffle)
    rho = _reflectances(transport, wall, jnp.asarray(cells), baffle)
    F = jnp.asarray(transport.F, rho.dtype)
    H0 = jnp.asarray(transport.H0, rho.dtype)
    eye = jnp.eye(F.shape[0], dtype=rho.dtype)
    # One band after another (lax.map): a batched LAPACK solve can hang jaxlib < 0.12
    # (estimation.small_solve).
    return jax.lax.map(lambda r: jnp.linalg.solve(eye - F * r[None, :], H0), rho)


@dataclasses.dataclass(frozen=True)
class IncidentLight:
    """Where the light on one cell of the sample plane comes from (`incident_light`).

    directions: (N + 1, 3) unit vectors from the cell's centre to every element and, last, to the
      entrance port's diffuser (plane frame: z along the plane's normal, into the sphere);
    total: (K, N + 1) the irradiance each contributes per band (W m^-2 for unit diffuser
      exitance): F_cj ρ_j H_j, and the diffuser's direct light H0_c;
    first: (K, N + 1) the part of it that left the diffuser at most one reflection before:
      F_cj ρ_j H0_j, and H0_c (what Eq. 1 calls the first reflection).
    """

    directions: np.ndarray
    total: jax.Array
    first: jax.Array


def incident_light(transport: SphereTransport, wall, cells, cell: tuple[int, int], baffle=None) -> IncidentLight:
    """The light on plane cell `cell` (row, col) by direction, for a scene: wall (K,), cells (K,
    rows, cols) and baffle as `irradiance`. Its `total` sums to the cell's irradiance. A sample's
    reading along its normal under it: `textile_brdf.normal_view_reading`."""
    wall = jnp.asarray(wall)
    baffle_rho = wall if baffle is None else jnp.asarray(baffle)
    cells = jnp.asarray(cells)
    H = irradiance(transport, wall, cells, baffle)  # (K, N)
    rho = _reflectances(transport, wall, cells, baffle_rho)
    rows, cols = transport.geometry.plane_cells
    index = int(np.ravel_multi_index(cell, (rows, cols)))
    centres = transport.elements.centres
    port = transport.geometry.entrance_port_centre
    towards = np.concatenate([centres, port[None]]) - centres[index]
    distance = np.linalg.norm(towards, axis=1)
    distance[index] = 1.0
    directions = towards / distance[:, None]
    directions[index] = (0.0, 0.0, 1.0)  # the cell itself: F_cc = 0, any unit vector
    F_row = jnp.asarray(transport.F[index], H.dtype)
    H0 = jnp.asarray(transport.H0, H.dtype)
    direct = jnp.broadcast_to(H0[index], (H.shape[0], 1))
    total = jnp.concatenate([F_row[None] * rho * H, direct], axis=1)
    first = jnp.concatenate([F_row[None] * rho * H0[None], direct], axis=1)
    return IncidentLight(directions, total, first)


@dataclasses.dataclass(frozen=True)
class PlaneTransport:
    """The sphere reduced to its sample plane, for one wall (and baffle) reflectance per band:

        H_P = g + G diag(ρ_P) H_P,     G = T F_WP,  g = H0_P + T H0_W,  T = F_PW R_W A,
        A = (I - F_WW R_W)^-1

    (W: every element but the plane's cells; R_W their reflectances), so that a scene's plane
    irradiance is one solve of the plane's C cells per band (`plane_irradiance`). Arrays: G
    (K, C, C), g (K, C), jax; `shape` (rows, cols) of the cells. Made by `plane_transport`.
    """

    G: jax.Array
    g: jax.Array
    shape: tuple[int, int]


def plane_transport(transport: SphereTransport, wall, baffle=None) -> PlaneTransport:
    """`PlaneTransport` of `transport` for the wall's reflectance (K,) per band (baffle: (K,),
    None for the wall's). Differentiable in both; one solve of the W non-plane elements per band."""
    kind = transport.elements.kind
    plane = kind == PLANE
    wall = jnp.asarray(wall)
    baffle = wall if baffle is None else jnp.asarray(baffle)
    rest_kind = jnp.asarray(kind[~plane])
    R_W = jnp.where(rest_kind[None, :] == WALL, wall[:, None], 0.0) + jnp.where(rest_kind[None, :] == BAFFLE, baffle[:, None], 0.0)
    dtype = R_W.dtype
    F = np.asarray(transport.F)
    F_WW = jnp.asarray(F[np.ix_(~plane, ~plane)], dtype)
    F_WP = jnp.asarray(F[np.ix_(~plane, plane)], dtype)
    F_PW = jnp.asarray(F[np.ix_(plane, ~plane)], dtype)
    H0_W = jnp.asarray(transport.H0[~plane], dtype)
    H0_P = jnp.asarray(transport.H0[plane], dtype)
    G, g = _eliminate_wall(R_W, F_WW, F_WP, F_PW, H0_W, H0_P)
    return PlaneTransport(G, g, transport.geometry.plane_cells)


@jax.jit
def _eliminate_wall(R_W, F_WW, F_WP, F_PW, H0_W, H0_P):
    """(G (K, C, C), g (K, C)) of `PlaneTransport` per band."""
    eye = jnp.eye(F_WW.shape[0], dtype=R_W.dtype)

    def one_band(r_w):
        # T^T = A^T R_W F_PW^T: one solve with the transposed system and C + 1 right-hand sides
        # (G and g together).
        system = (eye - F_WW * r_w[None, :]).T
        T_t = jnp.linalg.solve(system, r_w[:, None] * F_PW.T)  # (W, C)
        T = T_t.T
        return jnp.matmul(T, F_WP, precision=_HIGHEST), H0_P + jnp.matmul(T, H0_W, precision=_HIGHEST)

    # One band after another: a batched LAPACK solve can hang jaxlib < 0.12 (estimation.small_solve).
    return jax.lax.map(one_band, R_W)


def plane_irradiance(reduced: PlaneTransport, cells):
    """H (K, rows, cols): irradiance of the sample plane's cells per band, for the cells' mean
    reflectances `cells` (K, rows, cols) (the white patch and its mount are cells of the strip).
    Unit diffuser exitance; differentiable in `cells`."""
    cells = jnp.asarray(cells)
    rho = cells.reshape(cells.shape[0], -1)
    return _solve_cells(reduced.G.astype(rho.dtype), reduced.g.astype(rho.dtype), rho).reshape(cells.shape)


@jax.jit
def _solve_cells(G, g, rho):
    """H (K, C) with H = g + G diag(rho) H, per band."""
    eye = jnp.eye(rho.shape[1], dtype=rho.dtype)
    # One band after another: a batched LAPACK solve can hang jaxlib < 0.12 (estimation.small_solve).
    return jax.lax.map(lambda args: jnp.linalg.solve(eye - args[0] * args[1][None, :], args[2]), (G, rho, g))


def cell_means(values, shape: tuple[int, int]):
    """(..., rows, cols) means of `values` (..., H, W) over a rows x cols grid of equal cells
    (H and W multiples of rows and cols): a scene's reflectance per cell."""
    rows, cols = shape
    *lead, height, width = values.shape
    if height % rows or width % cols:
        raise ValueError(f"cell_means: a {height} x {width} image does not divide into {rows} x {cols} cells")
    return values.reshape(*lead, rows, height // rows, cols, width // cols).mean(axis=(-3, -1))


def pixel_irradiance(cell_irradiance, image_shape: tuple[int, int]):
    """(..., H, W) irradiance at the pixels, bilinear between the cells' centres (constant
    beyond the outer centres), from (..., rows, cols)."""
    lead = cell_irradiance.shape[:-2]
    return jax.image.resize(cell_irradiance, (*lead, *image_shape), method="linear", antialias=False)


__all__ = [
    "BAFFLE",
    "DETECTOR",
    "ENTRANCE",
    "PLANE",
    "WALL",
    "Elements",
    "IncidentLight",
    "PlaneTransport",
    "SphereGeometry",
    "SphereTransport",
    "diffuser_irradiance",
    "form_factors",
    "incident_light",
    "cell_means",
    "irradiance",
    "pixel_irradiance",
    "plane_irradiance",
    "plane_transport",
    "sphere_elements",
    "sphere_transport",
]
