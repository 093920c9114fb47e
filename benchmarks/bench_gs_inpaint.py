"""Each map filled the same way: 3DGS + Telea against mesh + Telea on finished repair runs.

Runs made before the ``gs_inpaint`` stage (``repair.baselines.gs_inpaint``) have the renders it is
made from: ``views/NNN/gs.png`` and ``alpha.png``. This rebuilds it from them and scores it,
beside raw 3DGS and the run's ``mesh_inpaint``, against ``work/gt`` at the held-out frames and at
the novel views (mean PSNR / SSIM over views, as ``metrics.json`` groups them).

    .venv/bin/python benchmarks/bench_gs_inpaint.py RUN... --out benchmarks/results/gs_inpaint_cpu.json

RUN is a repair run's folder (a ``bench_variants.py`` case's ``run/``, a demo's repair folder).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _case import held_views, write_result  # noqa: E402

METHODS = ("gs", "gs_inpaint", "mesh_inpaint")


def score_run(run: Path) -> dict:
    from gsfix_online.core.metrics import psnr, ssim
    from gsfix_online.repair.baselines import gs_inpaint
    from gsfix_online.repair.outputs import read_png_rgb as _rgb

    held = held_views(run)
    per: dict[str, dict[str, list[tuple[float, float]]]] = {}
    views = []
    for d in sorted((run / "views").iterdir()):
        gt_path = run / "work" / "gt" / f"{d.name}.png"
        if not gt_path.is_file() or not (d / "alpha.png").is_file():
            continue
        gt = _rgb(gt_path)
        alpha = cv2.imread(str(d / "alpha.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 255
        gs = _rgb(d / "gs.png")
        images = {
            "gs": gs,
            "gs_inpaint": gs_inpaint(gs, alpha),
            "mesh_inpaint": _rgb(d / "mesh_inpaint.png"),
        }
        group = "holdout" if int(d.name) in held else "novel"
        row = {"view": d.name, "group": group}
        for k, im in images.items():
            p, s = psnr(im, gt), ssim(im, gt)
            per.setdefault(group, {}).setdefault(k, []).append((p, s))
            row[k] = {"psnr_db": p, "ssim": s}
        views.append(row)
    groups = {
        g: {k: {"psnr_db": float(np.mean([p for p, _ in v])), "ssim": float(np.mean([s for _, s in v])),
                "views": len(v)} for k, v in by.items()}
        for g, by in per.items()
    }  # fmt: skip
    return {"run": str(run), "groups": groups, "views": views}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/gs_inpaint_cpu.json"))
    args = ap.parse_args()
    rows = [score_run(r) for r in args.runs]
    summary = []
    for r in rows:
        for g, by in r["groups"].items():
            cells = " | ".join(f"{k} {by[k]['psnr_db']:.2f} / {by[k]['ssim']:.3f}" for k in METHODS)
            gap = by["gs_inpaint"]["psnr_db"] - by["mesh_inpaint"]["psnr_db"]
            print(f"{r['run']} {g}: {cells} | gs_inpaint - mesh_inpaint {gap:+.2f} dB")
            summary.append({"run": r["run"], "group": g, "gs_inpaint_minus_mesh_inpaint_db": gap})
    write_result(args.out, __doc__, 0, summary, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
