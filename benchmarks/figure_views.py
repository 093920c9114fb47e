"""Side-by-side figure of repaired views: 3DGS, mesh, mesh fill + Telea, GSFixer, delivered
output, final map render and ground truth, one row per view, each tile labelled with its PSNR.

    .venv/bin/python benchmarks/figure_views.py outputs/demo/repair --gt outputs/demo/scene/novel/color \\
        --views 0 3 5 --out docs/repair_views.png

The images are the run's own files (``views/NNN/*.png``); ground truth from ``--gt DIR/NNN.png``
(default: the run's ``work/gt``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.inspection.metrics import psnr  # noqa: E402
from gsfix_online.repair.outputs import read_png_rgb, write_png  # noqa: E402

COLUMNS = (
    ("gs", "3DGS"),
    ("mesh", "mesh"),
    ("inpaint", "mesh fill + Telea"),
    ("fixed", "GSFixer"),
    ("output", "output"),
    ("final", "final map"),
    ("gt", "ground truth"),
)


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    bar = np.full((18, tile.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, tile])


def figure(run: Path, gt_dir: Path, view_ids: list[int]) -> np.ndarray:
    rows = []
    for vid in view_ids:
        d = run / "views" / f"{vid:03d}"
        gt = read_png_rgb(gt_dir / f"{vid:03d}.png")
        h, w = gt.shape[:2]
        tiles = []
        for key, title in COLUMNS:
            path = gt_dir / f"{vid:03d}.png" if key == "gt" else d / f"{key}.png"
            if not path.is_file():
                img, text = np.full((h, w, 3), 230, np.uint8), f"{title}: -"
            else:
                img = read_png_rgb(path, w, h)
                text = title if key in ("gt", "mesh") else f"{title} {psnr(img, gt):.2f} dB"
            tiles.append(_label(img, f"{vid:03d} {text}" if key == "gs" else text))
        rows.append(np.hstack([np.pad(t, ((0, 2), (0, 2), (0, 0)), constant_values=255)
                               for t in tiles]))  # fmt: skip
    return np.vstack(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a finished repair run folder")
    ap.add_argument("--gt", type=Path, default=None, help="ground truth NNN.png (default work/gt)")
    ap.add_argument("--views", nargs="+", type=int, default=None, help="default: repaired ones")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scale", type=float, default=1.0, help="resize the figure (area average)")
    args = ap.parse_args()
    gt_dir = args.gt or args.run / "work" / "gt"
    views = args.views
    if views is None:
        metrics = json.loads((args.run / "metrics.json").read_text())
        views = [v["view_id"] for v in metrics["views"] if v.get("repair")][:4]
    img = figure(args.run, gt_dir, views)
    if args.scale != 1.0:
        size = (round(img.shape[1] * args.scale), round(img.shape[0] * args.scale))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_png(args.out, img)
    print(f"{len(views)} views -> {args.out} ({img.shape[1]}x{img.shape[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
