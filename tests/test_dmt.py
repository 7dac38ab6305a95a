"""The DMT baseline (Arikan et al. 2014; DMRT paper Section 6.5) on a real GL context (llvmpipe in CI).

* Labeling: per-texel graph cut of every depth map, labels are photos that see the texel, the
  cut is smoother than winner-take-all, the cache in the bundle is reused and bad caches or
  resolutions are refused with the file named.
* Runtime stages against plain numpy: the grid triangulation with its discontinuity drop and the
  per-texel label lookup (one depth map seen from its own camera; the twin
  :func:`reference.twins.grid_mesh_depth`), the frustum culling.
* Whole frames against the Embree reference at photo cameras and novel views.
* The stitching threshold's artifacts of the paper's Fig. 11, on two hand-made scenes whose
  outcome is known in advance.

The ``tiny`` bundle (256-wide stored depth maps, 12 photos of 256x171) is copied per module, so the
DMT label caches written into it do not leak into other tests' bundle.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from dmrt.camera import Camera
from dmrt.errors import InputError
from helpers import novel_camera
from reference.twins import grid_mesh_depth

W, H = 160, 107  # frame size (the photos' aspect), small for llvmpipe


# ---------------------------------------------------------------------------------------------
# fixtures and helpers
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def bundle(tiny_bundle, tmp_path_factory):
    """A copy of ``tiny_bundle`` (overrides conftest's renderer test bundle here): DMT writes its
    label caches into the bundle."""
    from dmrt.io.bundle import read_bundle

    dst = tmp_path_factory.mktemp("dmt") / "tiny"
    shutil.copytree(tiny_bundle, dst)
    return read_bundle(dst)


@pytest.fixture(scope="module")
def dmt128(ctx, bundle):
    """DMT with 128-wide depth maps (graph-cut labels computed and cached on first use)."""
    from baselines.dmt import DMTConfig, DMTRenderer

    r = DMTRenderer(bundle, DMTConfig(width=128, async_photos=False, max_uploads_per_frame=0, progress=False), ctx)
    yield r
    r.release()


def views(cameras) -> list[Camera]:
    """Three photo cameras and two novel views halfway between nearby photo cameras."""
    out = [cameras[i] for i in (0, 5, 9)]
    pairs = sorted((np.linalg.norm(a.center - b.center), i, j) for i, a in enumerate(cameras)
                   for j, b in enumerate(cameras) if i < j and a.R[2] @ b.R[2] > 0.5)
    return out + [novel_camera(cameras[i], cameras[j]) for _, i, j in pairs[:2]]


def dmt_depths(bundle, width):
    from baselines.dmt.geometry import load_depth_map

    return [load_depth_map(bundle, i, width) for i in range(len(bundle.cameras))]


def dmt_mesh_raycaster(bundle, depths, threshold=0.20):
    """Embree on the union of every map's grid mesh (:func:`baselines.dmt.geometry.grid_mesh`):
    the nearest DMT surface along any ray, independently of the GPU."""
    from baselines.dmt.geometry import grid_mesh
    from reference.raycast import MeshRaycaster

    verts, faces, base = [], [], 0
    for cam, D in zip(bundle.cameras, depths):
        v, f = grid_mesh(D, cam.scaled(D.shape[1], D.shape[0]), threshold)
        verts.append(np.where(np.isnan(v), bundle.origin, v))  # unused rows (empty texels)
        faces.append(f + base)
        base += len(v)
    return MeshRaycaster(np.concatenate(verts), np.concatenate(faces), bundle.origin)


# ---------------------------------------------------------------------------------------------
# configuration, resolution, cache
# ---------------------------------------------------------------------------------------------
def test_resampling_and_bad_resolution(bundle):
    """Coarse texels take the stored texel nearest their centre; a DMT resolution above the stored
    one is refused naming the depth-map file, before any labeling."""
    from baselines.dmt import DMTConfig, DMTRenderer
    from baselines.dmt.geometry import resample_nearest

    d = np.arange(8 * 6, dtype=np.float32).reshape(6, 8)
    out = resample_nearest(d, 4, 3)
    np.testing.assert_array_equal(out, d[[1, 3, 5]][:, [1, 3, 5, 7]])
    np.testing.assert_array_equal(resample_nearest(d, 8, 6), d)
    with pytest.raises(InputError, match=r"depthmaps/.*\.exr: DMT resolution 512x342 is higher"):
        DMTRenderer(bundle, DMTConfig(width=512, progress=False))
    with pytest.raises(ValueError, match="labeler"):
        DMTConfig(labeler="icm")


def test_labeling_and_cache(bundle):
    """Graph-cut labels per texel at width 64: every label is a photo whose (stored) depth map sees
    the texel's point; the cut lowers the energy and has fewer label changes along grid edges than
    winner-take-all; the cache is reused (files untouched), and a corrupt cache is an error that
    names the file."""
    from baselines.dmt.geometry import grid_edges, texel_points
    from baselines.dmt.labeling import cache_dir, dmt_labels, DMTLabelingConfig

    labels, meta = dmt_labels(bundle, 64, progress=False)
    assert meta["cached"] is False
    folder = cache_dir(bundle, 64)
    npz = folder / "labels.npz"
    stamp = npz.stat().st_mtime_ns
    again, meta2 = dmt_labels(bundle, 64, progress=False)
    assert meta2["cached"] is True and npz.stat().st_mtime_ns == stamp
    for a, b in zip(labels, again):
        np.testing.assert_array_equal(a, b)
    assert meta["energy"]["final"] < meta["energy"]["initial"]
    print("DMT labeling at 64:", meta["timings"], meta["counts"])

    wta, _ = dmt_labels(bundle, 64, DMTLabelingConfig(labeler="wta"), progress=False)
    assert cache_dir(bundle, 64, "wta") != folder
    changes = {"graphcut": 0, "wta": 0}
    depths = dmt_depths(bundle, 64)
    stored = [bundle.depth_map(i) for i in range(len(bundle.cameras))]
    seen = total = 0
    for i, D in enumerate(depths):
        e = grid_edges(D, 0.20)
        for name, lab in (("graphcut", labels[i]), ("wta", wta[i])):
            flat = lab.ravel()
            changes[name] += int((flat[e[:, 0]] != flat[e[:, 1]]).sum())
        # independent visibility check: the label's stored depth map holds the point (same
        # tolerance as the candidate test: 3 splat radii + 2 stored texels) at one of the two
        # texels nearest its projection along each axis - a coarse texel centre falls on a stored
        # texel boundary when the resolutions' ratio is even, where rounding picks either side
        cam = bundle.cameras[i].scaled(*D.shape[::-1])
        pts = texel_points(D, cam).reshape(-1, 3)
        lab = labels[i].ravel()
        assert (lab[(D.ravel() == 0)] == -1).all()
        for j in np.unique(lab[lab >= 0]):
            m = lab == j
            Dj = stored[j]
            cj = bundle.cameras[j].scaled(Dj.shape[1], Dj.shape[0])
            uv, z = cj.project(pts[m])
            tol = 3 * meta["splat_radius_m"] + 2 * z / cj.fx
            ok = np.zeros(len(z), bool)
            for dc in (-0.5, 0.5):
                for dr in (-0.5, 0.5):
                    col = np.clip((uv[:, 0] + dc).astype(int), 0, Dj.shape[1] - 1)
                    row = np.clip((uv[:, 1] + dr).astype(int), 0, Dj.shape[0] - 1)
                    ok |= np.abs(Dj[row, col] - z) <= tol
            seen += int(ok.sum())
            total += int(m.sum())
    print("label changes along grid edges:", changes, f"labels seen by their photo: {seen}/{total}")
    assert seen == total
    assert changes["graphcut"] < 0.8 * changes["wta"]

    # corrupt caches: named in the error, not silently recomputed
    npz.write_bytes(b"not a zip file")
    with pytest.raises(InputError, match=r"labels\.npz: corrupt DMT labels cache"):
        dmt_labels(bundle, 64, progress=False)
    (folder / "dmt.json").write_text("{truncated")
    with pytest.raises(InputError, match=r"dmt\.json: corrupt DMT labels cache"):
        dmt_labels(bundle, 64, progress=False)
    labels3, meta3 = dmt_labels(bundle, 64, progress=False, recompute=True)
    assert meta3["cached"] is False
    for a, b in zip(labels, labels3):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------------------------
# runtime stages against numpy
# ---------------------------------------------------------------------------------------------
def test_grid_triangulation_matches_numpy(dmt128, bundle):
    """One depth map rendered alone from its own camera at twice its resolution (principal point
    shifted by a fraction of a pixel, so no pixel centre lies on a triangle edge): coverage must be
    the numpy grid mesh's (triangles with an empty texel or a depth span > 20 cm dropped), depth the
    plane of each triangle, label that of the texel holding the point. float32 vs float64 can flip
    pixels next to an edge: >= 99.5 % agree, depths to 1e-4 relative."""
    from baselines.dmt.geometry import grid_triangles

    depths = dmt_depths(bundle, 128)
    labels = [np.asarray(a) for a in _labels_of(dmt128)]
    for i in (2, 7):
        D = depths[i]
        h, w = D.shape
        mcam = bundle.cameras[i].scaled(w, h)
        cam = bundle.cameras[i].scaled(2 * w, 2 * h)
        cam.cx += 0.3
        cam.cy += 0.17
        frame = dmt128.render(cam, maps=[i])
        assert frame["stats"]["maps_drawn"] == 1
        j, r = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        p = np.stack([(j.ravel() - cam.cx) / cam.fx * mcam.fx + mcam.cx,
                      (r.ravel() - cam.cy) / cam.fy * mcam.fy + mcam.cy], 1)
        z, ok, texel = grid_mesh_depth(D, p, *grid_triangles(D, 0.20))
        hit = (frame["depth"] > 0).ravel()
        print(f"map {i}: coverage {ok.mean():.3f}, agreement {np.mean(hit == ok):.5f}")
        assert 0.3 < ok.mean() < 0.99  # a real test: surface and dropped triangles both present
        assert np.mean(hit == ok) >= 0.995
        both = hit & ok
        rel = np.abs(frame["depth"].ravel()[both] - z[both]) / z[both]
        assert np.mean(rel <= 1e-4) >= 0.995
        expected = labels[i][texel[:, 1], texel[:, 0]]
        assert np.mean(frame["label"].ravel()[both] == expected[both]) >= 0.995
        assert (frame["depth_map"].ravel()[hit] == i).all()


def _labels_of(renderer):
    """The label texture array of a DMTRenderer back as per-map arrays."""
    n = len(renderer.cameras)
    dims = (renderer.labels.width, renderer.labels.height)
    raw = np.frombuffer(renderer.labels.read(), np.int16 if renderer.labels.dtype == "i2" else np.int32)
    raw = raw.reshape(n, dims[1], dims[0])
    return [raw[i, :h, :w].astype(np.int32) for i, (w, h) in enumerate(renderer.sizes)]


def test_culling_matches_numpy(dmt128, bundle):
    """The GPU frustum culling culls exactly the maps the numpy test culls, some but not all in
    these views, and never a map with a texel point inside the view."""
    from baselines.dmt.geometry import frustum_culled, texel_points

    depths = dmt_depths(bundle, 128)
    cams = views(bundle.cameras)
    cams.append(Camera.look_at("outward", bundle.cameras[0].center, 2 * bundle.cameras[0].center
                               - bundle.cameras[3].center, 160, 107))
    culled_any = drawn_any = 0
    for cam in cams:
        cam = cam.resized(W)
        frame = dmt128.render(cam)
        vp = cam.gl_view_projection(dmt128.config.near, dmt128.far_plane(cam), bundle.origin)
        culled = frustum_culled(dmt128.boxes, vp)  # boxes and vp both origin-relative
        assert frame["stats"]["maps_culled"] == int(culled.sum())
        culled_any += int(culled.sum())
        drawn_any += int((~culled).sum())
        for i in np.flatnonzero(culled):
            pts = texel_points(depths[i], bundle.cameras[i].relative_to(bundle.origin).scaled(*depths[i].shape[::-1]))
            uv, z = cam.relative_to(bundle.origin).project(pts.reshape(-1, 3)[depths[i].ravel() > 0])
            assert not ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
                        & (uv[:, 1] < cam.height)).any()
    assert culled_any > 0 and drawn_any > 0


# ---------------------------------------------------------------------------------------------
# whole frames
# ---------------------------------------------------------------------------------------------
def test_frame_contract(dmt128, bundle):
    from baselines.dmt.renderer import STAGES

    cam = bundle.cameras[0]
    frame = dmt128.render(cam, W)
    h = round(W * cam.height / cam.width)
    assert frame["depth"].shape == (h, W) and frame["depth"].dtype == np.float32
    assert frame["color"].shape == (h, W, 3) and frame["color"].dtype == np.uint8
    assert frame["normal"].shape == (h, W, 3) and frame["normal"].dtype == np.float32
    for key in ("label", "depth_map"):
        assert frame[key].shape == (h, W) and frame[key].dtype == np.int32, key
    assert set(frame["timings"]) == set(STAGES)
    assert set(frame["cpu_ms"]) == {"status_read", "image_management"}
    hit = frame["depth"] > 0
    assert 0.5 < hit.mean() <= 1.0
    assert (frame["label"][~hit] == -1).all() and (frame["depth_map"][~hit] == -1).all()
    assert (frame["color"][~hit] == 0).all() and (frame["normal"][~hit] == 0).all()
    assert (frame["depth_map"][hit] >= 0).all()
    assert np.mean(frame["label"][hit] >= 0) > 0.99  # texels no photo sees are rare
    np.testing.assert_allclose(np.linalg.norm(frame["normal"][hit], axis=1), 1.0, atol=1e-4)
    dirs, _ = cam.resized(W).pixel_rays()
    assert (np.einsum("ij,ij->i", frame["normal"].reshape(-1, 3), dirs)[hit.ravel()] <= 0).all()
    assert set(dmt128.gpu_bytes) >= {"depthmaps", "labels", "images_low", "image_cache", "frame"}
    again = dmt128.render(cam, W)
    for key in ("depth", "label", "color", "normal"):
        np.testing.assert_array_equal(again[key], frame[key], err_msg=key)
    # the viewer's orbit key reads one pixel of the frame left on the GPU (through Staging)
    y, x = np.argwhere(hit)[len(np.argwhere(hit)) // 2]
    assert dmt128.depth_at(int(x), int(y)) == float(frame["depth"][y, x]) > 0
    # maps drawn in groups (the path for scenes whose vertex ids would pass 2^31): same frame
    whole = dmt128.maps_per_draw
    try:
        dmt128.maps_per_draw = 5
        grouped = dmt128.render(cam, W)
    finally:
        dmt128.maps_per_draw = whole
    for key in ("depth", "label", "depth_map"):
        np.testing.assert_array_equal(grouped[key], frame[key], err_msg=key)


@pytest.mark.parametrize("width", [128, pytest.param(256, marks=pytest.mark.slow)])
def test_against_embree(ctx, bundle, reference, dmt128, width):
    """Frames at photo cameras and novel views against two Embree ray casts.

    * The union of the DMT meshes (:func:`dmt_mesh_raycaster`, numpy triangulation): the pixels
      with surface must be the pixels whose ray meets a mesh, and each pixel's depth must lie
      between the nearest mesh hit and ε behind it (pass 1 finds the nearest surface, stitching
      picks within ε of it). float32 vs Embree rounding at triangle edges may flip a pixel:
      >= 99.5 % of the pixels agree, depths to 1e-4 relative plus ε.
    * The reference mesh (ground truth): median |dz| where both have surface at most a quarter of
      the median texel footprint of the winning depth map (z / f at the DMT resolution). The walls
      and boxes are planar, where a triangle through three samples is exact, so what remains is
      the stored depth maps' own splatting error and the resampling's half-stored-texel offset,
      both well under a DMT texel. Holes (reference surface, DMT background) are the pixels no
      depth map holds (scan shadows, grazing walls whose triangles span > 20 cm, splat-free
      borders): at most 10 % here, printed with the other figures.
    """
    from baselines.dmt import DMTConfig, DMTRenderer
    from reference.metrics import compare

    r = dmt128 if width == 128 else DMTRenderer(
        bundle, DMTConfig(width=width, labeler="wta", async_photos=False, max_uploads_per_frame=0, progress=False), ctx)
    meshes = dmt_mesh_raycaster(bundle, dmt_depths(bundle, width), r.config.discontinuity_threshold)
    eps = r.config.epsilon
    f_dm = np.array([c.fx * width / c.width for c in bundle.cameras])
    try:
        dz_all, fp_all, cover, window, holes = [], [], [], [], [0, 0]
        for cam in views(bundle.cameras):
            cam = cam.resized(W)
            frame, ref = r.render(cam), reference.render(cam)
            near, _, _ = meshes.cast_camera(cam)
            hit, mesh_hit = frame["depth"] > 0, near > 0
            cover.append(hit.ravel() == mesh_hit.ravel())
            both = hit & mesh_hit
            z, zn = frame["depth"][both].astype(np.float64), near[both]
            window.append((z >= zn * (1 - 1e-4)) & (z <= zn * (1 + 1e-4) + eps))
            # against the ground truth
            surf = hit & (ref["depth"] > 0)
            dirs, centre = cam.pixel_rays()
            pts = centre + dirs[surf.ravel()] * ref["depth"][surf].reshape(-1, 1).astype(np.float64)
            win = frame["depth_map"][surf]
            zc = np.einsum("ij,ij->i", pts - np.array([bundle.cameras[j].center for j in win]),
                           np.array([bundle.cameras[j].R[2] for j in win]))
            dz_all.append(np.abs(frame["depth"][surf].astype(np.float64) - ref["depth"][surf]))
            fp_all.append(zc / f_dm[win])
            c = compare(frame, ref)
            holes[0] += int(((ref["depth"] > 0) & ~hit).sum()); holes[1] += int((ref["depth"] > 0).sum())
            print(f"{cam.name}: median |dz| {1e3 * c['depth_median_m']:.2f} mm, holes {c['hole_rate']:.4f}, "
                  f"psnr {c['psnr_db']:.2f} dB, mesh coverage agreement {cover[-1].mean():.4f}")
        dz, fp = np.concatenate(dz_all), np.concatenate(fp_all)
        cover, window = np.concatenate(cover), np.concatenate(window)
        print(f"width {width}: median |dz| {np.median(dz) * 1e3:.2f} mm, median footprint {np.median(fp) * 1e3:.1f} mm, "
              f"holes {holes[0] / holes[1]:.4f}; vs Embree on the DMT meshes: coverage {cover.mean():.5f}, "
              f"depth in [nearest, nearest + eps] {window.mean():.5f}")
        assert cover.mean() >= 0.995 and window.mean() >= 0.995
        assert np.median(dz) <= 0.25 * np.median(fp)
        assert holes[0] <= 0.10 * holes[1]
    finally:
        if r is not dmt128:
            r.release()


# ---------------------------------------------------------------------------------------------
# the stitching threshold (paper Fig. 11)
# ---------------------------------------------------------------------------------------------
def plane_depth(cam: Camera, planes) -> np.ndarray:
    """Camera z of the first hit of each pixel ray with ``planes`` [(normal, offset, keep)], where
    ``keep(points) -> bool`` limits a plane to a region; (h, w) float32, 0 = none."""
    dirs, c = cam.pixel_rays()
    best = np.full(len(dirs), np.inf)
    for n, d0, keep in planes:
        n = np.asarray(n, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (d0 - n @ c) / (dirs @ n)
        ok = (s > 0) & keep(c + s[:, None] * dirs)
        best = np.where(ok & (s < best), s, best)
    return np.where(np.isfinite(best), best, 0).reshape(cam.height, cam.width).astype(np.float32)


def two_map_bundle(out, cameras, depths, colors):
    """A bundle of hand-made depth maps and single-colour photos (one proxy: unused by DMT)."""
    from PIL import Image

    from dmrt.io.bundle import BundleWriter, camera_to_json, read_bundle
    from dmrt.io.exr import write_depth_exr

    src = out.parent / f"{out.name}-photos"
    src.mkdir(parents=True, exist_ok=True)
    with BundleWriter(out, force=True) as bw:
        images, lows, dms = [], [], []
        for k, (cam, d, col) in enumerate(zip(cameras, depths, colors)):
            photo = np.zeros((cam.height, cam.width, 3), np.uint8) + np.array(col, np.uint8)
            Image.fromarray(photo).save(src / f"p{k}.png")
            images.append(bw.add_image(src / f"p{k}.png", f"p{k}.png"))
            Image.fromarray(photo[::2, ::2]).save(bw.tmp / "images_low" / f"p{k}.png")
            lows.append(f"images_low/p{k}.png")
            write_depth_exr(bw.tmp / "depthmaps" / f"p{k}.exr", d)
            dms.append(f"depthmaps/p{k}.exr")
        bw.write_proxy(positions=np.zeros((1, 3)), normals=[[0, 0, 1.0]], radii=[0.01], labels=[0])
        bw.finish({"origin": [0.0, 0.0, 0.0], "cameras": [camera_to_json(c) for c in cameras],
                   "images": images, "images_low": lows, "depthmaps": dms, "parameters": {}})
    return read_bundle(out)


def _render_with(ctx, b, eps, cam, maps=None):
    from baselines.dmt import DMTConfig, DMTRenderer

    labels = [np.full(d.shape, k, np.int32) for k, d in enumerate(b.depth_map(i) for i in range(len(b.cameras)))]
    r = DMTRenderer(b, DMTConfig(epsilon=eps, async_photos=False, max_uploads_per_frame=0, progress=False), ctx, labels)
    try:
        return r.render(cam, maps=maps)
    finally:
        r.release()


def test_small_epsilon_textures_the_low_resolution_surface(ctx, tmp_path):
    """Fig. 11 top. A concave room corner (walls x = 0 and y = 0) seen by a near photo A (2.4 cm
    texels) and a far photo B (11 cm texels), both maps 64 wide. B's triangles across the corner
    are chords in front of the corner by centimetres. Viewed from A: with ε = 10 cm A (better
    resolved) wins every pixel; with ε = 2 mm the pixels along the corner where B's chord lies more
    than ε in front of A's surface go to B - its geometry and its photo (green)."""
    inside = lambda p: (p[:, 0] >= -1e-9) & (p[:, 1] >= -1e-9)
    walls = [((1, 0, 0), 0.0, inside), ((0, 1, 0), 0.0, inside)]
    a = Camera.look_at("A", (1.2, 1.0, 0.0), (0.0, 0.0, 0.0), 64, 48, 60)
    b = Camera.look_at("B", (4.5, 5.0, 0.4), (0.0, 0.0, 0.0), 64, 48, 60)
    bundle = two_map_bundle(tmp_path / "corner", [a, b], [plane_depth(a, walls), plane_depth(b, walls)],
                            [(255, 0, 0), (0, 255, 0)])
    view = a.scaled(128, 96)
    only_a = _render_with(ctx, bundle, 0.10, view, maps=[0])
    large = _render_with(ctx, bundle, 0.10, view)
    small = _render_with(ctx, bundle, 0.002, view)
    hit = only_a["depth"] > 0
    assert hit.mean() > 0.95
    assert (large["depth_map"][hit] == 0).all()
    np.testing.assert_allclose(large["depth"][hit], only_a["depth"][hit], rtol=1e-5)
    won = (small["depth_map"] == 1) & hit  # (A's mesh ends half a texel inside the frame: B there)
    print(f"eps 2 mm: {won.sum()} of {hit.sum()} pixels textured from the far map")
    assert won.sum() >= 20
    # B wins only where its surface is in front of A's by more than ε: along the corner's image
    # column (the corner line x = y = 0 projects to one column of A's symmetric-ish view)
    corner_u, _ = view.project(np.array([[0.0, 0.0, 0.0]]))
    cols = np.nonzero(won)[1] + 0.5
    assert np.abs(cols - corner_u[0, 0]).max() <= 12
    assert (small["depth"][won] < only_a["depth"][won] - 0.002).all()
    assert (small["color"][won][:, 1] > 200).all() and (small["color"][won][:, 0] < 50).all()
    assert (small["depth_map"][hit & ~won] == 0).all()


def test_large_epsilon_lets_a_hidden_thin_feature_shine_through(ctx, tmp_path):
    """Fig. 11 bottom. A wall (plane y = 0) seen head-on by photo A from 3 m; a plate 2 cm behind
    it seen only by photo B from behind, close up (6.6 mm texels against A's 5.4 cm). Viewed from A:
    with ε = 5 cm the plate, hidden by the wall, is taken for the wall's surface and, better
    resolved, wins - the pixels of its projection show B's photo at the plate's depth; with
    ε = 1 cm visibility is right and A's wall is everywhere."""
    wall = [((0, 1, 0), 0.0, lambda p: np.ones(len(p), bool))]
    plate = [((0, 1, 0), 0.02, lambda p: (np.abs(p[:, 0]) < 0.3) & (np.abs(p[:, 2]) < 0.3))]
    a = Camera.look_at("A", (0.0, -3.0, 0.0), (0.0, 0.0, 0.0), 64, 48, 60)
    b = Camera.look_at("B", (0.0, 0.8, 0.0), (0.0, 0.0, 0.0), 64, 48, 30)
    db = plane_depth(b, plate)
    assert (db > 0).all()  # B sees nothing but the plate
    bundle = two_map_bundle(tmp_path / "plate", [a, b], [plane_depth(a, wall), db], [(255, 0, 0), (0, 255, 0)])
    view = a.scaled(128, 96)
    view.fx *= 1.1  # zoomed in: A's mesh (texel centres) then covers the whole frame
    view.fy *= 1.1
    small = _render_with(ctx, bundle, 0.01, view)
    large = _render_with(ctx, bundle, 0.05, view)
    hit = small["depth"] > 0
    assert hit.all() and (small["depth_map"] == 0).all()
    np.testing.assert_allclose(small["depth"], 3.0, rtol=1e-4)
    # the projection of B's mesh (texel centres: the outer half texel of the map has no triangle)
    bm = b.scaled(64, 48)
    corners = np.array([[u, v] for u in (0.5, 63.5) for v in (0.5, 47.5)])
    rays = np.stack([(corners[:, 0] - bm.cx) / bm.fx, (corners[:, 1] - bm.cy) / bm.fy, np.ones(4)], 1) @ bm.R
    s = (0.02 - bm.center[1]) / rays[:, 1]
    uv, _ = view.project(bm.center + s[:, None] * rays)
    lo, hi = uv.min(0), uv.max(0)
    j, i = np.meshgrid(np.arange(128) + 0.5, np.arange(96) + 0.5)
    inner = (j > lo[0] + 1) & (j < hi[0] - 1) & (i > lo[1] + 1) & (i < hi[1] - 1)
    outer = (j > lo[0] - 1) & (j < hi[0] + 1) & (i > lo[1] - 1) & (i < hi[1] + 1)
    won = large["depth_map"] == 1
    print(f"eps 5 cm: {won.sum()} pixels show the hidden plate (projection {inner.sum()}..{outer.sum()})")
    assert inner.sum() > 50
    assert won[inner].all() and not won[~outer].any()
    np.testing.assert_allclose(large["depth"][won], 3.02, rtol=1e-4)
    assert (large["color"][won][:, 1] > 200).all()


@pytest.mark.slow
def test_leveling_balances_photo_exposures(ctx, bundle, tiny_scene):
    """DMRT's screen-space leveling on DMT frames (the issue: "the same leveling"), against the
    generator's per-photo exposure x white-balance gains as in test_leveling. Photos can only be
    leveled against each other where the frame has seams between them: within each group of
    photos connected by seams of >= 16 samples (the solver's minimum), the spread of the effective
    log gains must at least halve; and the leveled colours are the unleveled ones times the
    pixel's photo's gain (8-bit rounding). At the bundle's own depth-map resolution: with 128-wide
    maps the triangulated surface is centimetres off, the two photos of a seam sample different
    texture points, and the spread only falls by 40 % (measured 0.114 -> 0.068)."""
    import json

    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    from baselines.dmt import DMTConfig, DMTRenderer

    truth = np.log(np.array(json.loads((tiny_scene / "synthetic.json").read_text())["photo_gains"]))
    n = len(bundle.cameras)
    # the photos' own colours (photometric off): leveling alone against the generator's exposures
    sync = {"async_photos": False, "max_uploads_per_frame": 0, "progress": False, "photometric": False}
    leveler = DMTRenderer(bundle, DMTConfig(leveling=True, **sync), ctx)
    plain_dmt = DMTRenderer(bundle, DMTConfig(**sync), ctx)
    before, after = [], []
    try:
        for j in range(12):
            frame, plain = leveler.render(bundle.cameras[j], W), plain_dmt.render(bundle.cameras[j], W)
            gains = frame["leveling_gains"]
            hit = frame["label"] >= 0
            expected = np.clip(plain["color"][hit] * gains[frame["label"][hit]], 0, 255)
            assert np.abs(frame["color"][hit] - expected).max() <= 1.0
            seams = np.frombuffer(leveler.leveler.pairs.read(), np.int32).reshape(n, n, 4)[..., 0] >= 16
            n_groups, group = connected_components(csr_matrix(seams), directed=False)
            for g in range(n_groups):
                members = np.flatnonzero(group == g)
                if len(members) >= 2:
                    before.append(truth[members].std(axis=0).mean())
                    after.append((truth[members] + np.log(gains[members])).std(axis=0).mean())
        print(f"DMT log-gain spread within seam-connected photos: before {np.mean(before):.3f}, "
              f"after leveling {np.mean(after):.3f} ({len(before)} groups)")
        assert len(before) >= 6 and np.mean(after) <= 0.5 * np.mean(before)
    finally:
        leveler.release()
        plain_dmt.release()


def test_own_photo_labeler(bundle):
    """The "own" labeler (frame-rate runs): every non-empty texel of map i carries photo i."""
    from baselines.dmt import DMTLabelingConfig, dmt_labels
    from baselines.dmt.geometry import load_depth_map

    labels, meta = dmt_labels(bundle, 64, DMTLabelingConfig(labeler="own"), progress=False)
    for i, lab in enumerate(labels):
        depth = load_depth_map(bundle, i, 64)
        np.testing.assert_array_equal(lab, np.where(depth > 0, i, -1))
    assert meta["labeler"] == "own"
