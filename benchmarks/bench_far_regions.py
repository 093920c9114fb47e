"""Far views recomposed by ``fallback.far_regions``: what each of its two rules does.

For finished repair runs made before ``far_regions`` (their views composed by ``regions()``
alone), every view that took the mesh first (``model.choice_from``) is composed again from
the candidates the run saved (``fixed.png``, ``inpaint.png``, ``mesh_inpaint.png``; no model
runs), with its own recorded choice and seams, in five arms:

- ``run``: the output as the run delivered it;
- ``regions``: recomposed by ``regions()``. Equal to ``run`` on the runs this was written for
  (made before ``far_regions``); on session 65's room seed 1 run views 000 and 001 are exact
  and 002-007 differ in 4-41 % of their pixels, in the 3DGS-only and no-map regions: the
  repair node took the "grown" pixels from its render's synthesised share, which those runs did
  not save, and the provenance's source (used for them) no longer says "grown" where the node
  made them holes. Runs whose ``provenance.npz`` keeps the regions the node composed by
  (``region``) are recomposed from those;
- ``flat``: holes with flat surroundings take mesh + Telea alone (``FLAT_RING_STD``);
- ``grown``: what only the 3DGS map covers and repaired views grew (the run's provenance
  ``gs_repaired`` there) is a hole (``FAR_GS_ONLY_HOLES`` "grown", the default);
- ``gs_only``: all that only the 3DGS map covers is a hole ("all");
- ``far_regions``: ``flat`` and ``grown``, as the repair node now composes a far view;
- ``flat+gs_only``: ``flat`` and ``gs_only``;

and ``mesh_inpaint`` (mesh + Telea, the floor) for reference. Per run the mean PSNR and SSIM
over those views, and per view the PSNR of each arm. The final map is not recomposed: for it,
run the input again.

    .venv/bin/python benchmarks/bench_far_regions.py RUN [RUN ...] [--json FILE]

(RUN: a demo's output folder, with ``repair/`` and the ground truth in ``scene/novel/color``.)
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import psnr, ssim  # noqa: E402
from gsfix_online.repair.fallback import (  # noqa: E402
    GS_ONLY,
    NEITHER,
    Choice,
    compose,
    far_regions,
    regions,
)
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402
from gsfix_online.repair.provenance import GS_REPAIRED  # noqa: E402

ARMS = ("run", "regions", "flat", "grown", "gs_only", "far_regions", "flat+gs_only", "mesh_inpaint")


@dataclass
class FarView:
    """A far view of a finished run, as saved: what recomposing it needs."""

    gt: np.ndarray  # [H, W, 3] the ground truth
    choice: Choice  # the run's recorded choice and blend shares
    feather: float
    detail: float
    cands: dict[str, np.ndarray]  # fixed, inpaint, mesh_inpaint
    region: np.ndarray  # [H, W] regions() of its renders
    grown: np.ndarray  # [H, W] 3DGS-only pixels that repaired views' Gaussians make


def far_view(run: Path, v: dict[str, Any]) -> FarView | None:
    """A view of ``run``'s metrics.json that took the mesh first and has ground truth, loaded
    from the files the run saved; None for any other view."""
    model = v.get("model") or {}
    d, gt_path = (
        run / "repair" / "views" / v["view"],
        run / "scene/novel/color" / f"{v['view']}.png",
    )
    if model.get("choice_from") != "mesh first" or not gt_path.is_file():
        return None
    share = {r: float(w) for r, w in model.get("choice_share", {}).items()}
    alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
    region = regions(alpha, read_png_rgb(d / "mesh.png").any(axis=2))
    with np.load(d / "provenance.npz") as z:
        if "region" in z:  # the regions the node composed by: its 3DGS-only pixels made holes
            grown = (z["region"] == NEITHER) & (region == GS_ONLY)
        else:  # runs before the file kept them (see ``regions`` above)
            grown = (z["source"] == GS_REPAIRED) & (region == GS_ONLY)
    return FarView(
        read_png_rgb(gt_path), Choice(dict(model["choice"]), {}, {}, 0, "", share),
        float(model.get("feather_px", 4.0)), float(model.get("detail_px", 8.0)),
        {c: read_png_rgb(d / f"{c}.png") for c in ("fixed", "inpaint", "mesh_inpaint")},
        region, grown,
    )  # fmt: skip


def bench_run(run: Path) -> dict[str, Any]:
    m = json.loads((run / "repair" / "metrics.json").read_text())
    rows = []
    for v in m["views"]:
        fv = far_view(run, v)
        if fv is None:
            continue
        d = run / "repair" / "views" / v["view"]
        gt, choice, feather, detail = fv.gt, fv.choice, fv.feather, fv.detail
        cands, region, grown = fv.cands, fv.region, fv.grown
        every = region == GS_ONLY
        images = {
            "run": read_png_rgb(d / "output.png"),
            "regions": compose(cands, region, choice, feather, detail),
            "flat": far_regions(region, cands, choice, feather),
            "grown": far_regions(region, cands, choice, feather, 0.0, grown),
            "gs_only": far_regions(region, cands, choice, feather, 0.0, every),
            "far_regions": far_regions(region, cands, choice, feather, holes=grown),
            "flat+gs_only": far_regions(region, cands, choice, feather, holes=every),
            "mesh_inpaint": cands["mesh_inpaint"],
        }
        for arm in ("flat", "grown", "gs_only", "far_regions", "flat+gs_only"):
            images[arm] = compose(cands, images[arm], choice, feather, detail)
        rows.append({
            "view": v["view"], "gs_only_share": float(every.mean()), "grown_share": float(grown.mean()),
            "psnr_db": {a: psnr(im, gt) for a, im in images.items()},
            "ssim": {a: ssim(im, gt) for a, im in images.items()},
        })  # fmt: skip
    mean = {
        k: {a: float(np.mean([r[k][a] for r in rows])) for a in ARMS} for k in ("psnr_db", "ssim")
    }
    return {"run": str(run), "views": rows, "mean": mean if rows else {}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, help="write the results here")
    a = ap.parse_args()
    out = []
    print("| run | far views | run dB | " + " | ".join(ARMS[1:]) + " |")
    print("|---|---:|---:|" + "---:|" * (len(ARMS) - 1))
    for run in a.runs:
        res = bench_run(run)
        out.append(res)
        if not res["views"]:
            print(f"| {run.name} | 0 | | {' | ' * (len(ARMS) - 2)}|")
            continue
        p = res["mean"]["psnr_db"]
        print(f"| {run.name} | {len(res['views'])} | {p['run']:.2f} | "
              + " | ".join(f"{p[x] - p['run']:+.3f}" for x in ARMS[1:]) + " |")  # fmt: skip
    if a.json:
        atomic_write_text(a.json, json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
