"""Frustum culling of spatial buckets: which runs of consecutive points a camera can see.

Preprocessing touches every (photo, point) pair twice: phase 3 splats P_HD into each photo's depth
map, and the candidates test projects P_LD into each photo. Both read the points in octree order,
where every level is in Morton order of its cells (:mod:`dmrt.preprocess.octree`), so a run of a
few thousand consecutive points of one level is a compact piece of the scene. A :class:`Buckets`
cuts the points into such runs and keeps each run's bounding box; a camera then skips the runs
whose box lies outside its frustum, and the cost of a photo follows what it sees instead of the
whole cloud (a gallery of 100 rooms: each photo sees a room or two).

Culling is conservative, so the culled result equals the whole one exactly:

* a box holds its points' splat discs whole (the box of ``p ± r``, not of ``p``), so a disc that
  reaches into the frustum from outside keeps its run;
* the frustum is that of the pixel rectangle widened by :data:`MARGIN_PX` on every side, and the
  boxes are widened by :data:`PAD_REL` of their distance from the origin (far above float32's
  rounding of the GPU's camera transform and ray-disc test);
* for splats (``lines=True``), a run that reaches the camera plane is also kept where it meets the
  frustum mirrored through the camera centre: the grazing-ray rule of the depth-map shaders
  (``splat_depth_ray`` in ``shaders/splat_depth_common.glsl``) measures a disc centre's distance
  to the pixel's whole line, behind the camera too.

A box is outside the frustum when it lies wholly outside one of its five planes (near, left, right,
top, bottom); that test keeps a few boxes near the frustum's edges that a full test would cull,
never the reverse.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmrt.camera import Camera

MARGIN_PX = 1.0
"""Pixels the image rectangle is widened by on every side (pixel centres lie 0.5 px inside it)."""
PAD_REL = 1e-5
"""Boxes are widened by this fraction of their largest coordinate (+ 1 m): 10 micrometres at
1 m, 1 cm at 1 km, beyond float32's ~1e-7 relative rounding of positions and camera transforms."""


@dataclass
class Buckets:
    """Consecutive runs of points and their bounding boxes.

    Attributes
    ----------
    starts : (b,) int64
        First point of each bucket; the buckets tile ``0 .. n`` in order.
    counts : (b,) int64
        Points in each bucket (>= 1).
    lo, hi : (b, 3) float64
        Corners of each bucket's box (its points' discs included, padded), metres, in the
        points' frame.
    """

    starts: np.ndarray
    counts: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def of(cls, positions: np.ndarray, radii: np.ndarray | None = None, size: int = 4096,
           breaks=()) -> "Buckets":
        """Buckets of at most ``size`` consecutive points, also cut at ``breaks``.

        Parameters
        ----------
        positions : (n, 3) float32 or float64, metres.
        radii : (n,) float, optional: each point's disc radius, metres (None: points).
        size : int, points per bucket at most.
        breaks : iterable of int, row indices where a bucket must start (e.g. where the octree's
            next level begins: the end of one level and the start of the next are far apart).
        """
        positions = np.asarray(positions)
        n = len(positions)
        cuts = np.union1d(np.arange(0, n, max(1, int(size)), dtype=np.int64),
                          np.asarray([b for b in breaks if 0 < b < n], np.int64))
        if n == 0:
            return cls(cuts, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
        counts = np.diff(np.append(cuts, n))
        if radii is None:
            lo = np.minimum.reduceat(positions, cuts, axis=0).astype(np.float64)
            hi = np.maximum.reduceat(positions, cuts, axis=0).astype(np.float64)
        else:
            # fmax: a NaN radius (which draws nothing) does not spoil its bucket's box
            rmax = np.maximum(np.fmax.reduceat(np.asarray(radii, np.float64), cuts), 0.0)
            lo = np.minimum.reduceat(positions, cuts, axis=0) - rmax[:, None]
            hi = np.maximum.reduceat(positions, cuts, axis=0) + rmax[:, None]
        pad = PAD_REL * (1.0 + np.maximum(np.abs(lo), np.abs(hi)).max(axis=1, initial=0.0))
        return cls(cuts, counts, lo - pad[:, None], hi + pad[:, None])

    def __len__(self) -> int:
        return len(self.starts)

    @property
    def n_points(self) -> int:
        return int(self.counts.sum())

    def visible(self, camera: Camera, lines: bool = False) -> np.ndarray:
        """(b,) bool: the buckets whose box may meet ``camera``'s frustum (module docstring).

        ``camera`` : in the points' frame, at the resolution whose pixel rectangle counts (a depth
        map's: :meth:`Camera.scaled`). ``lines`` : splats tested against each pixel's whole line
        (the depth-map shaders' grazing rule), not only its ray.
        """
        return self.visible_to([camera], lines)[0]

    def visible_to(self, cameras, lines: bool = False) -> np.ndarray:
        """(c, b) bool: :meth:`visible` of each of ``cameras`` (a sequence of c), in one pass over
        the boxes (a batch of points culled for 192 photos at once: ~1 ms instead of 192 x 0.1)."""
        if not len(self) or not len(cameras):
            return np.zeros((len(cameras), len(self)), bool)
        m = MARGIN_PX
        # camera-space planes n . x >= 0 bounding each frustum: near, left, right, top, bottom
        planes = np.array([[[0.0, 0.0, 1.0],
                            [c.fx, 0.0, c.cx + m],
                            [-c.fx, 0.0, c.width + m - c.cx],
                            [0.0, c.fy, c.cy + m],
                            [0.0, -c.fy, c.height + m - c.cy]] for c in cameras])
        R = np.stack([c.R for c in cameras])
        t = np.stack([c.t for c in cameras])
        # n . (R p + t), p in the points' frame: (c * 5, 3) normals and (c * 5,) offsets
        normals, offsets = (planes @ R).reshape(-1, 3), np.einsum("ckj,cj->ck", planes, t).reshape(-1)
        centre, half = (self.lo + self.hi) / 2, (self.hi - self.lo) / 2
        shape = (len(cameras), 5, len(self))
        mid = (_dot(normals, centre) + offsets[:, None]).reshape(shape)  # plane value at each box's centre
        reach = _dot(np.abs(normals), half).reshape(shape)               # its largest change over the box
        top = mid + reach
        # a box with a NaN (a NaN point) compares False everywhere: kept, as are infinite ones
        keep = ~np.isfinite(top).all(axis=1) | (top >= 0).all(axis=1)
        if lines:
            keep |= (mid - reach <= 0).all(axis=1) & (top[:, 0] > 0)
        return keep

    def runs(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The selected buckets as maximal runs of consecutive points.

        Returns ``(first (k,) int64, count (k,) int64)``: each run's first point and length.
        """
        mask = np.asarray(mask, bool)
        edges = np.flatnonzero(np.diff(np.concatenate([[False], mask, [False]]).astype(np.int8)))
        a, b = edges[0::2], edges[1::2]  # bucket index ranges [a, b)
        first = self.starts[a]
        return first, self.starts[b - 1] + self.counts[b - 1] - first

    def rows(self, mask: np.ndarray) -> np.ndarray:
        """(k,) int64: the points of the selected buckets, ascending."""
        first, count = self.runs(mask)
        skip = first - np.concatenate([[0], np.cumsum(count)[:-1]])  # rows left out before each run
        return np.repeat(skip, count) + np.arange(count.sum(), dtype=np.int64)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(m, n): ``a @ b.T`` of (m, 3) and (n, 3) float64, summed term by term: a BLAS product this
    thin took 2-10 ms for (960, 3) x (3, 249) where OpenBLAS's threads had to wake (0.1 ms in a
    tight loop), and several threads cull at once (:mod:`dmrt.preprocess.depthmaps`)."""
    return a[:, 0:1] * b[:, 0] + a[:, 1:2] * b[:, 1] + a[:, 2:3] * b[:, 2]
