"""Plain numpy twins of the GPU stages: float64, brute force, one function per pass.

Each twin computes what one shader pass computes, written independently of the GPU code (every
pixel against every disc, no bounding boxes, no tiling), so that each GPU wrapper can be tested
against its twin (gsplat's ``cuda/_torch_impl.py`` style). Tests in ``tests/`` compare them.

Twin -> shader(s) in ``shaders/`` -> GPU wrapper in ``dmrt/``:

* :func:`splat_depth_map` -> ``splat_depth_compute.glsl``, ``splat_depth_raster.glsl`` (and their
  ``_large`` programs; ``splat_depth_common.glsl``) -> ``dmrt.preprocess.depthmaps.DepthMapRenderer``
* :func:`disc_hits` -> ``dmrt_splat_common.glsl`` (``splat_depth_at``, the primitive of the
  visibility and labeling passes) -> used by the two twins below
* :func:`visibility_layers` -> ``dmrt_visibility.glsl``, ``dmrt_visibility_fragment.glsl``,
  ``dmrt_visibility_kbuffer.glsl`` -> ``dmrt.runtime.visibility`` (``Renderer.layers()``)
* :func:`surface_depth` -> ``dmrt_photos.glsl`` (``surface_depth``) -> used by the raytracing pass
* :func:`raytrace` -> ``dmrt_raytrace.glsl`` -> ``dmrt.runtime.renderer.Renderer`` (``depth``,
  ``layer_used``, ``step_stats``)
* :func:`labeling_pass` -> ``dmrt_labeling.glsl`` -> ``dmrt.runtime.renderer.Renderer`` (``label``
  with ``label_check=False``)
* :func:`visible_in_depth_map` -> ``dmrt_label_finalize.glsl`` (``sees``, the label check; with
  its own tolerance) -> ``dmrt.runtime.renderer.Renderer``; also the candidate test of
  ``dmrt.preprocess.candidates.find_candidates``
* :func:`texturing_pass` -> ``dmrt_texturing.glsl``, ``dmrt_photo_color.glsl`` ->
  ``dmrt.runtime.texturing`` (``color``)
* :func:`view_scores`, :func:`view_choice` -> ``dmrt_view_scores.glsl``, ``dmrt_view_choice.glsl``
  (``dmrt_view_common.glsl``) -> ``dmrt.runtime.view_choice.ViewChoice`` (``label`` and the blend
  with ``photo_choice="view"``)
* :func:`grid_mesh_depth` -> ``dmt_mesh.glsl`` -> ``baselines.dmt.DMTRenderer`` (one map from its
  own camera)

Conventions are the suite's (``DESIGN.md``, Contracts): metres, OpenCV camera axes, depth = camera
z with 0 = none, labels int with -1 = none, pixel and texel positions with the corner origin (the
centre of pixel (row i, column j) at (j + 0.5, i + 0.5)). A ``proxy`` is the bundle's proxy dict:
``positions`` (n, 3) float32 origin-relative metres, ``normals`` (n, 3) float32, ``radii`` (n,)
float32 metres, ``labels`` (n,) int32.
"""

from __future__ import annotations

import numpy as np

from dmrt.camera import Camera

GRAZING_COS = 1e-3  # the shaders' GRAZING_COS (shaders/splat_depth_common.glsl)

__all__ = ["GRAZING_COS", "disc_hits", "grid_mesh_depth", "labeling_pass", "pixel_points", "raytrace",
           "splat_depth_map", "surface_depth", "texturing_pass", "view_choice", "view_scores", "visibility_layers",
           "visible_in_depth_map"]


# ---------------------------------------------------------------------------------------------
# the splat primitive: ray-disc hits
# ---------------------------------------------------------------------------------------------
def _ray_disc(dirs, dlen, p, n, r2, zc):
    """Every (ray, disc) pair: two-sided disc hit, grazing rays take the centre's z within r of it.

    ``dirs`` (m, 3) ray directions with camera z = ray parameter, ``dlen`` (m, 1) their lengths,
    ``p`` (n, 3) disc centres relative to the camera centre, ``n`` (n, 3) unit normals, ``r2`` (n,)
    squared radii, ``zc`` (n,) the centres' camera z. Returns ``z`` (m, n) camera z of the hit
    (np.inf for a miss) and the terms the float32 ambiguity test needs: ``cos`` (m, n) |cos| of
    the ray and the normal, ``s`` and ``q2`` (m, n) the ray parameter of the plane hit and the
    squared distance of that hit from the centre, ``line2`` (m, n) the squared distance of the
    centre from the ray, ``regular`` (m, n) bool (not grazing).
    """
    nd = dirs @ n.T  # (pixels, discs)
    cos = np.abs(nd) / dlen
    dp = dirs @ p.T
    p2 = (p ** 2).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n * p).sum(1) / nd
        q2 = s ** 2 * dlen ** 2 - 2 * s * dp + p2  # |s d - p|^2, squared distance to the centre
    regular = cos > GRAZING_COS
    # grazing rays: the centre's depth where the ray passes within r of the centre
    line2 = p2 - (dp / dlen) ** 2
    z = np.where(regular & (s > 0) & (q2 <= r2), s, np.inf)
    z = np.where(~regular & (zc > 0) & (line2 <= r2), zc, z)
    return z, cos, s, q2, line2, regular


def splat_depth_map(camera: Camera, positions, normals, radii, width: int, height: int):
    """Depth map of oriented circular splats: nearest ray-disc hit per pixel (paper Section 4.1).

    Parameters
    ----------
    camera : Camera
        Any resolution; scaled to ``width`` x ``height``. Same frame as ``positions``.
    positions : (n, 3) float
        Disc centres, metres.
    normals : (n, 3) float
        Disc normals (any length; zero = facing the camera).
    radii : (n,) float
        Disc radii, metres.
    width, height : int
        Depth-map size, texels.

    Returns
    -------
    depth : (height, width) float64
        Camera z, metres; 0 where no disc is hit.
    ambiguous : (height, width) bool
        Pixels whose result float32 rounding may legitimately flip: some disc's rim passes within
        0.1 % of the pixel centre's ray, or the ray is near the grazing-angle switch.
    """
    cam = camera.scaled(width, height)
    dirs, centre = cam.pixel_rays()  # world directions with camera z = ray parameter
    dlen = np.linalg.norm(dirs, axis=1, keepdims=True)
    p = np.asarray(positions, np.float64) - centre
    n = np.asarray(normals, np.float64)
    nlen = np.linalg.norm(n, axis=1, keepdims=True)
    facing = -p / np.linalg.norm(p, axis=1, keepdims=True)
    n = np.where(nlen > 0, n / np.where(nlen > 0, nlen, 1), facing)
    r2 = np.asarray(radii, np.float64) ** 2
    zc = p @ cam.R[2]  # camera z of each centre
    depth = np.full(len(dirs), np.inf)
    ambiguous = np.zeros(len(dirs), bool)
    for b in range(0, len(p), 128):
        rb, zb = r2[b:b + 128], zc[b:b + 128]
        z, cos, s, q2, line2, regular = _ray_disc(dirs, dlen, p[b:b + 128], n[b:b + 128], rb, zb)
        depth = np.minimum(depth, z.min(1))
        rim = regular & (s > 0) & (np.abs(q2 / rb - 1) < 1e-3)
        rim |= ~regular & (zb > 0) & (np.abs(line2 / rb - 1) < 1e-3)
        switch = (np.abs(cos / GRAZING_COS - 1) < 0.5) & (line2 <= 1.001 * rb)  # near the grazing rule
        ambiguous |= (rim | switch).any(1)
    depth[~np.isfinite(depth)] = 0
    return depth.reshape(height, width), ambiguous.reshape(height, width)


def disc_hits(camera: Camera, proxy: dict) -> np.ndarray:
    """Camera z of every (pixel, disc) ray-disc hit.

    Parameters
    ----------
    camera : Camera
        In the proxies' frame (scene-origin-relative), at the frame's resolution (h, w).
    proxy : dict
        ``positions``, ``normals``, ``radii`` (see the module docstring).

    Returns
    -------
    (h*w, n) float64
        Camera z, metres, np.inf for a miss. Same primitive as ``splat_depth_at``
        (two-sided discs; grazing rays take the centre's z within r of it).
    """
    dirs, centre = camera.pixel_rays()
    dlen = np.linalg.norm(dirs, axis=1, keepdims=True)
    p = proxy["positions"].astype(np.float64) - centre
    n = proxy["normals"].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    r2 = proxy["radii"].astype(np.float64) ** 2
    return _ray_disc(dirs, dlen, p, n, r2, p @ camera.R[2])[0]


# ---------------------------------------------------------------------------------------------
# visibility stage
# ---------------------------------------------------------------------------------------------
def visibility_layers(camera: Camera, proxy: dict, k: int):
    """Depth-peeled label layers (paper Section 5.1.1), brute force.

    Layer i holds, per pixel, the nearest disc hit behind layer i-1's depth whose label differs
    from layer i-1's label; ties between equal depths go to the smallest label.

    Parameters
    ----------
    camera : Camera
        In the proxies' frame (scene-origin-relative), at the frame's resolution (h, w).
    proxy : dict
        ``positions``, ``normals``, ``radii``, ``labels`` (see the module docstring).
    k : int
        Number of layers.

    Returns
    -------
    depth : (k, h, w) float64
        Camera z, metres; 0 = empty.
    label : (k, h, w) int
        Proxy label; -1 = empty.
    """
    z = disc_hits(camera, proxy)
    labels = proxy["labels"]
    npix = len(z)
    depth = np.zeros((k, npix))
    label = np.full((k, npix), -1)
    prev_z, prev_l = np.full(npix, -np.inf), np.full(npix, -2)
    rows = np.arange(npix)
    for i in range(k):
        cand = np.where((z > prev_z[:, None]) & (labels[None, :] != prev_l[:, None]), z, np.inf)
        j = np.argmin(cand, axis=1)
        zi = cand[rows, j]
        hit = np.isfinite(zi)
        # ties: the smallest label among the discs at the same depth
        tie = cand == zi[:, None]
        li = np.where(tie, labels[None, :], np.iinfo(np.int32).max).min(1)
        depth[i, hit], label[i, hit] = zi[hit], li[hit]
        prev_z, prev_l = np.where(hit, zi, np.inf), np.where(hit, li, -2)
    shape = (k, camera.height, camera.width)
    return depth.reshape(shape), label.reshape(shape)


# ---------------------------------------------------------------------------------------------
# raytracing pass
# ---------------------------------------------------------------------------------------------
def _quad(D, i0):
    """The four texels (00, 10, 01, 11) of depth map ``D`` (h, w) at top-left texels ``i0`` (n, 2)
    int (column, row): (n, 4) float64 (0 where outside) and (n,) bool inside."""
    h, w = D.shape
    inside = (i0[:, 0] >= 0) & (i0[:, 1] >= 0) & (i0[:, 0] + 1 < w) & (i0[:, 1] + 1 < h)
    i = np.where(inside[:, None], i0, 0)
    q = np.stack([D[i[:, 1], i[:, 0]], D[i[:, 1], i[:, 0] + 1], D[i[:, 1] + 1, i[:, 0]],
                  D[i[:, 1] + 1, i[:, 0] + 1]], axis=1).astype(np.float64)
    return np.where(inside[:, None], q, 0.0), inside


def surface_depth(D: np.ndarray, uv: np.ndarray, max_span: float = 1e29, snap: float = 0.01):
    """Depth of a depth map's two-triangle surface at texel positions (``surface_depth`` of
    ``shaders/dmrt_photos.glsl``).

    Includes its choice of quad for positions within ``snap`` of a row or column of texel centres:
    the floor() quad if complete and spanning <= ``max_span``, else the first of the other quads
    (x, y, xy neighbour) that is, else the first complete one with a smaller span.

    Parameters
    ----------
    D : (h, w) float32
        Depth map, camera z in metres, 0 = empty.
    uv : (n, 2) float
        Texel positions (corner origin); NaN allowed (no surface).
    max_span : float
        Metres; the discontinuity threshold when choosing among the quads.
    snap : float
        Texels.

    Returns
    -------
    depth : (n,) float64
        Camera z of the surface, metres (meaningful where ``ok``).
    ok : (n,) bool
        The triangle holding the position has three non-empty texels.
    quad : (n, 4) float64
        The chosen quad's depths (00, 10, 01, 11), metres.
    f : (n, 2) float64
        Position within the quad, 0..1.
    """
    h, w = D.shape
    x = np.clip(np.nan_to_num(uv, nan=-10.0), -4.0, [w + 4.0, h + 4.0]) - 0.5
    i0 = np.floor(x).astype(np.int64)
    f = x - i0
    q, inside = _quad(D, i0)

    def span(q, inside):
        complete = inside & (q > 0).all(1)
        return np.where(complete, q.max(1) - q.min(1), 1e30)

    sp = span(q, inside)
    s = np.stack([np.where(f[:, 0] < snap, -1, np.where(f[:, 0] > 1 - snap, 1, 0)),
                  np.where(f[:, 1] < snap, -1, np.where(f[:, 1] > 1 - snap, 1, 0))], axis=1)
    todo = (sp > max_span) & (s != 0).any(1)
    done = np.zeros(len(x), bool)
    for t in (s * [1, 0], s * [0, 1], s):
        q2, in2 = _quad(D, i0 + t)
        sp2 = span(q2, in2)
        take = todo & ~done & (t != 0).any(1) & (sp2 < sp) & ((sp2 <= max_span) | (sp >= 1e30))
        i0[take], f[take], q[take], inside[take], sp[take] = (i0 + t)[take], np.clip(f - t, 0, 1)[take], q2[take], True, sp2[take]
        done |= take & (sp2 <= max_span)
    inv = 1.0 / np.where(q > 0, q, 1.0)
    t0 = f[:, 0] + f[:, 1] <= 1.0
    iz0 = inv[:, 0] + f[:, 0] * (inv[:, 1] - inv[:, 0]) + f[:, 1] * (inv[:, 2] - inv[:, 0])
    iz1 = inv[:, 3] + (1 - f[:, 1]) * (inv[:, 1] - inv[:, 3]) + (1 - f[:, 0]) * (inv[:, 2] - inv[:, 3])
    ok = inside & np.where(t0, (q[:, [0, 1, 2]] > 0).all(1), (q[:, [1, 3, 2]] > 0).all(1))
    return 1.0 / np.where(t0, iz0, iz1), ok, q, f


def raytrace(camera: Camera, cameras, depthmaps, layer_depth, layer_label, max_steps=100,
             binary_steps=20, threshold=0.20, steps=None, refine="illinois"):
    """The raytracing pass (``shaders/dmrt_raytrace.glsl``: the paper's adaptive search and quad
    test, Section 5.1.2), vectorised over pixels.

    Parameters
    ----------
    camera : Camera
        The frame's camera, world frame, at the frame's resolution (h, w).
    cameras : list of Camera
        The photo cameras, world frame (any resolution: scaled to their depth maps).
    depthmaps : list of (hj, wj) float32
        The photos' depth maps, camera z in metres, 0 = empty.
    layer_depth : (k, h, w) float
        Splat depth per layer, metres, 0 = empty (as :meth:`Renderer.layers` returns it).
    layer_label : (k, h, w) int
        Label per layer, -1 = empty.
    max_steps, binary_steps : int
        Iterative and (at most) refinement steps.
    threshold : float
        Discontinuity threshold, metres.
    steps : (k, bins, 2) float64, optional
        Per layer and step index (the last bin pools the later ones), the count and the summed
        length (metres along the ray) of the iterative steps taken are added to it (the renderer's
        ``step_stats``).
    refine : ``"illinois"`` or ``"bisection"``
        How an enclosed hit is refined (``RenderConfig.refine``).

    Returns
    -------
    depth : (h, w) float64
        Camera z of the hit, metres; 0 = none.
    layer : (h, w) int
        The layer that gave the hit; -1 = none.
    """
    dirs, centre = camera.pixel_rays()
    k = len(layer_depth)
    depth = np.zeros(len(dirs))
    layer = np.full(len(dirs), -1)
    for li in range(k):
        zs, ls = layer_depth[li].ravel(), layer_label[li].ravel()
        for lab in np.unique(ls[(zs > 0) & (layer < 0)]):
            idx = np.flatnonzero((zs > 0) & (ls == lab) & (layer < 0))
            s_hit, ok = _trace(centre, dirs[idx], zs[idx].astype(np.float64), cameras[lab],
                               depthmaps[lab], max_steps, binary_steps, threshold,
                               None if steps is None else steps[li], refine)
            depth[idx[ok]], layer[idx[ok]] = s_hit[ok], li
    shape = (camera.height, camera.width)
    return depth.reshape(shape), layer.reshape(shape)


def _trace(centre, d, s, photo, D, max_steps, binary_steps, threshold, steps=None, refine="illinois"):
    """One label's rays in its depth map: ``centre`` (3,) and ``d`` (m, 3) the rays (camera z =
    ray parameter), ``s`` (m,) float64 start parameters (the splat depth), ``photo`` the label's
    camera, ``D`` (h, w) its depth map. Returns the hit parameters (m,) float64 and (m,) bool ok."""
    h, w = D.shape
    c = photo.scaled(w, h)
    dlen = np.linalg.norm(d, axis=1)

    def F(s):
        with np.errstate(all="ignore"):
            pc = c.world_to_camera(centre + s[:, None] * d)
            uv = np.stack([c.fx * pc[:, 0] / pc[:, 2] + c.cx, c.fy * pc[:, 1] / pc[:, 2] + c.cy], 1)
            D_s, ok, _, _ = surface_depth(D, uv)
            ok &= pc[:, 2] > 1e-6
            return np.where(ok, (D_s - pc[:, 2]) * np.linalg.norm(pc, axis=1) / pc[:, 2], 0.0), ok

    s = s.copy()
    f, alive = F(s)
    found = np.zeros(len(s), bool)
    sa, sb, fa, fb = s.copy(), s.copy(), f.copy(), f.copy()
    for i in range(max_steps):
        act = alive & ~found
        if not act.any():
            break
        conv = act & (np.abs(f) <= 1e-5 * s)
        found |= conv
        sa[conv], sb[conv] = s[conv], s[conv]
        act &= ~conv
        sn = s + f / dlen
        fn, okn = F(sn)
        if steps is not None:  # the GPU records every step that stays in front of the camera
            taken = act & (sn > 0)
            b = min(i, len(steps) - 1)
            steps[b, 0] += taken.sum()
            steps[b, 1] += np.abs(sn - s)[taken].dot(dlen[taken])
        dead = act & ((sn <= 0) | ~okn)
        alive &= ~dead
        act &= ~dead
        enc = act & ((fn > 0) != (f > 0))
        found |= enc
        sa[enc], fa[enc], sb[enc], fb[enc] = s[enc], f[enc], sn[enc], fn[enc]
        step = act & ~enc
        s[step], f[step] = sn[step], fn[step]
    ok = alive & found
    bis = ok & (sa != sb)
    if refine == "illinois":
        s_hit, ok = _illinois(F, sa, fa, sb, fb, bis, ok, binary_steps)
    else:
        s_hit, ok = _bisection(F, sa, fa, sb, fb, bis, ok, binary_steps)
    with np.errstate(all="ignore"):
        pc = c.world_to_camera(centre + s_hit[:, None] * d)
        uv = np.stack([c.fx * pc[:, 0] / pc[:, 2] + c.cx, c.fy * pc[:, 1] / pc[:, 2] + c.cy], 1)
    _, _, q, _ = surface_depth(D, uv, max_span=threshold)
    inside = np.all(np.isfinite(uv), 1)
    pairs = [(0, 1), (0, 2), (1, 2), (1, 3), (3, 2)]
    ok &= inside & (pc[:, 2] > 1e-6) & (q > 0).all(1)
    ok &= np.all([np.abs(q[:, a] - q[:, b]) <= threshold for a, b in pairs], axis=0)
    return s_hit, ok


def _secant(sa, fa, sb, fb):
    with np.errstate(all="ignore"):
        return np.where(fa == fb, 0.5 * (sa + sb), sa + (sb - sa) * fa / (fa - fb))


def _bisection(F, sa, fa, sb, fb, bis, ok, n):
    """The paper's refinement of the intervals ``bis``: ``n`` bisection steps, then a secant step.
    Returns the hit parameters and ``ok`` less the rays whose probe fell on empty texels."""
    sa, fa, sb, fb, ok = sa.copy(), fa.copy(), sb.copy(), fb.copy(), ok.copy()
    for _ in range(n):
        sm = 0.5 * (sa + sb)
        fm, okm = F(sm)
        ok &= ~(bis & ~okm)
        same = (fm > 0) == (fa > 0)
        upd_a, upd_b = bis & same, bis & ~same
        sa[upd_a], fa[upd_a] = sm[upd_a], fm[upd_a]
        sb[upd_b], fb[upd_b] = sm[upd_b], fm[upd_b]
    return np.where(bis, _secant(sa, fa, sb, fb), sa), ok


def _illinois(F, sa, fa, sb, fb, bis, ok, n):
    """The Illinois refinement of ``shaders/dmrt_raytrace.glsl`` (``ILLINOIS``): at most ``n``
    regula-falsi steps, the kept end's value halved when the same end is kept twice, stopping at
    |h| <= 1e-6 of the depth; then a secant step for the rays that did not stop."""
    sa, fa, sb, fb, ok = sa.copy(), fa.copy(), sb.copy(), fb.copy(), ok.copy()
    side = np.zeros(len(sa), np.int8)
    active = bis & ok
    hit = sa.copy()
    for _ in range(n):
        act = active & (fa != fb)
        if not act.any():
            break
        with np.errstate(all="ignore"):
            sm = np.where(act, (sa * fb - sb * fa) / (fb - fa), sa)
        fm, okm = F(sm)
        ok &= ~(act & ~okm)
        act &= okm
        done = act & (np.abs(fm) <= 1e-6 * sm)
        hit[done] = sm[done]
        active &= ~done & ok
        act &= ~done
        keep_b = act & ((fm > 0) == (fb > 0))
        keep_a = act & ~keep_b
        fa[keep_b & (side == -1)] *= 0.5
        sb[keep_b], fb[keep_b] = sm[keep_b], fm[keep_b]
        fb[keep_a & (side == 1)] *= 0.5
        sa[keep_a], fa[keep_a] = sm[keep_a], fm[keep_a]
        side[keep_b], side[keep_a] = -1, 1
    return np.where(active, _secant(sa, fa, sb, fb), hit), ok


# ---------------------------------------------------------------------------------------------
# labeling pass
# ---------------------------------------------------------------------------------------------
def pixel_points(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """The points of a depth buffer.

    Parameters
    ----------
    camera : Camera
        At the buffer's resolution (h, w); its frame is the points' frame.
    depth : (h, w) float
        Camera z, metres (0 gives the camera centre).

    Returns
    -------
    (h*w, 3) float64
        Points, metres, row-major pixel order.
    """
    dirs, centre = camera.pixel_rays()
    return centre + dirs * depth.reshape(-1, 1).astype(np.float64)


def labeling_pass(camera: Camera, proxy: dict, depth: np.ndarray) -> np.ndarray:
    """The labeling pass (paper Section 5.2.1): geometry-aware Voronoi labels.

    Per hit pixel, the label of the covering disc nearest (in 3D) to the pixel's point; ties go to
    the smallest label.

    Parameters
    ----------
    camera : Camera
        In the proxies' frame (scene-origin-relative), at the frame's resolution (h, w).
    proxy : dict
        ``positions``, ``normals``, ``radii``, ``labels`` (see the module docstring).
    depth : (h, w) float
        The raytraced camera z, metres, 0 = none.

    Returns
    -------
    (h, w) int
        Label; -1 where no hit or no disc covers the pixel.
    """
    z = disc_hits(camera, proxy)
    q = pixel_points(camera, depth)
    dist = np.linalg.norm(q[:, None, :] - proxy["positions"].astype(np.float64)[None], axis=2)
    dist = np.where(np.isfinite(z), dist, np.inf)
    j = np.argmin(dist, axis=1)
    best = dist[np.arange(len(j)), j]
    tie = dist == best[:, None]
    lab = np.where(tie, proxy["labels"][None, :], np.iinfo(np.int32).max).min(1)
    out = np.where(np.isfinite(best) & (depth.ravel() > 0), lab, -1)
    return out.reshape(depth.shape)


def visible_in_depth_map(cam: Camera, depth: np.ndarray, points: np.ndarray, normals=None,
                         radii=None, slack: float = 0.03) -> np.ndarray:
    """The points that a photo's depth map sees (the label check's question, ``sees`` in
    ``shaders/dmrt_label_finalize.glsl``, and the candidate test of
    ``dmrt.preprocess.candidates.find_candidates``; with its own nearest-texel tolerance).

    A point is seen when the depth of its nearest texel is within ``slack`` plus two texel
    footprints of its own camera z; the footprints are divided by the cosine of the viewing angle
    when normals are given (depth changes faster across a texel on a surface seen at a grazing
    angle). With radii, a point just outside the frame whose disc reaches into it is tested at the
    nearest border texel (with the radius added to the tolerance): its splat covers frame pixels
    that no other proxy may cover.

    Parameters
    ----------
    cam : Camera
        The photo's camera, points' frame, at full resolution (scaled to the depth map).
    depth : (h, w) float32
        Its depth map, camera z in metres, 0 = empty.
    points : (n, 3) float
        Metres.
    normals : (n, 3) float, optional
        Unit normals.
    radii : (n,) float, optional
        Splat radii, metres.
    slack : float
        Metres.

    Returns
    -------
    (n,) bool
    """
    h, w = depth.shape
    c = cam.scaled(w, h)
    uv, z = c.project(points)
    ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
    uv = np.where(ok[:, None], uv, -1e9)
    margin = np.zeros(len(points)) if radii is None else np.where(ok, radii * c.fx / np.maximum(z, 1e-9), 0)
    outside = np.maximum(np.maximum(-uv[:, 0], uv[:, 0] - w), np.maximum(-uv[:, 1], uv[:, 1] - h))
    ok &= outside < margin
    col = np.clip(np.floor(uv[:, 0]), 0, w - 1).astype(np.int64)
    row = np.clip(np.floor(uv[:, 1]), 0, h - 1).astype(np.int64)
    d = np.where(ok, depth[row, col], 0.0)
    footprint = np.abs(z) / c.fx
    if normals is not None:
        to_eye = c.center - points
        cos = np.abs(np.einsum("ij,ij->i", to_eye, normals)) / np.maximum(np.linalg.norm(to_eye, axis=1), 1e-12)
        footprint = footprint / np.maximum(cos, 0.1)
    tol = slack + 2 * footprint + np.where(outside > 0, 0.0 if radii is None else radii, 0.0)
    return ok & (d > 0) & (np.abs(d - z) <= tol)


# ---------------------------------------------------------------------------------------------
# texturing pass
# ---------------------------------------------------------------------------------------------
def texturing_pass(camera: Camera, depth: np.ndarray, label: np.ndarray, cameras, image) -> np.ndarray:
    """The texturing pass (paper Section 5.2.3) from full-resolution photos: each pixel's surface
    point projected into the photo of its label, sampled bilinearly.

    Parameters
    ----------
    camera : Camera
        The frame's camera, world frame, at the frame's resolution (h, w).
    depth : (h, w) float
        Camera z, metres, 0 = none.
    label : (h, w) int
        Final label per pixel, -1 = none.
    cameras : list of Camera
        The photo cameras, world frame, at the photos' resolution.
    image : callable
        ``j -> (H, W, 3) uint8`` photo ``j``.

    Returns
    -------
    (h, w, 3) uint8
        RGB; 0 where the label is -1.
    """
    from reference.render import sample_bilinear

    expected = np.zeros(depth.shape + (3,), np.uint8)
    pts = pixel_points(camera, depth)
    labels = label.ravel()
    flat = expected.reshape(-1, 3)
    for j in np.unique(labels[labels >= 0]):
        m = labels == j
        uv, _ = cameras[j].project(pts[m])
        flat[m] = np.clip(np.rint(sample_bilinear(image(j), uv)), 0, 255).astype(np.uint8)
    return expected


# ---------------------------------------------------------------------------------------------
# view-dependent photo choice
# ---------------------------------------------------------------------------------------------
_MIN_PENALTY = 1e-3  # dmrt_view_common.glsl's MIN_PENALTY


def view_penalties(camera: Camera, points: np.ndarray, cameras, depthmaps, photo: np.ndarray,
                   tolerance: float, distance_weight: float, turn_weight: float) -> np.ndarray:
    """Penalty of photo ``photo[i]`` for point ``points[i]`` seen by ``camera`` (``view_penalty``
    and ``view_sees`` of ``shaders/dmrt_view_common.glsl``): the angle between the view ray and the
    photo's ray to the point, radians, plus ``distance_weight`` per octave by which the photo's
    distance to the point differs from the view's, plus ``turn_weight`` times the angle between the
    photo's optical axis and the view's; NaN where the photo does not see the point (behind it, outside its
    map, or its depth map more than ``tolerance`` metres off).

    Parameters
    ----------
    camera : Camera, the frame's (points' frame)
    points : (n, 3) float, metres
    cameras : list of Camera, the photos' (points' frame, full resolution)
    depthmaps : list of (h, w) float32, their depth maps
    photo : (n,) int, which photo each point is tested against

    Returns
    -------
    (n,) float64
    """
    out = np.full(len(points), np.nan)
    view = points - camera.center
    dist = np.linalg.norm(view, axis=1)
    for j in np.unique(photo):
        m = photo == j
        D = depthmaps[j]
        c = cameras[j].scaled(D.shape[1], D.shape[0])
        uv, z = c.project(points[m])
        inside = (z > 1e-6) & (uv >= 0).all(1) & (uv <= [D.shape[1], D.shape[0]]).all(1)
        depth, ok, _, _ = surface_depth(D, np.where(inside[:, None], uv, np.nan))
        seen = inside & ok & (np.abs(depth - z) <= tolerance)
        ray = points[m] - c.center
        length = np.linalg.norm(ray, axis=1)
        cos = np.einsum("ij,ij->i", view[m] / dist[m, None], ray / length[:, None])
        octaves = np.abs(np.log2(length / dist[m]))
        turn = np.arccos(np.clip(c.R[2] @ camera.R[2], -1, 1))
        pen = np.maximum(np.arccos(np.clip(cos, -1, 1)) + distance_weight * octaves + turn_weight * turn, _MIN_PENALTY)
        out[np.flatnonzero(m)[seen]] = pen[seen]
    return out


def _sample_points(camera: Camera, depth: np.ndarray, stride: int, grid) -> np.ndarray:
    """Flat pixel indices of the view-choice score samples (``dmrt.runtime.view_choice.sample_grid``)."""
    h, w = depth.shape
    xs = np.minimum(np.arange(grid[0]) * stride + stride // 2, w - 1)
    ys = np.minimum(np.arange(grid[1]) * stride + stride // 2, h - 1)
    return (ys[:, None] * w + xs[None, :]).ravel()


def view_scores(camera: Camera, depth: np.ndarray, cameras, depthmaps, stride: int, grid, tolerance: float,
                distance_weight: float, turn_weight: float) -> np.ndarray:
    """Each photo's score against the frame (``shaders/dmrt_view_scores.glsl``): the sum over the
    sample pixels (``stride`` apart, ``grid`` = (columns, rows)) whose point it sees of
    ``floor(64 / penalty)``.

    Returns
    -------
    (n_photos,) int64
    """
    pix = _sample_points(camera, depth, stride, grid)
    pix = pix[depth.ravel()[pix] > 0]
    pts = pixel_points(camera, depth).reshape(-1, 3)[pix]
    n = len(cameras)
    pen = view_penalties(camera, np.repeat(pts, n, 0), cameras, depthmaps, np.tile(np.arange(n), len(pts)),
                         tolerance, distance_weight, turn_weight).reshape(len(pts), n)
    return np.where(np.isnan(pen), 0, np.floor(64.0 / np.nan_to_num(pen, nan=1.0))).astype(np.int64).sum(0)


def view_choice(camera: Camera, depth: np.ndarray, label: np.ndarray, cameras, depthmaps, candidates, blend: int,
                tolerance: float, distance_weight: float, turn_weight: float,
                quads: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The per-pixel view-dependent choice (``shaders/dmrt_view_choice.glsl``): each pixel's label
    and the candidates ranked by :func:`view_penalties`, the ``blend`` best that see the point kept
    with unstructured-lumigraph weights ``(1 - p_i / p_t) / p_i`` normalised (``p_t`` the next best
    visible penalty, pi if none). With ``quads`` (``dmrt.runtime.view_choice.quads``), a 2x2 quad
    (even corners) of one surface - one label, depths within ``tolerance`` - takes its top-left
    pixel's choice.

    Parameters
    ----------
    camera : Camera, the frame's (h, w)
    depth : (h, w) float, camera z, 0 = none
    label : (h, w) int, the final labels before the choice, -1 = none
    cameras, depthmaps : the photos (as :func:`view_penalties`)
    candidates : (m,) int, the frame's candidates
    blend : int, 1-4

    Returns
    -------
    photos : (h, w, blend) int, best first, -1 = none (the first is the new final label)
    weights : (h, w, blend) float64, summing to 1 on labelled pixels, 0 elsewhere
    """
    h, w = depth.shape
    pts = pixel_points(camera, depth)
    lab = label.ravel()
    cand = np.concatenate([lab[:, None], np.broadcast_to(np.asarray(candidates, np.int64), (h * w, len(candidates)))], 1)
    cand = np.where(np.arange(cand.shape[1]) == 0, cand, np.where(cand == lab[:, None], -1, cand))
    valid = (lab >= 0) & (depth.ravel() > 0)
    cand[~valid] = -1
    pen = np.full(cand.shape, np.nan)
    m = cand >= 0
    rows = np.nonzero(m)[0]
    pen[m] = view_penalties(camera, pts[rows], cameras, depthmaps, cand[m], tolerance, distance_weight, turn_weight)
    pen = np.where(np.isnan(pen), np.inf, pen)
    order = np.argsort(pen, axis=1, kind="stable")[:, :blend + 1]
    best_pen = np.take_along_axis(pen, order, 1)
    best = np.where(np.isfinite(best_pen), np.take_along_axis(cand, order, 1), -1)
    none = valid & (best[:, 0] < 0)  # nobody sees the point: the label alone
    best[none, 0], best_pen[none, 0] = lab[none], _MIN_PENALTY
    if best.shape[1] <= blend:  # fewer candidates than blend + 1
        best = np.pad(best, ((0, 0), (0, blend + 1 - best.shape[1])), constant_values=-1)
        best_pen = np.pad(best_pen, ((0, 0), (0, blend + 1 - best_pen.shape[1])), constant_values=np.inf)
    thresh = np.where(best[:, blend] >= 0, best_pen[:, blend], np.pi)
    p = best_pen[:, :blend]
    wts = np.where(best[:, :blend] >= 0, np.maximum(1 - p / thresh[:, None], 0) / np.where(np.isfinite(p), p, 1), 0)
    total = wts.sum(1, keepdims=True)
    wts = np.where(total > 0, wts / np.where(total > 0, total, 1), np.eye(1, blend)[0])
    photos = np.where(wts > 0, best[:, :blend], -1)
    photos[:, 0] = best[:, 0]
    wts[~valid], photos[~valid] = 0, -1
    photos, wts = photos.reshape(h, w, blend), wts.reshape(h, w, blend)
    if not quads:
        return photos, wts
    # one choice a 2x2 quad (even corners) of one surface: its top-left pixel's, where the four hits
    # have one label and depths (float32, as on the GPU) within the tolerance
    qh, qw = h // 2, w // 2
    d = np.asarray(depth, np.float32)[:2 * qh, :2 * qw].reshape(qh, 2, qw, 2)
    lq = label[:2 * qh, :2 * qw].reshape(qh, 2, qw, 2)
    agree = ((d > 0).all((1, 3)) & (lq[:, :1, :, :1] >= 0).all((1, 3)) & (lq == lq[:, :1, :, :1]).all((1, 3))
             & (d.max((1, 3)) - d.min((1, 3)) <= np.float32(tolerance)))
    for out in (photos, wts):
        top_left = out[0:2 * qh:2, 0:2 * qw:2]
        for dy, dx in ((0, 1), (1, 0), (1, 1)):
            out[dy:2 * qh:2, dx:2 * qw:2][agree] = top_left[agree]
    return photos, wts


# ---------------------------------------------------------------------------------------------
# DMT: the grid triangulation of one depth map
# ---------------------------------------------------------------------------------------------
def grid_mesh_depth(depth: np.ndarray, p: np.ndarray, t0: np.ndarray, t1: np.ndarray):
    """Depth of one depth map's grid mesh (``shaders/dmt_mesh.glsl``), seen from the map's own
    camera.

    The triangle holding ``p`` (T0 = 00-10-01 where f.x + f.y <= 1, else T1 = 10-11-01) must exist;
    inside it 1/z is linear in image coordinates (exact for the plane through its three vertices).

    Parameters
    ----------
    depth : (h, w) float32
        The depth map, camera z in metres, 0 = empty.
    p : (n, 2) float
        Depth-map positions, texels, corner origin.
    t0, t1 : (h-1, w-1) bool
        Which lower (T0) and upper (T1) triangles of each quad exist (the discontinuity drop,
        ``baselines.dmt.geometry.grid_triangles``).

    Returns
    -------
    z : (n,) float64
        Camera z, metres (meaningful where ``ok``).
    ok : (n,) bool
        A triangle holds the position.
    texel : (n, 2) int
        The texel (column, row) holding the position (the per-texel label lookup).
    """
    h, w = depth.shape
    s = p - 0.5
    i0 = np.floor(s).astype(np.int64)
    f = s - i0
    inside = (i0[:, 0] >= 0) & (i0[:, 1] >= 0) & (i0[:, 0] < w - 1) & (i0[:, 1] < h - 1)
    c, r = np.where(inside, i0[:, 0], 0), np.where(inside, i0[:, 1], 0)
    lower = f[:, 0] + f[:, 1] <= 1.0
    ok = inside & np.where(lower, t0[r, c], t1[r, c])
    inv = 1.0 / np.where(depth > 0, depth, 1.0).astype(np.float64)
    i00, i10, i01, i11 = inv[r, c], inv[r, c + 1], inv[r + 1, c], inv[r + 1, c + 1]
    iz = np.where(lower, i00 + f[:, 0] * (i10 - i00) + f[:, 1] * (i01 - i00),
                  i11 + (1 - f[:, 1]) * (i10 - i11) + (1 - f[:, 0]) * (i01 - i11))
    texel = np.clip(np.floor(p).astype(np.int64), 0, [w - 1, h - 1])
    return 1.0 / iz, ok, texel
