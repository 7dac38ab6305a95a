"""Error metrics between a rendered frame and the reference frame, with per-pixel heat maps.

All metrics compare frames of the same camera and resolution (see :mod:`dmrt.io.frames`).
"""

from __future__ import annotations

import numpy as np

from dmrt.camera import Camera


def texel_footprint(points: np.ndarray, labels: np.ndarray, cameras: list[Camera],
                    depthmap_width: int) -> np.ndarray:
    """Size in metres of one depth-map texel at each point, in the depth map of its label.

    A depth map of ``depthmap_width`` texels across photo ``j`` samples the surface at
    ``z_j / f_j'`` metres per texel (``f_j'`` the focal length scaled to the depth map), which is
    the natural unit of a depth-map renderer's depth error.

    Parameters
    ----------
    points : (n, 3) float64 world.  labels : (n,) int, -1 = none (gives NaN).
    cameras : photo cameras.  depthmap_width : depth-map width in texels.

    Returns
    -------
    (n,) float64 metres.
    """
    out = np.full(len(points), np.nan)
    for j in np.unique(labels[labels >= 0]):
        sel = labels == j
        cam = cameras[int(j)]
        z = cam.world_to_camera(points[sel])[:, 2]
        out[sel] = np.abs(z) / (cam.fx * depthmap_width / cam.width)
    return out


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB between two uint8 colour images over ``mask`` (inf when equal, nan when empty)."""
    d = a.astype(np.float64) - b.astype(np.float64)
    if mask is not None:
        d = d[mask]
    if d.size == 0:
        return float("nan")
    mse = float(np.mean(d ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0 ** 2 / mse)


def compare(frame: dict, ref: dict, footprint: np.ndarray | None = None) -> dict:
    """Compare ``frame`` with the reference frame ``ref``.

    Parameters
    ----------
    frame, ref : frame dicts of the same shape.
    footprint : (h, w) float64, optional
        Depth-map texel footprint in metres per pixel (:func:`texel_footprint`); when given the
        depth error is also reported in texels.

    Returns
    -------
    dict with scalars
        ``depth_median_m``, ``depth_mean_m``, ``depth_p95_m`` (|dz| where both have surface),
        ``depth_median_texels`` (if footprint), ``hole_rate`` (share of the reference's surface
        pixels that are background in the frame), ``extra_rate`` (share of the reference's
        background pixels that have surface in the frame), ``psnr_db`` (colour, where both have
        surface), ``label_agreement`` (share of common surface pixels with the same label),
    and heat maps (h, w) float32 under ``maps``: ``depth_error_m`` (NaN where undefined),
    ``holes`` (1 = hole, -1 = extra surface, 0 = fine), ``color_error`` (RGB distance 0..441).
    """
    if frame["depth"].shape != ref["depth"].shape:
        raise ValueError(f"frame {frame['depth'].shape} and reference {ref['depth'].shape} differ in size")
    surf, rsurf = frame["depth"] > 0, ref["depth"] > 0
    both = surf & rsurf
    dz = np.abs(frame["depth"].astype(np.float64) - ref["depth"])
    dz_map = np.where(both, dz, np.nan).astype(np.float32)
    holes = np.zeros(surf.shape, np.float32)
    holes[rsurf & ~surf] = 1.0
    holes[surf & ~rsurf] = -1.0
    cdiff = np.linalg.norm(frame["color"].astype(np.float32) - ref["color"].astype(np.float32), axis=-1)
    out = {
        "pixels": int(surf.size),
        "reference_surface_pixels": int(rsurf.sum()),
        "depth_median_m": float(np.median(dz[both])) if both.any() else float("nan"),
        "depth_mean_m": float(np.mean(dz[both])) if both.any() else float("nan"),
        "depth_p95_m": float(np.percentile(dz[both], 95)) if both.any() else float("nan"),
        "hole_rate": float((rsurf & ~surf).sum() / max(rsurf.sum(), 1)),
        "extra_rate": float((surf & ~rsurf).sum() / max((~rsurf).sum(), 1)),
        "psnr_db": psnr(frame["color"], ref["color"], both),
        "label_agreement": float(np.mean(frame["label"][both] == ref["label"][both])) if both.any() else float("nan"),
        "maps": {"depth_error_m": dz_map, "holes": holes,
                 "color_error": np.where(both, cdiff, np.nan).astype(np.float32)},
    }
    if footprint is not None:
        ok = both & np.isfinite(footprint) & (footprint > 0)
        out["depth_median_texels"] = float(np.median(dz[ok] / footprint[ok])) if ok.any() else float("nan")
    return out


def flip(rendered: np.ndarray, photo: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """NVIDIA's FLIP (LDR-FLIP, Andersson et al. 2020: the perceived difference of two images
    flipped back and forth; the ``flip-evaluator`` package) of ``rendered`` against ``photo``.

    Both images are set to black outside ``mask`` (as the SSIM of :mod:`bench.real_views`), so the
    background never differs; the map is averaged over the mask. FLIP's default viewing
    condition (67 pixels per degree: a 0.7 m wide 4K monitor seen from 0.7 m).

    Parameters
    ----------
    rendered, photo : (h, w, 3) uint8 sRGB.  mask : (h, w) bool, default every pixel.

    Returns
    -------
    mean : the error map's mean over the mask, 0 (identical) .. 1; nan when the mask is empty.
    error : (h, w) float32 FLIP error map, 0 .. 1 (0 outside the mask).
    """
    try:
        import flip_evaluator
    except ImportError as exc:
        raise ImportError("FLIP needs the flip-evaluator package: pip install 'dmrt[bench]'") from exc

    if rendered.shape != photo.shape:
        raise ValueError(f"images differ in size: {rendered.shape} vs {photo.shape}")
    if mask is None:
        mask = np.ones(rendered.shape[:2], bool)
    if not mask.any():
        return float("nan"), np.zeros(mask.shape, np.float32)
    m = mask[..., None]
    a = np.where(m, rendered, 0).astype(np.float32) / 255.0
    b = np.where(m, photo, 0).astype(np.float32) / 255.0
    error, _, _ = flip_evaluator.evaluate(b, a, "LDR", applyMagma=False, computeMeanError=False)
    error = np.where(mask, np.asarray(error, np.float32).reshape(mask.shape), 0.0).astype(np.float32)
    return float(error[mask].mean()), error
