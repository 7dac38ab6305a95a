"""Temporal stability along a walkthrough: colour change between consecutive frames that the camera
motion does not explain.

A renderer that textures a surface point from a photo that changes as the camera moves (a seam
that jumps, a photo that pops in) makes that point's colour flicker although the scene stands
still. Frame ``t + 1``'s surface points (its depth and camera) are projected into frame ``t``;
where frame ``t`` sees the same point (its depth there agrees) its colour is sampled (bilinear)
and compared: what remains is not motion. Popping shows as spikes in the per-pair series.
"""

from __future__ import annotations

import numpy as np

from dmrt.camera import Camera
from dmrt.preprocess.candidates import sample_bilinear
from reference.reprojection import in_frame, surface_points

# Frame t sees frame t+1's point where its depth is within this share of the point's depth:
# walkthrough frames of one renderer differ by their depth-search precision (~1 %) and
# interpolation across a pixel; an occluding edge differs by far more.
SAME_POINT_REL = 0.03


def frame_change(prev: dict, nxt: dict, prev_cam: Camera, next_cam: Camera,
                 rel: float = SAME_POINT_REL) -> tuple[float, float]:
    """Colour change from frame ``prev`` to frame ``nxt`` on the surface both see, motion taken out.

    Parameters
    ----------
    prev, nxt : frames with ``color`` (h, w, 3) uint8 and ``depth`` (h, w) float camera z
        (metres, 0 = background), rendered at ``prev_cam`` and ``next_cam``.
    rel : relative depth agreement that makes a pixel of ``prev`` the same point.

    Returns
    -------
    change : mean absolute RGB difference, 8-bit levels (averaged over the channels), over the
        pixels of ``nxt`` whose point ``prev`` sees; nan when there are none.
    share : those pixels' share of ``nxt``'s frame.
    """
    points, hit = surface_points(next_cam, nxt["depth"])
    uv, z, inside = in_frame(prev_cam, points)
    d = prev["depth"]
    h, w = d.shape
    # the four texels bilinear sampling mixes must all hold the same surface (no background,
    # no other side of an edge): their depth within rel of the point's
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    same = inside.copy()
    for yy, xx in ((y0, x0), (y0, x1), (y1, x0), (y1, x1)):
        same &= np.abs(d[yy, xx] - z) <= rel * z
    if not same.any():
        return float("nan"), 0.0
    before = sample_bilinear(prev["color"], uv[same])
    after = nxt["color"][hit].astype(np.float32)[same]
    return float(np.abs(after - before).mean()), float(same.sum() / hit.size)


def walkthrough_change(frames: list[dict], cameras: list[Camera], rel: float = SAME_POINT_REL) -> dict:
    """:func:`frame_change` of each consecutive pair of ``frames`` (rendered at ``cameras``).

    Returns
    -------
    dict
        ``per_pair`` (n - 1 floats, 8-bit levels), ``shares`` (n - 1 floats), ``mean`` (over the
        pairs), ``max`` (the largest: a pop), ``median`` (the steady change), all nan-aware.
    """
    if len(frames) != len(cameras) or len(frames) < 2:
        raise ValueError(f"need >= 2 frames and one camera each (got {len(frames)} frames, {len(cameras)} cameras)")
    pairs = [frame_change(frames[t], frames[t + 1], cameras[t], cameras[t + 1], rel) for t in range(len(frames) - 1)]
    change = np.array([c for c, _ in pairs])
    ok = change[np.isfinite(change)]
    summary = {k: (float(f(ok)) if ok.size else float("nan"))
               for k, f in (("mean", np.mean), ("max", np.max), ("median", np.median))}
    return {"per_pair": change.tolist(), "shares": [s for _, s in pairs], **summary}
