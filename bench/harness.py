"""``dmrt bench``: run the experiments of a preset (:mod:`bench.experiments`) in a work folder
(:mod:`bench.workspace`) and write one result file per experiment.

    dmrt bench --preset ci --out results            # CPU, a few minutes
    dmrt bench --preset paper --out results --work /scratch/dmrt --only table2 fig7

One run generates the preset's synthetic scene, preprocesses it once (the *base* bundle, with as
many proxy levels as the proxy sweep needs), derives the other proxy sets from it
(:func:`bench.workspace.derive_proxy_bundle`) and runs the experiments. Each writes one JSON
file, asv-style::

    RESULTS_DIR/<machine>/<commit>-<preset>/<experiment>.json   (+ <experiment>.npz for image maps)
    RESULTS_DIR/<machine>/<commit>-<preset>@<scene>/...          the same for a user's scene (--scene)
    RESULTS_DIR/<machine>/machine.json

A user's scene has result sets of its own, named after its folder
(:func:`bench.workspace.result_label`): its
report carries its name and only the experiments run on it (:func:`bench.report.build_report`).

The work folder keeps the scene, the bundles and the Embree reference frames between runs (each
checked against the configuration that made it), so that the experiments of a preset can run in
several commands (``--only``) on a machine that limits a command's time.
"""

from __future__ import annotations

import dataclasses
import sys
import time
import traceback
from pathlib import Path

from bench.experiments import EXPERIMENTS, run_order
from bench.workspace import (PRESETS, RESULTS_FORMAT, BenchPreset, Workspace, commit_info, default_work,
                             machine_info, result_dir, result_label, scene_name, write_json)
from dmrt.errors import DMRTError


def run_bench(preset: str | BenchPreset, out, work=None, only=None, scene=None, progress: bool = True,
              machine_name: str | None = None, holdout_every: int | None = None,
              variants: list[str] | None = None) -> dict:
    """Run the experiments of ``preset`` and write their results under ``out``.

    Parameters
    ----------
    preset : name in :data:`PRESETS` or a BenchPreset
    out : results folder (``RESULTS_DIR``)
    work : work folder (default: ``$TMPDIR/dmrt-bench/<preset>``)
    only : experiment names to run (default: all)
    scene : an existing scene directory instead of the synthetic one (a user's scene: result sets
        of its own, :func:`bench.workspace.result_label`)
    machine_name : results folder name of the machine (default: from the GL renderer)
    holdout_every : the experiments that hold photos out (``real_views``) hold out photos 0, N,
        2N, ... (default: theirs, 8)
    variants : the experiments that compare renderer variants (``real_views``) run only these
        (names or patterns, e.g. ``dmrt*``; default: all)

    Returns
    -------
    dict
        ``dir`` (the result set's folder), ``written`` {experiment: path} and ``failed``
        {experiment: error}.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
        preset = PRESETS[preset]
    names = list(only) if only else run_order()
    if holdout_every is not None and holdout_every < 2:
        raise ValueError(f"--holdout-every {holdout_every}: must be >= 2 (1 would hold out every photo)")
    unknown = [n for n in names if n not in EXPERIMENTS]
    if unknown:
        raise ValueError(f"unknown experiment(s) {', '.join(unknown)} (choose from {', '.join(EXPERIMENTS)})")
    # the options an experiment takes when its parameters have the field; made before anything
    # runs, so that a bad value (its dataclass checks it) costs no experiment
    overrides = {k: v for k, v in (("holdout_every", holdout_every), ("variants", variants)) if v is not None}
    params_of = {}
    for name in names:
        params = EXPERIMENTS[name].params(preset)
        fields = {f.name for f in dataclasses.fields(params)}
        params_of[name] = dataclasses.replace(params, **{k: v for k, v in overrides.items() if k in fields})
    machine = machine_info()
    if machine_name:
        machine["name"] = machine_name
    commit = commit_info()
    rdir = result_dir(out, machine, commit, result_label(preset, scene))
    write_json(Path(out) / machine["name"] / "machine.json", machine)
    if machine["gl_is_software"]:
        print(f"[bench] note: {machine['gl_renderer']} is a software renderer: its GPU times do not measure the "
              f"work and are recorded as unavailable (NaN)", flush=True)
    name = scene_name(preset, scene)
    scene_info = None if name is None else {"name": name, "path": str(Path(scene).resolve())}
    ws = Workspace(preset, Path(work) if work else default_work(preset.name), scene, progress)
    status = {"dir": rdir, "written": {}, "failed": {}}
    t_all = time.perf_counter()
    for n, name in enumerate(names, 1):
        exp = EXPERIMENTS[name]
        params = params_of[name]
        print(f"[bench] {n}/{len(names)} {name}: {exp.title}", flush=True)
        t0 = time.perf_counter()
        (rdir / f"{name}.failed.json").unlink(missing_ok=True)
        try:
            measurements = exp.run(ws, params, rdir)
        except Exception as exc:  # one broken experiment must not cost the others' GPU time
            if not isinstance(exc, DMRTError):  # bad input is one line; anything else is a bug to read
                traceback.print_exc()
            print(f"[bench] {name}: FAILED: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
            status["failed"][name] = f"{type(exc).__name__}: {exc}"
            for stale in (rdir / f"{name}.json", rdir / f"{name}.npz"):  # an older result is no longer this commit's
                stale.unlink(missing_ok=True)
            write_json(rdir / f"{name}.failed.json", {"experiment": name, "error": status["failed"][name],
                                                      "traceback": traceback.format_exc()})
            continue
        seconds = time.perf_counter() - t0
        payload = {"experiment": name, "title": exp.title, "version": exp.version, "format": RESULTS_FORMAT,
                   "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "duration_s": round(seconds, 2),
                   "machine": machine, "commit": commit, "preset": preset.name, "scene": scene_info,
                   "preset_config": dataclasses.asdict(preset), "parameters": dataclasses.asdict(params),
                   "setup_s": dict(ws.setup_s), "measurements": measurements}
        path = rdir / f"{name}.json"
        write_json(path, payload)
        status["written"][name] = path
        print(f"[bench] {name}: done in {seconds:.1f} s -> {path}", flush=True)
    print(f"[bench] {len(status['written'])} written, {len(status['failed'])} failed in "
          f"{time.perf_counter() - t_all:.0f} s: {rdir}", flush=True)
    return status
