"""How much closer does a novel view see a surface than any input frame did? (issue 43's
observed-surface blur, benchmarks/results/observed_blur_cpu.md)

For a demo run (``RUN``: ``scene/`` and ``repair/``), each view's pixels that
``observed_blur.py`` reads (the output shows the mesh render, the input map's render opaque) are
lifted to 3D with the view's true depth (``scene/novel/depth``); every input frame
(``scene/tum``: poses, depth) that sees a point (inside its image, its depth within 5 % of the
point's) gives the point's distance from it. Printed per view: the median over the pixels of
the nearest input frame's distance over the novel view's (above 1: the input saw the surface
only from farther away, so its Gaussians are wider than the view's pixels there), and the share
of pixels no input frame saw.

    .venv/bin/python benchmarks/observed_distance.py RUN [--every 2]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEPTH_TOL = 0.05  # a frame sees a point whose depth there is within this share of the point's
MAX_POSE_GAP_NS = 20_000_000  # a depth frame's pose from poses at most this far apart


def main() -> int:
    from benchmarks.observed_blur import MIN_SHARE, observed_pixels
    from gsfix_online.sources.base import read_depth_png
    from gsfix_online.sources.tum import read_file_list, read_intrinsics_json, read_pose_list

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a demo run folder (scene/, repair/)")
    ap.add_argument("--every", type=int, default=2, help="use every n-th input frame")
    a = ap.parse_args()
    tum = a.run / "scene/tum"
    intr, scale = read_intrinsics_json(tum / "camera.json")
    scale = scale or 5000.0
    traj = read_pose_list(tum / "groundtruth.txt")
    stamps, paths = read_file_list(tum / "depth.txt")
    frames = []
    for t, p in list(zip(stamps, paths, strict=True))[:: a.every]:
        pose = traj.query(t, MAX_POSE_GAP_NS)
        if pose is not None:  # a depth frame with no pose near it sees nothing here
            frames.append((np.linalg.inv(pose), read_depth_png(tum / p, scale)))
    metrics = json.loads((a.run / "repair/metrics.json").read_text())
    print(
        "| view | pixels | nearest input distance over the view's (median, 10th-90th pct) | unseen |"
    )
    print("|---|---:|---|---:|")
    for v in metrics["views"]:
        d = a.run / "repair/views" / v["view"]
        truth = a.run / "scene/novel/depth" / f"{v['view']}.png"
        if not v.get("repair") or not (d / "alpha.png").is_file() or not truth.is_file():
            continue
        z = read_depth_png(truth, scale).astype(np.float64)
        sel = observed_pixels(d) & (z > 0)
        if sel.mean() < MIN_SHARE:
            continue
        T = np.reshape(v["camera"]["T_world_cam"], (4, 4))
        Kv = np.reshape(v["camera"]["K"], (3, 3))
        vv, uu = np.nonzero(sel)
        zz = z[vv, uu]
        pc = np.stack([(uu - Kv[0, 2]) / Kv[0, 0] * zz, (vv - Kv[1, 2]) / Kv[1, 1] * zz, zz], 1)
        X = pc @ T[:3, :3].T + T[:3, 3]
        nearest = np.full(len(X), np.inf)
        for T_cw, dep in frames:
            Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
            zc = Xc[:, 2]
            u = np.rint(Xc[:, 0] / np.maximum(zc, 1e-6) * intr.fx + intr.cx).astype(int)
            w = np.rint(Xc[:, 1] / np.maximum(zc, 1e-6) * intr.fy + intr.cy).astype(int)
            ok = (zc > 0.05) & (u >= 0) & (u < dep.shape[1]) & (w >= 0) & (w < dep.shape[0])
            at = np.zeros(len(X))
            at[ok] = dep[w[ok], u[ok]]
            seen = ok & (at > 0) & (np.abs(at - zc) < DEPTH_TOL * zc)
            nearest[seen] = np.minimum(nearest[seen], zc[seen])
        seen = np.isfinite(nearest)
        ratio = nearest[seen] / zz[seen]
        p10, p50, p90 = np.percentile(ratio, [10, 50, 90]) if seen.any() else (np.nan,) * 3
        print(f"| {v['view']} | {int(sel.sum())} | {p50:.2f} ({p10:.2f}-{p90:.2f}) | "
              f"{1 - seen.mean():.2f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
