"""Is the sharpness a final map loses against its output the truth's detail, or grain?

For each demo-layout run given (``RUN/repair`` with the scene's ground truth beside it in
``RUN/scene/novel/color``), on the pixels where the output shows the mesh render
(``provenance.npz``, eroded by 2 px off the seams), per repaired view:

- the output's and the final render's fine detail (luma minus a 1-px Gaussian blur of it): its
  RMS in grey levels beside the truth's, and its correlation with the truth's;
- the output's and the final render's PSNR there;
- what smoothing the output's mesh pixels would do (a Gaussian of ``--sigma`` px, feathered
  into the rest of the view): its PSNR change against the truth, and the final render's
  sharpness ratio against that smoothed output. A change that leaves PSNR where it is removes
  grain the truth does not have.

    .venv/bin/python benchmarks/grain_check.py RUN1 RUN2 ... [--sigma 0.7] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gsfix_online.core.metrics import sharpness
from gsfix_online.repair.outputs import read_png_rgb
from gsfix_online.repair.provenance import MESH

sys.path.insert(0, str(Path(__file__).resolve().parent))
from veil_table import correlation as corr  # noqa: E402
from veil_table import fine_detail as fine  # noqa: E402


def psnr(a: np.ndarray, b: np.ndarray, m: np.ndarray | None = None) -> float:
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    e = d.mean(-1)[m].mean() if m is not None else d.mean()
    return float(10 * np.log10(255.0**2 / e))


def view_row(d: Path, gt_path: Path, sigma: float) -> dict[str, float] | None:
    if not all((d / f).is_file() for f in ("output.png", "final.png", "provenance.npz")):
        return None
    if not gt_path.is_file():
        return None
    out, fin = read_png_rgb(d / "output.png"), read_png_rgb(d / "final.png")
    gt = read_png_rgb(gt_path, out.shape[1], out.shape[0])
    mesh = np.load(d / "provenance.npz")["source"] == MESH
    m = cv2.erode(mesh.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    if m.sum() < 500:
        return None
    fo, ff, fg = fine(out), fine(fin), fine(gt)
    w = cv2.GaussianBlur(mesh.astype(np.float32), (0, 0), 1.0)[..., None]
    smooth = cv2.GaussianBlur(out, (0, 0), sigma).astype(np.float32)
    new = np.clip(w * smooth + (1 - w) * out, 0, 255).round().astype(np.uint8)
    return {
        "mesh_share": float(mesh.mean()),
        "fine_rms_output": float(fo[m].std()),
        "fine_rms_final": float(ff[m].std()),
        "fine_rms_truth": float(fg[m].std()),
        "fine_corr_output": corr(fo[m], fg[m]),
        "fine_corr_final": corr(ff[m], fg[m]),
        "psnr_mesh_output": psnr(out, gt, m),
        "psnr_mesh_final": psnr(fin, gt, m),
        "sharpness": sharpness(fin) / sharpness(out),
        "smoothed_psnr_change": psnr(new, gt) - psnr(out, gt),
        "sharpness_vs_smoothed": sharpness(fin) / sharpness(new),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="demo run folders (RUN/repair, RUN/scene)")
    ap.add_argument("--sigma", type=float, default=0.7, help="the smoothing's Gaussian, px")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    table: dict[str, dict[str, dict[str, float]]] = {}
    for run in a.runs:
        rows = {}
        for d in sorted((run / "repair" / "views").iterdir()):
            r = view_row(d, run / "scene" / "novel" / "color" / f"{d.name}.png", a.sigma)
            if r is not None:
                rows[d.name] = r
        table[str(run)] = rows
        print(f"\n{run} (mesh pixels of the output)\n| view | mesh share | fine RMS output / "
              "final / truth | corr. with truth: output, final | PSNR output, final | "
              f"sharpness | smoothed {a.sigma:g} px: PSNR change, sharpness |\n"
              "|---|---:|---:|---:|---:|---:|---:|")  # fmt: skip
        for name, r in rows.items():
            print(f"| {name} | {r['mesh_share']:.0%} | {r['fine_rms_output']:.1f} / "
                  f"{r['fine_rms_final']:.1f} / {r['fine_rms_truth']:.1f} | "
                  f"{r['fine_corr_output']:.2f}, {r['fine_corr_final']:.2f} | "
                  f"{r['psnr_mesh_output']:.2f}, {r['psnr_mesh_final']:.2f} | "
                  f"{r['sharpness']:.2f} | {r['smoothed_psnr_change']:+.3f}, "
                  f"{r['sharpness_vs_smoothed']:.2f} |")  # fmt: skip
    every = [r for rows in table.values() for r in rows.values()]
    if every:
        gained = sum(r["fine_corr_final"] >= r["fine_corr_output"] for r in every)
        print(f"\n{len(every)} views: the final render's fine detail matches the truth at least "
              f"as well as the output's in {gained}; smoothing changes the output's PSNR by a "
              f"median {statistics.median(r['smoothed_psnr_change'] for r in every):+.3f} dB")  # fmt: skip
    if a.json:
        doc: dict[str, Any] = {"sigma_px": a.sigma, "runs": table}
        a.json.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
