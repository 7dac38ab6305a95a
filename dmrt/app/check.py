"""``dmrt check SCENE``: does every photo's pose fit the point cloud? A verdict per photo and for
the scene, a warning line on stderr for each photo that fails, and a page to look at::

    OUT/index.html         the table (coverage, points seen, agreement, edge contrast, verdict) and
                           every photo with the points' depth edges drawn over it
    OUT/overlays/*.png     those photos, at the check resolution
    OUT/check.json         the numbers

The measures and their thresholds: :mod:`dmrt.preprocess.registration`. ``--strict`` makes a
failed photo exit status 1 (bad input stays 2).
"""

from __future__ import annotations

import dataclasses
import html
import json
import sys
from pathlib import Path

import numpy as np

from dmrt.app.args import check_output, config_from_args
from dmrt.errors import InputError
from dmrt.io.atomic import atomic_dir


def cmd_check(args) -> None:
    from PIL import Image

    from dmrt.io.scene import load_scene
    from dmrt.preprocess.registration import MIN_POINTS, CheckConfig, check_photos, sample_cloud

    config = config_from_args(CheckConfig, args)
    out = Path(args.out) if args.out is not None else Path("out/check") / Path(args.scene).resolve().name
    check_output(out, folder=True)
    # the page replaces an earlier check there; any other folder with files in it is refused
    if out.is_dir() and any(out.iterdir()) and not (out / "check.json").is_file():
        raise InputError(out, "folder exists and holds files that are not a check (no check.json): "
                              "give a new or empty --out folder")
    scene = load_scene(args.scene)
    sample = sample_cloud(scene, config.sample_points)
    checks, seen_any = [], np.zeros(len(sample.positions), bool)
    with atomic_dir(out, force=True, what="check") as tmp:
        (tmp / "overlays").mkdir()
        bar = not args.quiet and sys.stderr.isatty()  # a terminal only: stderr stays the warnings
        for check, picture, seen in check_photos(scene, sample, config, progress=bar):
            Image.fromarray(picture).save(tmp / "overlays" / _overlay_name(check.name))
            for problem in check.problems:
                print(f"dmrt check: warning: {check.name}: {problem}", file=sys.stderr, flush=True)
            checks.append(check)
            seen_any |= seen
        failed = [c for c in checks if c.problems]
        summary = {
            "scene": str(Path(args.scene).resolve()), "photos": len(checks), "failed": len(failed),
            "verdict": "fail" if failed else "pass", "min_points": MIN_POINTS,
            "sample": {"points": len(sample.positions), "of": sample.of, "stride": sample.stride,
                       "brightness": sample.source, "seen_by_no_photo": float(1 - seen_any.mean())},
            "config": dataclasses.asdict(config),
        }
        (tmp / "check.json").write_text(json.dumps(
            {**summary, "per_photo": [{**dataclasses.asdict(c), "verdict": c.verdict} for c in checks]}, indent=1))
        (tmp / "index.html").write_text(_page(summary, checks))
    s = summary["sample"]
    print(f"checked {len(checks)} photos against {s['points']:,} of the {s['of']:,} points (1 in {s['stride']}; "
          f"brightness: {s['brightness'] or 'none'}); {s['seen_by_no_photo']:.0%} of them seen by no photo")
    print(f"verdict: {summary['verdict']}: {len(checks) - len(failed)} of {len(checks)} photos pass; "
          f"open {out / 'index.html'}")
    if failed and args.strict:
        raise SystemExit(1)


def _overlay_name(photo: str) -> str:
    """The overlay's file name for photo ``photo`` (a name may hold folders: flattened)."""
    return Path(photo).with_suffix(".png").as_posix().replace("/", "__")


def _page(summary: dict, checks) -> str:
    def num(v, fmt):
        return "-" if v is None else format(v, fmt)

    rows = []
    for c in checks:
        cells = [html.escape(c.name), f"{100 * c.coverage:.1f}", f"{c.points_seen:,} ({100 * c.points_share:.1f}%)",
                 num(c.agreement, ".2f"), num(c.edge_contrast, ".2f"), html.escape(c.verdict)]
        rows.append(f"<tr class=\"{'fail' if c.problems else 'ok'}\">"
                    + "".join(f"<td>{x}</td>" for x in cells) + "</tr>")
    figures = "\n".join(f"<figure class=\"{'fail' if c.problems else 'ok'}\"><img src=\"overlays/"
                        f"{html.escape(_overlay_name(c.name))}\"><figcaption>{html.escape(c.name)}: "
                        f"{html.escape(c.verdict)}</figcaption></figure>" for c in checks)
    s, cfg = summary["sample"], summary["config"]
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>dmrt check: {html.escape(Path(summary['scene']).name)}</title>
<style>body{{font-family:sans-serif;margin:2em}}td,th{{padding:.2em .7em;text-align:right}}
td:first-child,td:last-child{{text-align:left}}tr.fail,figure.fail figcaption{{color:#b00}}
figure{{display:inline-block;margin:.3em}}figcaption{{font-size:80%}}</style></head><body>
<h1>Registration check: {summary['verdict']} ({summary['photos'] - summary['failed']} of {summary['photos']} photos
pass)</h1>
<p>Scene <code>{html.escape(summary['scene'])}</code>. {s['points']:,} of its {s['of']:,} points (1 in
{s['stride']}, in file order) splatted into every photo {cfg['width']} pixels wide; {100 * s['seen_by_no_photo']:.0f}%
of them are seen by no photo. Point brightness: {s['brightness'] or 'none (the edge contrast decides)'}.</p>
<p>A photo fails when the points cover less than {100 * cfg['min_coverage']:.0f}% of it or it sees fewer than
{summary['min_points']} sample points, or when its brightness
correlates less than {cfg['min_agreement']} with the brightness of the points it sees (agreement; aligned photos
score near 1, misplaced ones near 0); for a cloud without colour or intensity, when its gradient at the points'
depth edges is less than {cfg['min_edge_contrast']}&times; its gradient elsewhere (edge contrast). In the pictures:
depth edges of the points in magenta, pixels no point covers darkened. Depth edges where the scan has a shadow
(a surface scanned from one side) have no edge in the photo; edges that run beside the photo's own by a
constant offset mean a small pose error.</p>
<table><tr><th>photo</th><th>coverage (%)</th><th>points seen</th><th>agreement</th><th>edge contrast</th>
<th>verdict</th></tr>
{chr(10).join(rows)}
</table>
{figures}
</body></html>
"""
