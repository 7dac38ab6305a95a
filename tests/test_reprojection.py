"""reference/reprojection.py and reference/stability.py on analytic scenes: a textured plane z = 0
seen by pinhole cameras, whose photos and depths are computed exactly (ray-plane intersections),
so every reprojected colour, choice and frame change has a known value."""

from __future__ import annotations

import numpy as np
import pytest

from dmrt.camera import Camera
from reference.raycast import MeshRaycaster
from reference.reprojection import ViewClosest, depth_map_visibility, reproject, reproject_photos
from reference.stability import frame_change, walkthrough_change

W, H = 64, 48


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n, 3) float64 RGB of the plane at world (x, y): smooth (periods of 2-3 m against pixels of
    ~3 cm), so bilinear sampling is exact to a fraction of a level."""
    return np.stack([128 + 80 * np.sin(2.1 * x), 128 + 80 * np.cos(2.9 * y), 128 + 60 * np.sin(x + y)], axis=1)


def shoot(cam: Camera, tint=(0.0, 0.0, 0.0)):
    """The plane's exact depth (h, w) and photo (h, w, 3) uint8 at ``cam`` (+ ``tint`` levels)."""
    dirs, c = cam.pixel_rays()
    s = -c[2] / dirs[:, 2]  # ray parameter = camera z (pixel_rays' scaling)
    p = c + s[:, None] * dirs
    color = np.clip(np.rint(texture(p[:, 0], p[:, 1]) + tint), 0, 255).astype(np.uint8)
    return s.reshape(cam.height, cam.width).astype(np.float32), color.reshape(cam.height, cam.width, 3)


def down(x: float, name: str) -> Camera:
    """A camera 2 m above the plane at (x, 0), looking straight down (80 degrees across)."""
    return Camera.look_at(name, (x, 0.0, 2.0), (x, 0.0, 0.0), W, H, fov_x_deg=80.0, up=(0.0, 1.0, 0.0))


def plane_mesh():
    v = np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0]], np.float64)
    return MeshRaycaster(v, np.array([[0, 1, 2], [0, 2, 3]]))


def test_reprojection_of_a_plane_seen_by_two_cameras():
    """Photo B reprojected into view A through the plane gives A's own photo wherever B sees the
    point; A's pixels beyond B's frame are not seen. The same with Embree occlusion (mesh) and with
    B's depth map, which also rejects what an occluder hides from B."""
    view, other = down(0.0, "a"), Camera.look_at("b", (0.7, 0.3, 2.5), (0.2, 0.1, 0.0), W, H, fov_x_deg=70.0)
    depth, photo = shoot(view)
    b_depth, b_photo = shoot(other)
    mesh = plane_mesh()
    r = reproject(view, depth, 1, other, b_photo, lambda p: mesh.visible(p, other.center))
    share = r.seen.mean()
    assert 0.3 < share < 0.95  # B sees part of A's frame (the rest: outside B's frame)
    rays = view.pixel_rays()[0]
    uv, _ = other.project(view.center + depth.reshape(-1, 1) * rays)
    # within B's outer half pixel bilinear sampling clamps to the edge texel (up to half a texel of
    # the texture's gradient, ~4 levels): checked inside it
    core = r.seen & ((uv >= 0.5) & (uv <= [W - 0.5, H - 0.5])).all(axis=1).reshape(H, W)
    err = np.abs(r.color - photo)[core]
    # bilinear interpolation of a smooth texture (curvature x texel^2 / 8 < 0.1 level) plus the
    # two photos' 8-bit rounding (<= 1 level)
    assert core.sum() > 0.9 * r.seen.sum() and err.max() < 1.6 and err.mean() < 0.6
    assert np.all(r.color[~r.seen] == 0) and np.all(r.cos[~r.seen] == -1)
    # the angle between the rays: the exact value at one pixel
    i, j = np.argwhere(r.seen)[len(np.argwhere(r.seen)) // 2]
    p = view.center + depth[i, j] * rays[i * W + j]
    a, b = p - view.center, p - other.center
    assert r.cos[i, j] == pytest.approx(a @ b / np.linalg.norm(a) / np.linalg.norm(b), abs=1e-6)

    by_map = reproject(view, depth, 1, other, b_photo, depth_map_visibility(other, b_depth))
    assert (by_map.seen != r.seen).mean() < 0.01  # nearest-texel lookups at B's frame edge
    # an occluder 1 m in front of the plane over B's left half: B's depth map shows it there
    occluded = b_depth.copy()
    occluded[:, : W // 2] -= 1.0
    hidden = reproject(view, depth, 1, other, b_photo, depth_map_visibility(other, occluded))
    left = uv[r.seen.ravel(), 0] < W // 2
    assert not hidden.seen[r.seen][left].any() and hidden.seen[r.seen][~left].mean() > 0.98


def closest_labels(view, depth, cams, shots, maps=None):
    closest = ViewClosest(H, W)
    maps = maps or [d for d, _ in shots]
    for r in reproject_photos(view, depth, cams, lambda j: shots[j][1], lambda j: depth_map_visibility(cams[j], maps[j])):
        closest.add(r)
    return closest


def test_view_closest_picks_the_photo_nearest_in_angle():
    """A photo taken from the view's own centre sees every point at angle 0, so it is chosen
    wherever it sees: a narrower one (40 degrees, tinted +40 red) at the view's centre wins exactly
    on the centred rectangle of the view that its frame covers, with its own colour; a photo 1 m
    to the side (tinted +40 blue) gets the rest. Where the centre photo's depth map shows an
    occluder, the side photo is chosen instead. Two photos mirrored about the view (x = -1, +1)
    give a mirrored choice."""
    view = down(0.0, "view")
    depth, exact = shoot(view)
    centre = Camera.look_at("centre", (0.0, 0.0, 2.0), (0.0, 0.0, 0.0), W, H, fov_x_deg=40.0, up=(0.0, 1.0, 0.0))
    side = down(1.0, "side")
    cams = [centre, side]
    shots = [shoot(centre, (40, 0, 0)), shoot(side, (0, 0, 40))]
    closest = closest_labels(view, depth, cams, shots)
    # the centre photo's frame in the view's pixels: same centre and axes, focal ratio f_c / f_v
    ratio = centre.fx / view.fx
    j = np.abs(np.arange(W) + 0.5 - view.cx) < 0.5 * W / ratio
    i = np.abs(np.arange(H) + 0.5 - view.cy) < 0.5 * H / ratio
    inner = i[:, None] & j[None, :]
    assert 0.1 < inner.mean() < 0.5 and (closest.label[inner] == 0).all()
    outer = ~inner & closest.seen
    assert outer.mean() > 0.2 and (closest.label[outer] == 1).all()
    tint = closest.color - exact
    # bilinear sampling of a smooth texture + 8-bit rounding (see the test above), away from the
    # photo's outer half pixel where sampling clamps
    core = inner & np.roll(inner, 1, 0) & np.roll(inner, -1, 0) & np.roll(inner, 1, 1) & np.roll(inner, -1, 1)
    assert np.abs(tint[core] - [40, 0, 0]).max() < 1.6 and np.abs(tint[outer] - [0, 0, 40]).mean() < 1.0

    blocked = shots[0][0].copy()
    blocked[: H // 2] -= 1.0  # an occluder 1 m above the plane hides the upper half from the centre photo
    occluded = closest_labels(view, depth, cams, shots, [blocked, shots[1][0]])
    top = inner & (np.arange(H) < H // 2)[:, None]
    # (the side photo's frame misses a corner of it: no photo there)
    assert not (occluded.label[top] == 0).any() and (occluded.label[top] == 1).mean() > 0.95
    assert (occluded.label[inner & ~top] == 0).all()

    pair = [down(-1.0, "left"), down(1.0, "right")]
    mirrored = closest_labels(view, depth, pair, [shoot(c) for c in pair])
    both = mirrored.seen & mirrored.seen[:, ::-1]
    assert both.mean() > 0.5 and np.array_equal(mirrored.label[both], 1 - mirrored.label[:, ::-1][both])
    assert 0.3 < (mirrored.label[both] == 0).mean() < 0.7


def test_walkthrough_change_sees_a_pop_and_not_the_motion():
    """A slow path over the textured plane, rendered exactly: consecutive frames differ by the
    motion only, which the warp takes out (under a level). Frame 5 with a seam that popped (its
    left half 30 levels brighter) gives spikes at pairs 4-5 and 5-6 of ~30 x the half of the
    pixels, and nothing elsewhere."""
    cams = [down(0.03 * t, f"f{t}") for t in range(9)]
    frames = [dict(zip(("depth", "color"), shoot(c))) for c in cams]
    still = walkthrough_change(frames, cams)
    assert len(still["per_pair"]) == 8 and still["max"] < 1.0  # interpolation + 8-bit rounding
    assert min(still["shares"]) > 0.9  # 3 cm a frame moves the view by ~1 pixel of 64
    popped = [dict(f) for f in frames]
    c = popped[5]["color"].astype(np.int32)
    c[:, : W // 2] += 30
    popped[5]["color"] = np.clip(c, 0, 255).astype(np.uint8)
    got = walkthrough_change(popped, cams)["per_pair"]
    for t in (4, 5):
        assert got[t] == pytest.approx(15.0, abs=1.5)  # 30 levels on about half of the pixels both see
    assert max(got[t] for t in (0, 1, 2, 3, 6, 7)) < 1.0
    # a background pixel in the previous frame is not the same point: not counted
    holed = dict(frames[0])
    holed["depth"] = frames[0]["depth"].copy()
    holed["depth"][:, : W // 2] = 0
    _, share = frame_change(holed, frames[1], cams[0], cams[1])
    assert share < 0.55
