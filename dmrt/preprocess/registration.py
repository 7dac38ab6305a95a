"""Registration check: do the photos' poses fit the point cloud?

A subsample of the cloud (:func:`sample_cloud`) is splatted into every photo's camera on the GPU
(the depth-map code of :mod:`dmrt.preprocess.depthmaps`: discs sized by the subsample's own
density, facing the camera) at a small check resolution. Per photo this gives

* **coverage**: the share of the photo's pixels the points cover;
* **points seen**: the sample points in its frame, in front, and not hidden behind other points;
* **agreement**: the correlation between the photo's brightness where the seen points project
  and the points' own brightness (their colours, or the scanner's return intensity);
* **edge contrast**: the photo's mean Sobel gradient at the points' depth edges (occlusion
  boundaries) over its mean on the other covered pixels.

Why agreement decides and edge contrast mostly informs (measured with the defaults on the tiny
synthetic scene, 12 photos, and on copies whose photos were moved 2 m along each camera axis, 36
photos): the edge ratio, a unitless number needing no edge-detector threshold, was the first
choice, but it does not separate the two. Aligned photos gave 0.74 to 1.67, moved ones 0.34 to
1.79: a laser scan seen from a photo's viewpoint has depth edges where the scan's own shadow
ends (half a column scanned from the other side) with no edge in the photo, and textured walls
have strong gradients everywhere; a chamfer distance to detected image edges suffers the same two
ways. The brightness correlation separates them cleanly: 0.88 to 0.97 aligned, -0.07 to 0.28
moved (the RGB-D kitchen: 0.62 to 0.81, and -0.53 to 0.34 with its 200 photos moved 2 m, all
flagged); it is invariant to each photo's exposure and white balance, and needs only what most
clouds carry. So a photo fails when it sees almost nothing, or when its agreement is below
:attr:`CheckConfig.min_agreement` (all 36 moved photos fail, none of the aligned). Only for a cloud with neither colour nor intensity does the edge contrast decide,
with a threshold below every aligned photo's (:attr:`CheckConfig.min_edge_contrast`): a weak test
(it flags 5 of the 25 moved photos that have enough depth edges). Either way the overlay of the
depth edges on each photo lets a person judge at a glance.

Also here: the coverage summary preprocessing prints from its candidates (:func:`coverage_summary`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from dmrt.camera import Camera
from dmrt.options import option, validate

# below these counts a photo's statistic is not trusted (too few to average): None, no verdict;
# and a photo that sees fewer than MIN_POINTS sample points sees almost nothing
_MIN_EDGE_PIXELS = 40
MIN_POINTS = 100
# a depth edge: a jump between neighbouring covered pixels of more than this share of the nearer
# depth (scale-free: one value suits a room and a street) ...
_EDGE_JUMP_RELATIVE = 0.1
# ... and of more than the suite's discontinuity threshold, metres (paper Section 5.1.2)
_EDGE_JUMP_MIN_M = 0.20
# pixels around a depth edge left out of the "elsewhere" mean (the Sobel kernel spreads a step
# over 3 pixels; one more for the splats' rounded silhouettes)
_EDGE_BAND_PX = 2
_GREY = np.array([0.299, 0.587, 0.114], np.float32)  # Rec. 601 luma


@dataclass
class CheckConfig:
    """How ``dmrt check`` tests a scene's registration."""

    sample_points: int = option(200_000, "points of the cloud splatted into every photo: an even stride through "
                                         "the file (enough to outline every surface at the check resolution)",
                                minimum=1000)
    width: int = option(320, "check resolution: photos and splatted points compared this many pixels wide",
                        minimum=32, maximum=4096)
    min_coverage: float = option(0.05, "a photo whose pixels the points cover less than this share sees almost "
                                       "nothing", minimum=0.0, maximum=1.0)
    # measured: aligned 0.88-0.97 (the kitchen 0.62-0.81), moved 2 m -0.07-0.28 (module docstring)
    min_agreement: float = option(0.5, "a photo whose brightness correlates less than this with the brightness "
                                       "(colour or intensity) of the points it sees does not line up",
                                  minimum=-1.0, maximum=1.0)
    # measured: aligned 0.74-1.67 (the kitchen 0.78-2.14), moved 0.34-1.79 (module docstring): clear misfits only
    min_edge_contrast: float = option(0.7, "for a cloud with neither colour nor intensity: a photo whose gradient "
                                           "at the points' depth edges is less than this multiple of its gradient "
                                           "elsewhere does not line up", minimum=0.0)

    def __post_init__(self):
        validate(self)


@dataclass
class PhotoCheck:
    """One photo's result.

    Attributes
    ----------
    name : the photo's image name.
    coverage : share of its pixels (at the check resolution) that the sample points cover, 0..1.
    points_seen : sample points it sees (in frame, in front, not occluded).
    points_share : ``points_seen`` / sample size.
    agreement : correlation of photo and point brightness over the points seen, -1..1; None
        without point brightness or with too few points seen.
    edge_pixels : depth-edge pixels found (occlusion boundaries between covered pixels).
    edge_contrast : photo gradient at the depth edges / elsewhere; None with too few edge pixels.
    problems : what failed, one short phrase each; empty when the photo passes.
    """

    name: str
    coverage: float
    points_seen: int
    points_share: float
    agreement: float | None
    edge_pixels: int
    edge_contrast: float | None
    problems: list[str] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        """``"ok"``, or the problems joined."""
        return "; ".join(self.problems) or "ok"


@dataclass
class Sample:
    """The subsample of the cloud the check uses.

    ``positions`` (m, 3) float64 world metres; ``brightness`` (m,) float32 (grey of the colours
    0..255, or the intensity as stored) or None; ``stride``: every stride-th point of the file;
    ``of``: the cloud's points; ``source``: ``"colour"``, ``"intensity"`` or None.
    """

    positions: np.ndarray
    brightness: np.ndarray | None
    stride: int
    of: int
    source: str | None


def sample_cloud(scene, n: int) -> Sample:
    """An even subsample of ``scene``'s cloud, at most ``n`` points: every ``ceil(n_points / n)``-th
    point in file order (a scanner writes its points sweep by sweep, so a stride thins them evenly), with its
    brightness: the colours' grey, else the intensity (E57), else None."""
    stride = max(1, -(-scene.n_points // int(n)))
    positions, colours, intensity, start = [], [], [], 0
    for pc in scene.iter_points():
        take = slice((-start) % stride, None, stride)  # this chunk's indices on the global stride
        positions.append(np.asarray(pc.positions[take], np.float64))
        colours.append(None if pc.colors is None else pc.colors[take].astype(np.float32) @ _GREY)
        intensity.append(None if pc.intensity is None else np.asarray(pc.intensity[take], np.float32))
        start += len(pc)
    brightness, source = None, None
    for name, parts in (("colour", colours), ("intensity", intensity)):
        if all(p is not None for p in parts):
            brightness, source = np.concatenate(parts), name
            break
    return Sample(np.concatenate(positions), brightness, stride, scene.n_points, source)


def depth_edges(depth: np.ndarray) -> np.ndarray:
    """(h, w) bool: covered pixels at an occlusion boundary, on its near side: a 4-neighbour is
    covered and deeper by more than :data:`_EDGE_JUMP_RELATIVE` of this depth and
    :data:`_EDGE_JUMP_MIN_M`. Boundaries with uncovered pixels are left out: those are as often
    gaps in the scan as silhouettes."""
    d = depth.astype(np.float64)
    edge = np.zeros(d.shape, bool)
    for a, b, ea, eb in ((d[:-1], d[1:], edge[:-1], edge[1:]), (d[:, :-1], d[:, 1:], edge[:, :-1], edge[:, 1:])):
        both = (a > 0) & (b > 0)
        gap = np.maximum(_EDGE_JUMP_MIN_M, _EDGE_JUMP_RELATIVE * np.minimum(a, b))
        ea |= both & (b - a > gap)  # views: marks ``edge`` in place
        eb |= both & (a - b > gap)
    return edge


def edge_contrast(grey: np.ndarray, edges: np.ndarray, covered: np.ndarray) -> float | None:
    """The photo's mean Sobel gradient magnitude at the depth edges over its mean on the covered
    pixels at least :data:`_EDGE_BAND_PX` from any edge; None with fewer than
    :data:`_MIN_EDGE_PIXELS` edge pixels or no such other pixel.

    Parameters
    ----------
    grey : (h, w) float32, the photo's brightness.
    edges : (h, w) bool, :func:`depth_edges`.  covered : (h, w) bool, pixels the points cover.
    """
    from scipy import ndimage

    if edges.sum() < _MIN_EDGE_PIXELS:
        return None
    rest = covered & ~ndimage.binary_dilation(edges, iterations=_EDGE_BAND_PX)
    if not rest.any():
        return None
    gradient = np.hypot(ndimage.sobel(grey, axis=0), ndimage.sobel(grey, axis=1))
    return float(gradient[edges].mean()) / max(float(gradient[rest].mean()), 1e-6)


def seen_points(camera: Camera, depth: np.ndarray, points: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(n,) bool: which ``points`` (n, 3), origin-relative metres, ``camera``'s depth map ``depth``
    ((h, w) float32 camera z, 0 = empty; the camera at any resolution) sees: in its frame, in
    front, and within two splat radii ``radii`` (n,) plus two texel footprints of the surface
    there (the discs were drawn with those radii; the footprint allows for sampling)."""
    h, w = depth.shape
    cam = camera.scaled(w, h)
    uv, z = cam.project(points)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    col = np.where(inside, uv[:, 0], 0).astype(np.int64)
    row = np.where(inside, uv[:, 1], 0).astype(np.int64)
    d = np.where(inside, depth[row, col], 0.0)
    return inside & (d > 0) & (np.abs(d - z) <= 2 * radii + 2 * z / cam.fx)


def agreement(camera: Camera, photo_grey: np.ndarray, points: np.ndarray, brightness: np.ndarray) -> float | None:
    """Pearson correlation of the photo's brightness at the projections of ``points`` (n, 3)
    (seen by ``camera``, at the photo's resolution) with their own ``brightness`` (n,); None with
    fewer than :data:`MIN_POINTS` points or no variation."""
    from dmrt.preprocess.candidates import sample_bilinear

    if len(points) < MIN_POINTS:
        return None
    uv, _ = camera.project(points)
    photo = sample_bilinear(photo_grey[..., None], uv)[:, 0]
    a, b = photo - photo.mean(), brightness - brightness.mean()
    norm = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum()) / norm if norm > 0 else None


def overlay(photo: np.ndarray, covered: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8: ``photo`` (same size) with the pixels no point covers darkened to a third
    and the depth edges drawn in magenta (a colour rare in photos)."""
    out = photo.astype(np.float32)
    out[~covered] *= 1 / 3
    out = out.astype(np.uint8)
    out[edges] = (255, 0, 255)
    return out


def check_photos(scene, sample: Sample, config: CheckConfig | None = None,
                 progress: bool = False) -> Iterator[tuple[PhotoCheck, np.ndarray, np.ndarray]]:
    """Check every photo of ``scene`` (a :class:`~dmrt.io.scene.Scene`) against ``sample``
    (:func:`sample_cloud`), on this process's GL context.

    Yields
    ------
    check : PhotoCheck, in photo order.
    overlay : (h, w, 3) uint8, the photo at the check resolution with the depth edges drawn
        (:func:`overlay`).
    seen : (m,) bool, the sample points this photo sees.
    """
    from PIL import Image

    from dmrt.gl import get_context
    from dmrt.preprocess.depthmaps import DepthMapConfig, DepthMapRenderer
    from dmrt.preprocess.normals import splat_radii

    config = config or CheckConfig()
    points = sample.positions - scene.origin
    # discs that close the gaps between sample points: the 8th neighbour's radius (normals.py)
    # times 1.5 for irregular sampling, as the renderer tests' proxies; zero normals face the camera
    radii = splat_radii(points, k=8, scale=1.5)
    chunk = (points.astype(np.float32), np.zeros((len(points), 3), np.float32), radii)
    cameras = [c.relative_to(scene.origin) for c in scene.cameras]
    renderer = DepthMapRenderer(get_context(), DepthMapConfig(width=config.width, chunk_points=len(points)))
    try:
        for j, depth in renderer.render_many(cameras, lambda: [chunk], progress=progress):
            full = scene.read_image(j)
            h, w = depth.shape
            photo = np.asarray(Image.fromarray(full).resize((w, h), Image.BOX))
            covered, edges = depth > 0, depth_edges(depth)
            seen = seen_points(cameras[j], depth, points, radii)
            agree = None
            if sample.brightness is not None:
                agree = agreement(cameras[j], full.astype(np.float32) @ _GREY, points[seen], sample.brightness[seen])
            n_seen = int(seen.sum())
            check = PhotoCheck(scene.cameras[j].name, float(covered.mean()), n_seen, n_seen / len(points), agree,
                               int(edges.sum()), edge_contrast(photo.astype(np.float32) @ _GREY, edges, covered))
            check.problems.extend(photo_problems(check, sample.source is not None, config))
            yield check, overlay(photo, covered, edges), seen
    finally:
        renderer.release()


def photo_problems(c: PhotoCheck, has_brightness: bool, config: CheckConfig) -> list[str]:
    """The verdict's rules (module docstring): what ``c`` fails, at most one phrase; the edge
    contrast counts only without point brightness (``has_brightness`` False)."""
    if c.coverage < config.min_coverage:
        return [f"sees almost nothing ({c.coverage:.1%} of its pixels covered, < {config.min_coverage:.0%})"]
    if c.points_seen < MIN_POINTS:  # its pixels covered by a few near discs: in or at a surface
        return [f"sees almost nothing ({c.points_seen} sample points, < {MIN_POINTS})"]
    if has_brightness:
        if c.agreement is not None and c.agreement < config.min_agreement:
            return [f"does not line up (brightness agreement {c.agreement:.2f} < {config.min_agreement})"]
    elif c.edge_contrast is not None and c.edge_contrast < config.min_edge_contrast:
        return [f"edges do not line up (edge contrast {c.edge_contrast:.2f} < {config.min_edge_contrast})"]
    return []


@dataclass
class Coverage:
    """Which proxies the photos see and which photos see proxies (from the candidates)."""

    proxies: int
    unseen_proxies: int  # proxies seen by no photo
    photos: int
    blind_photos: list[str]  # names of the photos that see no proxy

    # more than this share of proxies seen by no photo is worth a warning. Some are normal: scan
    # areas no photo shows, and candidates missed on noisy clouds (measured: the tiny synthetic
    # scene 24%, the RGB-D kitchen 29% though its cloud comes from the photos' own viewpoints).
    # Misplaced photos give more (the tiny scene's photos moved 2 m: 42%; an E57 whose photos see
    # none of the points: 100%), as do photos that cover a small part of the scan (nuScenes: 65%)
    WARN_UNSEEN = 0.4

    def line(self) -> str:
        """The one-line summary."""
        blind = len(self.blind_photos)
        names = f" ({', '.join(self.blind_photos[:3])}{', ...' if blind > 3 else ''})" if blind else ""
        return (f"coverage: {self.unseen_proxies} of {self.proxies} proxies ({self.unseen_share:.1%}) seen by no "
                f"photo; {blind} of {self.photos} photos see no proxy{names}")

    def counts(self) -> dict:
        """bundle.json's coverage counts."""
        return {"proxies_seen_by_no_photo": self.unseen_proxies, "photos_seeing_no_proxy": len(self.blind_photos)}

    @property
    def unseen_share(self) -> float:
        return self.unseen_proxies / max(self.proxies, 1)

    def warning(self) -> str | None:
        """A one-line warning when more than :attr:`WARN_UNSEEN` of the proxies are seen by no photo."""
        if self.unseen_share <= self.WARN_UNSEEN:
            return None
        return (f"warning: {self.unseen_share:.0%} of the proxies are seen by no photo (more than "
                f"{self.WARN_UNSEEN:.0%}): they stay untextured; check the registration with 'dmrt check SCENE'")


def coverage_summary(candidates, names: list[str]) -> Coverage:
    """:class:`Coverage` from a :class:`~dmrt.preprocess.labeling.Candidates` and the photos'
    names (in photo order)."""
    counts = np.diff(candidates.indptr)
    seeing = np.bincount(candidates.photos, minlength=len(names))
    return Coverage(len(counts), int((counts == 0).sum()), len(names), [n for n, k in zip(names, seeing) if k == 0])
