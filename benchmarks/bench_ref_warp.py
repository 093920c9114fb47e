"""Reference-view warping (repair.ref_warp) at the held-out frames of finished repair runs.

Each held-out frame of a ``--holdout`` run is rebuilt from the run's other input frames (read
with the run's own reader settings, at its processing resolution, with the poses the run used),
warped into it by the depth of the run's ``mesh.ply`` rendered at the frame's pose; and scored
(PSNR / SSIM, whole view and per region class of ``repair.fallback.regions``) beside the run's
classical candidates (``views/NNN/*.png``) against ``work/gt``. Reference sets: every mapped
frame (``all``), every 4th of them (``every4``, what the repair node would keep as frame
samples) and the run's keyframes (``keyframes``, ``work/keyframes/*.npz``). Variants change one
setting of :class:`RefWarpConfig` or the fill order at a time. Novel views that have a ground
truth (``work/gt``) are scored too, as a second group (metres off the trajectory: where the warp
is expected to run out of references).

    .venv/bin/python benchmarks/bench_ref_warp.py RUN... \\
        --out benchmarks/results/ref_warp_cpu.json --figure benchmarks/results/ref_warp_views_cpu.png

RUN is a repair run's folder made with ``--holdout K``; runs without held-out frames are skipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _case import held_views, write_result  # noqa: E402

CLASSICAL = ("mesh_inpaint", "inpaint", "gs_inpaint")
# (name, reference set, config changes, occlusion depth: "sensor" or "mesh")
VARIANTS: list[tuple[str, str, dict[str, Any], str]] = [
    ("k4", "all", {}, "sensor"),
    ("k1", "all", {"k": 1}, "sensor"),
    ("k2", "all", {"k": 2}, "sensor"),
    ("k8", "all", {"k": 8}, "sensor"),
    ("best", "all", {"blend": "best"}, "sensor"),
    ("angle5", "all", {"angle_sigma_deg": 5.0}, "sensor"),
    ("tol0.02", "all", {"occlusion_tol": 0.02}, "sensor"),
    ("tol0.05", "all", {"occlusion_tol": 0.05}, "sensor"),
    ("tol0.10", "all", {"occlusion_tol": 0.10}, "sensor"),
    ("tol0.25", "all", {"occlusion_tol": 0.25}, "sensor"),
    ("unknown1", "all", {"unknown_depth_weight": 1.0}, "sensor"),
    ("reject_behind", "all", {"reject_behind": True}, "sensor"),
    ("mesh_occlusion", "all", {}, "mesh"),
    ("every4", "every4", {}, "sensor"),
    ("keyframes", "keyframes", {}, "sensor"),
    ("estimated", "estimated", {}, "sensor"),
]


def references(
    run: Path, graph: dict[str, Any]
) -> tuple[dict[str, list[Any]], list[np.ndarray] | None]:
    """The run's mapped input frames as references (all, every 4th, the keyframes), and, where
    the input has an ``estimated.txt`` beside the poses the run used, the held-out frames' and
    the mapped frames' poses from it (held-out list first, then a reference list)."""
    from gsfix_online.core.config import build
    from gsfix_online.repair.ref_warp import Reference
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.replay import is_held_out

    params = graph["replay"]["params"]
    every = int(params["replay"]["holdout_every"])
    reader = open_source(build(SourceConfig, base=params["source"]))
    mapped = [Reference.from_frame(f) for n, f in enumerate(reader) if not is_held_out(n, every)]
    est = None
    if Path(params["source"]["path"], "estimated.txt").is_file():
        src = {**params["source"], "pose_file": "estimated.txt"}
        poses = [f.T_world_cam for f in open_source(build(SourceConfig, base=src))]
        est = [p for n, p in enumerate(poses) if is_held_out(n, every)]
        est += [p for n, p in enumerate(poses) if not is_held_out(n, every)]
    kfs = []
    for p in sorted((run / "work" / "keyframes").glob("kf_*.npz")):
        z = np.load(p)
        kfs.append(Reference(z["color"], z["depth"], z["K"], z["T_world_cam"]))
    return {"all": mapped, "every4": mapped[::4], "keyframes": kfs}, est


def with_relative_poses(
    refs: list[Any], T_view: np.ndarray, T_view_est: np.ndarray, ref_est: list[np.ndarray]
) -> list[Any]:
    """The references placed around the view by the estimator's poses relative to the view's
    (``T_view @ inv(T_view_est) @ T_ref_est``): the mesh and the view stay in the run's frame,
    the references carry the estimator's relative error."""
    from gsfix_online.core.se3 import inv_T

    A = T_view @ inv_T(T_view_est)
    return [dataclasses.replace(r, T_world_cam=A @ T) for r, T in zip(refs, ref_est, strict=True)]


def with_mesh_depth(refs: list[Any], renderer: Any) -> list[Any]:
    """The references with their depth replaced by the mesh's at their pose (0 where none)."""
    from gsfix_online.core.types import Intrinsics

    out = []
    for r in refs:
        h, w = r.depth_m.shape
        m = renderer.render(r.T_world_cam, Intrinsics.from_K(r.K, w, h))
        out.append(dataclasses.replace(r, depth_m=m.depth_m))
    return out


def score(img: np.ndarray, gt: np.ndarray, region: np.ndarray) -> dict[str, Any]:
    from gsfix_online.core.metrics import region_scores
    from gsfix_online.repair.fallback import REGIONS

    whole, parts = region_scores(img, gt, region, REGIONS)
    return {"psnr_db": whole.psnr_db, "ssim": whole.ssim,
            "regions": {k: {"psnr_db": v.psnr_db, "ssim": v.ssim, "mse": v.mse, "pixels": v.pixels}
                        for k, v in parts.items()}}  # fmt: skip


def score_run(run: Path, figure_rows: list[np.ndarray]) -> dict[str, Any] | None:
    import json

    from gsfix_online.core.config import read_yaml
    from gsfix_online.core.se3 import pose_distances
    from gsfix_online.core.types import Intrinsics
    from gsfix_online.mapping.mesh import read_mesh
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.repair.fallback import regions
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.ref_warp import RefWarpConfig, ref_warp, ref_warp_inpaint

    held = held_views(run)
    if not held:
        print(f"{run}: no held-out frames, skipped")
        return None
    graph = read_yaml(run / "work" / "graph.yaml")["nodes"]
    t0 = time.perf_counter()
    ref_sets, est = references(run, graph)
    read_s = time.perf_counter() - t0
    renderer = MeshRenderer(read_mesh(run / "mesh.ply"))
    mesh_refs = with_mesh_depth(ref_sets["all"], renderer)
    first = min(held)
    cams = {int(v["view"]): v["camera"] for v in json.loads((run / "metrics.json").read_text())["views"]}  # fmt: skip
    gts = {int(p.stem) for p in (run / "work" / "gt").glob("*.png")}
    novel = sorted(v for v in gts if v not in held and (run / "views" / f"{v:03d}").is_dir())
    rows, times = [], []
    for vid in [*sorted(held), *novel]:
        d = run / "views" / f"{vid:03d}"
        cam = cams[vid]
        K = np.asarray(cam["K"], np.float64).reshape(3, 3)
        T = np.asarray(cam["T_world_cam"], np.float64).reshape(4, 4)
        w, h = int(cam["width"]), int(cam["height"])
        gt = read_png_rgb(run / "work" / "gt" / f"{vid:03d}.png", w, h)
        alpha = cv2.imread(str(d / "alpha.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 255
        m = renderer.render(T, Intrinsics.from_K(K, w, h))
        region = regions(alpha, m.valid)
        gs = read_png_rgb(d / "gs.png")
        images = {c: read_png_rgb(d / f"{c}.png") for c in CLASSICAL}
        group = "holdout" if vid in held else "novel"
        row: dict[str, Any] = {"view": f"{vid:03d}", "group": group, "scores": {}, "coverage": {},
                               "used": {}}  # fmt: skip
        all_T = np.stack([r.T_world_cam for r in ref_sets["all"]])
        row["nearest_ref_m"] = float(pose_distances(T, all_T, 0.0).min())  # translation only
        ref_sets.pop("estimated", None)
        if est is not None and group == "holdout":
            n_held = len(est) - len(ref_sets["all"])
            ref_sets["estimated"] = with_relative_poses(
                ref_sets["all"], T, est[vid - first], est[n_held:]
            )
        for name, refset, change, occl in VARIANTS:
            if refset not in ref_sets:
                continue
            refs = mesh_refs if occl == "mesh" else ref_sets[refset]
            cfg = dataclasses.replace(RefWarpConfig(), **change)
            t = time.perf_counter()
            warp = ref_warp(K, T, m.depth_m, m.valid, w, h, refs, cfg)
            if name == "k4":
                times.append(time.perf_counter() - t)
            rgb = m.rgb()
            images[f"ref_warp:{name}"] = warp.image
            images[f"ref_warp_inpaint:{name}"] = ref_warp_inpaint(warp, rgb, m.valid)
            if name == "k4":  # the other fill orders, for the default setting only
                images["ref_warp_fill:k4"] = ref_warp_inpaint(warp, rgb, m.valid, gs, alpha)
                gs_first = np.where((alpha >= 0.5)[..., None], gs, images["ref_warp_inpaint:k4"])
                images["gs_ref_warp_inpaint:k4"] = gs_first
            row["coverage"][name] = warp.coverage
            row["used"][name] = len(warp.used)
        for k, img in images.items():
            row["scores"][k] = score(img, gt, region)
        row["region_pixels"] = {r: int((region == i).sum()) for i, r in enumerate(("both", "gs_only", "mesh_only", "neither"))}  # fmt: skip
        rows.append(row)
        best = max(CLASSICAL, key=lambda c: row["scores"][c]["psnr_db"])
        if group == "holdout":
            figure_rows.append(np.concatenate(
                [gt, images[best], images["ref_warp:k4"], images["ref_warp_inpaint:k4"]], axis=1))  # fmt: skip
        print(f"{run.name} {group} {vid:03d}: " + " ".join(
            f"{k} {row['scores'][k]['psnr_db']:.2f}" for k in (*CLASSICAL, "ref_warp:k4", "ref_warp_inpaint:k4")
        ) + f" cov {row['coverage']['k4']:.3f}", flush=True)  # fmt: skip
    return {"run": str(run), "size": [w, h], "references": {k: len(v) for k, v in ref_sets.items()},
            "read_s": read_s, "warp_s_median": float(np.median(times)), "views": rows}  # fmt: skip


def medians(result: dict[str, Any], group: str) -> dict[str, Any] | None:
    """Per image kind: median PSNR / SSIM over the group's views, and pooled per-region PSNR."""
    from gsfix_online.core.metrics import _psnr_db

    views = [v for v in result["views"] if v["group"] == group]
    if not views:
        return None
    out: dict[str, Any] = {}
    for k in views[0]["scores"]:
        p = [v["scores"][k]["psnr_db"] for v in views]
        s = [v["scores"][k]["ssim"] for v in views]
        reg = {}
        for r in ("both", "gs_only", "mesh_only", "neither"):
            parts = [v["scores"][k]["regions"][r] for v in views if r in v["scores"][k]["regions"]]
            n = sum(x["pixels"] for x in parts)
            if n:
                reg[r] = _psnr_db(sum(x["mse"] * x["pixels"] for x in parts) / n)
        out[k] = {
            "psnr_db": float(np.median(p)),
            "ssim": float(np.median(s)),
            "region_psnr_db": reg,
        }
    out["coverage"] = {n: float(np.median([v["coverage"][n] for v in views]))
                       for n in views[0]["coverage"]}  # fmt: skip
    return out


def compact(x: Any, keep_regions: tuple[str, ...]) -> Any:
    """The rows for the JSON: floats to 4 decimals, per-view region scores only for the kinds
    in ``keep_regions`` (the medians keep every kind's)."""
    if isinstance(x, float):
        return round(x, 4)
    if isinstance(x, list):
        return [compact(v, keep_regions) for v in x]
    if not isinstance(x, dict):
        return x
    if "scores" in x and "group" in x:  # a view's row
        x = {**x, "scores": {k: (v if k in keep_regions else {a: v[a] for a in ("psnr_db", "ssim")})
                             for k, v in x["scores"].items()}}  # fmt: skip
    return {k: compact(v, keep_regions) for k, v in x.items()}


REGION_KINDS = (*CLASSICAL, "ref_warp:k4", "ref_warp_inpaint:k4", "ref_warp_fill:k4")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/ref_warp_cpu.json"))
    ap.add_argument("--figure", type=Path, default=None, help="PNG: gt | best classical | warp | warp + Telea")  # fmt: skip
    ap.add_argument("--figure-views", type=int, default=4)
    ap.add_argument("--figure-scale", type=float, default=0.75)
    ap.add_argument("--variants", default="", help="comma-separated variant names (default: all)")
    args = ap.parse_args()
    if args.variants:
        keep = set(args.variants.split(",")) | {"k4"}  # k4: the default, always measured
        unknown = keep - {v[0] for v in VARIANTS}
        if unknown:
            ap.error(f"unknown variant(s) {sorted(unknown)}; known: {[v[0] for v in VARIANTS]}")
        VARIANTS[:] = [v for v in VARIANTS if v[0] in keep]
    cv2.setNumThreads(1)
    rows, summary, fig = [], [], []
    for run in args.runs:
        figure_rows: list[np.ndarray] = []
        r = score_run(run, figure_rows)
        if r is None:
            continue
        r["median"] = medians(r, "holdout")
        r["novel_median"] = medians(r, "novel")
        rows.append(r)
        summary.append({"run": str(run), "median": r["median"], "novel_median": r["novel_median"],
                        "warp_s_median": r["warp_s_median"]})  # fmt: skip
        if not fig:  # the first run's views only: one image size
            step = max(1, len(figure_rows) // args.figure_views)
            fig = figure_rows[::step][: args.figure_views]
        for group in ("median", "novel_median"):
            for k, v in (r[group] or {}).items():
                if k != "coverage":
                    reg = " ".join(f"{a} {b:.2f}" for a, b in v["region_psnr_db"].items())
                    print(f"{run.name} {group} {k}: {v['psnr_db']:.2f} / {v['ssim']:.3f} | {reg}")
            if r[group]:
                print(f"{run.name} {group} coverage {r[group]['coverage']}")
        print(f"{run.name} warp {r['warp_s_median']:.3f} s")
    write_result(args.out, __doc__, 1, compact(summary, REGION_KINDS), compact(rows, REGION_KINDS))
    if args.figure and fig:
        img = np.concatenate(fig, axis=0)
        img = cv2.resize(img, None, fx=args.figure_scale, fy=args.figure_scale, interpolation=cv2.INTER_AREA)  # fmt: skip
        # 256 colours, no dithering: the noisy room compresses to 700 KB in full colour, 200 KB so
        from PIL import Image

        Image.fromarray(img).quantize(256, dither=Image.Dither.NONE).save(args.figure, optimize=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
