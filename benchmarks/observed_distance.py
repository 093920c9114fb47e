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
import numpy.typing as npt

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEPTH_TOL = 0.05  # a frame sees a point whose depth there is within this share of the point's


def pose(t: npt.ArrayLike, q: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """T_world_cam from a translation and a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])  # fmt: skip
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def main() -> int:
    import cv2

    from benchmarks.observed_blur import ERODE_PX, OPAQUE
    from gsfix_online.repair.provenance import SOURCES

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a demo run folder (scene/, repair/)")
    ap.add_argument("--every", type=int, default=2, help="use every n-th input frame")
    a = ap.parse_args()
    tum = a.run / "scene/tum"
    cam = json.loads((tum / "camera.json").read_text())
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    rows = [ln.split() for ln in (tum / "groundtruth.txt").read_text().splitlines()
            if ln and not ln.startswith("#")]  # fmt: skip
    depths = dict(ln.split() for ln in (tum / "depth.txt").read_text().splitlines()
                  if ln and not ln.startswith("#"))  # fmt: skip
    frames = []
    for r in rows[:: a.every]:
        d = cv2.imread(str(tum / depths[r[0]]), cv2.IMREAD_UNCHANGED).astype(np.float64)
        frames.append((np.linalg.inv(pose(np.float64(r[1:4]), np.float64(r[4:8]))),
                       d / cam["depth_scale"]))  # fmt: skip
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
        alpha = cv2.imread(str(d / "alpha.png"), cv2.IMREAD_UNCHANGED)
        alpha = alpha.astype(np.float32) / np.iinfo(alpha.dtype).max
        alpha = alpha[..., 0] if alpha.ndim == 3 else alpha
        kernel = np.ones((2 * ERODE_PX + 1,) * 2, np.uint8)
        opaque = cv2.erode((alpha >= OPAQUE).astype(np.uint8), kernel) > 0
        z = cv2.imread(str(truth), cv2.IMREAD_UNCHANGED).astype(np.float64) / cam["depth_scale"]
        sel = (np.load(d / "provenance.npz")["source"] == SOURCES.index("mesh")) & opaque & (z > 0)
        if sel.mean() < 0.05:
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
            u = np.rint(Xc[:, 0] / np.maximum(zc, 1e-6) * K[0, 0] + K[0, 2]).astype(int)
            w = np.rint(Xc[:, 1] / np.maximum(zc, 1e-6) * K[1, 1] + K[1, 2]).astype(int)
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
