"""The benchmark report: ``dmrt report RESULTS_DIR --out reports/<name>/``.

Built only from the result files of :mod:`bench.harness` (``<machine>/<commit>-<preset>/*.json``
and the ``.npz`` image maps beside them), asv-style. The newest result set gives the tables and the
report's commit. An experiment that set lacks (neither a result nor a failure there: a run of some
experiments only, ``dmrt bench --only``) is *carried*: its result comes from the newest older set of
the same machine and preset that has one, and the header and its section name that set's commit and
date (:func:`carry_forward`). A failure in the newest set stays a failure. All sets of the same
machine and preset give the history plot. Output::

    OUT/index.html   OUT/REPORT.md   the same tables (numbers formatted once, by fmt) and figures
    OUT/figures/*.png                matplotlib figures
    OUT/csv/*.csv                    every table, raw numbers
    OUT/results/*.json               the result files the report was built from (carried ones too)

The report is assembled in ``OUT.partial`` and renamed: an interrupted build never leaves a
report that looks whole. An experiment with a result neither in the newest set nor in an older one
shows as "not run", one that failed in the newest set as "FAILED", and the report's first line then
says INCOMPLETE; :func:`missing_experiments` is the completeness check (``dmrt report --check``):
carried experiments count as run.
"""

from __future__ import annotations

import html
import re
import json
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from bench import paper  # noqa: E402
from bench.experiments import EXPERIMENTS, required_experiments  # noqa: E402
from bench.workspace import SCENE_MARK  # noqa: E402
from dmrt.errors import InputError  # noqa: E402
from dmrt.io.atomic import atomic_dir  # noqa: E402

# The experiments a complete report needs (the CI and nightly completeness check), and every
# experiment the report has a section for, in the report's order: both from the one registry.
REQUIRED_EXPERIMENTS = required_experiments()
SECTIONS = list(EXPERIMENTS)


# ----------------------------------------------------------------------------------------------
# Reading results
# ----------------------------------------------------------------------------------------------
@dataclass
class ResultSet:
    """The result files of one machine, commit and preset (one folder), and the results carried
    into it from older sets of the same machine and preset (:func:`carry_forward`)."""

    dir: Path
    machine: str
    commit: str
    preset: str
    experiments: dict = field(default_factory=dict)  # name -> result payload (carried ones included)
    failed: dict = field(default_factory=dict)       # name -> error message
    carried: dict = field(default_factory=dict)      # name -> the older ResultSet its result comes from

    def source(self, name: str) -> ResultSet:
        """The result set whose folder holds experiment ``name``'s files: an older one when carried."""
        return self.carried.get(name, self)

    def _own(self) -> list[dict]:
        return [p for name, p in self.experiments.items() if name not in self.carried]

    @property
    def date(self) -> str:
        """The newest own (not carried) result's date (ISO), '' when none."""
        return max((p.get("date") or "" for p in self._own()), default="")

    @property
    def info(self) -> dict:
        """Machine and commit of the newest own (not carried) result."""
        newest = max(self._own(), key=lambda p: p.get("date") or "", default={})
        return {"machine": newest.get("machine", {}), "commit": newest.get("commit", {})}


def read_result(path: Path) -> dict:
    """One result file, checked: a clear :class:`InputError` naming the file otherwise."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise InputError(path, f"cannot read result file ({exc})") from exc
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc}): truncated by an interrupted run? "
                               f"Delete it or run the experiment again") from exc
    if not isinstance(data, dict):
        raise InputError(path, "not a result file (expected a JSON object)")
    for key in ("experiment", "version", "measurements"):
        if key not in data:
            raise InputError(path, f"not a result file: field '{key}' missing")
    return data


def load_results(results_dir) -> list[ResultSet]:
    """Every result set under ``results_dir`` (``<machine>/<commit>-<preset>/``), oldest first."""
    root = Path(results_dir)
    if not root.is_dir():
        raise InputError(root, "results directory not found")
    sets = []
    for mdir in sorted(p for p in root.iterdir() if p.is_dir()):
        for sdir in sorted(p for p in mdir.iterdir() if p.is_dir()):
            files = sorted(sdir.glob("*.json"))
            if not files:
                continue
            # a commit hash has no "-", a preset name may (paper-full)
            commit, _, preset = sdir.name.partition("-")
            if not preset:  # not <commit>-<preset>: e.g. the results/ of a report kept beside them
                continue
            rs = ResultSet(sdir, mdir.name, commit, preset)
            for f in files:
                if f.name.endswith(".failed.json"):
                    try:
                        rs.failed[f.name[: -len(".failed.json")]] = json.loads(f.read_text()).get("error", "?")
                    except (OSError, json.JSONDecodeError):
                        rs.failed[f.name[: -len(".failed.json")]] = "(unreadable failure record)"
                    continue
                data = read_result(f)
                rs.experiments[data["experiment"]] = data
            if rs.experiments or rs.failed:
                sets.append(rs)
    if not sets:
        raise InputError(root, "no result files (<machine>/<commit>-<preset>/<experiment>.json) found")
    return sorted(sets, key=lambda s: s.date)


def carry_forward(rs: ResultSet, older: list[ResultSet], names=None) -> ResultSet:
    """``rs`` completed from ``older`` (result sets of the same machine and preset, oldest first): each
    experiment of ``names`` (default: every section's) that ``rs`` has neither a result nor a failure
    of takes the result of the newest set of ``older`` that has one, recorded in ``carried``. A failure
    in ``rs`` is kept (the new commit broke it). A new ResultSet: ``rs`` itself is not changed (the
    history plot reads it as it is)."""
    out = ResultSet(rs.dir, rs.machine, rs.commit, rs.preset, dict(rs.experiments), dict(rs.failed), dict(rs.carried))
    for name in (SECTIONS if names is None else names):
        if name in out.experiments or name in out.failed:
            continue
        src = next((s for s in reversed(older) if name in s.experiments and name not in s.carried), None)
        if src is not None:
            out.experiments[name] = src.experiments[name]
            out.carried[name] = src
    return out


def missing_experiments(rs: ResultSet, required=None) -> list[str]:
    """Required experiments neither run nor failed in ``rs`` (carried ones count as run; see
    ``rs.failed`` for the failed ones)."""
    return [name for name in (REQUIRED_EXPERIMENTS if required is None else required)
            if name not in rs.experiments and name not in rs.failed]


# ----------------------------------------------------------------------------------------------
# Document model: sections of text, tables and figures, rendered to Markdown and HTML
# ----------------------------------------------------------------------------------------------
def fmt(v) -> str:
    """The one number format of the report (Markdown and HTML alike): 4 significant digits; "n/a"
    for no value: None, or NaN (a time that was not measured, e.g. a GPU time on a software
    renderer: dmrt.gl.timer; and every empty cell of a table: pandas reads a missing value as NaN)."""
    if v is None:
        return "n/a"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if math.isnan(v):
            return "n/a"
        if math.isinf(v):
            return "∞" if v > 0 else "-∞"
        return f"{v:.4g}"
    return str(v)


@dataclass
class Table:
    name: str          # file stem of the CSV
    caption: str
    df: pd.DataFrame   # raw values; percentages as numbers with "%" in the column name


@dataclass
class Section:
    key: str
    title: str
    blocks: list = field(default_factory=list)  # str (paragraph) | Table | ("figure", file, caption)

    def text(self, s: str) -> None:
        self.blocks.append(s)

    def table(self, name: str, caption: str, rows) -> None:
        self.blocks.append(Table(name, caption, pd.DataFrame(rows)))

    def figure(self, file: str, caption: str) -> None:
        self.blocks.append(("figure", file, caption))


def _cells(df: pd.DataFrame) -> tuple[list[str], list[list[str]]]:
    return [str(c) for c in df.columns], [[fmt(v) for v in row] for row in df.itertuples(index=False)]


def render_markdown(title: str, header: list[str], sections: list[Section]) -> str:
    out = [f"# {title}", ""]
    for h in header:
        out += [h, ""]
    for s in sections:
        out += [f"## {s.title}", ""]
        for b in s.blocks:
            if isinstance(b, str):
                out += [b, ""]
            elif isinstance(b, Table):
                cols, rows = _cells(b.df)
                out += [f"**{b.caption}** ([csv](csv/{b.name}.csv))", "",
                        "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
                out += ["| " + " | ".join(r) + " |" for r in rows]
                out.append("")
            else:
                out += [f"![{b[2]}](figures/{b[1]})", "", f"*{b[2]}*", ""]
    return "\n".join(out)


_CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em;font-size:90%}td,th{border:1px solid #ccc;padding:3px 8px;
text-align:right}th{background:#f3f3f3}td:first-child{text-align:left}img{max-width:100%;border:1px solid #ddd}
.bad{background:#fde2e2;padding:.5em 1em;border-left:4px solid #c00}.carried{background:#fff4d6;padding:.5em 1em;
border-left:4px solid #c90}.ok{background:#e6f4e6;padding:.5em 1em;
border-left:4px solid #080}figure{margin:0 0 2em}figcaption{font-style:italic;color:#555}"""


def render_html(title: str, header: list[str], sections: list[Section]) -> str:
    def para(s: str) -> str:
        cls = ' class="bad"' if s.startswith(("**INCOMPLETE", "**Not run", "**FAILED", "**Note")) else (
            ' class="ok"' if s.startswith("**Complete") else ' class="carried"' if s.startswith("**Carried") else "")
        body = html.escape(s).replace("\n", "<br>")
        # the Markdown emphasis used in paragraphs: **bold** and `code`
        body = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", body)
        body = re.sub(r"`(.+?)`", r"<code>\1</code>", body)
        return f"<p{cls}>{body}</p>"

    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
           f"<style>{_CSS}</style></head><body>", f"<h1>{html.escape(title)}</h1>"]
    out += [para(h) for h in header if h]
    out.append("<ul>" + "".join(f"<li><a href='#{s.key}'>{html.escape(s.title)}</a></li>" for s in sections) + "</ul>")
    for s in sections:
        out.append(f"<h2 id='{s.key}'>{html.escape(s.title)}</h2>")
        for b in s.blocks:
            if isinstance(b, str):
                out.append(para(b))
            elif isinstance(b, Table):
                cols, rows = _cells(b.df)
                out.append(f"<p><b>{html.escape(b.caption)}</b> (<a href='csv/{b.name}.csv'>csv</a>)</p><table><tr>"
                           + "".join(f"<th>{html.escape(c)}</th>" for c in cols) + "</tr>"
                           + "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
                           + "</table>")
            else:
                out.append(f"<figure><img src='figures/{b[1]}' alt='{html.escape(b[2])}'>"
                           f"<figcaption>{html.escape(b[2])}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out)


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------
def _ratio(a, b):
    try:
        return float(a) / float(b) if b not in (None, 0) and a is not None else None
    except (TypeError, ValueError):
        return None


def _pct(x):
    return None if x is None else 100.0 * float(x)


def _save(fig, out: Path, name: str) -> str:
    fig.tight_layout()
    fig.savefig(out / "figures" / name, dpi=110)
    plt.close(fig)
    return name


def _meas(rs: ResultSet, name: str) -> dict | None:
    p = rs.experiments.get(name)
    return None if p is None else p["measurements"]


# figures drawn from the .npz image maps, which reports/history does not keep (JSON only)
REAL_VIEWS_CAPTION = ("Held-out photos, the renders at their cameras and the data's bounds (black: no surface or no "
                      "photo), each with its FLIP error map beneath (0 = no perceived difference, 1 = most)")
MAP_FIGURES = {"fig8": "fig8_heatmaps.png", "fig13": "fig13_holes.png", "real_views": "real_views.png"}


def _maps(rs: ResultSet, name: str) -> dict | None:
    """The image maps of experiment ``name`` (its .npz beside the JSON, in the folder of the set it
    comes from when carried); None when the file is not there (a result set rebuilt from
    reports/history), an error when it is unreadable."""
    path = rs.source(name).dir / _meas(rs, name)["maps_file"]
    if not path.exists():
        return None
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read the maps of {name}.json ({exc})") from exc


def _kept_figure(s: Section, out: Path, name: str, caption: str) -> Section:
    """Without the maps: the figure as the previous build of this report drew it from the same
    result set's maps (build_report keeps it), said so in the caption."""
    if (out / "figures" / MAP_FIGURES[name]).is_file():
        s.figure(MAP_FIGURES[name], f"{caption} (drawn by an earlier build of this report: the image maps of "
                                    f"this result set are not in the results folder)")
    else:
        s.text(f"No figure: {name}'s image maps (.npz) are not in the results folder.")
    return s


def _not_run(rs: ResultSet, s: Section, name: str) -> bool:
    """Write the not-run / failed notice into ``s``; True when there is no result to show."""
    if name in rs.experiments:
        return False
    if name in rs.failed:
        s.text(f"**FAILED**: `{name}` raised {rs.failed[name]} (see {name}.failed.json in the results).")
    else:
        s.text(f"**Not run**: no `{name}.json` in {rs.dir.name}.")
    return True


# ----------------------------------------------------------------------------------------------
# Sections
# ----------------------------------------------------------------------------------------------
def section_table1(rs: ResultSet, out: Path, key: str = "table1",
                   title: str = "Table 1: scene characteristics and preprocessing",
                   paper_scene: str = "Scene 2") -> Section:
    """Table 1 of ``rs`` beside the paper's ``paper_scene`` (a key of ``paper.TABLE1``: the paper
    gives Scene 3's points and photos only, so its other rows stay empty)."""
    s = Section(key, title)
    if _not_run(rs, s, "table1"):
        return s
    m = _meas(rs, "table1")
    c, p2, col = m["counts"], paper.TABLE1[paper_scene], f"paper ({paper_scene})"
    sub = c["points"] / max(c["proxies"], 1)
    size = p2.get("depthmap_size")
    rows = [{"quantity": q, "ours": c[q], col: p2.get(q), "ours / paper": _ratio(c[q], p2.get(q))}
            for q in ("points", "photos", "proxies")]
    rows += [
        {"quantity": "sub-sampling factor", "ours": sub, col: p2.get("subsampling_factor"),
         "ours / paper": _ratio(sub, p2.get("subsampling_factor"))},
        {"quantity": "proxy levels (LOD k)", "ours": c["proxy_levels"], col: None, "ours / paper": None},
        {"quantity": "depth-map size", "ours": "x".join(map(str, m["depthmap_size"])),
         col: size and "x".join(map(str, size)), "ours / paper": None},
        {"quantity": "photo size", "ours": "x".join(map(str, m["photo_size"])), col: None,
         "ours / paper": None},
    ]
    s.table(f"{key}_scene", "Scene characteristics (paper Table 1)", rows)
    phases = [{"phase": k.removesuffix("_s"), "seconds": v} for k, v in m["phases_s"].items()]
    phases.append({"phase": "total (these phases)", "seconds": m["preprocess_total_s"]})
    if m.get("bundle_total_s") is not None:
        phases.append({"phase": "the whole preprocessing (scene loading and bundle writing included)",
                       "seconds": m["bundle_total_s"]})
    if m.get("scene_generation_s") is not None:
        phases.append({"phase": "scene generation (not preprocessing)", "seconds": m["scene_generation_s"]})
    s.table(f"{key}_preprocessing", "Preprocessing wall-clock seconds per phase", phases)
    cpu, anon = m.get("cpu_s_per_phase"), m.get("peak_anon_mb") or {}
    if cpu:  # CPU seconds are kept per phase as bundle.json groups them (proxies to labeling: one)
        wall = dict(m["phases_s"], proxies_candidates_labeling_s=sum(
            m["phases_s"].get(k) or 0.0 for k in ("proxies_s", "candidates_s", "labeling_s")))
        rows = [{"phase": k.removesuffix("_s"), "wall s": wall.get(k), "CPU s (workers included)": v,
                 "cores busy": v / wall[k] if wall.get(k) else None,
                 "peak anonymous MiB": anon.get(k, anon.get("labeling_s"))} for k, v in cpu.items()]
        s.table(f"{key}_cpu", f"CPU and memory per phase ({m.get('cores')} cores; "
                              f"{c['points'] / m['preprocess_total_s'] / 1e6:.2f}M points per second)", rows)
    if m.get("derived_from_base"):
        s.text("The proxies, candidates and labeling phases were run for this proxy set on the depth maps of "
               "the preset's one preprocessing (bench.harness.derive_proxy_bundle), exactly as `dmrt preprocess` "
               "runs them; the other phases are that preprocessing's.")
    return s


def _table2_runs(m: dict) -> dict:
    return {(r["method"], r["layers"]): r for r in m["runs"]}


def _gpu_ms(r: dict) -> tuple[dict, float]:
    """A Table 2 run's GPU ms per stage and total: the medians of its sustained timed pass (frames
    back to back, clocks warm: bench.experiments.measure_walkthrough), else, in runs made before
    that pass existed, of its timed pass."""
    st = r.get("sustained_timed")
    if st:
        return st["median_ms"], st["median_total_ms"]
    return r["median_ms"], r["median_total_ms"]


def section_table2(rs: ResultSet, out: Path) -> Section:
    s = Section("table2", "Table 2: GPU milliseconds per stage (walkthrough medians, frames back to back)")
    if _not_run(rs, s, "table2"):
        return s
    m = _meas(rs, "table2")
    runs = _table2_runs(m)
    layers = sorted({k for _, k in runs})
    methods = list(dict.fromkeys(mm for mm, _ in runs))  # the run's order: its default path first
    stages = list(next(iter(runs.values()))["median_ms"])
    p = paper.TABLE2
    for method in methods:
        rows = []
        for st in stages + ["total", "fps"]:
            row = {"stage": st}
            for k in layers:
                r = runs.get((method, k))
                ms, total = _gpu_ms(r) if r is not None else ({}, None)
                if r is None:
                    val = None
                elif st == "total":
                    val = total
                elif st == "fps":
                    val = 1e3 / total if total else None
                else:
                    val = ms.get(st, 0.0)
                row[f"{k} ours"] = val
                pk = paper.TABLE2_LAYERS.index(k) if k in paper.TABLE2_LAYERS else None
                row[f"{k} paper"] = p[st][pk] if (pk is not None and st in p) else None
            rows.append(row)
        s.table(f"table2_{method}", f"{method} visibility: GPU ms per stage, medians over the walkthrough rendered "
                                    f"back to back with warm clocks (fps = 1000 / median total), columns by "
                                    f"layer count, paper's GTX TITAN numbers beside ours", rows)
    ratio_rows = []
    main = methods[0]
    for k in layers:
        d = runs.get((main, k))
        pk = paper.TABLE2_LAYERS.index(k) if k in paper.TABLE2_LAYERS else None
        pt = p["total"][pk] if pk is not None else None
        ratio_rows.append({
            "layers": k, **{f"total {mm} (ms)": _gpu_ms(runs[(mm, k)])[1] if (mm, k) in runs else None
                            for mm in methods},
            "total paper (ms)": pt, f"{main} / paper total": _ratio(d and _gpu_ms(d)[1], pt),
            **{f"visibility {pair}": v.get(str(k)) for pair, v in m["visibility_ratios"].items()},
            f"fps {main} (min/avg/max, frames timed one by one)": "/".join(fmt(x) for x in d["fps_min_avg_max"]) if d else None,
            "fps paper": p["fps"][pk] if pk is not None else None,
            "mean search steps": d and d["mean_iterations"],
            "p95 total (ms)": d and (d.get("sustained_timed") or d).get("p95_total_ms"),
            "median total ms, frames timed one by one": d and d["median_total_ms"],
            "median / p95 wall ms (render call)": d and "/".join(fmt(x) for x in (d["median_wall_ms"],
                                                                                  d.get("p95_wall_ms"))),
            "frame": d and "x".join(map(str, d.get("frame_size", []))) or None,
            "sustained ms/frame (back to back)": d and d.get("sustained_ms"),
            "SM clock MHz (after)": d and ((d.get("gpu_clocks") or {}).get("after") or {}).get("sm_mhz")})
    s.table("table2_ratios", f"Ratios: ours ({main} visibility, the default) vs paper; visibility stage of the "
                             f"paper's peeling by rasterization (raster) vs peeling by compute splatting (compute) "
                             f"vs the one-pass k-buffer (kbuffer)", ratio_rows)
    large_rows = []
    for r in m.get("large_runs", []):
        base = runs.get((r["method"], r["layers"]))
        large_rows.append({
            "frame": "x".join(map(str, r["frame_size"])), "method": r["method"], "layers": r["layers"],
            **{st: _gpu_ms(r)[0].get(st, 0.0) for st in stages}, "total (ms)": _gpu_ms(r)[1],
            "p95 total (ms)": (r.get("sustained_timed") or r).get("p95_total_ms"),
            "median total ms, frames timed one by one": r["median_total_ms"],
            "sustained ms/frame (back to back)": r.get("sustained_ms"),
            "median wall ms (render call)": r.get("median_wall_ms"),
            "total / same path at " + ("x".join(map(str, base["frame_size"])) if base else "the main size"):
                _ratio(_gpu_ms(r)[1], base and _gpu_ms(base)[1]),
            "SM clock MHz (after)": ((r.get("gpu_clocks") or {}).get("after") or {}).get("sm_mhz")})
    if large_rows:
        s.table("table2_large", "Larger frames: the same walkthrough resized, GPU ms per stage (medians, frames back "
                                "to back) and the sustained wall ms per frame; the paper has no such rows", large_rows)

    # stacked bars: one bar per (layer count, source)
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(layers) * (len(methods) + 1)), 4.2))
    colors = plt.cm.tab10.colors
    x, labels = 0, []
    for k in layers:
        bars = [(f"{mm}", runs.get((mm, k)) and _gpu_ms(runs[(mm, k)])[0]) for mm in methods]
        if k in paper.TABLE2_LAYERS:
            pk = paper.TABLE2_LAYERS.index(k)
            bars.append(("paper", {st: p[st][pk] for st in ("visibility", "raytracing", "labeling",
                                                            "image_management", "texturing")}))
        for name, ms in bars:
            bottom = 0.0
            for i, st in enumerate(stages):
                v = (ms or {}).get(st, 0.0)
                ax.bar(x, v, bottom=bottom, color=colors[i % 10], label=st if x == 0 else None)
                bottom += v
            labels.append((x, f"{name}\nk={k}"))
            x += 1
        x += 0.6
    ax.set_xticks([a for a, _ in labels], [b for _, b in labels], fontsize=7)
    ax.set_ylabel("GPU ms per frame (median)")
    ax.legend(fontsize=7, ncol=3)
    ax.set_title("Table 2: per-stage GPU time, ours (compute / raster visibility) vs paper")
    s.figure(_save(fig, out, "table2_stages.png"), "Per-stage GPU ms per layer count (stacked), ours and the paper's")
    return s


def _dmt_labeling_cells(e: dict, pp: dict | None) -> dict:
    """The labeling columns of one DMT row (results of version 1 have ``seconds`` and one ratio)."""
    lab = e["labeling"]
    ratio = e.get("labeling_ratio_dmt_over_dmrt")
    ratio = ratio if isinstance(ratio, dict) else {"wall": ratio, "cpu": None}
    per_map = lab.get("cpu_s_per_map") or {}
    return {"maps labelled": f"{lab['maps']} of {lab['maps_total']}" if "maps" in lab else None,
            "labeling wall (s)": lab.get("wall_s_all", lab.get("seconds")), "labeling CPU (s)": lab.get("cpu_s_all"),
            "CPU s per map median/p10/p90": "/".join(fmt(per_map[k]) for k in ("median", "p10", "p90"))
            if per_map else None,
            "paper labeling (s)": pp and pp["labeling_s"],
            "CPU DMT / DMRT": ratio.get("cpu"), "wall DMT / DMRT": ratio.get("wall"),
            "paper DMT / DMRT": pp and _ratio(pp["labeling_s"], paper.TABLE3_DMRT["labeling_s"])}


def _dmt_notes(d: dict, e: dict) -> list[str]:
    lab = e["labeling"]
    labeler = lab.get("labeler", d.get("labeler"))
    notes = []
    if lab.get("extrapolated"):
        notes.append(f"extrapolated from {lab['maps']} of {lab['maps_total']} maps (seeded random subset, seed "
                     f"{lab.get('seed')}: mean CPU s per map x {lab['maps_total']}; wall = that / the parallelism "
                     f"{fmt(lab.get('parallelism'))} measured on the subset)")
    if lab.get("cached"):
        notes.append("labels cached: their recorded times")
    if labeler in ("wta", "own"):
        notes.append(f"{labeler} labels: labeling time not comparable")
    render = e.get("render_labeler")
    if render and render != labeler:
        notes.append(f"fps with {render} labels (graph cuts labelled a subset; frame rates do not depend on "
                     f"the labels' values)")
    return notes


def table3_rows(m: dict) -> tuple[list[dict], dict]:
    """Table 3 rows and Fig. 12's fps per frame from :func:`bench.bench_dmt.run`'s result (``m["dmt"]``).

    DMT rows are matched to the paper's by position (the ci preset's 64/128/256 stand for 256/512/1024).
    Labeling: wall-clock and summed CPU seconds of every map (extrapolated where a subset was
    labelled); the DMT / DMRT ratios against DMRT's labeling run again in the same run. The paper's
    ratio is of CPU time: the CPU ratio is the one to compare with it.
    """
    d = m["dmt"]
    for key in ("dmt", "dmrt", "dmrt_labeling_s"):
        if key not in d:
            raise KeyError(f"measurements.dmt has no '{key}' (keys: {', '.join(sorted(d))}): "
                           f"bench.bench_dmt.run's result differs from what bench.report.table3_rows reads")
    dmrt = d["dmrt"]
    dmrt_lab = dmrt.get("labeling") or {}
    pdmt, pd_ = list(paper.TABLE3_DMT.values()), paper.TABLE3_DMRT
    rows, per_frame = [], {}
    for i, e in enumerate(d["dmt"]):
        pp = pdmt[i] if i < len(pdmt) else None
        row = {"method": f"DMT {e['size'][0]}x{e['size'][1]}",
               "paper row": pp and f"DMT {pp['size'][0]}x{pp['size'][1]}"}
        if "error" in e:
            rows.append({**row, "note": f"not measured: {e['error']}"})
            continue
        fps = e["fps_min_avg_max"]
        rows.append({**row, **_dmt_labeling_cells(e, pp), "fps min": fps[0], "fps avg": fps[1], "fps max": fps[2],
                     "paper fps min/avg/max": pp and "/".join(map(str, pp["fps"])),
                     "avg fps DMRT / DMT": d.get("fps_ratio_dmrt_over_dmt", {}).get(str(e["width"])),
                     "paper DMRT / DMT": pp and _ratio(pd_["fps"][1], pp["fps"][1]),
                     "note": "; ".join(_dmt_notes(d, e)) or None})
        per_frame[f"DMT {e['size'][0]}x{e['size'][1]}"] = e["fps_per_frame"]
    fps = dmrt["fps_min_avg_max"]
    note = None
    if dmrt_lab.get("wall_s") is not None:
        note = (f"labeling (candidates + graph cut of the {dmrt_lab['proxies']} proxies) run again in one process "
                f"in this run; preprocessing recorded {fmt(dmrt['labeling_s'])} s wall; labels equal to the "
                f"bundle's for {fmt(100 * dmrt_lab['labels_equal_bundle'])} % of the proxies")
    elif dmrt_lab.get("error"):
        note = f"labeling not run again: {dmrt_lab['error']}"
    rows.append({"method": f"DMRT ({dmrt['layers']} layers)", "paper row": "DMRT 1024x684, 1M proxies, 5 layers",
                 "maps labelled": None, "labeling wall (s)": dmrt_lab.get("wall_s", dmrt["labeling_s"]),
                 "labeling CPU (s)": dmrt_lab.get("cpu_s"), "CPU s per map median/p10/p90": None,
                 "paper labeling (s)": pd_["labeling_s"], "CPU DMT / DMRT": 1.0, "wall DMT / DMRT": 1.0,
                 "paper DMT / DMRT": 1.0, "fps min": fps[0], "fps avg": fps[1],
                 "fps max": fps[2], "paper fps min/avg/max": "/".join(map(str, pd_["fps"])),
                 "avg fps DMRT / DMT": 1.0, "paper DMRT / DMT": 1.0, "note": note})
    per_frame["DMRT"] = dmrt["fps_per_frame"]
    return rows, per_frame


def section_table3(rs: ResultSet, out: Path) -> Section:
    s = Section("table3_fig12", "Table 3 and Fig. 12: DMT vs DMRT")
    if _not_run(rs, s, "table3_fig12"):
        return s
    m = _meas(rs, "table3_fig12")
    rows, per_frame = table3_rows(m)
    workers = next((e["labeling"].get("workers") for e in m["dmt"]["dmt"] if "labeling" in e), None)
    s.table("table3", "Labeling time (wall clock, and CPU seconds summed over the processes) and min/avg/max fps "
                      "over the walkthrough; ratios DMT/DMRT labeling (CPU: the paper's comparison; wall: what a "
                      "user waits for) and DMRT/DMT fps, ours and the paper's", rows)
    s.text(f"DMT's graph cuts label one depth map per process ({workers} processes, machine of "
           f"{(m['dmt'].get('machine') or {}).get('cpus')} cores); DMRT's labeling runs in one process, as "
           f"preprocessing runs it. The paper's 26x at 1024x684 is a ratio of CPU time: compare it with the CPU "
           f"ratio.")
    if per_frame:
        fig, ax = plt.subplots(figsize=(8, 3.8))
        for name, fps in per_frame.items():
            ax.plot(np.arange(len(fps)), fps, label=name, lw=2 if name == "DMRT" else 1)
        ax.set_xlabel("walkthrough frame")
        ax.set_ylabel("fps")
        ax.set_yscale("log")
        ax.legend(fontsize=8)
        ax.set_title("Fig. 12: fps along the walkthrough, DMT per depth-map width vs DMRT")
        s.figure(_save(fig, out, "fig12_fps.png"), "Fig. 12: fps per frame along the walkthrough")
    else:
        s.text("**Note**: the DMT result has no `fps_per_frame`: Fig. 12 cannot be drawn.")
    return s


def section_fig7(rs: ResultSet, out: Path) -> Section:
    s = Section("fig7", "Fig. 7: proxy-cloud size vs labeling time, layers and fps")
    if _not_run(rs, s, "fig7"):
        return s
    m = _meas(rs, "fig7")
    par = rs.experiments["fig7"]["parameters"]
    sets = sorted(m["sets"], key=lambda x: -x["proxies"])  # the paper's order: most proxies first
    rows = []
    for i, st in enumerate(sets):
        pp = paper.FIG7[i] if i < len(paper.FIG7) else None
        k = st["layers_needed"] or st["layers_to_converge"]
        f = st["fps"].get(str(k))
        rows.append({"proxies": st["proxies"], "sub-sampling": st["subsampling_factor"],
                     "labeling incl. candidates (s)": st["labeling_total_s"],
                     "paper proxies": pp and pp["proxies"], "paper labeling (s)": pp and pp["labeling_s"],
                     "labeling ours / paper": pp and _ratio(st["labeling_total_s"], pp["labeling_s"]),
                     f"layers needed (holes <= {100 * par['hole_rate_target']:g}%)": st["layers_needed"],
                     "layers to converge": st["layers_to_converge"],
                     "paper layers": pp and "/".join(str(a) for a, _ in pp["layers_fps"]),
                     "fps at layers needed (else converged)": f and f["fps_median"],
                     "paper fps": pp and "/".join(str(b) for _, b in pp["layers_fps"]),
                     **{f"fps {kk} layers": st["fps"][kk]["fps_median"] for kk in sorted(st["fps"], key=int)}})
    s.table("fig7", "Per proxy set (ours: LOD levels of the octree; paper: 4.4M / 1M / 0.2M); fps = 1000 / median "
                    "GPU frame ms over the walkthrough", rows)
    kmax = len(sets[0]["hole_rate_per_layers"])
    hole_rows = [{"layers": k, **{f"{st['proxies']} proxies: representable (%)":
                                  _pct(st["hole_rate_representable_per_layers"][k - 1]) for st in sets},
                  **{f"{st['proxies']} proxies: all (%)": _pct(st["hole_rate_per_layers"][k - 1]) for st in sets}}
                 for k in range(1, kmax + 1)]
    s.table("fig7_holes", f"Hole rate vs Embree at {len(m['cameras'])} photo cameras per layer count: over the "
                          f"reference pixels some depth map can show (representable) and over all", hole_rows)
    fig, axs = plt.subplots(1, 3, figsize=(13, 3.8))
    for st in sets:
        axs[0].plot(range(1, kmax + 1), [_pct(x) for x in st["hole_rate_representable_per_layers"]], "o-",
                    label=f"{st['proxies']:,} proxies")
    axs[0].axhline(100 * par["hole_rate_target"], color="k", ls="--", lw=0.8, label="target")
    axs[0].set(xlabel="layers", ylabel="holes (% of representable pixels)", title="holes vs layers")
    axs[0].legend(fontsize=7)
    axs[1].loglog([st["proxies"] for st in sets], [st["labeling_total_s"] for st in sets], "o-", label="ours")
    axs[1].loglog([pp["proxies"] for pp in paper.FIG7], [pp["labeling_s"] for pp in paper.FIG7], "s--", label="paper")
    axs[1].xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # 2x10^5, 3x10^5 ... overlap
    axs[1].set(xlabel="proxies", ylabel="labeling s", title="labeling time")
    axs[1].legend(fontsize=7)
    for st in sets:
        ks = sorted(st["fps"], key=int)
        axs[2].plot([int(k) for k in ks], [st["fps"][k]["fps_median"] for k in ks], "o-", label=f"{st['proxies']:,}")
    for pp in paper.FIG7:
        axs[2].plot(*zip(*pp["layers_fps"]), "s--", color="gray", alpha=0.6)
    axs[2].set(xlabel="layers", ylabel="fps", title="fps (gray: paper)", yscale="log")
    axs[2].legend(fontsize=7)
    s.figure(_save(fig, out, "fig7_proxies.png"), "Fig. 7: holes per layer count, labeling time, fps per proxy set")
    return s


def _heat(ax, img, title, vmax=None, cmap="inferno"):
    a = np.asarray(img, np.float64)
    finite = a[np.isfinite(a)]
    vmax = vmax or (float(np.percentile(finite, 99)) if finite.size else 1.0) or 1.0
    im = ax.imshow(np.where(np.isfinite(a), a, np.nan), cmap=cmap, vmin=0, vmax=vmax)
    ax.set_title(title, fontsize=8)
    ax.axis("off")
    plt.colorbar(im, ax=ax, fraction=0.035)


def section_fig8(rs: ResultSet, out: Path) -> Section:
    s = Section("fig8", "Fig. 8: reconstruction error vs the Embree reference at a photo camera")
    if _not_run(rs, s, "fig8"):
        return s
    m = _meas(rs, "fig8")
    rows = [{"stage": st, "depth median (mm)": 1e3 * v["depth_median_m"], "depth mean (mm)": 1e3 * v["depth_mean_m"],
             "depth p95 (mm)": 1e3 * v["depth_p95_m"], "depth median (texels)": v.get("depth_median_texels"),
             "holes (%)": _pct(v["hole_rate"]), "holes representable (%)": _pct(v.get("hole_rate_representable")),
             "extra surface (%)": _pct(v["extra_rate"]), "PSNR (dB)": v["psnr_db"],
             "label agreement (%)": _pct(v["label_agreement"])} for st, v in m["stages"].items()]
    s.table("fig8", f"Camera {m['camera']} ({m['frame_size'][0]}x{m['frame_size'][1]}), "
                    f"{rs.experiments['fig8']['parameters']['layers']} layers: coarse splats (8b), raytraced (8c), "
                    f"raytraced + per-pixel labels (8d)", rows)
    maps = _maps(rs, "fig8")
    if maps is None:
        return _kept_figure(s, out, "fig8", "Fig. 8: colour, depth-error and colour-error heat maps per stage")
    stages = list(m["stages"])
    dz = np.concatenate([maps[f"{st}_depth_error_m"].ravel() for st in stages]) * 1e3
    dz_max = float(np.nanpercentile(dz, 99)) if np.isfinite(dz).any() else 1.0
    fig, axs = plt.subplots(len(stages) + 1, 3, figsize=(12, 2.9 * (len(stages) + 1)))
    axs[0, 0].imshow(maps["reference_color"])
    axs[0, 0].set_title("Embree reference colour", fontsize=8)
    _heat(axs[0, 1], maps["reference_depth"], "reference depth (m)", cmap="viridis")
    axs[0, 2].imshow(maps["representable"], cmap="gray")
    axs[0, 2].set_title("representable pixels (white)", fontsize=8)
    for a in axs[0]:
        a.axis("off")
    for i, st in enumerate(stages, 1):
        axs[i, 0].imshow(maps[f"{st}_color"])
        axs[i, 0].set_title(st, fontsize=8)
        axs[i, 0].axis("off")
        _heat(axs[i, 1], maps[f"{st}_depth_error_m"] * 1e3, "|depth error| (mm)", vmax=dz_max)
        _heat(axs[i, 2], maps[f"{st}_color_error"], "colour error (RGB distance)", vmax=120)
    s.figure(_save(fig, out, "fig8_heatmaps.png"), "Fig. 8: colour, depth-error and colour-error heat maps per stage")
    return s


def section_fig9(rs: ResultSet, out: Path) -> Section:
    s = Section("fig9_10", "Figs. 9 and 10: convergence of the iterative search")
    if _not_run(rs, s, "fig9_10"):
        return s
    m = _meas(rs, "fig9_10")
    rows = []
    for c in m["cases"]:
        pp = next((x for x in paper.CONVERGENCE if x["radius_scale"] == c["radius_scale"]
                   and x["layers"] == c["layers"]), None)
        rows.append({"case": c["case"], "layers": c["layers"], "mean steps per surface pixel": c["mean_iterations"],
                     "mean steps per searched pixel": c["mean_iterations_searched"],
                     "paper mean steps": pp and pp["mean_iterations"],
                     "raytracing (ms)": c["raytracing_ms_median"], "paper raytracing (ms)": pp and pp["raytracing_ms"],
                     "raytracing ours / paper": pp and _ratio(c["raytracing_ms_median"], pp["raytracing_ms"]),
                     "holes (%)": _pct(c["hole_rate"]), "holes representable (%)": _pct(c["hole_rate_representable"]),
                     "step lengths": ("not measured: " + c["step_statistics_error"]) if "step_mean_m" not in c else "measured"})
    s.table("fig9_10", "Iterative-search steps and raytracing-pass GPU ms over the walkthrough; holes at photo "
                       "cameras. Worst case (Fig. 10): splat radii x2.5", rows)
    cases = m["cases"]
    fig, axs = plt.subplots(1, len(cases), figsize=(4.3 * len(cases), 3.6), squeeze=False)
    for ax, c in zip(axs[0], cases):
        if "step_mean_m" not in c:
            ax.set(title=f"{c['case']}, {c['layers']} layers: not measured")
            continue
        mean, count = np.asarray(c["step_mean_m"]), np.asarray(c["step_count"])
        for layer in range(min(len(mean), 6)):
            ok = count[layer] > 0
            if ok.any():
                ax.semilogy(np.flatnonzero(ok) + 1, mean[layer][ok], "o-", ms=3, label=f"layer {layer + 1}")
        ax.set(xlabel="iterative-search step", ylabel="mean |step| (m)", title=f"{c['case']}, {c['layers']} layers")
        ax.legend(fontsize=7)
    s.figure(_save(fig, out, "fig9_step_sizes.png"), "Fig. 9/10: mean step length per step index and layer "
                                                       "(the last bin pools later steps)")
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for c in cases:
        h = np.asarray(c["iterations_histogram"], np.float64)
        ax.bar(np.arange(len(h)) + 0.25 * cases.index(c), h / max(h.sum(), 1), width=0.25,
               label=f"{c['case']}, {c['layers']} layers")
    ax.set(xlabel="iterative-search steps per pixel (all layers tried)", ylabel="share of searched pixels",
           xlim=(-0.5, 25))
    ax.legend(fontsize=7)
    s.figure(_save(fig, out, "fig9_iterations.png"), "Iterations per pixel histogram (walkthrough frames)")
    return s


def section_fig13(rs: ResultSet, out: Path) -> Section:
    s = Section("fig13", "Fig. 13: 1, 2 and 3 layers: holes at silhouettes")
    if _not_run(rs, s, "fig13"):
        return s
    m = _meas(rs, "fig13")
    rows = [{"layers": r["layers"], "holes (%)": _pct(r["hole_rate"]),
             "holes representable (%)": _pct(r["hole_rate_representable"]), "extra surface (%)": _pct(r["extra_rate"]),
             f"holes at {m['shown_camera']} (%)": _pct(r["shown_camera"]["hole_rate"]),
             # beyond the paper (results from version 2 on): the renderer's default hole filling
             **({f"holes, {r['fill_passes']} fill passes (%)": _pct(r["hole_rate_filled"]),
                 "representable, filled (%)": _pct(r["hole_rate_representable_filled"]),
                 "extra, filled (%)": _pct(r["extra_rate_filled"])} if "hole_rate_filled" in r else {})}
            for r in m["rows"]]
    s.table("fig13", f"Hole rates vs Embree at {len(m['cameras'])} photo cameras (paper: 2 layers leave barely "
                     f"visible holes, 3 almost none). The paper's rates are the layers' own; the 'filled' "
                     f"columns add this renderer's hole filling from neighbouring depth maps", rows)
    maps = _maps(rs, "fig13")
    if maps is None:
        return _kept_figure(s, out, "fig13", f"Fig. 13: frames and hole maps at {m['shown_camera']}")
    ks = [r["layers"] for r in m["rows"]]
    fig, axs = plt.subplots(2, len(ks) + 1, figsize=(3.6 * (len(ks) + 1), 5.2))
    axs[0, 0].imshow(maps["reference_color"])
    axs[0, 0].set_title("Embree reference", fontsize=8)
    axs[1, 0].imshow(maps["representable"], cmap="gray")
    axs[1, 0].set_title("representable pixels", fontsize=8)
    for j, k in enumerate(ks, 1):
        axs[0, j].imshow(maps[f"color_{k}"])
        axs[0, j].set_title(f"{k} layer(s)", fontsize=8)
        holes = maps[f"holes_{k}"]
        rgb = np.ones(holes.shape + (3,))
        rgb[holes > 0] = (0.85, 0.1, 0.1)   # hole: reference surface, frame background
        rgb[holes < 0] = (0.1, 0.3, 0.9)    # extra: frame surface, reference background
        axs[1, j].imshow(rgb)
        axs[1, j].set_title(f"holes (red) / extra (blue), {k} layer(s)", fontsize=8)
    for a in axs.ravel():
        a.axis("off")
    s.figure(_save(fig, out, "fig13_holes.png"), f"Fig. 13: frames and hole maps at {m['shown_camera']}")
    return s


def section_memory(rs: ResultSet, out: Path) -> Section:
    s = Section("memory", "Section 6.2: GPU memory per resource")
    if _not_run(rs, s, "memory"):
        return s
    m = _meas(rs, "memory")
    mb = 1e-6
    pm = paper.MEMORY_MB
    paper_mb = {"depthmaps": f"{pm['depthmap_each']} each", "images_low": f"{pm['images_low_each']} each",
                "proxies": f"{pm['proxies']} (1M proxies)", "layers": f"{pm['layers']} (5 layers, 1280x720)",
                "image_cache": f"{pm['image_cache']} (reserved)"}
    rows = []
    for res in sorted(set(m["gpu_bytes"]) | set(m["formula_bytes"])):
        got, want = m["gpu_bytes"].get(res), m["formula_bytes"].get(res)
        rows.append({"resource": res, "measured (MB)": got and got * mb, "paper formula (MB)": want and want * mb,
                     "measured / formula": _ratio(got, want), "paper (MB)": paper_mb.get(res)})
    rows.append({"resource": "total", "measured (MB)": m["total_measured_bytes"] * mb, "paper formula (MB)": None,
                 "measured / formula": None, "paper (MB)": f"{pm['depthmaps_and_images_low']} + 65 + cache"})
    s.table("memory", f"GL objects allocated by the renderer ({m['photos']} photos, {m['bundle']['proxies']} proxies, "
                      f"{m['layers']} layers at {m['frame_size'][0]}x{m['frame_size'][1]}) vs the paper's formulas "
                      f"for the same counts (depth map: 1 float per texel; low-res photo RGB8; proxy 6 floats + 1 int; "
                      f"layer pixel 2 floats; photo cache: the smaller of the renderer's budget and every photo at full size, "
                      f"RGB8)", rows)
    s.text("The paper's 37 MB (proxies) and 28 MB (layers) are swapped with respect to its own formulas "
           "(1M x 28 B = 28 MB, 1280 x 720 x 8 B x 5 = 36.9 MB); their sum, 65 MB, agrees. The photo cache's "
           "slots are RGBA8 since session 14 (an RGBA8 upload is a copy, an RGB8 one is widened by the driver on "
           "the CPU, and the GPU stores RGB8 in 4 bytes a texel as well): 4/3 of the RGB8 formula where every "
           "photo fits the budget.")
    return s


def section_real_views(rs: ResultSet, out: Path) -> Section:
    s = Section("real_views", "Real views: renders at held-out photos vs the photos")
    if _not_run(rs, s, "real_views"):
        return s
    m = _meas(rs, "real_views")
    ph = m.get("photometric") or {}
    s.text(f"Scene `{m['scene']}`: {m['photos']} photos, of which {len(m['held_out'])} held out (every "
           f"{m['holdout_every']}th: {', '.join(m['held_out'])}); the other {m['kept']} preprocessed without them "
           f"({m['points']:,} points, {m['proxies']:,} proxies, {fmt(m['preprocess_s'])} s). Each held-out camera "
           f"is rendered and compared with its photo over the pixels the frame has a surface at (PSNR over 8-bit RGB; "
           f"SSIM of scikit-image and FLIP (NVIDIA's perceptual difference, LDR, 67 pixels per degree: 0 = "
           f"identical, 1 = most different) with both images black outside that surface, their maps averaged over "
           f"it); 'common pixels' = those every variant covers; 'exposure-matched' = after the per-channel gain that "
           f"best maps the frame onto the held-out photo (a diagnostic: that photo's own exposure, which no renderer "
           f"can know, taken out). Gains: the global photometric adjustment of "
           f"preprocessing ({ph.get('photos_adjusted', 0)} of {m['kept']} photos adjusted: tied to others by >= "
           f"{(ph.get('parameters') or {}).get('min_shared', '?')} shared proxies on a cycle of ties, in "
           f"{ph.get('groups', 0)} group(s); {ph.get('observations', 0)} observations; log residual RMS "
           f"{fmt(ph.get('rms_log_before'))} -> {fmt(ph.get('rms_log_after'))}; the others keep gain 1); "
           f"leveling: the per-frame screen-space leveling. `dmrt bench --variants` picks the variants (seconds "
           f"below: each variant's renderer made, its views and its walkthrough rendered).")
    g = m.get("gain_recovery")
    if g:
        s.text(f"Synthetic scene: the spread of the photos' known log exposure x white balance is "
               f"{fmt(g['log_spread_before'])}; after the solved gains {fmt(g['log_spread_after'])} "
               f"(0 = the photos agree up to a common scale).")
    base = next((r for r in m["variants"] if r["variant"] == "dmrt"), None)
    rows = [{"variant": r["variant"], "renderer": r["renderer"], "gains": r.get("photometric", False),
             "leveling": r.get("leveling", False), "PSNR (dB)": r["mean_psnr_db"], "SSIM": r["mean_ssim"],
             "FLIP": r.get("mean_flip"),
             "surface (%)": _pct(r["mean_surface_share"]), "PSNR common pixels (dB)": r["mean_psnr_common_db"],
             "PSNR exposure-matched (dB)": r.get("mean_psnr_matched_db"),
             "ΔPSNR vs dmrt (dB)": None if base is None or r["mean_psnr_db"] is None or base["mean_psnr_db"] is None
             else r["mean_psnr_db"] - base["mean_psnr_db"], "seconds": r.get("seconds")} for r in m["variants"]]
    s.table("real_views", "Means over the held-out photos per variant (dmrt: the paper's DMRT with the photos' own "
                          "colours; splats: the coarse splats, RenderConfig(raytrace=False))", rows)
    _real_views_bounds(s, m)
    per = []
    for k, v in enumerate(m["views"]):
        row = {"photo": v["photo"], "frame": "x".join(map(str, v["frame_size"])),
               "common surface (%)": _pct(v["common_share"])}
        for r in m["variants"]:
            row[f"{r['variant']} PSNR"] = r["views"][k]["psnr_db"]
        for r in m["variants"]:
            if r["variant"] in ("dmrt", "dmrt-view", "dmrt+gains", "dmt", "splats"):
                row[f"{r['variant']} SSIM"] = r["views"][k]["ssim"]
                row[f"{r['variant']} FLIP"] = r["views"][k].get("flip")
                row[f"{r['variant']} surface (%)"] = _pct(r["views"][k]["surface_share"])
        per.append(row)
    s.table("real_views_per_photo", "Per held-out photo: PSNR (dB) of every variant, SSIM, FLIP and surface share", per)
    src = []
    for v in m["views"]:
        gained = {x["photo"]: x for x in v["sources"].get("dmrt+gains", [])}
        for x in v["sources"].get("dmrt", []):
            if x["share"] < 0.02:  # the JSON has them all
                continue
            src.append({"held-out photo": v["photo"], "textured from": x["photo"], "share (%)": _pct(x["share"]),
                        "PSNR (dB)": x["psnr_db"], "PSNR with gains (dB)": (gained.get(x["photo"]) or {}).get("psnr_db")})
    if src:
        s.table("real_views_sources", "Where the error comes from: per held-out photo, the photos DMRT textured >= 2 % "
                                      "of it from, their share of its surface pixels and how well those pixels agree "
                                      "with it", src)
    if not m.get("maps_file"):
        return s
    maps = _maps(rs, "real_views")
    if maps is None:
        return _kept_figure(s, out, "real_views", REAL_VIEWS_CAPTION)
    _real_views_figure(s, out, m, maps)
    return s


# the data's own bounds of real_views (bench/real_views.py BOUNDS), as the report names them
BOUND_NAMES = {"best_single": "best single photo", "view_closest": "view-closest photo per pixel"}
BOUND_COLUMNS = {"best_single": "best single", "view_closest": "view-closest"}


def _real_views_bounds(s: Section, m: dict) -> None:
    """The bounds tables: per variant, its PSNR and FLIP on each bound's pixels against the
    bound's, and its walkthrough change; per held-out photo, each bound."""
    b = m.get("bounds")
    walk = m.get("walkthrough")
    if not b and not walk:
        return
    if b:
        tol = b.get("depth_tolerance") or {}
        s.text(f"What the photos allow: at each held-out view the kept photos are reprojected through the scene's "
               f"geometry ({b['geometry']}: a photo sees a point where its depth map agrees within "
               f"{_pct(tol.get('relative'))} % of its depth + {fmt(tol.get('texels'))} texels), "
               f"on the pixels every variant covers ({fmt(b.get('seconds_per_view'))} s per view). **Best single photo**: "
               f"the kept photo with the highest PSNR among those that see at least "
               f"{_pct(b['best_single_min_share'])} % of the pixels some kept photo sees, alone (on the pixels it "
               f"sees). **View-closest photo per pixel**: at each pixel, of the kept photos that see the point, the "
               f"one whose ray to it is closest in angle to the view's ray (Debevec et al. 1996; Buehler et al. "
               f"2001). Each variant is measured on each bound's own pixels: the gap is how far it is from what "
               f"the photos allow.")
    if walk:
        s.text(f"Walkthrough change: along a slow walkthrough ({walk['frames']} frames of "
               f"{walk['frame_size'][0]}x{walk['frame_size'][1]} from {' to '.join(walk['keys'])}), each frame's "
               f"surface points are projected into the frame before; where that frame sees the same point, the mean "
               f"absolute RGB change (8-bit levels) is what the motion does not explain: flicker. Mean over the "
               f"frame pairs and the largest (a popping seam shows as a spike).")
    rows = []
    for r in m["variants"]:
        row = {"variant": r["variant"]}
        for key, col in (BOUND_COLUMNS.items() if b else ()):
            bound = b[key]
            got = r.get(f"mean_{key}_pixels_psnr_db")
            row[f"{col}: PSNR (dB)"] = got
            row[f"{col}: bound PSNR (dB)"] = bound["mean_psnr_db"]
            row[f"{col}: gap (dB)"] = None if got is None or bound["mean_psnr_db"] is None else bound["mean_psnr_db"] - got
            row[f"{col}: FLIP"] = r.get(f"mean_{key}_pixels_flip")
            row[f"{col}: bound FLIP"] = bound["mean_flip"]
        st = r.get("stability") or {}
        row["walkthrough change (levels)"] = st.get("mean")
        row["largest change (levels)"] = st.get("max")
        rows.append(row)
    s.table("real_views_vs_bounds", "Per variant, means over the held-out photos: PSNR and FLIP on each bound's "
                                    "pixels next to the bound's own (gap = bound - variant), and the walkthrough "
                                    "change", rows)
    if not b:
        return
    per = []
    for k, v in enumerate(m["views"]):
        for key, name in BOUND_NAMES.items():
            got = (v.get("bounds") or {}).get(key)
            if got is None:
                per.append({"held-out photo": v["photo"], "bound": name, "from": "no kept photo sees enough of it"})
                continue
            row = {"held-out photo": v["photo"], "bound": name, "from": got["photo"] or "per pixel",
                   "share of common (%)": _pct(got["share"]), "PSNR (dB)": got["psnr_db"], "SSIM": got["ssim"],
                   "FLIP": got["flip"]}
            for r in m["variants"]:
                row[f"{r['variant']} PSNR"] = (r["views"][k].get(f"{key}_pixels") or {}).get("psnr_db")
            per.append(row)
    s.table("real_views_bounds_per_photo", "Per held-out photo, each bound (its source photo, its share of the "
                                           "pixels every variant covers, its PSNR, SSIM and FLIP there) and every "
                                           "variant's PSNR (dB) on the same pixels", per)


def _real_views_figure(s: Section, out: Path, m: dict, maps: dict) -> None:
    """Per shown view: the held-out photo, the shown variants' frames and the bounds' images, each
    with its FLIP error map beneath (result sets before FLIP: the mean absolute RGB error)."""
    shown, variants = m["shown_views"], m["shown_variants"]
    bounds = [b for b in BOUND_NAMES if any(f"{b}_color_{k}" in maps for k in shown)]
    columns = [(v, f"{v}") for v in variants] + [(b, BOUND_NAMES[b]) for b in bounds]
    ncol = 1 + len(columns)
    fig, axs = plt.subplots(2 * len(shown), ncol, figsize=(2.3 * ncol, 3.6 * len(shown) + 0.4), squeeze=False)
    for i, k in enumerate(shown):
        top, bottom = axs[2 * i], axs[2 * i + 1]
        photo = maps[f"photo_{k}"]
        top[0].imshow(photo)
        top[0].set_title(f"held-out {m['views'][k]['photo']}", fontsize=7)
        for j, (key, title) in enumerate(columns, 1):
            if f"{key}_color_{k}" not in maps:
                continue
            mask = maps[f"{key}_mask_{k}"]
            top[j].imshow(np.where(mask[..., None], maps[f"{key}_color_{k}"], 0))
            got = (next((r for r in m["variants"] if r["variant"] == key), None) or {}).get("views", [{}] * (k + 1))[k] \
                if key in variants else m["views"][k]["bounds"][key]
            top[j].set_title(f"{title}: {fmt(got['psnr_db'])} dB", fontsize=7)
            if f"{key}_flip_{k}" in maps:
                im = bottom[j].imshow(np.where(mask, maps[f"{key}_flip_{k}"].astype(np.float32), np.nan), cmap="magma",
                                      vmin=0, vmax=1)
                bottom[j].set_title(f"FLIP {fmt(got.get('flip'))}", fontsize=7)
            else:
                err = np.abs(maps[f"{key}_color_{k}"].astype(np.float64) - photo).mean(axis=-1)
                im = bottom[j].imshow(np.where(mask, err, np.nan), cmap="inferno", vmin=0, vmax=64)
                bottom[j].set_title("|error| (levels)", fontsize=7)
            if j == len(columns):  # one scale per row
                plt.colorbar(im, ax=bottom[j], fraction=0.035)
        for a in (*top, *bottom):
            a.axis("off")
    s.figure(_save(fig, out, MAP_FIGURES["real_views"]), REAL_VIEWS_CAPTION)


# Table 1 at the paper's own scene sizes, each a preset of its own (bench/scale_run.sh,
# bench/scene3_run.sh): preset -> (section key, title, the paper's scene)
FULL_PRESETS = {
    "paper-full": ("table1_full", "Table 1 at Scene 2's size", "Scene 2"),
    "paper-full-scan": ("table1_full_scan", "Table 1 at Scene 2's size, radii from the scan's grid", "Scene 2"),
    "paper-scene3": ("table1_scene3", "Table 1 at Scene 3's size", "Scene 3"),
}
BUILDERS = {"table1": section_table1, "table2": section_table2, "table3_fig12": section_table3,
            "fig7": section_fig7, "fig8": section_fig8, "fig9_10": section_fig9, "fig13": section_fig13,
            "memory": section_memory, "real_views": section_real_views}


def _history_value(rs: ResultSet) -> dict | None:
    """The default path's run nearest 5 layers in ``rs``'s Table 2: ``method`` (the first of the
    run: the default of its commit, kbuffer before tiles), ``layers``, ``frame`` (WxH), ``ms``
    (median GPU ms), ``fps`` and ``sustained_ms``; None without a Table 2."""
    p = rs.experiments.get("table2")
    runs = (p or {}).get("measurements", {}).get("runs")
    if not runs:
        return None
    method = runs[0].get("method")
    r = min((r for r in runs if r.get("method") == method), key=lambda r: abs(r["layers"] - 5))
    # frame_size is in each run since the sustained pass; before, only in the parameters' walk
    size = r.get("frame_size") or ((p.get("parameters") or {}).get("walk") or {}).get("frame_size")
    ms = r["median_total_ms"]
    return {"method": method, "layers": r["layers"], "frame": "x".join(map(str, size)) if size else None,
            "ms": ms, "fps": r.get("fps_median", 1e3 / ms if ms else None), "sustained_ms": r.get("sustained_ms")}


def section_history(sets: list[ResultSet], out: Path) -> Section | None:
    """Frame time per result set of one machine and preset, oldest first: every set with a Table 2,
    whatever its default visibility path and frame size (both shown), so the trend runs from the
    paper-era pipeline to the newest."""
    rows = []
    for rs in sets:
        v = _history_value(rs)
        if v is None:
            continue
        lab = _meas(rs, "table1")
        rows.append({"date": rs.date, "commit": rs.commit, "dirty": rs.info["commit"].get("dirty"),
                     "method": v["method"], "frame": v["frame"], "layers": v["layers"], "total GPU ms": v["ms"],
                     "fps": v["fps"], "sustained ms/frame": v["sustained_ms"],
                     "labeling (s)": lab and lab["phases_s"].get("labeling_s")})
    if len(rows) < 2:
        return None
    s = Section("history", "History (nightly trend)")
    s.table("history", "Per result set of this machine and preset, oldest first: frame time of the default "
                       "visibility path of its commit (method), at its frame size", rows)
    fig, axs = plt.subplots(1, 2, figsize=(max(11, 0.9 * len(rows)), 3.8))
    x = np.arange(len(rows))
    labels = [f"{r['commit'][:8]}\n{r['method']}\n{r['frame'] or '?'}" for r in rows]
    for ax, key, ylabel in ((axs[0], "total GPU ms", "median frame GPU ms (layers as in the table)"),
                            (axs[1], "fps", "fps")):
        ax.plot(x, [r[key] for r in rows], "-", color="0.7", zorder=1)
        for k, method in enumerate(dict.fromkeys(r["method"] for r in rows)):  # one marker colour per method
            idx = [i for i, r in enumerate(rows) if r["method"] == method]
            ax.scatter(idx, [rows[i][key] for i in idx], color=f"C{k}", label=method, zorder=2)
        ax.set(ylabel=ylabel, title=f"{key} per commit")
        ax.set_xticks(x, labels, fontsize=6)
        ax.legend(fontsize=7, title="visibility", title_fontsize=7)
    s.figure(_save(fig, out, "history.png"), "Frame time and fps along the result history (commit, default "
                                             "visibility path, frame size)")
    return s


# ----------------------------------------------------------------------------------------------
# Building
# ----------------------------------------------------------------------------------------------
@dataclass
class ReportResult:
    out: Path
    result_set: ResultSet  # the newest set, with the experiments carried into it (its ``carried``)
    missing: list
    failed: list


def select(sets: list[ResultSet], preset: str | None = None, machine: str | None = None) -> ResultSet:
    """The newest result set (of ``preset`` / ``machine`` when given)."""
    cand = [s for s in sets if (preset is None or s.preset == preset) and (machine is None or s.machine == machine)]
    if not cand:
        raise InputError(sets[0].dir.parent.parent, f"no result set for preset={preset!r} machine={machine!r} "
                                                    f"(have: {', '.join(f'{s.machine}/{s.dir.name}' for s in sets)})")
    return cand[-1]


def scene_of(rs: ResultSet) -> str | None:
    """The user's scene ``rs`` was measured on (its label ``<preset>@<scene>``,
    :func:`bench.workspace.result_label`); None for the preset's synthetic scene."""
    return rs.preset.partition(SCENE_MARK)[2] or None


def build_report(results_dir, out, preset: str | None = None, machine: str | None = None,
                 required=None) -> ReportResult:
    """Build the report of the newest result set under ``results_dir`` into ``out``; the experiments
    it lacks are carried from older sets of its machine and preset (:func:`carry_forward`).

    A preset's synthetic scene gets every section, an experiment without a result shown as not
    run (the nightly completeness check: ``required``, default :data:`REQUIRED_EXPERIMENTS`). A
    user's scene (:func:`scene_of`) gets its name in the title and the sections of the experiments
    run on it only; ``required`` defaults to those.

    Returns
    -------
    ReportResult
        ``out``, the result set used (with the carried experiments), and the ``missing`` required /
        ``failed`` experiments.
    """
    sets = load_results(results_dir)
    newest = select(sets, preset, machine)
    history = [s for s in sets if s.machine == newest.machine and s.preset == newest.preset]
    rs = carry_forward(newest, history[:-1], list(dict.fromkeys([*SECTIONS, *(required or [])])))
    scene = scene_of(rs)
    keys = SECTIONS if scene is None else [k for k in SECTIONS if k in rs.experiments or k in rs.failed]
    if scene is not None and required is None:
        required = keys
    out = Path(out)
    with atomic_dir(out, what="report") as tmp:
        for sub in ("figures", "csv", "results"):
            (tmp / sub).mkdir()
        # the figures drawn from image maps, for sections whose maps are gone (_kept_figure); a
        # section that has its maps draws its figure anew over the copy
        for name in MAP_FIGURES.values():
            if (out / "figures" / name).is_file():
                shutil.copy2(out / "figures" / name, tmp / "figures" / name)
        sections = []
        for key in keys:
            try:
                sections.append(BUILDERS[key](rs, tmp))
            except InputError:
                raise
            except (KeyError, TypeError, ValueError, IndexError) as exc:
                raise InputError(rs.source(key).dir / f"{key}.json", f"cannot build the {key} section: "
                                                                    f"{type(exc).__name__}: {exc}") from exc
            if key in rs.carried:
                src = rs.carried[key]
                sections[-1].blocks.insert(0, f"**Carried**: `{key}` was not run at commit `{rs.commit}`; this "
                                              f"section shows the result of commit `{src.commit}` "
                                              f"({rs.experiments[key].get('date') or src.date}, `{src.dir.name}`).")
        # Table 1 at the paper's own scene sizes: each preset's newest result on this machine
        # stands beside this preset's
        at = 1
        for preset, (key, title, paper_scene) in FULL_PRESETS.items():
            full = [f for f in sets if f.machine == rs.machine and f.preset == preset and "table1" in f.experiments]
            if full and rs.preset not in FULL_PRESETS and scene is None:
                sections.insert(at, section_table1(full[-1], tmp, key, f"{title}: the `{preset}` preset (commit "
                                                   f"{full[-1].commit}, {full[-1].date})", paper_scene))
                shutil.copy2(full[-1].dir / "table1.json", tmp / "results" / f"{preset}-table1.json")
                at += 1
        hist = section_history(history, tmp)
        if hist is not None:
            sections.append(hist)
        missing = missing_experiments(rs, required)
        failed = sorted(rs.failed)
        header = _header(rs, missing, failed, keys)
        title = f"DMRT benchmark report: {rs.preset} preset" if scene is None else \
            f"DMRT benchmark report: scene {scene} ({rs.preset.partition(SCENE_MARK)[0]} preset)"
        for s in sections:
            for b in s.blocks:
                if isinstance(b, Table):
                    b.df.to_csv(tmp / "csv" / f"{b.name}.csv", index=False)
        (tmp / "REPORT.md").write_text(render_markdown(title, header, sections))
        (tmp / "index.html").write_text(render_html(title, header, sections))
        for f in sorted(rs.dir.glob("*.json")):
            shutil.copy2(f, tmp / "results" / f.name)
        for name, src in rs.carried.items():  # the newest set has no file of that name
            shutil.copy2(src.dir / f"{name}.json", tmp / "results" / f"{name}.json")
        mfile = rs.dir.parent / "machine.json"
        if mfile.is_file():
            shutil.copy2(mfile, tmp / "results" / "machine.json")
    return ReportResult(out, rs, missing, failed)


def _header(rs: ResultSet, missing: list, failed: list, keys: list) -> list[str]:
    info = rs.info
    mach, com = info["machine"], info["commit"]
    preset, _, scene = rs.preset.partition(SCENE_MARK)
    lines = []
    if missing or failed:
        parts = [f"{what}: {', '.join(names)}" for what, names in (("not run", missing), ("failed", failed)) if names]
        lines.append(f"**INCOMPLETE** ({'; '.join(parts)}).")
    elif scene:
        lines.append(f"**Complete**: every experiment run on scene `{scene}` has a result ({', '.join(keys)})"
                     + ("; some carried from earlier runs: see below." if rs.carried else "."))
    else:
        lines.append("**Complete**: every required experiment has a result"
                     + (" (some carried from earlier runs: see below)." if rs.carried else "."))
    if rs.carried:
        groups: dict = {}  # (commit, day) -> experiments, in the report's order
        for name, src in rs.carried.items():
            day = (rs.experiments[name].get("date") or src.date)[:10]
            groups.setdefault((src.commit, day), []).append(name)
        lines.append(f"**Carried** from earlier runs of this machine and preset, not run at commit `{rs.commit}`: "
                     + "; ".join(f"{', '.join(names)} (commit {commit}, {day})"
                                 for (commit, day), names in groups.items()) + ".")
    lines.append(f"Machine `{rs.machine}`: GL renderer {mach.get('gl_renderer')} ({mach.get('gl_version')}); CPU "
                 f"{mach.get('cpu')}, {mach.get('cpu_cores')} cores, {fmt(mach.get('memory_gib'))} GiB.")
    lines.append(f"Commit `{com.get('hash', rs.commit)}`{' (uncommitted changes)' if com.get('dirty') else ''}, "
                 f"committed {com.get('date')}; "
                 + (f"scene `{scene}` ({_scene_path(rs)}), " if scene else "")
                 + f"preset `{preset}`; newest result {rs.date}; results from `{rs.dir}`.")
    if mach.get("gl_is_software"):
        lines.append("**Note**: a software GL renderer (Mesa llvmpipe): its GPU timer values do not measure the "
                     "work, so GPU milliseconds, fps and speed ratios below are n/a (results made before they "
                     "were recorded as unavailable show numbers that measure nothing); the quality numbers "
                     "(depth error, holes, steps) are measurements.")

    def state(k: str) -> str:
        if k in rs.carried:
            return f"carried from {rs.carried[k].commit}"
        return "ok" if k in rs.experiments else "FAILED" if k in rs.failed else "not run"

    lines.append(f"Paper: {paper.MACHINE}. Experiments: " + ", ".join(f"{k} ({state(k)})" for k in keys) + ".")
    return lines


def _scene_path(rs: ResultSet) -> str:
    """Where the user's scene of ``rs`` was read from (its results record it)."""
    return next((f"`{p['scene']['path']}`" for p in rs.experiments.values() if p.get("scene")), "path not recorded")
