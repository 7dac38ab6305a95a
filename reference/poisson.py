"""A reference mesh from the point cloud, for scenes that come without one.

Screened Poisson reconstruction (Kazhdan & Hoppe 2013) through pymeshlab: MeshLab's own filter,
maintained, pip-installable with no system dependencies, and it takes our normals as they are
(Open3D would do the same at four times the download). Poisson closes every surface, so faces
farther than ``trim`` from any input point are removed: they are invented, not measured.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from dmrt.io.atomic import atomic_file

from reference.raycast import write_mesh_ply


def reconstruct_mesh(positions: np.ndarray, normals: np.ndarray, depth: int = 9,
                     trim: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson surface of an oriented point cloud.

    Parameters
    ----------
    positions : (n, 3) float64, metres (any frame; large offsets are removed internally).
    normals : (n, 3) float32, unit, oriented outward (toward the scanner).
    depth : octree depth of the reconstruction: a grid of about 2^depth cells across the scene.
    trim : metres; faces whose centroid is farther than this from the cloud are dropped.
        Default: the larger of 5x the median nearest-neighbour spacing (random sampling leaves
        gaps of a few spacings that are surface, not holes) and 2 Poisson grid cells.

    Returns
    -------
    vertices : (v, 3) float64 in the input frame.  faces : (f, 3) int64.
    """
    import pymeshlab

    positions = np.asarray(positions, np.float64)
    if len(positions) < 100:
        raise ValueError(f"Poisson reconstruction needs at least 100 points, got {len(positions)}")
    center = np.round(0.5 * (positions.min(0) + positions.max(0)))
    local = positions - center
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=local, v_normals_matrix=np.asarray(normals, np.float64)))
    # MeshLab's default of 8 OpenMP threads busy-waits itself to a crawl on a 2-core machine.
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True,
                                                        threads=min(os.cpu_count() or 1, 8))
    mesh = ms.current_mesh()
    vertices, faces = mesh.vertex_matrix(), mesh.face_matrix().astype(np.int64)
    tree = cKDTree(local)
    if trim is None:
        spacing, _ = tree.query(local[:: max(1, len(local) // 20000)], k=2)
        cell = float(np.max(local.max(0) - local.min(0))) / 2 ** depth
        trim = max(5.0 * float(np.median(spacing[:, 1])), 2.0 * cell)
    dist, _ = tree.query(vertices[faces].mean(axis=1), workers=-1)
    faces = faces[dist <= trim]
    used, faces = np.unique(faces, return_inverse=True)
    return vertices[used] + center, faces.reshape(-1, 3)


def build_scene_mesh(scene, out: Path | None = None, depth: int = 9, normals_k: int = 16) -> Path:
    """Reconstruct ``SCENE/mesh.ply`` (or ``out``) from a loaded scene's points.

    Normals missing from the cloud are estimated and oriented toward the nearest photo camera.
    """
    from dmrt.preprocess.normals import estimate_normals

    cloud = scene.read_points()
    normals = cloud.normals
    if normals is None:
        centers = np.array([c.center for c in scene.cameras])
        nearest = centers[cKDTree(centers).query(cloud.positions)[1]]
        normals = estimate_normals(cloud.positions - scene.origin, k=normals_k, viewpoints=nearest - scene.origin)
    vertices, faces = reconstruct_mesh(cloud.positions, normals, depth=depth)
    out = Path(out) if out is not None else scene.root / "mesh.ply"
    with atomic_file(out) as tmp:
        write_mesh_ply(tmp, vertices, faces)
    return out
