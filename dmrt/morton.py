"""Morton (Z-order) codes: one implementation for the octree's cell keys, the normals' buckets, the
labeling's spatial sort and the proxies' GPU order."""

from __future__ import annotations

import numpy as np

MAX_BITS_PER_AXIS = 21  # 3 * 21 = 63 bits: keys fit a non-negative int64


def _part1by2(v: np.ndarray) -> np.ndarray:
    """Spread the low 21 bits of ``v`` (uint64) to every third bit."""
    v = v & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


def morton_encode(q: np.ndarray) -> np.ndarray:
    """Morton (z-order) keys of integer cell coordinates.

    Parameters
    ----------
    q : (n, 3) int64, each in ``[0, 2**21)``

    Returns
    -------
    (n,) int64 keys; the key of the parent cell (coordinates ``q >> 1``) is ``key >> 3``.
    """
    q = q.astype(np.uint64, copy=False)
    k = _part1by2(q[:, 0]) | (_part1by2(q[:, 1]) << np.uint64(1)) | (_part1by2(q[:, 2]) << np.uint64(2))
    return k.view(np.int64)


def morton_order(positions: np.ndarray, bits: int = 10) -> np.ndarray:
    """Permutation sorting points along a 3D Z-order curve.

    Parameters
    ----------
    positions : (n, 3) float, metres
    bits : int
        Grid resolution per axis over the points' bounding cube (10: 1024 cells a side, enough to
        keep neighbours together; finer only costs time).

    Returns
    -------
    (n,) int64 indices, a stable sort of the points' Morton keys.
    """
    p = np.asarray(positions, np.float64)
    lo, hi = p.min(0), p.max(0)
    q = ((p - lo) / max(float((hi - lo).max()), 1e-12) * ((1 << bits) - 1)).astype(np.int64)
    return np.argsort(morton_encode(q), kind="stable")
