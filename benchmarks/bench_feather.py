"""Seams of the per-region composition: the repair's output re-composed with feathered borders.

The repair node composes each repaired view from GSFixer and the two fallbacks, one per region
(``repair.fallback.compose``). With hard borders a seam shows where the choice switches. For the
repaired views of finished repair runs this re-composes the output from the run's own images
(``fixed.png``, ``inpaint.png``, ``mesh_inpaint.png``; regions from ``alpha.png`` and the mesh
render's coverage) with the run's choice, for each ``feather_px``, and scores it against the
ground truth (``work/gt``). ``feather_px`` 0 must reproduce the run's ``output.png`` (checked:
the share of equal pixels is printed).

    .venv/bin/python benchmarks/bench_feather.py RUN [RUN ...] --feather 0 1 2 4

Results: ``benchmarks/results/feather_cpu.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import scores  # noqa: E402
from gsfix_online.repair.fallback import Choice, compose, regions  # noqa: E402
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402


def bench_run(run: Path, feathers: list[float]) -> list[dict[str, Any]]:
    metrics = json.loads((run / "metrics.json").read_text())
    rows = []
    for v in metrics["views"]:
        name = f"{v['view_id']:03d}"
        d, gt_path = run / "views" / name, run / "work" / "gt" / f"{name}.png"
        if not v.get("repair") or not (d / "fixed.png").is_file() or not gt_path.is_file():
            continue
        choice_json = (v.get("model") or {}).get("choice")
        if not choice_json:
            continue
        choice = Choice(dict(choice_json), {}, {}, 0, "")  # metrics.json keeps the per-region part
        gt = read_png_rgb(gt_path)
        cands = {k: read_png_rgb(d / f"{k}.png") for k in ("fixed", "inpaint", "mesh_inpaint")}
        alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
        valid = read_png_rgb(d / "mesh.png").any(axis=2)  # the mesh render is black off-surface
        region = regions(alpha, valid)
        output = read_png_rgb(d / "output.png")
        row: dict[str, Any] = {"run": str(run), "view": name, "group": v.get("group", ""),
                               "feather": {}}  # fmt: skip
        for f in feathers:
            img = compose(cands, region, choice, feather_px=f)
            if f == 0:
                row["reproduced"] = float((img == output).all(axis=2).mean())
            s = scores(img, gt)
            row["feather"][str(f)] = {"psnr_db": s.psnr_db, "ssim": s.ssim}
        rows.append(row)
        print(f"{run.parent.name} view {name}: reproduced {row['reproduced']:.3f}; " + "; ".join(
            f"{k}: {x['psnr_db']:.2f} dB / {x['ssim']:.3f}" for k, x in row["feather"].items()),
            flush=True)  # fmt: skip
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--feather", nargs="+", type=float, default=[0.0, 1.0, 2.0, 4.0])
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "feather_cpu.json"
    )
    args = ap.parse_args()
    rows = [r for run in args.runs for r in bench_run(run, args.feather)]
    if not rows:
        raise SystemExit("no repaired view with a choice and ground truth in these runs")
    base = str(args.feather[0])
    summary = {}
    for f in map(str, args.feather):
        gains = [r["feather"][f]["psnr_db"] - r["feather"][base]["psnr_db"] for r in rows]
        summary[f] = {
            "median_psnr_db": statistics.median(r["feather"][f]["psnr_db"] for r in rows),
            "median_ssim": statistics.median(r["feather"][f]["ssim"] for r in rows),
            "median_gain_db": statistics.median(gains),
            "views_better": sum(g > 0 for g in gains),
        }
        print(f"feather {f}: median {summary[f]['median_psnr_db']:.2f} dB, SSIM "
              f"{summary[f]['median_ssim']:.3f}, gain over {base}: median "
              f"{summary[f]['median_gain_db']:+.3f} dB, {summary[f]['views_better']}/{len(rows)} "
              "views better")  # fmt: skip
    result = {"about": __doc__.split("\n")[0], "argv": sys.argv[1:], "views": len(rows),
              "summary": summary, "rows": rows}  # fmt: skip
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
