"""Where a repaired view's final render is blurrier than its output on observed surfaces: whose
Gaussians paint those pixels, and how sharp was the map there before the repair? (issue 43)

For each repair run folder (``RUN/repair``), every repaired view scored against the truth, over
the pixels where the output shows the mesh render (``provenance.npz``) and the input map's own
render (``alpha.png``, before any repair) was opaque (alpha 0.99 or more, eroded by 2 px: no
hole border in the window): their share of the view; the sharpness (``core.metrics.sharpness``)
of the final render, of the 3DGS render before the repair (``gs.png``) and of the mesh render
(``mesh.png``), each over the output's; and how much of the truth's edges each reproduces at
their contrast (``core.metrics.edge_gain``; the truth from ``RUN/../scene/novel/color``). With
the run's ``work/map.pt`` (kept with ``--keep-work`` runs), also the mean difference in 8-bit
levels there between the final map's render and its render without the Gaussians grown from
repaired views: near 0, distillation's seeds do not paint those pixels and the blur is the
input's Gaussians'.

    .venv/bin/python benchmarks/observed_blur.py RUN1/repair RUN2/repair [--json F]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

OPAQUE = 0.99  # the input map's render counts as a surface from this alpha
ERODE_PX = 2  # away from the render's hole borders by this much
MIN_SHARE = 0.05  # views where such pixels cover less are left out


def observed_pixels(view_dir: Path) -> Any:  # [H, W] bool
    """A repaired view's pixels where the output shows the mesh render and the input map's own
    render (``alpha.png``) is opaque (``OPAQUE``, eroded by ``ERODE_PX``)."""
    import cv2
    import numpy as np

    from gsfix_online.repair.provenance import SOURCES

    alpha = cv2.imread(str(view_dir / "alpha.png"), cv2.IMREAD_UNCHANGED)
    alpha = alpha.astype(np.float32) / np.iinfo(alpha.dtype).max
    alpha = alpha[..., 0] if alpha.ndim == 3 else alpha
    kernel = np.ones((2 * ERODE_PX + 1,) * 2, np.uint8)
    opaque = cv2.erode((alpha >= OPAQUE).astype(np.uint8), kernel) > 0
    return (np.load(view_dir / "provenance.npz")["source"] == SOURCES.index("mesh")) & opaque


def seed_paint(run: Path, views: list[dict[str, Any]], masks: dict[str, Any]) -> dict[str, float]:
    """view -> mean |all - without repaired views' Gaussians| over its pixels, 8-bit levels."""
    import numpy as np
    import torch
    import yaml

    from gsfix_online.core.config import build
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.services.splat import load_snapshot

    graph = yaml.safe_load((run / "work/graph.yaml").read_text())
    m = load_snapshot(build(MapperConfig, base=graph["nodes"]["splat"]["params"]["mapper"]),
                      run / "work/map.pt")  # fmt: skip
    observed = ~m.gmap.repaired()
    out = {}
    for v in views:
        sel = masks.get(v["view"])
        if sel is None:
            continue
        T, K = np.reshape(v["camera"]["T_world_cam"], (4, 4)), np.reshape(v["camera"]["K"], (3, 3))
        H, W = sel.shape
        with torch.no_grad():
            a = m.render(T, K, W, H).color.clamp(0, 1).cpu().numpy()
            b = m.render(T, K, W, H, keep=observed).color.clamp(0, 1).cpu().numpy()
        out[v["view"]] = float(np.abs(a - b).mean(-1)[sel].mean() * 255)
    return out


def run_rows(run: Path) -> dict[str, dict[str, float]]:
    from gsfix_online.core.metrics import edge_gain, sharpness
    from gsfix_online.repair.outputs import read_png_rgb

    views = [v for v in json.loads((run / "metrics.json").read_text())["views"]
             if v.get("repair") and "final" in (v.get("metrics") or {})]  # fmt: skip
    rows, masks = {}, {}
    for v in views:
        d, name = run / "views" / v["view"], v["view"]
        truth_png = run.parent / "scene/novel/color" / f"{name}.png"
        if not truth_png.is_file():
            continue
        im = {k: read_png_rgb(d / f"{k}.png") for k in ("output", "final", "gs", "mesh")}
        sel = observed_pixels(d)
        if sel.mean() < MIN_SHARE:
            continue
        truth = read_png_rgb(truth_png)
        base = sharpness(im["output"], sel)
        rows[name] = {"share": float(sel.mean())}
        for k in ("final", "gs", "mesh"):
            rows[name][f"sharpness_{k}"] = sharpness(im[k], sel) / base
        for k in ("output", "final", "gs", "mesh"):
            rows[name][f"truth_gain_{k}"] = edge_gain(im[k], truth, sel)
        masks[name] = sel
    if (run / "work/map.pt").is_file():
        for name, x in seed_paint(run, views, masks).items():
            rows[name]["seeds_paint_levels"] = x
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="repair run folders (metrics.json)")
    ap.add_argument("--json", type=Path, help="write the rows here too")
    a = ap.parse_args()
    data = {}
    for run in a.runs:
        rows = data[str(run)] = run_rows(run)
        print(f"\n{run}\n| view | share | sharpness over the output: final, 3DGS before, mesh | "
              "truth's edges: output, final, 3DGS before, mesh | seeds' paint (levels) |\n"
              "|---|---:|---|---|---:|")  # fmt: skip
        for name, r in rows.items():
            paint = r.get("seeds_paint_levels")
            print(f"| {name} | {r['share']:.2f} | {r['sharpness_final']:.2f}, {r['sharpness_gs']:.2f}, "
                  f"{r['sharpness_mesh']:.2f} | {r['truth_gain_output']:.3f}, {r['truth_gain_final']:.3f}, "
                  f"{r['truth_gain_gs']:.3f}, {r['truth_gain_mesh']:.3f} | "
                  f"{'-' if paint is None else f'{paint:.1f}'} |")  # fmt: skip
    if a.json:
        a.json.write_text(json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
