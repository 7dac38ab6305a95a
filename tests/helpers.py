"""Plain helpers shared by the test modules: the renderer test bundle, evaluation views and the
masks the comparisons against the Embree reference use. Fixtures built on them live in
``conftest.py``; the numpy twins of the GPU stages live in :mod:`reference.twins`.

The test bundle (:func:`build_test_bundle`) is built from the ``tiny`` synthetic scene,
independently of the suite's preprocessing, so that the renderer is tested against inputs whose
every property is known:

* depth maps are Embree ray casts of the reference mesh at the photo cameras, 256 texels wide:
  exact (no splatting error), so any depth error is the renderer's own;
* proxies are a spatially even subsample of the laser scan (one point per 15 cm voxel) with PCA
  normals of the full scan and radii from the proxies' density (``splat_radii`` with
  ``scale=1.5``, the factor its docstring gives for irregular sampling);
* each proxy's label is the photo, among those whose depth map sees it, with the smallest texel
  footprint, penalised for every rim point of its disc the photo does not see (a winner-take-all
  data term); proxies no photo sees are dropped (no depth map could render them).
"""

from __future__ import annotations

import numpy as np

from dmrt.camera import Camera
from reference.twins import pixel_points, visible_in_depth_map

DM_WIDTH = 256     # test bundle: depth-map width, texels
LOW_WIDTH = 128    # test bundle: low-resolution photo copies (the photos are 256 wide)
VOXEL = 0.15       # test bundle: proxies, one scan point per 15 cm voxel
W, H = 192, 128    # frame size of most renderer tests (llvmpipe time)

reference_points = pixel_points  # (h*w, 3) world points of a depth buffer seen by a camera


# ---------------------------------------------------------------------------------------------
# the test bundle
# ---------------------------------------------------------------------------------------------
def even_subsample(points: np.ndarray, voxel: float, seed: int = 0) -> np.ndarray:
    """Indices of a spatially even subsample: one random point per occupied ``voxel``-sized cube."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(points))
    keys = np.floor((points[order] - points.min(0)) / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(order[first])


def build_test_bundle(scene_root, out, voxel: float = VOXEL, seed: int = 0):
    """Write a bundle for ``scene_root`` (a synthetic scene with ``mesh.ply``) to ``out``
    (see the module docstring) and return it read back."""
    from PIL import Image

    from dmrt.io.bundle import BundleWriter, camera_to_json, read_bundle
    from dmrt.io.scene import load_scene
    from dmrt.io.exr import write_depth_exr
    from dmrt.preprocess.depthmaps import depth_map_size
    from dmrt.preprocess.normals import estimate_normals, splat_radii
    from reference.raycast import MeshRaycaster

    scene = load_scene(scene_root)
    origin = scene.origin
    cloud = scene.read_points()
    positions = np.asarray(cloud.positions, np.float64)
    normals = estimate_normals(positions - origin, k=16)
    pick = even_subsample(positions - origin, voxel, seed)
    proxy_pos, proxy_n = positions[pick], normals[pick]
    radii = splat_radii(proxy_pos - origin, k=8, scale=1.5)

    raycaster = MeshRaycaster.from_file(scene.mesh_path, origin=origin)
    depths = []
    for cam in scene.cameras:
        w, h = depth_map_size(cam, DM_WIDTH)
        depths.append(raycaster.cast_camera(cam.scaled(w, h))[0])

    # rim points of each disc (at 0.8 r in its plane): a photo that sees the whole disc is preferred
    u = np.cross(proxy_n, np.where(np.abs(proxy_n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(proxy_n, u)
    angles = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    rims = [proxy_pos + 0.8 * radii[:, None] * (np.cos(a) * u + np.sin(a) * v) for a in angles]
    best = np.full(len(pick), np.inf)
    labels = np.full(len(pick), -1, np.int32)
    for j, (cam, depth) in enumerate(zip(scene.cameras, depths)):
        vis = visible_in_depth_map(cam, depth, proxy_pos, proxy_n, radii)
        rim = np.mean([visible_in_depth_map(cam, depth, q, proxy_n) for q in rims], axis=0)
        to_eye = cam.center - proxy_pos
        dist = np.linalg.norm(to_eye, axis=1)
        cos = np.abs(np.einsum("ij,ij->i", to_eye, proxy_n)) / np.maximum(dist, 1e-12)
        cost = dist / (cam.fx * np.maximum(cos, 0.05)) * (1 + 10 * (1 - rim))
        better = vis & (cost < best)
        best[better], labels[better] = cost[better], j
    keep = labels >= 0

    with BundleWriter(out, force=True) as bw:
        images, lows, dms = [], [], []
        for cam, path, depth in zip(scene.cameras, scene.image_paths, depths):
            stem = path.stem
            images.append(bw.add_image(path, cam.name))
            write_depth_exr(bw.tmp / "depthmaps" / f"{stem}.exr", depth)
            dms.append(f"depthmaps/{stem}.exr")
            with Image.open(path) as im:
                low_h = max(1, round(LOW_WIDTH * im.height / im.width))
                im.convert("RGB").resize((LOW_WIDTH, low_h), Image.LANCZOS).save(bw.tmp / "images_low" / f"{stem}.png")
            lows.append(f"images_low/{stem}.png")
        # radii from the density of the proxies that remain (a dropped neighbour leaves a gap)
        kept = proxy_pos[keep] - origin
        bw.write_proxy(positions=kept.astype(np.float32), normals=proxy_n[keep],
                       radii=splat_radii(kept, k=8, scale=1.5), labels=labels[keep])
        bw.finish({"origin": origin.tolist(), "cameras": [camera_to_json(c) for c in scene.cameras],
                   "images": images, "images_low": lows, "depthmaps": dms,
                   "parameters": {"note": "test bundle (tests/helpers.py)"}})
    return read_bundle(out)


# ---------------------------------------------------------------------------------------------
# views
# ---------------------------------------------------------------------------------------------
def novel_camera(a: Camera, b: Camera, t: float = 0.5) -> Camera:
    """A camera between ``a`` and ``b``: centre interpolated linearly, rotation by slerp."""
    from scipy.spatial.transform import Rotation, Slerp

    R = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a.R, b.R])))(t).as_matrix()
    c = (1 - t) * a.center + t * b.center
    return Camera(f"between_{a.name}_{b.name}", a.width, a.height, a.fx, a.fy, a.cx, a.cy, R, -R @ c)


def views_for_tests(cameras: list[Camera], n_photo: int = 4, n_novel: int = 4) -> list[Camera]:
    """Evaluation views: ``n_photo`` photo cameras spread over the list, and novel views halfway
    between pairs of nearby photo cameras (< 3 m apart, viewing directions < 60 degrees apart),
    the closest pairs first. Chosen from the geometry so that they follow the scene generator."""
    views = [cameras[i] for i in np.linspace(0, len(cameras) - 1, n_photo).round().astype(int)]
    pairs = []
    for i, a in enumerate(cameras):
        for j in range(i + 1, len(cameras)):
            b = cameras[j]
            d = np.linalg.norm(a.center - b.center)
            if d < 3.0 and a.R[2] @ b.R[2] > np.cos(np.radians(60)):
                pairs.append((d, i, j))
    return views + [novel_camera(cameras[i], cameras[j]) for _, i, j in sorted(pairs)[:n_novel]]


# ---------------------------------------------------------------------------------------------
# masks for comparisons against the reference
# ---------------------------------------------------------------------------------------------
def silhouette_band(depth: np.ndarray, px: int = 2, jump: float = 0.20) -> np.ndarray:
    """(h, w) bool: pixels within ``px`` pixels of a depth jump > ``jump`` metres (or of background)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    d = np.where(depth > 0, depth, 1e6)
    edge = (maximum_filter(d, size=3) - minimum_filter(d, size=3)) > jump
    return maximum_filter(edge, size=2 * px + 1)


def representable(points: np.ndarray, cameras, depthmaps, threshold: float = 0.20, slack: float = 0.01):
    """(n,) bool: some depth map holds the point on a quad that passes the discontinuity test.

    This is what any DMRT frame can show at best: a point on no continuous quad of any depth map
    (unseen by the photos, within a texel of an occluding edge in all of them, or seen at a grazing
    angle where neighbouring texels jump by more than the threshold) is a hole by design.
    """
    out = np.zeros(len(points), bool)
    for cam, D in zip(cameras, depthmaps):
        h, w = D.shape
        c = cam.scaled(w, h)
        uv, z = c.project(points)
        ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
        x = np.where(ok[:, None], uv, -10.0) - 0.5
        i0 = np.floor(x).astype(np.int64)
        ok &= (i0[:, 0] >= 0) & (i0[:, 1] >= 0) & (i0[:, 0] + 1 < w) & (i0[:, 1] + 1 < h)
        i0 = np.where(ok[:, None], i0, 0)
        q = np.stack([D[i0[:, 1], i0[:, 0]], D[i0[:, 1], i0[:, 0] + 1], D[i0[:, 1] + 1, i0[:, 0]],
                      D[i0[:, 1] + 1, i0[:, 0] + 1]], axis=1).astype(np.float64)
        ok &= (q > 0).all(1) & (q.max(1) - q.min(1) <= threshold)
        f = x - i0
        inv = 1.0 / np.where(q > 0, q, 1.0)
        iz = ((inv[:, 0] * (1 - f[:, 0]) + inv[:, 1] * f[:, 0]) * (1 - f[:, 1])
              + (inv[:, 2] * (1 - f[:, 0]) + inv[:, 3] * f[:, 0]) * f[:, 1])
        ok &= np.abs(1.0 / iz - z) <= slack + 2 * np.abs(z) / c.fx
        out |= ok
    return out


def assert_bundles_equal(a, b) -> None:
    """Two bundles of one scene and configuration, bit for bit: metadata, depth maps, proxies."""
    for key in ("parameters", "cameras", "counts", "origin", "depthmaps", "depthmap_sizes", "images",
                "images_low"):
        assert a.meta[key] == b.meta[key], key
    for key in ("energy_per_sweep", "data_energy", "smooth_energy", "edges"):
        assert a.meta["labeling"][key] == b.meta["labeling"][key], key
    for i in range(len(a.cameras)):
        da, db = a.depth_map(i), b.depth_map(i)
        assert da.dtype == db.dtype and da.tobytes() == db.tobytes(), a.meta["depthmaps"][i]
    for name in ("positions", "normals", "radii", "labels", "hd_radii"):
        pa, pb = a.proxy[name], b.proxy[name]
        assert pa.dtype == pb.dtype and np.array_equal(pa, pb), name
