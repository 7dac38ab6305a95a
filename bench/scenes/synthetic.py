"""Deterministic synthetic laser-scan scenes: building interiors, a simulated TLS, photographs.

In the spirit of the paper's excavation houses: a grid of rooms joined by doorways, wall niches,
columns, steps, free-standing objects and thin poles that make silhouettes and occlusions, under
a roof. Surfaces are textured with public-domain photographs that scikit-image ships offline
(frescoes on the walls, "marble" on columns) mapped tri-planarly in world coordinates, so the
colour of any surface point is a pure function of (material, position, normal).

A simulated terrestrial laser scanner (Embree ray casts on an azimuth x elevation grid from
stations in every room, with Gaussian range noise) makes P_HD: density falls off with distance
and occlusion shadows are real. Photographs are Embree renders of the same textured mesh, with a
per-photo exposure and white balance that can be switched off. The output is the scene input
format every user scene has (``points.ply``, ``sparse/``, ``images/``, ``mesh.ply``) plus
``synthetic.json`` (the configuration, each photo's exposure and the lights) for tests.

By default the photos are matte and see exactly the scanned surface, so all photos of a point
agree. Two options make the choice of photo matter, as it does for real photos (see
:class:`Studio`): a glossy highlight that depends on the camera's direction (``specular``), and
a photographed surface that lies ``photo_surface_offset`` in front of the scanned one (the mesh,
the scan and the photos' registration stay exact; only what the photos show moves), so a photo
reprojected through the scan drifts with the angle between it and the view. :class:`Studio` renders
the photo any camera would take, held-out views included.
"""

from __future__ import annotations

import collections
import contextlib
import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh
from tqdm import tqdm

from dmrt.camera import Camera
from dmrt.errors import ConfigError, InputError, require
from dmrt.io.atomic import atomic_dir
from dmrt.io.stations import SphericalGrid, Station, write_scans_json
from dmrt.options import option, validate
from dmrt.preprocess.parallel import default_workers
from reference.raycast import MeshRaycaster, write_mesh_ply


@dataclass
class SynthConfig:
    """One synthetic scene (lengths in metres, angles in degrees); each field is a ``dmrt scene
    synth`` option."""

    name: str = option("tiny", "scene name")
    seed: int = option(0, "random seed: the same seed gives the same files")
    rooms: tuple[int, int] = option((2, 1), "grid of rooms (x, y)", minimum=1)
    # rooms must hold a doorway (<= 1.3 m plus 0.4 m jambs) and cameras 1.5 m from a wall
    room_size: tuple[float, float] = option((4.0, 6.0), "random interior width range of each grid row and column, "
                                                        "metres", minimum=2.5)
    wall_height: float = option(3.0, "wall height, metres", minimum=0.5)
    wall_thickness: float = option(0.4, "wall thickness, metres", minimum=0.05)
    ceiling: bool = option(True, "a protective roof, as over excavation houses")
    # every consumer must prove it keeps a scene origin instead of pushing 10^6 m through float32
    offset: tuple[float, float, float] = option((512300.0, 5312700.0, 210.0), "large real-world (UTM-like) "
                                                "coordinates added to everything, metres")
    points: int = option(200_000, "laser scanner: target |P_HD|; sets the angular step", minimum=1)
    stations_per_room: int = option(1, "scanner stations per room", minimum=1)
    scan_elevation: tuple[float, float] = option((-70.0, 90.0), "scanned elevation range, degrees (below -70 "
                                                                "the tripod hides the floor)",
                                                 minimum=-90.0, maximum=90.0)
    range_noise: float = option(0.002, "1-sigma range noise, metres (a typical phase-based scanner)", minimum=0.0)
    write_normals: bool = option(False, "write normals with the points (real scans often lack them: "
                                        "preprocessing estimates them)")
    normals_type: Literal["float", "short", "char"] = option(
        "float", "PLY type of the written normals: float (12 bytes a point), short or char (6 or 3 bytes: "
                 "signed, times 32767 or 127; read back as unit normals within 0.002 or 0.4 degrees)")
    float_positions: bool = option(False, "write positions as float32, 12 bytes a point less (a 682M-point "
                                          "cloud must fit a 64 GB disk twice); needs an offset within 1 km, "
                                          "where float32 keeps ~0.1 mm")
    photos: int = option(12, "photographs", minimum=1)
    photo_size: tuple[int, int] = option((256, 171), "photo width and height, pixels (the paper's 1024x684 "
                                                     "aspect)", minimum=8)
    fov_x: float = option(80.0, "horizontal field of view of the photos, degrees", minimum=1.0, maximum=179.0)
    supersample: int = option(2, "s x s rays per pixel, box-filtered (anti-aliasing)", minimum=1)
    lighting_variation: bool = option(True, "per-photo exposure and white balance")
    exposure_range: tuple[float, float] = option((0.75, 1.25), "range of the per-photo exposure gain", minimum=0.0)
    white_balance_range: tuple[float, float] = option((0.92, 1.08), "range of the per-channel white-balance gain",
                                                      minimum=0.0)
    # Both off by default: matte photos of exactly the scanned surface (Studio states the model).
    specular: float = option(0.0, "strength k_s of a white Blinn-Phong highlight in the photos, from point "
                                  "lights in every room (0: matte photos that agree)", minimum=0.0)
    shininess: float = option(50.0, "Blinn-Phong exponent of the highlight (50: half strength 9.5 degrees "
                                    "off the half vector)", minimum=1.0)
    lights_per_room: int = option(2, "point lights per room (0.85 x wall height, shadowed) for the highlight",
                                  minimum=1)
    # bounds: -2 cm keeps the 3 cm poles solid; 10 cm is half the 0.20 m discontinuity threshold
    photo_surface_offset: float = option(0.0, "the photographed surfaces lie this far in front of the scanned "
                                              "ones along their outward normals, metres (negative: behind)",
                                         minimum=-0.02, maximum=0.1)
    chunk_rays: int = option(2_000_000, "rays per Embree batch: bounds memory on big presets", minimum=1)
    photographer: Literal["auto", "embree", "gl"] = option(
        "embree", "what renders the photos: embree (ray casts on the CPU: the truth, the same photos on any "
                  "machine), gl (OpenGL rasterization, matte photos only: specular 0) or auto (gl when specular is "
                  "0 and an OpenGL 4.3 context can be made); the two agree on >= 99 % of pixels and differ at "
                  "texel boundaries and triangle edges")

    def __post_init__(self):
        validate(self)
        if self.room_size[0] > self.room_size[1]:
            raise ConfigError("room_size", f"the range {self.room_size} must be (min, max)")
        if self.photographer == "gl" and self.specular > 0:
            raise ConfigError("photographer", "'gl' takes matte photos only: with --specular > 0 the highlight's "
                                              "shadow rays need 'embree' (or 'auto')")
        if self.float_positions and max(abs(v) for v in self.offset) > 1000.0:
            raise ConfigError("float_positions", f"float32 keeps only ~{max(map(abs, self.offset)) * 6e-8:.2g} m "
                                                 f"at the offset {self.offset}: use an offset within 1 km")


PRESETS = {
    # CI: about 200k points, 12 photos of 256x171 (6 per room), seconds on 2 cores.
    "tiny": SynthConfig(),
    "small": SynthConfig(name="small", rooms=(3, 2), points=2_000_000, photos=48, photo_size=(512, 342)),
    # The paper's Scene 2 budget (192 photos of 1024x684) with >= 30M points, streamed to disk.
    "paper": SynthConfig(name="paper", rooms=(4, 3), stations_per_room=2, points=32_000_000, photos=192,
                         photo_size=(1024, 684), supersample=1),
    # The paper's Scene 2 itself: >= 682M points (the scan grid lands within ~0.1 % of its target)
    # and 192 photos of 1024x684. The scan's normals are written (estimating them would be the
    # longest phase) and positions are float32 near the origin: 27 bytes a point, 18 GB.
    "paper-full": SynthConfig(name="paper-full", rooms=(4, 3), stations_per_room=2, points=683_000_000,
                              photos=192, photo_size=(1024, 684), supersample=1, write_normals=True,
                              offset=(0.0, 0.0, 0.0), float_positions=True),
    # The paper's Scene 3 (Centcelles: 1,091M points, 161 photos of 1024x684). The paper gives no
    # areas; its scenes are scans of the same kind (terrestrial scans of Roman buildings), so the
    # density is paper-full's: 20 rooms instead of 12 hold 220k points per m^2 of the mesh (4,947 m^2)
    # against paper-full's 225k (3,042 m^2), 54.6M points a room against 56.9M, two stations each.
    # The target lands the 40 stations' grids of 7838 x 3483 beams (every beam hits: the building
    # is closed) at 1,091,990,160 points. Normals as char (3 bytes) and float32 positions: 18 bytes a
    # point, a 19.7 GB PLY, so that the scene and its preprocessing fit a 64 GB disk
    # (bench/scenes/disk.py, docs/scene3.md).
    "paper-scene3": SynthConfig(name="paper-scene3", rooms=(5, 4), stations_per_room=2, points=1_092_000_000,
                                photos=161, photo_size=(1024, 684), supersample=1, write_normals=True,
                                normals_type="char", offset=(0.0, 0.0, 0.0), float_positions=True),
    # Thousands of photos (issue #39): a city block of 2 x 64 rooms (345 x 11 m), 80 photos of
    # 1024x684 in each (10,240), `paper`'s 32M points (250k a room, one station each). Photos cost
    # the generation: 0.43 s of one core each (Embree + shading 0.36, PNG 0.08; measured on the
    # 2-core CI machine), 20 min measured on the H200 machine's 16 cores (8.7 photos/s); the
    # OpenGL photographer (bench/scenes/glphoto.py, "auto": the photos are matte) leaves the workers
    # only the PNGs; 10.5 GB of PNGs. --photo-size 512 342 takes a quarter of that, at half the
    # paper's photo resolution.
    "many": SynthConfig(name="many", rooms=(64, 2), points=32_000_000, photos=10_240, photo_size=(1024, 684),
                        supersample=1, photographer="auto"),
    # The tiny scene with more photos than a texture array has layers (GL_MAX_ARRAY_TEXTURE_LAYERS
    # = 2048 on Mesa and NVIDIA): 2,100 photos of 64x43, for the Mesa tests of issue #39.
    "tiny-many": SynthConfig(name="tiny-many", photos=2_100, photo_size=(64, 43), photographer="auto"),
}

LIGHT = np.array([0.35, 0.25, 0.9]) / np.linalg.norm([0.35, 0.25, 0.9])
# Highlight contributions below this are not shadow-tested (skipped): 40x below one 8-bit level.
SPECULAR_CUTOFF = 1e-4


# ----------------------------------------------------------------------------------------------
# Materials: photographic textures mapped tri-planarly in world coordinates
# ----------------------------------------------------------------------------------------------
@dataclass
class Material:
    name: str
    texture: np.ndarray  # (h, w, 3) float32 albedo 0..1
    tile: float          # metres covered by one repeat of the texture


def _rgb(img: np.ndarray, tint=(1.0, 1.0, 1.0)) -> np.ndarray:
    img = img.astype(np.float32) / 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.clip(img[..., :3] * np.asarray(tint, np.float32), 0, 1)


def make_materials() -> list[Material]:
    """The material palette (index = material id). Photos from ``skimage.data`` (public domain)."""
    require("skimage", "the synthetic scenes' textures", "bench")
    from skimage import data

    return [
        Material("floor-gravel", _rgb(data.gravel(), (0.95, 0.85, 0.7)), 1.5),
        Material("roof-plaster", _rgb(data.grass(), (0.8, 0.8, 0.75)) * 0.5 + 0.4, 2.0),
        Material("wall-brick", _rgb(data.brick(), (1.0, 0.62, 0.45)), 1.6),
        Material("fresco-astronaut", _rgb(data.astronaut()), 2.4),
        Material("fresco-coffee", _rgb(data.coffee()), 2.2),
        Material("fresco-cat", _rgb(data.chelsea()), 2.0),
        Material("fresco-rocket", _rgb(data.rocket()), 2.6),
        Material("marble", _rgb(data.immunohistochemistry()) * 0.6 + 0.35, 0.9),
        Material("stone-steps", _rgb(data.gravel(), (0.7, 0.7, 0.75)) * 0.8 + 0.15, 1.0),
        Material("painted-wood", _rgb(data.colorwheel()) * 0.8, 1.2),
        Material("bronze", _rgb(data.coins(), (0.8, 0.55, 0.3)), 0.6),
    ]


FLOOR, ROOF, BRICK, FRESCOES, MARBLE, STEPS, WOOD, BRONZE = 0, 1, 2, (3, 4, 5, 6), 7, 8, 9, 10


def albedo(materials: list[Material], material_ids: np.ndarray, points: np.ndarray,
           normals: np.ndarray) -> np.ndarray:
    """Surface colour of each point.

    Parameters
    ----------
    material_ids : (n,) int.  points : (n, 3) float64, scene-local metres (offset removed).
    normals : (n, 3) float32 unit.

    Returns
    -------
    (n, 3) float32 albedo 0..1: the material's texture at the point's two world coordinates
    across the dominant normal axis (tri-planar mapping, nearest texel).
    """
    out = np.zeros((len(points), 3), np.float32)
    axis = np.argmax(np.abs(normals), axis=1)
    uv_axes = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    u = np.take_along_axis(points, uv_axes[:, :1], 1)[:, 0]
    v = np.take_along_axis(points, uv_axes[:, 1:], 1)[:, 0]
    for m in np.unique(material_ids):
        sel = material_ids == m
        mat = materials[int(m)]
        h, w = mat.texture.shape[:2]
        scale = max(h, w) / mat.tile  # texels per metre
        col = np.floor(u[sel] * scale).astype(np.int64) % w
        row = (-np.floor(v[sel] * scale).astype(np.int64) - 1) % h  # image up = world up
        out[sel] = mat.texture[row, col]
    return out


def shade(normals: np.ndarray) -> np.ndarray:
    """(n,) float32 view-independent light (ambient + one distant light), so photos agree."""
    return (0.6 + 0.4 * np.clip(normals @ LIGHT, 0, None)).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Geometry: rooms, walls with doorways and niches, furniture
# ----------------------------------------------------------------------------------------------
@dataclass
class Geometry:
    """The scene's triangle mesh in scene-local metres, with a material per face."""

    vertices: np.ndarray      # (v, 3) float64
    faces: np.ndarray         # (f, 3) int64
    face_material: np.ndarray  # (f,) int32
    rooms: list = field(default_factory=list)  # [(xmin, xmax, ymin, ymax)] room interiors


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def _wall(plan_lo, plan_hi, along: int, height: float, openings, interior_sign: int):
    """Boxes of a straight wall with openings.

    ``plan_lo``/``plan_hi``: (x, y) corners of the wall's footprint; ``along``: 0 if it runs along
    x; ``openings``: [(a, b, z0, z1, depth)] spans along the wall, ``depth`` = full thickness for a
    doorway, less for a niche recessed from the side ``interior_sign`` (+1: the high side).
    """
    lo, hi = np.array([*plan_lo, 0.0]), np.array([*plan_hi, height])
    across = 1 - along
    boxes, pos = [], lo[along]
    for a, b, z0, z1, depth in sorted(openings):
        if a > pos:
            boxes.append((np.r_[lo[:2], 0], hi.copy()))
            boxes[-1][0][along], boxes[-1][1][along] = pos, a
        for zlo, zhi in ((0.0, z0), (z1, height)):
            if zhi > zlo:
                b_lo, b_hi = lo.copy(), hi.copy()
                b_lo[along], b_hi[along], b_lo[2], b_hi[2] = a, b, zlo, zhi
                boxes.append((b_lo, b_hi))
        thickness = hi[across] - lo[across]
        if depth < thickness:  # a niche: the wall's back stays
            b_lo, b_hi = lo.copy(), hi.copy()
            b_lo[along], b_hi[along], b_lo[2], b_hi[2] = a, b, z0, z1
            if interior_sign > 0:
                b_hi[across] = hi[across] - depth
            else:
                b_lo[across] = lo[across] + depth
            boxes.append((b_lo, b_hi))
        pos = b
    if pos < hi[along]:
        b_lo = lo.copy()
        b_lo[along] = pos
        boxes.append((b_lo, hi.copy()))
    return [_box(a, b) for a, b in boxes]


def build_geometry(config: SynthConfig, grow: float = 0.0) -> Geometry:
    """The scene mesh, deterministic in ``config.seed``; with ``grow`` (metres) every face of every
    part lies that far out along its outward normal (see :func:`_grow`)."""
    rng = np.random.default_rng(config.seed)
    T, H = config.wall_thickness, config.wall_height
    nx, ny = config.rooms
    # Wall centre lines; rooms of random size between them.
    X = np.concatenate([[0.0], np.cumsum(rng.uniform(*config.room_size, nx) + T)])
    Y = np.concatenate([[0.0], np.cumsum(rng.uniform(*config.room_size, ny) + T)])
    parts: list[tuple[trimesh.Trimesh, int]] = []
    ext_lo, ext_hi = (X[0] - T / 2, Y[0] - T / 2), (X[-1] + T / 2, Y[-1] + T / 2)
    parts.append((_box((*ext_lo, -0.3), (*ext_hi, 0.0)), FLOOR))
    if config.ceiling:
        parts.append((_box((*ext_lo, H), (*ext_hi, H + 0.3)), ROOF))
    palette, first = FRESCOES + (BRICK,), int(rng.integers(5))  # neighbouring rooms differ
    room_material = {(i, j): palette[(first + i * ny + j) % 5] for i in range(nx) for j in range(ny)}

    def openings(lo_c, hi_c, exterior):
        """A doorway through interior walls, a niche (maybe) in exterior ones."""
        length = hi_c - lo_c
        if not exterior:
            w = rng.uniform(0.9, 1.3)
            a = rng.uniform(lo_c + 0.4, hi_c - 0.4 - w)
            return [(a, a + w, 0.0, rng.uniform(2.0, 2.4), T)]
        if rng.random() < 0.75 and length > 2.0:
            w = rng.uniform(0.6, 1.2)
            a = rng.uniform(lo_c + 0.4, hi_c - 0.4 - w)
            z0 = rng.uniform(0.5, 1.0)
            return [(a, a + w, z0, z0 + rng.uniform(0.8, 1.4), 0.6 * T)]
        return []

    # Walls along x (at each Y) run the full length; walls along y fit between them.
    for j, y in enumerate(Y):
        exterior = j in (0, ny)
        for i in range(nx):
            lo_c, hi_c = X[i] - (T / 2 if i == 0 else -T / 2), X[i + 1] + (T / 2 if i == nx - 1 else -T / 2)
            mat = room_material[(i, min(j, ny - 1))]
            for box in _wall((lo_c, y - T / 2), (hi_c, y + T / 2), 0, H,
                             openings(X[i] + T / 2, X[i + 1] - T / 2, exterior), 1 if j == 0 else -1):
                parts.append((box, mat))
            # fill the corner pieces between consecutive segments
            if i < nx - 1:
                parts.append((_box((X[i + 1] - T / 2, y - T / 2, 0), (X[i + 1] + T / 2, y + T / 2, H)), mat))
    for i, x in enumerate(X):
        exterior = i in (0, nx)
        for j in range(ny):
            mat = room_material[(min(i, nx - 1), j)]
            for box in _wall((x - T / 2, Y[j] + T / 2), (x + T / 2, Y[j + 1] - T / 2), 1, H,
                             openings(Y[j] + T / 2, Y[j + 1] - T / 2, exterior), 1 if i == 0 else -1):
                parts.append((box, mat))

    rooms = []
    for i in range(nx):
        for j in range(ny):
            x0, x1, y0, y1 = X[i] + T / 2, X[i + 1] - T / 2, Y[j] + T / 2, Y[j + 1] - T / 2
            rooms.append((x0, x1, y0, y1))
            parts.extend(_furnish(rng, (x0, x1, y0, y1), H))
    meshes = [_grow(m, grow) if grow else m for m, _ in parts]
    mesh = trimesh.util.concatenate(meshes)
    face_material = np.concatenate([np.full(len(m.faces), k, np.int32) for m, k in parts])
    return Geometry(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), face_material, rooms)


def _grow(mesh: trimesh.Trimesh, distance: float) -> trimesh.Trimesh:
    """A closed convex part with each face moved ``distance`` metres along its outward normal.

    Each vertex moves by the least-squares ``x`` of ``n_f . x = distance`` over its faces ``f``:
    exact where at most three planes meet (boxes, the cylinders' rims and caps), within 0.03 % of
    ``distance`` on the icospheres (measured). Every part is convex, so the union of the
    grown parts is the scene's surface moved along its normals (doorways narrow by twice as much).
    """
    n = mesh.face_normals
    A = np.zeros((len(mesh.vertices), 3, 3))
    b = np.zeros((len(mesh.vertices), 3))
    for k in range(3):
        np.add.at(A, mesh.faces[:, k], n[:, :, None] * n[:, None, :])
        np.add.at(b, mesh.faces[:, k], n)
    # rank 1 at a cap's centre: the pseudo-inverse moves it along the cap's normal
    x = np.einsum("vij,vj->vi", np.linalg.pinv(A, rcond=1e-6, hermitian=True), b)
    return trimesh.Trimesh(mesh.vertices + distance * x, mesh.faces, process=False)


def _furnish(rng, room, H):
    """Columns, steps, an altar, a statue, a thin pole: silhouettes and occluders for one room."""
    x0, x1, y0, y1 = room
    taken: list[tuple[float, float, float]] = []

    def spot(radius, margin=0.3):
        for _ in range(100):
            p = (rng.uniform(x0 + margin + radius, x1 - margin - radius), rng.uniform(y0 + margin + radius, y1 - margin - radius))
            if all(np.hypot(p[0] - q[0], p[1] - q[1]) > radius + r + 0.5 for *q, r in taken):
                taken.append((*p, radius))
                return p
        return None

    parts = []
    # Steps against a wall: three stacked slabs (a podium).
    w = rng.uniform(1.2, 1.8)
    sx = rng.uniform(x0 + 0.2, x1 - 0.2 - w)
    taken.append((sx + w / 2, y1 - 0.7, w / 2 + 0.2))
    for k in range(3):
        depth = 1.2 - 0.35 * k
        parts.append((_box((sx + 0.1 * k, y1 - depth, 0.0), (sx + w - 0.1 * k, y1, 0.15 * (k + 1))), STEPS))
    # A column from floor to roof.
    if (p := spot(0.25, margin=0.8)) is not None:
        col = trimesh.creation.cylinder(radius=rng.uniform(0.15, 0.25), height=H, sections=24)
        col.apply_translation((p[0], p[1], H / 2))
        parts.append((col, MARBLE))
    # An altar: a rotated box.
    if (p := spot(0.7)) is not None:
        altar = trimesh.creation.box(extents=(rng.uniform(0.8, 1.3), rng.uniform(0.5, 0.8), rng.uniform(0.7, 1.0)))
        altar.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), (0, 0, 1)))
        altar.apply_translation((p[0], p[1], altar.extents[2] / 2))
        parts.append((altar, WOOD))
    # A statue: a sphere on a pedestal.
    if (p := spot(0.35)) is not None:
        ped_h = rng.uniform(0.8, 1.2)
        parts.append((_box((p[0] - 0.25, p[1] - 0.25, 0), (p[0] + 0.25, p[1] + 0.25, ped_h)), MARBLE))
        ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
        ball.apply_translation((p[0], p[1], ped_h + 0.3))
        parts.append((ball, BRONZE))
    # A thin pole (a railing post): the thin features that shine through in DMT (Fig. 11).
    if (p := spot(0.05)) is not None:
        pole = trimesh.creation.cylinder(radius=0.03, height=1.1, sections=12)
        pole.apply_translation((p[0], p[1], 0.55))
        parts.append((pole, BRONZE))
    return parts


# ----------------------------------------------------------------------------------------------
# Sensors
# ----------------------------------------------------------------------------------------------
def _free(raycaster: MeshRaycaster, p: np.ndarray, clearance: float) -> bool:
    """Whether ``p`` is inside the building and at least ``clearance`` from every surface."""
    dirs = np.concatenate([np.eye(3), -np.eye(3), np.array([[1, 1, 0], [1, -1, 0], [-1, 1, 0], [-1, -1, 0]]) / np.sqrt(2)])
    t, face = raycaster.intersect(p, dirs)
    if (face < 0).any() or (t < clearance).any():
        return False
    # Inside a solid the first hit is a back face (normal pointing along the ray).
    return bool((np.einsum("ij,ij->i", raycaster.face_normals[face], dirs) < 0).all())


def place_stations(config: SynthConfig, geom: Geometry, raycaster, rng) -> np.ndarray:
    """(s, 3) scanner positions, scene-local metres: on tripods (1.6 m) in every room."""
    out = []
    for (x0, x1, y0, y1) in geom.rooms:
        for _ in range(config.stations_per_room):
            for _ in range(200):
                p = np.array([rng.uniform(x0 + 0.8, x1 - 0.8), rng.uniform(y0 + 0.8, y1 - 0.8), 1.6])
                if _free(raycaster, p, 0.5):
                    out.append(p)
                    break
    return np.array(out)


def place_cameras(config: SynthConfig, geom: Geometry, raycaster, rng) -> list[Camera]:
    """Photo cameras, scene-local, placed the way a documentation campaign covers a room: each
    photo looks at one wall (cycling through the four) from across the room, a little off-axis,
    so that the walls, floor and roof of every room are seen."""
    cams = []
    w, h = config.photo_size
    n_rooms = len(geom.rooms)
    digits = max(4, len(str(config.photos - 1)))  # names sort in photo order
    for k in range(config.photos):
        x0, x1, y0, y1 = geom.rooms[k % n_rooms]
        side = (k // n_rooms) % 4
        for _ in range(500):
            if side < 2:  # wall at x0 or x1
                normal = np.array([1.0 if side == 0 else -1.0, 0, 0])
                target = np.array([x0 if side == 0 else x1, rng.uniform(y0, y1), 0.0])
                depth, width = x1 - x0, y1 - y0
            else:
                normal = np.array([0, 1.0 if side == 2 else -1.0, 0])
                target = np.array([rng.uniform(x0, x1), y0 if side == 2 else y1, 0.0])
                depth, width = y1 - y0, x1 - x0
            center = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
            lateral = np.cross(normal, (0, 0, 1))
            target[:2] += (center - target[:2]) * np.abs(lateral[:2]) * 0.6  # towards the wall centre
            target[2] = rng.uniform(0.8, 1.8)
            eye = target + normal * depth * rng.uniform(0.55, 0.92) + lateral * rng.uniform(-0.25, 0.25) * width
            eye[2] = rng.uniform(1.3, 1.9)
            if not (x0 + 0.3 < eye[0] < x1 - 0.3 and y0 + 0.3 < eye[1] < y1 - 0.3) or not _free(raycaster, eye, 0.3):
                continue
            cam = Camera.look_at(f"photo_{k:0{digits}d}.png", eye, target + rng.normal(0, 0.2, 3), w, h, config.fov_x)
            # The photo must show mostly surface within reach (not a pole 10 cm in front).
            t, face = raycaster.intersect(eye, cam.R[2][None])
            if face[0] >= 0 and t[0] > 0.8:
                cams.append(cam)
                break
        else:
            raise RuntimeError(f"could not place photo {k} in room {k % n_rooms}")
    return cams


def scan_grid(config: SynthConfig, n_stations: int) -> SphericalGrid:
    """Each station's grid of beams: azimuth x elevation at one angular step, chosen so that all
    stations together fire about ``config.points`` beams; rows (elevations) bottom up, each row's
    columns (azimuths) from +x toward +y."""
    el0, el1 = np.radians(config.scan_elevation)
    # grid rays per station = (2 pi / step) * ((el1 - el0) / step)
    step = float(np.sqrt(2 * np.pi * (el1 - el0) * n_stations / config.points))
    return SphericalGrid(0.0, step, len(np.arange(0, 2 * np.pi, step)), float(el0 + step / 2), step,
                         len(np.arange(el0 + step / 2, el1, step)))


def scan_directions(config: SynthConfig, n_stations: int, start: int = 0, stop: int | None = None) -> np.ndarray:
    """(r, 3) unit beam directions of one station, its grid (:func:`scan_grid`) row by row: beams
    ``start:stop`` of them (default all), the same values as that slice of the whole grid's, so a
    batch of beams is made where it is cast and no station's grid is ever held whole."""
    el0, el1 = np.radians(config.scan_elevation)
    step = scan_grid(config, n_stations).azimuth_step
    azimuths, elevations = np.arange(0, 2 * np.pi, step), np.arange(el0 + step / 2, el1, step)
    beam = np.arange(start, len(azimuths) * len(elevations) if stop is None else stop)
    A, E = azimuths[beam % len(azimuths)], elevations[beam // len(azimuths)]
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1)


def scan_points(config: SynthConfig) -> int:
    """Points the scene's scan holds, from its configuration alone: every beam of every station
    (``rooms x stations_per_room`` of them) hits, the building being closed (tested)."""
    n_stations = config.rooms[0] * config.rooms[1] * config.stations_per_room
    grid = scan_grid(config, n_stations)
    return n_stations * grid.rows * grid.columns


def _beam_batches(n_beams: int, chunk_rays: int) -> list[tuple[int, int]]:
    """``[start, stop)`` of each batch of a station's beams: ``np.array_split`` of them into
    ``ceil(n_beams / chunk_rays)`` parts (the first ``n_beams % parts`` one longer)."""
    parts = -(-n_beams // chunk_rays)
    each, extra = divmod(n_beams, parts)
    stops = np.cumsum([each + 1] * extra + [each] * (parts - extra)).tolist()
    return list(zip([0] + stops[:-1], stops))


def scan_beams(config: SynthConfig, geom: Geometry, raycaster, materials, station: np.ndarray,
               dirs: np.ndarray, rng):
    """Simulated TLS returns of one batch of beams from ``station`` (scene-local metres).

    Returns positions (n, 3) float64 with Gaussian range noise along the beam, the surface normals
    facing the scanner (n, 3) float32, and the scanner's colours (n, 3) uint8.
    """
    t, face = raycaster.intersect(station, dirs)
    hit = face >= 0
    d, t, face = dirs[hit], t[hit], face[hit]
    pos = station + d * (t + rng.normal(0, config.range_noise, len(t)))[:, None]
    n = raycaster.face_normals[face]
    n[np.einsum("ij,ij->i", n, d) > 0] *= -1  # the side the scanner saw
    true_pos = station + d * t[:, None]
    rgb = albedo(materials, geom.face_material[face], true_pos, n) * shade(n)[:, None]
    return pos, n, np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8)


def place_lights(config: SynthConfig, geom: Geometry, raycaster) -> np.ndarray:
    """(l, 3) float64 point lights of the highlights, scene-local metres: ``lights_per_room`` per
    room at 0.85 x the wall height, 0.3 m clear of every surface. Their own random stream, so
    switching the highlight on changes nothing else in the scene."""
    rng = np.random.default_rng([config.seed, 3])
    out = []
    for r, (x0, x1, y0, y1) in enumerate(geom.rooms):
        for _ in range(config.lights_per_room):
            for _ in range(200):
                p = np.array([rng.uniform(x0 + 0.5, x1 - 0.5), rng.uniform(y0 + 0.5, y1 - 0.5),
                              0.85 * config.wall_height])
                if _free(raycaster, p, 0.3):
                    out.append(p)
                    break
            else:
                raise RuntimeError(f"could not place a light in room {r}")
    return np.array(out).reshape(-1, 3)


class Studio:
    """The synthetic scene as the photographs see it: renders the photo any camera would take.

    The colour of a surface point ``p`` with unit normal ``n`` (facing the camera), seen from the
    camera centre ``e``, before the photo's gain (exposure x white balance) and 8-bit rounding::

        c = albedo(p) * (0.6 + 0.4 max(0, n . LIGHT))                 matte, as the scan's colours
          + k_s * sum_l [n . l_l > 0] V_l(p) (n . h_l)^s              white Blinn-Phong highlight

    with ``l_l`` the unit direction from ``p`` to light ``l`` (:func:`place_lights`), ``v`` the unit
    direction from ``p`` to ``e``, ``h_l = (l_l + v) / |l_l + v|``, ``V_l(p)`` 1 when the segment to
    the light is free (shadows), ``k_s = config.specular``, ``s = config.shininess``; terms below
    ``SPECULAR_CUTOFF`` are dropped. The photographed surface is the scanned mesh grown by
    ``config.photo_surface_offset`` along its outward normals (:func:`build_geometry`); the
    textures stay fixed in world space (tri-planar), so a moved wall shows the same paint.

    Built deterministically from the configuration, so the truth at a held-out or novel view is
    ``Studio.from_scene(scene_dir).photograph(camera, world=True)``.

    Attributes
    ----------
    geom : Geometry
        The scanned surface (``mesh.ply``, the laser scan), scene-local.
    scan_raycaster, photo_raycaster : MeshRaycaster
        The scanned and the photographed surface (the same object when the offset is 0).
    lights : (l, 3) float64
        Highlight lights, scene-local metres; (0, 3) when ``specular`` is 0.
    """

    def __init__(self, config: SynthConfig):
        self.config = config
        self.geom = build_geometry(config)
        self.materials = make_materials()
        self.scan_raycaster = MeshRaycaster(self.geom.vertices, self.geom.faces, origin=np.zeros(3))
        self.photo_geom, self.photo_raycaster = self.geom, self.scan_raycaster
        if config.photo_surface_offset:
            self.photo_geom = build_geometry(config, grow=config.photo_surface_offset)
            self.photo_raycaster = MeshRaycaster(self.photo_geom.vertices, self.photo_geom.faces,
                                                 origin=np.zeros(3))
        self.lights = (place_lights(config, self.photo_geom, self.photo_raycaster) if config.specular > 0
                       else np.zeros((0, 3)))

    @classmethod
    def from_scene(cls, scene_dir) -> "Studio":
        """The studio of a generated scene, from its ``synthetic.json``.

        Raises
        ------
        InputError
            No ``synthetic.json`` (not a synthetic scene) or one this generator cannot read.
        """
        path = Path(scene_dir) / "synthetic.json"
        try:
            fields = json.loads(path.read_text())["config"]
            config = SynthConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(path, f"not a synthetic scene's description ({exc})") from exc
        return cls(config)

    def specular(self, points: np.ndarray, normals: np.ndarray, eye: np.ndarray) -> np.ndarray:
        """(n,) float32 highlight ``k_s sum_l [n . l > 0] V_l (n . h_l)^s`` (class docstring).

        ``points`` (n, 3) float64 on the photographed surface, ``normals`` (n, 3) unit facing
        ``eye`` (3,), all scene-local metres.
        """
        out = np.zeros(len(points), np.float32)
        v = eye - points
        v /= np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
        nv = np.einsum("ij,ij->i", normals, v)
        for light in self.lights:
            lv = light - points
            lv /= np.sqrt(np.einsum("ij,ij->i", lv, lv))[:, None]
            nl = np.einsum("ij,ij->i", normals, lv)
            lit = np.flatnonzero(nl > 0)
            # n . h = (n . l + n . v) / |l + v|, and |l + v|^2 = 2 + 2 l . v (> 0: l and v both face n)
            nh = (nl[lit] + nv[lit]) / np.sqrt(2 + 2 * np.einsum("ij,ij->i", lv[lit], v[lit]))
            s = self.config.specular * nh ** self.config.shininess
            lit, s = lit[s >= SPECULAR_CUTOFF], s[s >= SPECULAR_CUTOFF]
            seen = self.photo_raycaster.visible(points[lit], light)
            out[lit[seen]] += s[seen]
        return out

    def photograph(self, camera: Camera, gain=None, world: bool = False) -> np.ndarray:
        """(h, w, 3) uint8 Embree render of the photographed surface through ``camera``.

        ``gain`` (3,): exposure x white balance (default 1); ``world``: the camera is in the
        scene's world coordinates (its ``sparse/`` model), else scene-local. Each pixel averages
        ``supersample`` x ``supersample`` rays.
        """
        if world:
            camera = camera.relative_to(self.config.offset)
        s = self.config.supersample
        big = camera.scaled(camera.width * s, camera.height * s)
        dirs, center = big.pixel_rays()
        t, face = self.photo_raycaster.intersect(center, dirs)
        rgb = np.zeros((len(t), 3), np.float32)
        hit = face >= 0
        n = self.photo_raycaster.face_normals[face[hit]]
        n[np.einsum("ij,ij->i", n, dirs[hit]) > 0] *= -1
        p = center + dirs[hit] * t[hit, None]
        rgb[hit] = albedo(self.materials, self.photo_geom.face_material[face[hit]], p, n) * shade(n)[:, None]
        if len(self.lights):
            rgb[hit] += self.specular(p, n, center)[:, None]
        return develop(rgb, camera, s, gain)


def develop(rgb: np.ndarray, camera: Camera, supersample: int, gain=None) -> np.ndarray:
    """The photo ``camera`` keeps of its rays' colours: each pixel the box-filtered mean of its
    ``supersample`` x ``supersample`` rays, times the ``gain`` (3,) (default 1), 8-bit.

    ``rgb``: (height * s, width * s, 3) or (height * s * width * s, 3) float32 linear colour 0..1,
    row-major from the top-left ray. Returns (height, width, 3) uint8. Shared by both
    photographers (Embree here, OpenGL in :mod:`bench.scenes.glphoto`) so that they round alike.
    """
    s = supersample
    img = rgb.reshape(camera.height, s, camera.width, s, 3)
    # the mean of one ray is the ray (x / 1), skipped: the GL photographer's main process runs this
    # for every photo, and the in-place float64 steps below halve its time (1024x684: 15 ms)
    img = img.mean(axis=(1, 3)) if s > 1 else img.reshape(camera.height, camera.width, 3)
    img = img * (np.ones(3) if gain is None else np.asarray(gain))
    img *= 255
    return np.clip(np.rint(img, out=img), 0, 255, out=img).astype(np.uint8)


# Each worker process builds the scene once (Embree scenes do not pickle) and serves batches.
_WORKER: dict = {}


def _init_worker(config: SynthConfig) -> None:
    _WORKER.update(config=config, studio=Studio(config))


def _scan_task(args):
    k, station, n_stations, start, stop = args
    w, st = _WORKER, _WORKER["studio"]
    rng = np.random.default_rng([w["config"].seed, 2, k])  # per batch: same points for any worker count
    dirs = scan_directions(w["config"], n_stations, start, stop)
    return scan_beams(w["config"], st.geom, st.scan_raycaster, st.materials, station, dirs, rng)


def _png_task(args):
    img, path = args
    from PIL import Image

    # compress level 1: 3x faster than PIL's default 6 for 4 % more bytes (1024x684: 0.08 against
    # 0.24 s, the third of a photo's time at the default)
    Image.fromarray(img).save(path, compress_level=1)
    return path


def _photo_task(args):
    cam, gain, path = args
    return _png_task((_WORKER["studio"].photograph(cam, gain), path))


# The GL photographer's photos agree with Embree's on 99.87-99.95 % of the pixels exactly on Mesa
# (tests/test_synth_gl.py); below this, the driver renders something else (a depth format, a
# rasterization rule): refused rather than written as a scene.
GL_CHECK_EQUAL = 0.99


def _check_gl_photo(studio: Studio, gl, camera: Camera, gain) -> dict:
    """The first photo by both photographers: ``{"photo", "equal_fraction"}`` for ``synthetic.json``;
    a :class:`ConfigError` naming ``--photographer embree`` when they agree on fewer than
    ``GL_CHECK_EQUAL`` of the pixels (a driver whose rasterization differs from Mesa's, where the
    GL photographer was checked)."""
    equal = float(np.mean(np.all(gl.photograph(camera, gain) == studio.photograph(camera, gain), axis=-1)))
    if equal < GL_CHECK_EQUAL:
        raise ConfigError("photographer", f"the OpenGL photographer agrees with Embree on only {equal:.2%} of "
                                          f"photo {camera.name}'s pixels (>= {GL_CHECK_EQUAL:.0%} expected): "
                                          f"generate with --photographer embree")
    return {"photo": camera.name, "equal_fraction": round(equal, 6)}


# ----------------------------------------------------------------------------------------------
# The scene on disk
# ----------------------------------------------------------------------------------------------
class _Deferred:
    """An inline pool's ``apply_async`` result: the call runs when its result is asked for."""

    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def get(self):
        return self.fn(*self.args)


class _InlinePool:
    """The pool interface, run in this process (one worker: no start-up cost)."""

    def __init__(self, studio: Studio):
        _WORKER.update(config=studio.config, studio=studio)

    imap = imap_unordered = staticmethod(map)

    @staticmethod
    def apply_async(fn, args):
        return _Deferred(fn, args)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        _WORKER.clear()


def _pool(studio: Studio, workers: int):
    import multiprocessing

    if workers <= 1:
        return _InlinePool(studio)
    # spawn, not fork: the parent may hold a GL context or Embree threads
    return multiprocessing.get_context("spawn").Pool(workers, _init_worker, (studio.config,))


def _in_order(pool, fn, tasks, ahead: int):
    """``fn(task)`` of each task on ``pool``, results in task order, with at most ``ahead`` tasks
    submitted and not yet taken: results wait in the workers' queue for the writer instead of
    piling up in this process (``Pool.imap`` queues every task at once and keeps every result that
    the consumer has not reached)."""
    pending: collections.deque = collections.deque()
    for task in tasks:
        pending.append(pool.apply_async(fn, (task,)))
        if len(pending) >= ahead:
            yield pending.popleft().get()
    while pending:
        yield pending.popleft().get()


def generate_scene(config: SynthConfig, out, force: bool = False, progress: bool = True,
                   workers: int | None = None) -> Path:
    """Write a synthetic scene in the scene input format to ``out``; returns the path.

    ``workers`` processes (default: one per CPU core) scan and photograph in parallel; the
    result does not depend on their number. With the OpenGL photographer
    (:func:`~bench.scenes.glphoto.choose_photographer`, recorded in ``synthetic.json`` as
    ``photographer``) this process renders the photos and the workers PNG-encode them.

    The scene is assembled in ``<out>.partial`` and renamed when complete, so an interrupted run
    never leaves a scene that looks whole. An existing ``out`` is replaced only with ``force``.
    A file system with less free space than the scene takes (:mod:`bench.scenes.disk`) is an
    :class:`InputError` before any work.
    """
    from bench.scenes.disk import check_free, scene_files
    from bench.scenes.glphoto import GLPhotographer, choose_photographer
    from dmrt.io.colmap import write_model
    from dmrt.io.pointcloud import PointCloud, PointWriter

    out = Path(out)
    require("skimage", "the synthetic scenes' textures", "bench")  # before any work
    check_free(sum(scene_files(config).values()), out.parent, f"the {config.name!r} scene")
    photographer = choose_photographer(config)
    rng = np.random.default_rng(config.seed + 1)
    workers = workers if workers is not None else default_workers()
    offset = np.asarray(config.offset, np.float64)
    with atomic_dir(out, force=force, what="scene") as tmp:
        (tmp / "images").mkdir()
        studio = Studio(config)
        geom, raycaster = studio.geom, studio.scan_raycaster
        write_mesh_ply(tmp / "mesh.ply", geom.vertices + offset, geom.faces)

        stations = place_stations(config, geom, raycaster, rng)
        cameras = place_cameras(config, geom, raycaster, rng)
        gains = [rng.uniform(*config.exposure_range) * rng.uniform(*config.white_balance_range, 3)
                 if config.lighting_variation else np.ones(3) for _ in cameras]
        grid = scan_grid(config, len(stations))
        # batches of beams as (station, first beam, end), each cast by a worker that makes its
        # directions: memory is a few batches in flight, whatever the number of points
        batches = [(i, a, b) for i in range(len(stations))
                   for a, b in _beam_batches(grid.rows * grid.columns, config.chunk_rays)]
        tasks = [(k, stations[i], len(stations), a, b) for k, (i, a, b) in enumerate(batches)]
        hits = np.zeros(len(stations) + 1, np.int64)  # each station's points, after the ones before
        with _pool(studio, workers) as pool:
            bar = tqdm(total=config.points, desc="scanning", unit="pt", unit_scale=True, disable=not progress)
            with PointWriter(tmp / "points.ply", normals=config.write_normals, colors=True,
                             float_positions=config.float_positions, normals_type=config.normals_type) as writer:
                # in order (deterministic), two batches a worker ahead of the writer
                for (i, _, _), (pos, n, rgb) in zip(batches, _in_order(pool, _scan_task, tasks, 2 * max(workers, 1))):
                    writer.write(PointCloud(pos + offset, n if config.write_normals else None, rgb))
                    hits[i + 1] += len(pos)
                    bar.update(len(pos))
            bar.close()
            # the scan structure (dmrt.io.stations): station runs of the file, each's grid
            first = np.cumsum(hits)
            write_scans_json(tmp / "scans.json", [Station(s + offset, np.eye(3), (int(first[i]), int(first[i + 1])),
                                                          grid) for i, s in enumerate(stations)])
            tasks = [(cam, g, tmp / "images" / cam.name) for cam, g in zip(cameras, gains)]
            with GLPhotographer(studio) if photographer == "gl" else contextlib.nullcontext() as gl:
                if gl is None:
                    done = pool.imap_unordered(_photo_task, tasks)
                else:  # rendered here, one photo at a time; the workers only encode, two photos each in flight
                    check = _check_gl_photo(studio, gl, *tasks[0][:2])
                    photos = ((gl.photograph(cam, g), path) for cam, g, path in tasks)
                    done = _in_order(pool, _png_task, photos, 2 * max(workers, 1))
                for _ in tqdm(done, total=len(tasks), desc=f"photographing ({photographer})", unit="photo",
                              disable=not progress):
                    pass
        # Cameras go to disk in world coordinates: t_world = t_local - R @ offset.
        world = [replace(c, t=c.t - c.R @ offset) for c in cameras]
        write_model(tmp / "sparse", world, binary=False)
        meta = {"generator": "bench.scenes.synthetic", "config": asdict(config), "photographer": photographer,
                "photographer_check": check if photographer == "gl" else None,
                "stations": (stations + offset).tolist(),
                "photo_gains": [g.tolist() for g in gains],
                "lights": (studio.lights + offset).tolist(),
                "materials": [m.name for m in studio.materials]}
        (tmp / "synthetic.json").write_text(json.dumps(meta, indent=1))
    return out
