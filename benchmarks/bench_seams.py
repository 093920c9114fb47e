"""Double images where a blend mixes GSFixer into a fallback: finished runs' outputs recomposed.

Where neither map covers a far view the repair blends GSFixer into mesh + Telea
(``repair.fallback.FAR_NEITHER_SHARE``). Their per-pixel mean shows Telea's facets through
GSFixer's wash. For every repaired view with ground truth of finished repair runs this
recomposes the output from the run's own saved candidates (``fixed.png``, ``inpaint.png``,
``mesh_inpaint.png``; regions from ``alpha.png`` and the mesh render's coverage; the run's
choice, shares and seam feathering) by each rule (arm) and scores it against the ground truth:

- ``mean``: the per-pixel mean by the share (the rule before; must reproduce ``output.png``),
- ``detail:S``: GSFixer by its share over the fallback's colours blurred by a Gaussian of S px
  (``repair.fallback.blend``; the fallback's edges never show),
- ``gsdetail:S``: both blurred by S px and mixed by the share, the detail above that GSFixer's
  at full contrast,
- ``pick:T``: the mean where the two fills agree (their difference, blurred by 2 px, under 10
  levels), one fill where they differ (over 30 levels; a ramp between): T is ``fixer``,
  ``fill``, ``smoother`` (the one of lower local gradient energy) or ``depth`` (Telea within
  4 px of the mesh's coverage, GSFixer from 12 px on).

Measures per view: PSNR and SSIM of the whole view; in the ``neither`` region, PSNR, the
sharpness (mean gradient magnitude against the ground truth's) and ``facet``: the output's mean
gradient magnitude on Telea's facet edges (pixels where mesh + Telea has an edge, > 2 levels/px,
and the ground truth none, < 1) over Telea's own there (1: the facets fully there; GSFixer
alone scores what its own output has on those pixels). Medians per run, over all its views and
over the views that blend (the others are equal in every arm). With ``--strip`` it saves
ground truth, mesh + Telea, GSFixer, the output before (``mean``) and after (the first
``detail`` arm) of the named views side by side.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_seams.py \\
        demo_fixed=/work/runs/demo_fixed/repair:/work/runs/demo_fixed/scene/novel/color \\
        demo_after=/work/runs/demo_after/repair:/work/runs/demo_after/scene/novel/color \\
        demo_after400=/work/runs/demo_after400/repair:/work/runs/demo_after400/scene/novel/color \\
        room=/work/runs/room_run:/work/runs/room_run/work/gt \\
        --arms mean detail:8 detail:2 detail:4 detail:16 gsdetail:8 pick:fixer pick:fill \\
        pick:smoother pick:depth --strip demo_fixed/000 demo_fixed/004 demo_fixed/006 room/000

Results: ``benchmarks/results/seams_cpu.json`` (and ``seams_strip.png``), page ``seams_cpu.md``.
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
import numpy.typing as npt

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import masked_scores, scores  # noqa: E402
from gsfix_online.repair.fallback import (  # noqa: E402
    REGIONS,
    Choice,
    compose,
    lowpass,
    region_weights,
    regions,
)
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402

NEITHER = REGIONS.index("neither")


def grad(img: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:  # [H, W] levels/px
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    return np.hypot(gx, gy)


def load(name: str, run: Path, gt_dir: Path) -> list[dict[str, Any]]:
    metrics = json.loads((run / "metrics.json").read_text())
    out = []
    for v in metrics["views"]:
        d, gt = run / "views" / v["view"], gt_dir / f"{v['view']}.png"
        mod = v.get("model") or {}
        if not v.get("repair") or not gt.is_file() or "choice" not in mod:
            continue
        c = {k: read_png_rgb(d / f"{k}.png") for k in ("fixed", "inpaint", "mesh_inpaint")}
        alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
        valid = read_png_rgb(d / "mesh.png").any(axis=2)  # the mesh render is black off-surface
        h, w = alpha.shape
        share = {r: float(x) for r, x in mod.get("choice_share", {}).items()}
        choice = Choice({r: mod["choice"][r] for r in REGIONS}, {}, {}, 0, "", share)
        out.append({"run": name, "view": v["view"], "gt": read_png_rgb(gt, w, h), "c": c,
                    "valid": valid, "region": regions(alpha, valid), "choice": choice,
                    "feather": float(mod.get("feather_px", 4.0)),
                    "output": read_png_rgb(d / "output.png")})  # fmt: skip
    return out


def pick_share(
    f: npt.NDArray[np.uint8], b: npt.NDArray[np.uint8], share: float, valid: npt.NDArray, to: str
) -> npt.NDArray[np.float32]:  # [H, W] GSFixer's share per pixel
    diff = lowpass(np.abs(f.astype(np.float32) - b.astype(np.float32)).mean(axis=2), 2.0)
    gate = np.clip((diff - 10.0) / 20.0, 0.0, 1.0)
    if to == "fixer":
        t = np.ones_like(gate)
    elif to == "fill":
        t = np.zeros_like(gate)
    elif to == "smoother":
        t = lowpass(
            (lowpass(grad(f) ** 2, 4.0) < lowpass(grad(b) ** 2, 4.0)).astype(np.float32), 2.0
        )
    elif to == "depth":
        dist = cv2.distanceTransform((~valid).astype(np.uint8), cv2.DIST_L2, 5)
        t = np.clip((dist - 4.0) / 8.0, 0.0, 1.0)
    else:
        raise SystemExit(f"pick must be fixer, fill, smoother or depth, got {to!r}")
    return ((1.0 - gate) * share + gate * t).astype(np.float32)


def recompose(x: dict[str, Any], arm: str) -> npt.NDArray[np.uint8]:
    kind, _, arg = arm.partition(":")
    ch, region, c = x["choice"], x["region"], x["c"]
    if kind == "mean":
        return compose(c, region, ch, x["feather"], detail_px=0.0)
    if kind == "detail":
        return compose(c, region, ch, x["feather"], detail_px=float(arg))
    if kind not in ("pick", "gsdetail"):
        raise SystemExit(f"an arm is mean, detail:S, gsdetail:S or pick:T, got {arm!r}")
    # each blended source mixed per pixel, then the regions feathered as compose does
    src = {r: c[ch.per_region[r]] for r in REGIONS}
    for r, w in ch.share.items():
        f, b = c["fixed"].astype(np.float32), c[ch.per_region[r]].astype(np.float32)
        if kind == "gsdetail":
            src[r] = np.clip(np.rint(f + (1 - w) * lowpass(b - f, float(arg))), 0, 255)
            continue
        s = pick_share(c["fixed"], c[ch.per_region[r]], w, x["valid"], arg)[..., None]
        src[r] = np.clip(np.rint(s * f + (1 - s) * b), 0, 255)
    index = np.arange(len(REGIONS), dtype=np.uint8)
    weights = region_weights(region, len(REGIONS), index, x["feather"])
    acc = sum(
        w[..., None] * src[r].astype(np.float32) for w, r in zip(weights, REGIONS, strict=True)
    )
    return np.clip(np.rint(acc), 0, 255).astype(np.uint8)


def measure(img: npt.NDArray[np.uint8], x: dict[str, Any]) -> dict[str, float]:
    gt, nei = x["gt"], x["region"] == NEITHER
    s = scores(img, gt)
    out = {"psnr_db": s.psnr_db, "ssim": s.ssim}
    if nei.sum() < 200:
        return out
    out["neither_psnr_db"] = masked_scores(img, gt, {"n": nei})["n"].psnr_db
    go, gg, gm = grad(img), grad(gt), grad(x["c"]["mesh_inpaint"])
    out["neither_sharpness"] = float(go[nei].mean() / max(float(gg[nei].mean()), 1e-6))
    facet = nei & (gm > 2.0) & (gg < 1.0)  # Telea's edges where the truth has none
    if facet.sum() >= 50:
        out["facet"] = float(go[facet].mean() / gm[facet].mean())
    return out


def medians(rows: list[dict[str, float]]) -> dict[str, float]:
    keys = ("psnr_db", "ssim", "neither_psnr_db", "neither_sharpness", "facet")
    return {k: statistics.median(r[k] for r in rows if k in r) for k in keys
            if any(k in r for r in rows)}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="NAME=REPAIR_DIR:GT_DIR")
    ap.add_argument("--arms", nargs="+", default=["mean", "detail:8"])
    ap.add_argument("--strip", nargs="*", default=[], help="RUN/VIEW to show before and after")
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "seams_cpu.json"
    )
    args = ap.parse_args()
    data = {}
    for spec in args.runs:
        name, _, dirs = spec.partition("=")
        run, _, gt = dirs.partition(":")
        data[name] = load(name, Path(run), Path(gt))
        print(f"{name}: {len(data[name])} views with ground truth", flush=True)
    rows: dict[str, dict[str, Any]] = {}
    images: dict[tuple[str, str, str], npt.NDArray[np.uint8]] = {}
    for name, xs in data.items():
        for x in xs:
            key = f"{name}/{x['view']}"
            rows[key] = {"blends": bool(x["choice"].share), "arms": {}}
            for arm in args.arms:
                if not x["choice"].share and arm != args.arms[0]:  # nothing blends: all equal
                    rows[key]["arms"][arm] = rows[key]["arms"][args.arms[0]]
                    continue
                img = recompose(x, arm)
                if arm == "mean":
                    rows[key]["reproduced"] = float((img == x["output"]).all(axis=2).mean())
                if key in args.strip:
                    images[name, x["view"], arm] = img
                rows[key]["arms"][arm] = measure(img, x)
        print(f"{name}: done", flush=True)
    summary: dict[str, Any] = {}
    for name in data:
        keys = [k for k in rows if k.startswith(name + "/")]
        summary[name] = {
            arm: {"all": medians([rows[k]["arms"][arm] for k in keys]),
                  "blending": medians([rows[k]["arms"][arm] for k in keys if rows[k]["blends"]])
                  if any(rows[k]["blends"] for k in keys) else {}}
            for arm in args.arms
        }  # fmt: skip
    print("| run | arm | views | PSNR dB | SSIM | blending views | PSNR dB | SSIM | no-map PSNR dB "
          "| no-map sharpness | Telea facets |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in data:
        n_all = sum(k.startswith(name + "/") for k in rows)
        n_bl = sum(k.startswith(name + "/") and rows[k]["blends"] for k in rows)
        for arm in args.arms:
            a, b = summary[name][arm]["all"], summary[name][arm]["blending"]
            print(f"| {name} | {arm} | {n_all} | {a['psnr_db']:.2f} | {a['ssim']:.3f} | {n_bl} | "
                  f"{b.get('psnr_db', float('nan')):.2f} | {b.get('ssim', float('nan')):.3f} | "
                  f"{b.get('neither_psnr_db', float('nan')):.2f} | "
                  f"{b.get('neither_sharpness', float('nan')):.2f} | "
                  f"{b.get('facet', float('nan')):.2f} |")  # fmt: skip
    repro = [r["reproduced"] for r in rows.values() if "reproduced" in r]
    if repro:
        print(f"mean reproduces the runs' output.png: min share of equal pixels {min(repro):.3f}")
    if args.strip and images:
        after = next(a for a in args.arms if a.startswith("detail"))
        strip = []
        for key in args.strip:
            name, view = key.split("/")
            x = next(x for x in data[name] if x["view"] == view)
            tiles = [x["gt"], x["c"]["mesh_inpaint"], x["c"]["fixed"],
                     images[name, view, "mean"], images[name, view, after]]  # fmt: skip
            w = 320  # every tile 320 px wide, the room's 16:9 views lower than the tank's 4:3
            tiles = [cv2.resize(t, (w, round(t.shape[0] * w / t.shape[1])), interpolation=cv2.INTER_AREA)
                     for t in tiles]  # fmt: skip
            strip.append(np.concatenate(tiles, axis=1))
        width = max(s.shape[1] for s in strip)
        strip = [
            np.pad(s, ((0, 4), (0, width - s.shape[1]), (0, 0)), constant_values=255) for s in strip
        ]
        png = args.out.with_name(args.out.stem.replace("_cpu", "") + "_strip.png")
        bgr = cv2.cvtColor(np.concatenate(strip, axis=0), cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(png), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9])  # photographs: ~1.5 MB
        print(
            f"-> {png} (columns: ground truth, mesh + Telea, GSFixer, before: mean, after: {after})"
        )
    result = {
        "about": __doc__.split("\n")[0],
        "argv": sys.argv[1:],
        "summary": summary,
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
