"""What every experiment of ``dmrt bench`` shares: presets, the work folder, result files.

    dmrt bench --preset ci --out results            # CPU, a few minutes
    dmrt bench --preset paper --out results --work /scratch/dmrt --only table2 fig7

One run generates the preset's synthetic scene, preprocesses it once (the *base* bundle, with as
many proxy levels as the proxy sweep needs), derives the other proxy sets from it (see
:func:`derive_proxy_bundle`) and runs the experiments of :mod:`bench.experiments`. Each writes
one JSON file, asv-style::

    RESULTS_DIR/<machine>/<commit>-<preset>/<experiment>.json   (+ <experiment>.npz for image maps)
    RESULTS_DIR/<machine>/machine.json

The work folder keeps the scene, the bundles and the Embree reference frames between runs (each
checked against the configuration that made it), so that the experiments of a preset can run in
several commands (``--only``) on a machine that limits a command's time.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dmrt.errors import InputError
from dmrt.io.atomic import atomic_dir, atomic_file, write_text

RESULTS_FORMAT = 1  # layout and common fields of a result file (each experiment has its own version)


# ----------------------------------------------------------------------------------------------
# Presets
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BenchPreset:
    """Everything a benchmark preset fixes; each experiment derives its parameters from it."""

    name: str
    # Synthetic scene: a preset of bench.scenes.synthetic.PRESETS and overrides of its SynthConfig.
    scene: str
    synth: dict = field(default_factory=dict)
    # Overrides of dmrt.preprocess.pipeline.PreprocessConfig for the base bundle (proxy_levels is set here).
    preprocess: dict = field(default_factory=dict)
    # Frames of the walkthroughs (the paper: 1280x720).
    frame_size: tuple[int, int] = (1280, 720)
    # Walkthrough: frames measured, key photo cameras it glides through, and Table 3's warm-up
    # frames rendered first and not measured (-1 = the whole path once: a photo cache in steady
    # state; the other experiments always render the whole path once first, reading it back).
    walkthrough_frames: int = 30
    walkthrough_keys: int = 12
    warmup_frames: int = -1
    # Table 2: layer counts and visibility paths (RenderConfig.method; the first is the default path,
    # used by every other experiment).
    layers: tuple[int, ...] = (1, 3, 5, 7, 9, 11)
    methods: tuple[str, ...] = ("tiles", "compute", "kbuffer", "raster")
    # and the same walkthrough at larger frames (4K: 3840x2160) with 5 layers, every path but the
    # paper's raster peeling (over half a second a frame at 4K)
    large_frames: tuple[tuple[int, int], ...] = ((3840, 2160),)
    # Fig. 7: proxy sets as numbers of coarsest octree levels (LOD k); the main bundle of every other
    # experiment uses main_proxy_levels (None: the preprocessing default, PreprocessConfig.proxy_factor).
    proxy_levels: tuple[int, ...] = (3, 4, 5)
    main_proxy_levels: int | None = None
    # Quality measurements at photo cameras (Figs. 7, 8, 13): how many photo cameras (spread over
    # the photos) and the frame width there (height: the photo's aspect).
    photo_cameras: int = 8
    quality_width: int = 1280
    # Fig. 7: layer counts tried to find the count a proxy set needs, and the fps measured per set.
    max_layers: int = 11
    fig7_fps_layers: tuple[int, ...] = (3, 4, 7)
    # Table 3 / Fig. 12: DMT depth-map widths, and the wall-clock seconds per width its graph cuts
    # (the paper's DMT labeling, on every core) may take: when all maps do not fit, a seeded random
    # subset is labelled and extrapolated, and the frame rates use each map's own photo as labels
    # (None: every map, however long).
    dmt_resolutions: tuple[int, ...] = (256, 512, 1024)
    dmt_budget_s: float | None = 120.0
    # DMT's labels where only frame rates and images matter (real views): "graphcut", "wta" or
    # "own" (winner-take-all / each map's own photo: seconds, for scenes where graph cuts take long).
    dmt_labeler: str = "graphcut"


PRESETS = {
    # CI on 2 CPU cores (Mesa llvmpipe): the tiny scene (the photos are 256x171, so depth maps too),
    # small frames, short walkthroughs. GPU timings are meaningless on llvmpipe but present.
    "ci": BenchPreset(
        name="ci", scene="tiny", preprocess={"depthmap_width": 256}, frame_size=(192, 128),
        walkthrough_frames=10, walkthrough_keys=6, warmup_frames=2, layers=(1, 3, 5),
        proxy_levels=(1, 2, 3), photo_cameras=4, quality_width=192, max_layers=5,
        fig7_fps_layers=(1, 3), dmt_resolutions=(64, 128, 256), methods=("tiles", "compute", "raster"),
        large_frames=((288, 192),)),
    "small": BenchPreset(
        name="small", scene="small", preprocess={"depthmap_width": 512}, frame_size=(640, 360),
        walkthrough_frames=20, warmup_frames=5, layers=(1, 3, 5, 7), proxy_levels=(2, 3, 4),
        photo_cameras=6, quality_width=512, max_layers=7, fig7_fps_layers=(3, 4),
        dmt_resolutions=(128, 256, 512)),
    # The paper's setting on a GPU: 32M points, 192 photos of 1024x684, 1280x720 frames. The scan
    # carries normals (their estimation, 4 of the 7 minutes of preprocessing, is measured by
    # bench/bench_preprocess.py); LOD 3/4/5 = 0.17M/0.71M/3.0M proxies (paper: 0.2M/1M/4.4M). DMT's
    # graph cuts on 192 maps (the paper: 7 / 23 / 87 min on one core) get 60 s per width on every
    # core, so that Table 3 stays within about 6 minutes on 16 cores: the 1024-wide maps are then a
    # subset, extrapolated. Real views render DMT with each map's own photo as labels.
    "paper": BenchPreset(
        name="paper", scene="paper", synth={"write_normals": True},
        preprocess={"depthmap_width": 1024, "memory_limit_mb": 16000}, dmt_budget_s=60.0, dmt_labeler="own"),
    # The paper's Scene 2 at its own size, for Table 1 (bench/scale_run.sh): 683M points, 192 photos
    # of 1024x684, on one GPU machine of 16 cores, 128 GB and a 64 GB disk. The octree spill and
    # the kNN buckets get 64 GB of memory, the depth maps keep the whole cloud (28 bytes a point,
    # 19 GB) on the GPU; LOD 4 is the ~1M proxies of the paper's Scene 2 (the coarse levels are
    # the `paper` preset's: the rooms are the same).
    "paper-full": BenchPreset(
        name="paper-full", scene="paper-full",
        preprocess={"depthmap_width": 1024, "memory_limit_mb": 64000, "resident_mb": 40000},
        proxy_levels=(4,), main_proxy_levels=4),
    # The same scene with its radii from the scanner's grid (dmrt/preprocess/scangrid.py: range x
    # angular step, no kNN; the PLY's normals kept): issue #40's >= 5M points/s is measured on it
    # (PRESET=paper-full-scan bench/scale_run.sh), beside paper-full's kNN radii.
    "paper-full-scan": BenchPreset(
        name="paper-full-scan", scene="paper-full",
        preprocess={"depthmap_width": 1024, "memory_limit_mb": 64000, "resident_mb": 40000, "radii": "scan"},
        proxy_levels=(4,), main_proxy_levels=4),
    # The paper's Scene 3 at its own size, for Table 1 (bench/scene3_run.sh): 1,092M points, 161
    # photos of 1024x684, on the same machine. The radii come from the scan's grid: the kNN path's
    # spill files (21 bytes a point and halos, 25 GB) do not fit a 64 GB disk beside the PLY and the
    # octree (bench/scenes/disk.py: 60.8 GB at the peak so, 88.9 with float normals and kNN radii).
    # Half paper-full's memory limit: the octree's select holds up to W + 1 buckets on disk twice,
    # 2.5 GB at 32 GB (and ~230 buckets of 4.8M points keep 16 cores busy); the depth maps keep
    # the cloud (28 bytes a point, 30.6 GB) on the GPU.
    "paper-scene3": BenchPreset(
        name="paper-scene3", scene="paper-scene3",
        preprocess={"depthmap_width": 1024, "memory_limit_mb": 32000, "resident_mb": 40000, "radii": "scan"},
        proxy_levels=(4,), main_proxy_levels=4),
    # paper-scene3's rooms and stations at 1/2000 of its points, 40 photos of 256x171 (two a room):
    # the CPU dry run of bench/scene3_run.sh (15 - 30 s on 2 shared cores)
    "paper-scene3-mini": BenchPreset(
        name="paper-scene3-mini", scene="paper-scene3",
        synth={"points": 546_000, "photos": 40, "photo_size": (256, 171)},
        preprocess={"depthmap_width": 256, "radii": "scan"}, proxy_levels=(4,), main_proxy_levels=4),
}


# ----------------------------------------------------------------------------------------------
# Machine and commit
# ----------------------------------------------------------------------------------------------
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """The machine a result was measured on: GL renderer and driver, CPU, cores, memory.

    ``name`` (the results folder) is the GL renderer string made path-safe, so runs on different
    hosts with the same GPU share a history.
    """
    from dmrt.gl import get_context, renderer_info

    gl = renderer_info(get_context())
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 30
    except (ValueError, OSError, AttributeError):
        mem = None
    name = re.sub(r"[^a-z0-9.]+", "-", gl["renderer"].lower()).strip("-")[:60] or "unknown-gl"
    return {"name": name, "gl_renderer": gl["renderer"], "gl_vendor": gl["vendor"], "gl_version": gl["version"],
            "gl_is_software": gl["is_software"], "cpu": _cpu_model(), "cpu_cores": os.cpu_count(),
            "memory_gib": round(mem, 1) if mem else None, "host": platform.node(),
            "platform": platform.platform(), "python": platform.python_version()}


def gpu_clocks() -> dict | None:
    """The NVIDIA GPU's current and maximum SM clock and memory clock in MHz (``nvidia-smi``), or
    None where there is no such tool. GPUs drop their clocks on light load (an H200 idles at 345
    MHz), so timed walkthroughs record the clocks they ran at."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=clocks.sm,clocks.max.sm,clocks.mem",
                              "--format=csv,noheader,nounits"], capture_output=True, text=True, timeout=10,
                             check=True).stdout.splitlines()[0]
        sm, sm_max, mem = (float(v) for v in out.split(","))
    except (OSError, subprocess.SubprocessError, IndexError, ValueError):
        return None
    return {"sm_mhz": sm, "sm_max_mhz": sm_max, "mem_mhz": mem}


def commit_info(repo: Path | None = None) -> dict:
    """``hash`` (12 hex digits, "unknown" outside a git checkout), ``date`` (commit time, ISO) and
    ``dirty`` (uncommitted changes to tracked files). ``DMRT_COMMIT`` in the environment overrides
    the hash (a copy of the tree without its git history, e.g. on a rented GPU machine)."""
    repo = repo or Path(__file__).resolve().parent.parent
    if os.environ.get("DMRT_COMMIT"):
        return {"hash": os.environ["DMRT_COMMIT"][:12], "date": None, "dirty": None}

    def git(*args):
        return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=30,
                              check=True).stdout.strip()

    try:
        return {"hash": git("rev-parse", "--short=12", "HEAD"), "date": git("show", "-s", "--format=%cI", "HEAD"),
                "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}
    except (OSError, subprocess.SubprocessError):
        return {"hash": "unknown", "date": None, "dirty": None}


def result_dir(out: Path, machine: dict, commit: dict, preset: str) -> Path:
    """``out/<machine>/<commit>-<preset>`` (asv's layout)."""
    return Path(out) / machine["name"] / f"{commit['hash']}-{preset}"


SCENE_MARK = "@"  # between the preset and a user's scene in a result set's label


def scene_name(preset: BenchPreset, scene=None) -> str | None:
    """The name a user's scene gives its result sets: its folder's name (characters other than
    letters, digits, ``.``, ``_`` and ``-`` as ``_``); None for the preset's own synthetic scene,
    generated or given with ``--scene`` (its ``synthetic.json`` names the preset's scene)."""
    if scene is None:
        return None
    try:
        if json.loads((Path(scene) / "synthetic.json").read_text())["config"]["name"] == preset.scene:
            return None
    except (OSError, ValueError, KeyError, TypeError):  # not one of the suite's synthetic scenes
        pass
    return re.sub(r"[^A-Za-z0-9._-]", "_", Path(scene).resolve().name) or "scene"


def result_label(preset: BenchPreset, scene=None) -> str:
    """The label of a result set (its folder: ``<commit>-<label>``): the preset's name, and for a
    user's scene ``<preset>@<scene name>`` (:func:`scene_name`), so that its results never mix
    with the synthetic scene's."""
    name = scene_name(preset, scene)
    return preset.name if name is None else f"{preset.name}{SCENE_MARK}{name}"


def write_json(path: Path, payload: dict) -> None:
    """Write JSON through a temporary file and a rename: a result file is whole or absent."""
    write_text(path, json.dumps(payload, indent=1, default=_json_default))


def _json_default(x):
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


# ----------------------------------------------------------------------------------------------
# The work folder: scene, bundles, reference frames
# ----------------------------------------------------------------------------------------------
def _bytes_under(path: Path) -> int:
    """Bytes of the files under ``path`` (0 where there is nothing)."""
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file() and not f.is_symlink())


def _stamp_ok(path: Path, stamp: dict) -> bool:
    try:
        return json.loads(path.read_text())["config"] == json.loads(json.dumps(stamp, default=_json_default))
    except (OSError, ValueError, KeyError):
        return False


def _config(cls, d: dict):
    """``cls(**d)`` keeping only ``cls``'s fields (a bundle.json may come from an older version)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in d.items() if k in names})


def derive_proxy_bundle(base: Path, levels: int, out: Path, progress: bool = False) -> Path:
    """A bundle like ``base`` whose proxies are the ``levels`` coarsest octree levels.

    The base bundle's proxies are LOD ``L`` = octree levels ``0 .. L-1`` concatenated in level order
    (:meth:`dmrt.preprocess.octree.Octree.read_lod`), so LOD ``levels <= L`` is their first ``lod_counts[levels-1]``
    rows. Steps 4-6 of preprocessing are redone for them by the function preprocessing calls
    (:func:`dmrt.preprocess.proxies.label_proxies`: splat radii from their own density, candidates
    from the base's depth maps, alpha-expansion labeling) and timed; depth maps and photos are
    shared through symbolic links. The proxy sweep costs one labeling per proxy set instead of one
    whole preprocessing.
    """
    from dmrt.io.bundle import PROXY_ARRAYS, read_bundle
    from dmrt.preprocess.config import PreprocessConfig
    from dmrt.preprocess.labeling import LabelingConfig
    from dmrt.preprocess.proxies import label_proxies, proxy_prefix

    src = read_bundle(base)
    meta = json.loads(json.dumps(src.meta))
    counts = meta["counts"]
    if levels == counts["proxy_levels"]:
        return Path(base)
    if not 1 <= levels < counts["proxy_levels"]:
        raise ValueError(f"{base}: proxies of {levels} levels cannot be derived from a bundle with "
                         f"{counts['proxy_levels']} (raise the preset's proxy levels)")
    if "hd_radii" not in src.proxy:
        raise InputError(Path(base) / "proxy.npz", "array 'hd_radii' missing (preprocess the scene again)")
    pcfg = _config(PreprocessConfig, meta["parameters"]["preprocess"])
    lcfg = _config(LabelingConfig, meta["parameters"]["labeling"])
    n = counts["lod_counts"][levels - 1]
    cams = [c.relative_to(src.origin) for c in src.cameras]
    proxies = label_proxies(proxy_prefix(src.proxy, n), cams, src.depth_map, src.image, pcfg, lcfg,
                            progress=progress)

    with atomic_dir(out) as tmp:
        for sub in sorted({Path(p).parts[0] for key in ("images", "images_low", "depthmaps") for p in meta[key]}):
            os.symlink(os.path.relpath(Path(base).resolve() / sub, Path(out).resolve()), tmp / sub)  # relative: movable
        proxy = {key: np.ascontiguousarray(proxies.proxy[key], dtype=dtype) for key, (dtype, _) in PROXY_ARRAYS.items()}
        np.savez(tmp / "proxy.npz", **{**proxies.proxy, **proxy})
        counts.update(proxies.counts(), proxy_levels=levels)
        meta["parameters"]["preprocess"]["proxy_levels"] = levels
        meta["timings"].update(proxies.timings)
        meta["labeling"] = proxies.labeling_meta()
        meta["derived_from"] = {"bundle": str(Path(base).resolve()), "created": src.meta.get("created"),
                                "redone": sorted(proxies.timings)}
        (tmp / "bundle.json").write_text(json.dumps(meta, indent=1, default=_json_default))
    return Path(out)


class Workspace:
    """The scene, bundles and reference frames of one preset in a work folder, made on demand.

    Parameters
    ----------
    preset : BenchPreset
    work : Path
        Folder for everything derived (reused by later runs when the configuration matches).
    scene : Path, optional
        Use this scene instead of generating the preset's synthetic one.
    progress : bool
        Progress bars (tqdm) for the long steps.
    check_disk : bool
        Refuse at once (:meth:`check_disk`) when the disk cannot hold what is still to be made.
    """

    def __init__(self, preset: BenchPreset, work: Path, scene: Path | None = None, progress: bool = True,
                 check_disk: bool = True):
        self.preset = preset
        self.work = Path(work)
        self.progress = progress
        self._scene_arg = Path(scene) if scene is not None else None
        self._bundles: dict = {}
        self._reference = None
        self.setup_s: dict = {}
        if check_disk:  # before any work: a run that cannot fit fails now, not after an hour
            self.check_disk()
        self.work.mkdir(parents=True, exist_ok=True)

    # -- disk ---------------------------------------------------------------------------------
    def disk_estimate(self, workers: int | None = None):
        """:class:`bench.scenes.disk.DiskEstimate` of the preset's synthetic scene and base bundle."""
        from bench.scenes.disk import estimate

        return estimate(self._synth_config(), self._base_config(), workers)

    def disk_needed(self) -> tuple[int, str]:
        """Bytes of free disk this workspace still needs, and for what: the estimate's peak, less
        the scene when it is made already (0 when the base bundle is made too), less what a stale
        scene or bundle holds (:meth:`scene_dir` and :meth:`base_bundle` delete them before
        remaking them). (0, "") for a user's scene (``--scene``): its size is not the preset's."""
        if self._scene_arg is not None or self._bundle_ready():
            return 0, ""
        estimate, scene_made = self.disk_estimate(), self._scene_ready()
        peak = estimate.peak[1] - (estimate.scene if scene_made else 0)
        stale = [self.work / "bundle-base"] + ([] if scene_made else [self.work / "scene"])
        what = "preprocessing" if scene_made else "scene and its preprocessing"
        return max(0, peak - sum(_bytes_under(p) for p in stale)), f"the {self.preset.name!r} preset's {what}"

    def check_disk(self) -> None:
        """Raise :class:`InputError` naming the work folder when its file system has less free
        space than :meth:`disk_needed`."""
        from bench.scenes.disk import check_free

        needed, what = self.disk_needed()
        if needed:
            check_free(needed, self.work, what)

    def _synth_config(self):
        from bench.scenes.synthetic import PRESETS as SYNTH

        return dataclasses.replace(SYNTH[self.preset.scene], **self.preset.synth)

    def _base_config(self):
        from dmrt.preprocess.pipeline import PreprocessConfig

        return PreprocessConfig(**{**self.preset.preprocess, "proxy_levels": self.base_levels})

    def _scene_wanted(self) -> dict:
        return {"synth": dataclasses.asdict(self._synth_config())}

    def _scene_ready(self) -> bool:
        return _stamp_ok(self.work / "scene.stamp.json", self._scene_wanted()) and (self.work / "scene").is_dir()

    def _base_wanted(self, scene: Path) -> dict:
        return {"scene": str(scene.resolve()), "preprocess": dataclasses.asdict(self._base_config()),
                "scene_stamp": self._file_text(self.work / "scene.stamp.json")}

    def _bundle_ready(self) -> bool:
        scene = self._scene_arg if self._scene_arg is not None else self.work / "scene"
        return (_stamp_ok(self.work / "bundle-base.stamp.json", self._base_wanted(scene))
                and (self.work / "bundle-base" / "bundle.json").is_file())

    # -- scene --------------------------------------------------------------------------------
    @property
    def scene_dir(self) -> Path:
        """The scene: the one given, else the preset's synthetic scene (generated on first use)."""
        if self._scene_arg is not None:
            if not (self._scene_arg / "sparse").exists() and not (self._scene_arg / "synthetic.json").exists():
                raise InputError(self._scene_arg, "not a scene directory (no sparse/ model)")
            return self._scene_arg
        from bench.scenes.synthetic import generate_scene

        config, wanted = self._synth_config(), self._scene_wanted()
        out, stamp = self.work / "scene", self.work / "scene.stamp.json"
        if not self._scene_ready():
            stamp.unlink(missing_ok=True)
            shutil.rmtree(out, ignore_errors=True)  # stale: the disk holds one scene at a time
            print(f"[bench] generating the {config.name!r} scene in {out}", flush=True)
            t0 = time.perf_counter()
            generate_scene(config, out, force=True, progress=self.progress)
            write_json(stamp, {"config": wanted, "seconds": round(time.perf_counter() - t0, 2)})
            shutil.rmtree(self.work / "reference", ignore_errors=True)
        self.setup_s["scene_generation"] = json.loads(stamp.read_text())["seconds"]
        return out

    # -- bundles ------------------------------------------------------------------------------
    @property
    def base_levels(self) -> int:
        """Proxy levels of the base bundle: the most any experiment uses."""
        main = (self.preset.main_proxy_levels,) if self.preset.main_proxy_levels else ()
        return max(self.preset.proxy_levels + main)

    def base_bundle(self) -> Path:
        """The preset's one full preprocessing (proxies: the finest level count any experiment uses)."""
        if "base" in self._bundles:
            return self._bundles["base"]
        from dmrt.preprocess.parallel import open_executor
        from dmrt.preprocess.pipeline import preprocess

        scene = self.scene_dir
        config, wanted = self._base_config(), self._base_wanted(scene)
        out, stamp = self.work / "bundle-base", self.work / "bundle-base.stamp.json"
        if not self._bundle_ready():
            stamp.unlink(missing_ok=True)
            shutil.rmtree(out, ignore_errors=True)  # stale: its bytes go before the new one's
            print(f"[bench] preprocessing {scene} -> {out} ({self.base_levels} proxy levels)", flush=True)
            t0 = time.perf_counter()
            with open_executor(None, workers=None) as executor:  # every core, as `dmrt preprocess`
                preprocess(scene, out, config, force=True, progress=self.progress, executor=executor)
            write_json(stamp, {"config": wanted, "seconds": round(time.perf_counter() - t0, 2)})
            shutil.rmtree(self.work / "reference", ignore_errors=True)  # representable masks: its depth maps
        self.setup_s["preprocess"] = json.loads(stamp.read_text())["seconds"]
        self._bundles["base"] = out
        return out

    @staticmethod
    def _file_text(path: Path) -> str | None:
        return path.read_text() if path.is_file() else None

    @property
    def main_levels(self) -> int:
        """Proxy levels of the main bundle: the preset's, else what ``dmrt preprocess`` would choose."""
        if self.preset.main_proxy_levels:
            return self.preset.main_proxy_levels
        from dmrt.preprocess.pipeline import PreprocessConfig, choose_proxy_levels

        counts = json.loads((self.base_bundle() / "bundle.json").read_text())["counts"]
        config = PreprocessConfig(**{k: v for k, v in self.preset.preprocess.items() if k != "proxy_levels"})
        k = choose_proxy_levels(counts["lod_counts"], counts["points"], config)
        if k > self.base_levels:
            raise ValueError(f"preset {self.preset.name!r}: the default proxy set has {k} levels, more than "
                             f"the base bundle's {self.base_levels}: add {k} to BenchPreset.proxy_levels")
        return k

    def bundle_path(self, levels: int | None = None) -> Path:
        """Bundle whose proxies are LOD ``levels`` (default: the main bundle)."""
        levels = levels or self.main_levels
        if levels in self._bundles:
            return self._bundles[levels]
        base = self.base_bundle()
        out = self.work / f"bundle-L{levels}"
        path = base if levels == self.base_levels else out
        if path is out:
            created = json.loads((base / "bundle.json").read_text()).get("created")
            try:
                meta = json.loads((out / "bundle.json").read_text())
                fresh = meta["derived_from"]["created"] == created and meta["counts"]["proxy_levels"] == levels
            except (OSError, ValueError, KeyError):
                fresh = False
            if not fresh:
                print(f"[bench] labeling the proxies of LOD {levels} -> {out}", flush=True)
                derive_proxy_bundle(base, levels, out, progress=self.progress)
        self._bundles[levels] = path
        return path

    def bundle(self, levels: int | None = None):
        """:class:`dmrt.io.bundle.Bundle` of :meth:`bundle_path` (read once)."""
        from dmrt.io.bundle import read_bundle

        key = ("read", levels or self.main_levels)
        if key not in self._bundles:
            self._bundles[key] = read_bundle(self.bundle_path(levels))
        return self._bundles[key]

    # -- cameras ------------------------------------------------------------------------------
    def photo_cameras(self, count: int | None = None) -> list:
        """``count`` photo cameras spread evenly over the photos (default: the preset's)."""
        cams = self.bundle().cameras
        count = min(count or self.preset.photo_cameras, len(cams))
        return [cams[i] for i in np.linspace(0, len(cams) - 1, count).round().astype(int)]

    # -- reference ----------------------------------------------------------------------------
    def reference(self, camera) -> dict:
        """Embree ground-truth frame of ``camera`` (its own size), cached in ``work/reference``.

        Returns
        -------
        dict
            ``depth``, ``label``, ``color``, ``normal`` (the frame contract) and ``representable``
            (h, w) bool: reference surface pixels that some depth map can show
            (:func:`representable_mask`).
        """
        path = self.work / "reference" / f"{Path(camera.name).stem}-{camera.width}x{camera.height}.npz"
        if path.is_file():
            with np.load(path) as z:
                return {k: z[k] for k in z.files}
        if self._reference is None:
            from dmrt.io.scene import load_scene
            from reference.render import EmbreeReference

            self._reference = EmbreeReference.from_scene(load_scene(self.scene_dir))
        frame = self._reference.render(camera, camera.width, camera.height)
        arrays = {k: frame[k] for k in ("depth", "label", "color", "normal")}
        arrays["representable"] = representable_mask(camera, arrays["depth"], self.bundle())
        with atomic_file(path) as tmp:
            np.savez_compressed(tmp, **arrays)
        return arrays


def representable_mask(camera, depth: np.ndarray, bundle, threshold: float = 0.20, slack: float = 0.01) -> np.ndarray:
    """(h, w) bool: reference surface pixels that some depth map holds on a continuous quad.

    What any DMRT frame can show at best: a surface point that no depth map holds within
    ``slack`` + 2 texels (unscanned, in every photo's occlusion shadow) or holds only on a quad whose
    texels differ by more than the discontinuity ``threshold`` (metres) is a hole by design, and
    the hole rate over these pixels is the one the layer count can bring down (Figs. 7, 13).

    Parameters
    ----------
    camera : Camera of the reference frame.  depth : (h, w) float32 reference camera z (0 = none).
    bundle : dmrt.io.bundle.Bundle (its depth maps and cameras).
    """
    dirs, center = camera.pixel_rays()
    sel = np.flatnonzero(depth.ravel() > 0)
    points = center + dirs[sel] * depth.ravel()[sel, None].astype(np.float64)
    found = np.zeros(len(points), bool)
    for j, cam in enumerate(bundle.cameras):
        rest = np.flatnonzero(~found)  # a point found once need not be projected again
        if rest.size == 0:
            break
        D = bundle.depth_map(j)
        h, w = D.shape
        c = cam.scaled(w, h)
        uv, z = c.project(points[rest])
        ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
        x = np.where(ok[:, None], uv, -10.0) - 0.5
        i0 = np.floor(x).astype(np.int64)
        ok &= (i0[:, 0] >= 0) & (i0[:, 1] >= 0) & (i0[:, 0] + 1 < w) & (i0[:, 1] + 1 < h)
        idx = np.flatnonzero(ok)
        i0, f, z = i0[idx], (x - np.floor(x))[idx], z[idx]
        q = np.stack([D[i0[:, 1], i0[:, 0]], D[i0[:, 1], i0[:, 0] + 1], D[i0[:, 1] + 1, i0[:, 0]],
                      D[i0[:, 1] + 1, i0[:, 0] + 1]], axis=1).astype(np.float64)
        good = (q > 0).all(1) & (q.max(1) - q.min(1) <= threshold)
        inv = 1.0 / np.where(q > 0, q, 1.0)  # bilinear in 1/z: exact for planes under perspective
        iz = ((inv[:, 0] * (1 - f[:, 0]) + inv[:, 1] * f[:, 0]) * (1 - f[:, 1])
              + (inv[:, 2] * (1 - f[:, 0]) + inv[:, 3] * f[:, 0]) * f[:, 1])
        good &= np.abs(1.0 / iz - z) <= slack + 2 * np.abs(z) / c.fx  # 2 texel footprints
        found[rest[idx[good]]] = True
    out = np.zeros(depth.size, bool)
    out[sel] = found
    return out.reshape(depth.shape)


# ----------------------------------------------------------------------------------------------
# Running
# ----------------------------------------------------------------------------------------------
def default_work(preset: str) -> Path:
    return Path(tempfile.gettempdir()) / "dmrt-bench" / preset


def main(argv=None) -> None:
    """``python -m bench.workspace PRESET WORK [--scene SCENE] [--dry-run [--json FILE]]``: make the
    preset's main bundle in the work folder (as ``dmrt bench`` does: scene, preprocessing, proxy
    set; kept between runs) and print its path (the GPU-machine scripts time renderers on it); with
    ``--dry-run``, generate and preprocess nothing: print the disk the preset takes
    (:mod:`bench.scenes.disk`), what the work folder still needs and has, and exit 2 when that is
    short, as the run would."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="python -m bench.workspace",
                                description="make a bench preset's main bundle in a work folder and print its path")
    p.add_argument("preset", choices=sorted(PRESETS))
    p.add_argument("work", type=Path)
    p.add_argument("--scene", type=Path, help="a scene made already (default: the preset's, generated)")
    p.add_argument("--dry-run", action="store_true", help="make nothing: print the disk estimate and check it")
    p.add_argument("--json", type=Path, help="with --dry-run: also write the estimate here as JSON")
    args = p.parse_args(argv)
    try:
        if args.dry_run:
            _dry_run(PRESETS[args.preset], args.work, args.scene, args.json)
            return
        path = Workspace(PRESETS[args.preset], args.work, scene=args.scene, progress=False).bundle_path()
    except InputError as exc:
        print(f"bench.workspace: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    print(path)


def _dry_run(preset: BenchPreset, work: Path, scene, json_path) -> None:
    from bench.scenes.disk import GB, free_bytes

    ws = Workspace(preset, work, scene, progress=False, check_disk=False)
    estimate = ws.disk_estimate()
    needed, what = ws.disk_needed()
    free = free_bytes(work)
    print("\n".join(estimate.lines()))
    print(f"{work}: needs {needed / GB:.2f} GB more ({what or 'nothing left to make'}), {free / GB:.2f} GB free")
    if json_path is not None:
        write_json(json_path, {"preset": preset.name, **estimate.to_json(), "needed_bytes": needed,
                               "free_bytes": free, "work": str(work)})
    ws.check_disk()


if __name__ == "__main__":
    main()
