"""Proxy points P_LD (paper Section 4.2) and their labels: one function takes a proxy set through
radii, candidates and labeling, for preprocessing, the benchmark's derived proxy sets and the
viewer's proxy-set switch alike.

P_LD is the ``k`` coarsest octree levels. A bundle stores its proxies coarsest level first, so the
proxies of fewer levels are a prefix of its arrays (:func:`proxy_prefix`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dmrt.preprocess.candidates import find_candidates
from dmrt.preprocess.config import PreprocessConfig
from dmrt.preprocess.labeling import Candidates, LabelingConfig, LabelingResult, label_points
from dmrt.preprocess.normals import splat_radii


def choose_proxy_levels(lod_counts: list[int], n_points: int, config: PreprocessConfig) -> int:
    """Number of coarsest octree levels that form P_LD."""
    if config.proxy_levels is not None:
        return max(1, min(int(config.proxy_levels), len(lod_counts)))
    factor = n_points / config.proxy_count if config.proxy_count else config.proxy_factor
    # levels of detail grow ~4x apart on surfaces: take the nearest on a log scale
    error = [abs(np.log(n_points / count / factor)) for count in lod_counts]
    return int(np.argmin(error)) + 1


def proxy_prefix(proxy: dict, n: int) -> dict:
    """The first ``n`` proxies of every array of ``proxy`` (the LOD of fewer octree levels)."""
    return {name: np.asarray(a)[:n] for name, a in proxy.items()}


@dataclass
class ProxySet:
    """A labelled proxy set.

    ``proxy`` holds ``positions`` (n, 3) float32 origin-relative metres, ``normals`` (n, 3)
    float32, ``radii`` (n,) float32 metres (from the proxies' own density), ``hd_radii`` (n,)
    float32 (their P_HD radii, which drew the depth maps) and ``labels`` (n,) int32 (-1 = none).
    ``candidates`` and ``labeling`` are None when the labels were kept, not recomputed.
    """

    proxy: dict
    candidates: Candidates | None = None
    labeling: LabelingResult | None = None
    timings: dict = field(default_factory=dict)  # proxies_s, candidates_s, labeling_s (wall seconds)

    def counts(self) -> dict:
        """The bundle.json counts this proxy set determines."""
        out = {"proxies": len(self.proxy["positions"])}
        if self.candidates is not None:
            c = self.candidates.counts()
            out["candidates_mean"] = float(c.mean()) if len(c) else 0.0
        out["unlabeled_proxies"] = int((np.asarray(self.proxy["labels"]) < 0).sum())
        return out

    def labeling_meta(self) -> dict:
        """bundle.json's ``labeling`` record (energies per sweep, seconds, edges)."""
        r = self.labeling
        return {"energy_per_sweep": r.energy_per_sweep, "seconds_per_sweep": r.seconds_per_sweep,
                "data_energy": r.data_energy, "smooth_energy": r.smooth_energy, "edges": r.n_edges}


def label_proxies(proxy: dict, cameras, depth_maps, photos, config: PreprocessConfig | None = None,
                  labeling: LabelingConfig | None = None, relabel: bool = True,
                  progress: bool = False, executor=None, phase_done=None) -> ProxySet:
    """Steps 4-6 of preprocessing for one proxy set: radii, candidates, labels.

    Parameters
    ----------
    proxy : dict
        ``positions``, ``normals``, ``hd_radii`` as in :class:`ProxySet` (and ``labels`` when
        ``relabel`` is False).
    cameras : list of Camera, origin-relative, photo resolution.
    depth_maps : callable ``j -> (h, w) float32`` depth map of photo ``j``.
    photos : callable ``j -> (H, W, 3) uint8`` photo ``j``.
    relabel : bool
        False: only the splat radii are recomputed (a sparser set needs larger discs) and the
        labels are kept, as the viewer does for an interactive switch.
    executor : optional, :mod:`dmrt.preprocess.parallel`: runs the candidates' per-photo tests as
        tasks (``depth_maps`` and ``photos`` must then pickle); the labeling stays global, here.
    phase_done : callable, optional: called with ``"proxies_s"``, ``"candidates_s"`` and
        ``"labeling_s"`` as each step ends (preprocessing records each step's memory and CPU time).
    """
    phase_done = phase_done or (lambda name: None)
    config = config or PreprocessConfig()
    proxy = dict(proxy)
    out = ProxySet(proxy)
    t0 = time.perf_counter()
    proxy["positions"] = np.asarray(proxy["positions"], np.float32)
    proxy["normals"] = np.asarray(proxy["normals"], np.float32)
    proxy["radii"] = splat_radii(proxy["positions"], k=config.radius_k, scale=config.radius_scale)
    out.timings["proxies_s"] = round(time.perf_counter() - t0, 3)
    phase_done("proxies_s")
    if not relabel:
        return out
    t0 = time.perf_counter()
    out.candidates = find_candidates(proxy["positions"], proxy["normals"], np.asarray(proxy["hd_radii"], np.float32),
                                     cameras, depth_maps, photos, config, progress, radii=proxy["radii"],
                                     executor=executor)
    out.timings["candidates_s"] = round(time.perf_counter() - t0, 3)
    phase_done("candidates_s")
    t0 = time.perf_counter()
    out.labeling = label_points(proxy["positions"], proxy["normals"], out.candidates, cameras,
                                config=labeling or LabelingConfig(), progress=progress)
    out.timings["labeling_s"] = round(time.perf_counter() - t0, 3)
    phase_done("labeling_s")
    proxy["labels"] = out.labeling.labels
    return out
