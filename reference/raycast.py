"""Embree ray casts of a reference mesh: the ground truth every renderer is compared with.

Embree works in float32, so the mesh and all rays are moved into a frame centred on ``origin``
(the scene origin) before they reach it: UTM-sized coordinates would otherwise lose centimetres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from embreex import mesh_construction, rtcore_scene

from dmrt.camera import Camera
from dmrt.errors import InputError

# Rays leave a surface this far along their direction (metres) so they do not hit it again;
# far below the millimetre range noise of a terrestrial scanner.
SURFACE_EPSILON = 1e-4
# Embree's ray batches are cut into pieces of this many rays to bound temporary memory.
BATCH = 1 << 20


class MeshRaycaster:
    """First-hit and occlusion queries against a triangle mesh.

    Parameters
    ----------
    vertices : (v, 3) float64
        World coordinates, metres.
    faces : (f, 3) int
        Vertex indices of each triangle.
    origin : (3,) float64, optional
        Frame centre for Embree's float32 arithmetic; default the bounding-box centre.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, origin=None):
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if len(faces) == 0:
            raise ValueError("reference mesh has no triangles")
        self.origin = (0.5 * (vertices.min(0) + vertices.max(0)) if origin is None
                       else np.asarray(origin, dtype=np.float64))
        self.vertices, self.faces = vertices, faces
        tri = vertices[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_normals = (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)).astype(np.float32)
        self._scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(self._scene, (vertices - self.origin).astype(np.float32),
                                       faces.astype(np.int32))

    @classmethod
    def from_file(cls, path, origin=None) -> "MeshRaycaster":
        """Load ``mesh.ply`` (or any format trimesh reads) with a clear error when it is unusable."""
        import trimesh

        path = Path(path)
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types for broken files
            raise InputError(path, f"cannot read reference mesh ({exc})") from exc
        if len(mesh.faces) == 0:
            raise InputError(path, "reference mesh has no triangles")
        if not np.isfinite(mesh.vertices).all():
            raise InputError(path, "reference mesh has NaN/inf vertex coordinates")
        return cls(mesh.vertices, mesh.faces, origin)

    def intersect(self, origins: np.ndarray, directions: np.ndarray):
        """Nearest hit of each ray.

        Parameters
        ----------
        origins : (n, 3) or (3,) float64
            World coordinates, metres.
        directions : (n, 3) float64
            Need not be unit length: the hit parameter is in units of each direction's length.

        Returns
        -------
        t : (n,) float64
            Hit parameter (``origin + t * direction``), ``inf`` where the ray misses.
        face : (n,) int64
            Triangle index, -1 on a miss.
        """
        directions = np.asarray(directions, dtype=np.float64)
        origins = np.broadcast_to(np.asarray(origins, dtype=np.float64) - self.origin, directions.shape)
        t = np.full(len(directions), np.inf)
        face = np.full(len(directions), -1, dtype=np.int64)
        for s in range(0, len(directions), BATCH):
            sl = slice(s, s + BATCH)
            res = self._scene.run(np.ascontiguousarray(origins[sl], dtype=np.float32),
                                  np.ascontiguousarray(directions[sl], dtype=np.float32), output=1)
            hit = res["geomID"] != -1
            t[sl][hit] = res["tfar"][hit]
            face[sl][hit] = res["primID"][hit]
        return t, face

    def visible(self, points: np.ndarray, eye: np.ndarray) -> np.ndarray:
        """(n,) bool: whether the segment from each surface point to ``eye`` is free of the mesh.

        ``points`` (n, 3) float64 world; ``eye`` (3,) float64 world.
        """
        points = np.asarray(points, dtype=np.float64)
        d = np.asarray(eye, dtype=np.float64) - points
        length = np.linalg.norm(d, axis=1)
        d = d / np.maximum(length, 1e-12)[:, None]
        start = points - self.origin + SURFACE_EPSILON * d
        out = np.empty(len(points), dtype=bool)
        for s in range(0, len(points), BATCH):
            sl = slice(s, s + BATCH)
            res = self._scene.run(start[sl].astype(np.float32), d[sl].astype(np.float32),
                                  dists=np.maximum(length[sl] - 2 * SURFACE_EPSILON, 0).astype(np.float32),
                                  query="OCCLUDED")
            out[sl] = res == -1
        return out

    def cast_camera(self, camera: Camera):
        """Depth, face and unit normal of every pixel of ``camera``.

        Returns
        -------
        depth : (h, w) float32
            Camera-space z in metres, 0 where the ray misses.
        face : (h, w) int64
            Triangle index, -1 on a miss.
        normal : (h, w, 3) float32
            Unit world-space normal facing the camera, 0 on a miss.
        """
        dirs, center = camera.pixel_rays()  # scaled so the hit parameter is camera z
        t, face = self.intersect(center, dirs)
        hit = face >= 0
        depth = np.where(hit, t, 0.0).astype(np.float32)
        normal = np.zeros((len(face), 3), dtype=np.float32)
        n = self.face_normals[face[hit]]
        flip = np.einsum("ij,ij->i", n, dirs[hit]) > 0
        n[flip] *= -1
        normal[hit] = n
        h, w = camera.height, camera.width
        return depth.reshape(h, w), face.reshape(h, w), normal.reshape(h, w, 3)


def write_mesh_ply(path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary PLY with *double* vertices: trimesh's exporter writes float32, which rounds
    UTM-sized coordinates to half a metre."""
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    rec = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", 3)])
    rec["n"], rec["v"] = 3, faces
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.asarray(vertices, "<f8").tobytes())
        f.write(rec.tobytes())
