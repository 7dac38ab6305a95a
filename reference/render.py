"""The Embree reference renderer: ground-truth frames of a scene's reference mesh.

Depth and normal come from ray casting the mesh. Label and colour come from the photographs, the
way a perfect image-based renderer would texture the true surface: each visible surface point is
given the photo that sees it unoccluded, in front and inside the frame with the smallest texel
footprint (metres of surface per photo pixel, ``z_j / (f_j |cos theta_j|)``, the same
orthogonal-and-close preference as the labeling data term), and that photo's colour there.
"""

from __future__ import annotations

import time

import numpy as np

from dmrt.camera import Camera
from dmrt.io.frames import empty_frame
from dmrt.preprocess.candidates import sample_bilinear
from reference.raycast import MeshRaycaster

# Grazing views (|cos theta| below this) texture badly and are not chosen.
MIN_COS = 0.05


def best_photos(raycaster: MeshRaycaster, points: np.ndarray, normals: np.ndarray,
                cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Pick for each surface point the photo with the smallest texel footprint that sees it.

    Parameters
    ----------
    points : (n, 3) float64, world metres.  normals : (n, 3) float32, unit.
    cameras : the photos' cameras.

    Returns
    -------
    labels : (n,) int32, photo index or -1 when no photo sees the point.
    uv : (n, 2) float64, the point's pixel coordinates in its photo.
    """
    n = len(points)
    best = np.full(n, np.inf)
    labels = np.full(n, -1, np.int32)
    uv_best = np.zeros((n, 2))
    for j, cam in enumerate(cameras):
        uv, z = cam.project(points)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        to_eye = cam.center - points
        dist = np.linalg.norm(to_eye, axis=1)
        cos = np.abs(np.einsum("ij,ij->i", to_eye, normals)) / np.maximum(dist, 1e-12)
        footprint = np.where(cos > MIN_COS, z / (cam.fx * np.maximum(cos, MIN_COS)), np.inf)
        cand = np.flatnonzero(inside & (footprint < best))
        if len(cand) == 0:
            continue
        cand = cand[raycaster.visible(points[cand], cam.center)]
        best[cand] = footprint[cand]
        labels[cand] = j
        uv_best[cand] = uv[cand]
    return labels, uv_best


class EmbreeReference:
    """Ground-truth renderer with the interface every renderer shares.

    Parameters
    ----------
    raycaster : MeshRaycaster over the reference mesh.
    cameras : list of Camera, the photos' cameras (world frame).
    images : list of (h, w, 3) uint8 arrays (or a callable ``i -> array``), the photos.
    """

    name = "embree"
    gpu_bytes: dict = {}  # Embree runs on the CPU

    def __init__(self, raycaster: MeshRaycaster, cameras: list[Camera], images):
        self.raycaster = raycaster
        self.cameras = cameras
        self._images = images
        self._cache: dict[int, np.ndarray] = {}

    @classmethod
    def from_scene(cls, scene) -> "EmbreeReference":
        """Build from a loaded :class:`dmrt.io.scene.Scene` that has a ``mesh.ply``."""
        if scene.mesh_path is None:
            from dmrt.errors import InputError
            raise InputError(scene.root, "scene has no mesh.ply: the Embree reference needs a reference mesh")
        return cls(MeshRaycaster.from_file(scene.mesh_path, origin=scene.origin), scene.cameras,
                   scene.read_image)

    def image(self, i: int) -> np.ndarray:
        if i not in self._cache:
            self._cache[i] = self._images(i) if callable(self._images) else self._images[i]
        return self._cache[i]

    def render(self, camera: Camera, width: int | None = None, height: int | None = None,
               readback: bool = True) -> dict:
        """Frame outputs (see :mod:`dmrt.io.frames`) for ``camera`` at ``width`` x ``height``
        (:class:`dmrt.runtime.protocol.FrameRenderer`; ``readback`` is moot on the CPU).

        ``timings`` holds wall-clock ms of the CPU stages (Embree runs on the CPU).
        """
        camera = camera.resized(width, height)
        t0 = time.perf_counter()
        depth, face, normal = self.raycaster.cast_camera(camera)
        t1 = time.perf_counter()
        frame = empty_frame(camera.height, camera.width)
        frame["depth"], frame["normal"] = depth, normal
        hit = face >= 0
        dirs, center = camera.pixel_rays()
        points = center + dirs[hit.ravel()] * depth[hit].astype(np.float64)[:, None]
        labels, uv = best_photos(self.raycaster, points, normal[hit], self.cameras)
        t2 = time.perf_counter()
        colors = np.zeros((len(points), 3), np.float32)
        for j in np.unique(labels[labels >= 0]):
            sel = labels == j
            colors[sel] = sample_bilinear(self.image(int(j)), uv[sel])
        frame["label"][hit] = labels
        frame["color"][hit] = np.clip(np.rint(colors), 0, 255).astype(np.uint8)
        frame["timings"] = {"raycast": (t1 - t0) * 1e3, "labels": (t2 - t1) * 1e3,
                            "texturing": (time.perf_counter() - t2) * 1e3}
        return frame

    def flush_photos(self) -> int:
        """Photos are read whole on first use: nothing is ever pending."""
        return 0

    def release(self) -> None:
        self._cache.clear()
