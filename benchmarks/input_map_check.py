"""Who drew a view's pixels: the map as the input left it, or distillation's Gaussians?

For a ``gsfix-online demo`` run and some of its novel views: the map at the end of the input
(``repair/work/map.pt.prev``, before any repaired view), the final map (``repair/work/map.pt``)
with and without the Gaussians distillation grew (``Mapper.seeded``), and the delivered output,
each scored against the ground truth on the output's pixels of each source (``provenance.npz``).
Where the input's map scores far below the output on pixels marked as the 3DGS render, the
output shows what other views' repairs grew there, not what a frame saw. Writes the renders
side by side (ground truth, output, input map, final map, final map without distillation's
Gaussians) with ``--image``.

    .venv/bin/python benchmarks/input_map_check.py outputs/demo 004,007 [--image views.png]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def psnr(a: np.ndarray, b: np.ndarray, m: np.ndarray | None = None) -> float:
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    return float(10 * np.log10(255.0**2 / (d if m is None else d[m]).mean()))


def main() -> int:
    import cv2
    import torch

    from gsfix_online.core.config import build, read_yaml
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.services.splat import load_snapshot

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("demo", type=Path, help="a gsfix-online demo output folder")
    ap.add_argument("views", help="comma-separated view names, e.g. 004,007")
    ap.add_argument("--image", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(2)
    run = args.demo / "repair"
    graph = read_yaml(run / "work" / "graph.yaml")["nodes"]
    cfg = build(MapperConfig, base={**graph["splat"]["params"].get("mapper", {}), "backend": "cpu"})
    before = load_snapshot(cfg, run / "work" / "map.pt.prev")
    final = load_snapshot(cfg, run / "work" / "map.pt")
    records = {v["view"]: v for v in json.loads((run / "metrics.json").read_text())["views"]}
    rows = []
    for name in args.views.split(","):
        cam = records[name]["camera"]
        T, K = np.reshape(cam["T_world_cam"], (4, 4)), np.reshape(cam["K"], (3, 3))
        gt = read_png_rgb(args.demo / "scene" / "novel" / "color" / f"{name}.png")
        H, W = gt.shape[:2]
        out = read_png_rgb(run / "views" / name / "output.png", W, H)
        with np.load(run / "views" / name / "provenance.npz") as z:
            src, sources = z["source"], [str(s) for s in z["sources"]]
        images = [gt, out]
        arms = (("input map", before, None), ("final map", final, None),
                ("final without distillation's", final, ~final.seeded()))  # fmt: skip
        for label, m, keep in (("output", None, None), *arms):
            if m is None:
                img = out
            else:
                with torch.no_grad():
                    c = m.render(T, K, W, H, keep=keep).color.clamp(0, 1).numpy()
                img = np.rint(np.broadcast_to(c, (H, W, 3)) * 255).astype(np.uint8)
                images.append(img)
            per = {s: round(psnr(img, gt, src == i), 2) for i, s in enumerate(sources)
                   if (src == i).sum() > 500}  # fmt: skip
            print(f"{name} {label}: {psnr(img, gt):.2f} dB; on the output's pixels by source {per}")
        rows.append(np.hstack([cv2.resize(i, (320, 240)) for i in images]))
    if args.image is not None:
        cv2.imwrite(str(args.image), cv2.cvtColor(np.vstack(rows), cv2.COLOR_RGB2BGR))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
