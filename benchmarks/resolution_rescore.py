"""Score two repair runs of the same input at two processing widths on the same footing, from
their view images alone (no metrics.json needed): every view of both runs at the camera's
resolution (the narrower run's images bicubic-upsampled, as ``writer.upsample_to_camera`` does)
and at the narrower run's resolution (the wider run's images area-averaged down), against the
wider run's ground truth (``work/gt``, the held-out input frames at the camera's size).

    .venv/bin/python benchmarks/resolution_rescore.py WIDE_RUN NARROW_RUN \\
        [--json benchmarks/results/processing_resolution_cpu.json]

The two runs must hold the same views (``repair --holdout K`` on the same input numbers the
held-out frames the same way); the script checks that the narrower run's ground truth is the
wider one's, downsampled.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

STAGES = ("output", "final", "mesh_inpaint", "inpaint", "gs_inpaint")


def main() -> int:
    from gsfix_online.core.metrics import psnr, ssim
    from gsfix_online.repair.outputs import read_png_rgb

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("wide", type=Path)
    ap.add_argument("narrow", type=Path)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    names = sorted(p.stem for p in (a.wide / "work" / "gt").glob("*.png"))
    rows: dict[str, list[tuple[float, float, float, float]]] = {}
    for n in names:
        gt = read_png_rgb(a.wide / "work" / "gt" / f"{n}.png")
        gt_narrow = read_png_rgb(a.narrow / "work" / "gt" / f"{n}.png")
        cam, small = (gt.shape[1], gt.shape[0]), (gt_narrow.shape[1], gt_narrow.shape[0])
        same = psnr(cv2.resize(gt, small, interpolation=cv2.INTER_AREA), gt_narrow)
        if same < 35:
            raise SystemExit(f"view {n}: the runs' ground truths differ ({same:.1f} dB)")
        for arm, run in (("wide", a.wide), ("narrow", a.narrow)):
            for st in STAGES:
                p = run / "views" / n / f"{st}.png"
                if not p.is_file():
                    continue
                img = read_png_rgb(p)
                at_cam = (
                    img if arm == "wide" else cv2.resize(img, cam, interpolation=cv2.INTER_CUBIC)
                )
                at_small = (
                    cv2.resize(img, small, interpolation=cv2.INTER_AREA) if arm == "wide" else img
                )
                rows.setdefault(f"{arm}/{st}", []).append(
                    (psnr(at_cam, gt), ssim(at_cam, gt), psnr(at_small, gt_narrow),
                     ssim(at_small, gt_narrow))
                )  # fmt: skip
    out = {}
    print("| run / stage | views | camera PSNR / SSIM | narrow PSNR / SSIM |\n|---|---:|---|---|")
    for k, v in sorted(rows.items()):
        m = np.asarray(v).mean(axis=0)
        out[k] = {"views": len(v), "camera_psnr_db": m[0], "camera_ssim": m[1],
                  "narrow_psnr_db": m[2], "narrow_ssim": m[3]}  # fmt: skip
        print(f"| {k} | {len(v)} | {m[0]:.2f} / {m[1]:.3f} | {m[2]:.2f} / {m[3]:.3f} |")
    if a.json:
        a.json.write_text(
            json.dumps({"wide": str(a.wide), "narrow": str(a.narrow), **out}, indent=1)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
