"""Fine-tuning seed spread: GSFixer's 2D repairs after the repair graph's fine-tuning, once per
fine-tuning seed, against the OpenCV baseline and the untuned base, at a run's novel views and
held-out frames.

A repair run decides its GSFixer-vs-Telea margin with one fine-tuning run, and that margin moves
with the seed of the masks, crops, noise and timesteps. This benchmark replays the fine-tuning of
the repair graph's trainer node on the keyframes a finished run saved, once per seed:

- the trainer node's own service (``nodes/trainer.py``) with the graph's trainer parameters
  (``configs/graphs/repair.yaml``) plus any ``KEY=VALUE`` overrides (to compare a variant, e.g.
  ``fixer.train.lr=1e-4 policy.max_steps_per_run=300 fixer.train.wise_alpha=0.5``);
- trained until it announces the end of its run, as the repair node waits for it
  (``checkpoint: run``); the announced checkpoint repairs the run's views from exactly the
  renders the run's repair node had (``views/NNN/gs.png``, ``mesh.png``);
- scored against the run's ground truth (``work/gt``: the user's novel views, then the held-out
  frames of ``--holdout``; a demo's: its scene's novel views, ``summary.ground_truth``) next
  to the run's own Telea baseline (``inpaint.png``) and the untuned packaged base repairing
  the same renders.

RUN is a repair run's output folder (``gsfix-online repair --out RUN``; a demo's
``outputs/demo/repair``; a ``bench_variants.py`` case's ``run/``). Its keyframes are in
``RUN/work/keyframes`` and its mesh is the final ``RUN/mesh.ply`` (the trainer's one run starts
after mapping, on about the final mesh)::

    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_fixer_seeds.py RUN \\
        --seeds 4 --jobs 2 [KEY=VALUE ...]

Results: ``benchmarks/results/fixer_seeds_cpu.json`` (one entry per invocation, appended).
"""

from __future__ import annotations

import argparse
import functools
import json
import platform
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._case import held_views  # noqa: E402
from gsfix_online.core.io import atomic_write_text  # noqa: E402

GRAPH = Path(__file__).resolve().parents[1] / "configs" / "graphs" / "repair.yaml"
GROUPS = ("novel", "holdout")


@functools.cache
def _gt_dir(run: Path) -> Path:
    """The run's ground-truth folder: where its summary says (a demo: the scene's novel views),
    else ``RUN/work/gt`` (``--holdout`` runs); read once per run."""
    metrics = json.loads((run / "metrics.json").read_text())
    return Path(metrics["summary"].get("ground_truth") or run / "work" / "gt")


def _gt(run: Path, name: str) -> Path:
    return _gt_dir(run) / f"{name}.png"


def _views(run: Path) -> list[dict[str, Any]]:
    """The run's repaired views with a ground truth: name, group, the run's Telea and output."""
    metrics = json.loads((run / "metrics.json").read_text())
    held = held_views(run)
    views = []
    for v in metrics["views"]:
        name = f"{v['view_id']:03d}"
        if not v.get("repair") or "inpaint" not in v.get("metrics", {}):
            continue
        if not _gt(run, name).is_file():
            continue
        group = "holdout" if v["view_id"] in held else "novel"
        views.append({"name": name, "group": group,
                      "inpaint": v["metrics"]["inpaint"]["psnr_db"],
                      "output": v["metrics"]["output"]["psnr_db"]})  # fmt: skip
    if not views:
        raise SystemExit(f"{run}: no repaired views scored against ground truth")
    return views


def _scores(
    rep: Any, run: Path, views: list[dict[str, Any]], images: list[Any] | None = None
) -> list[tuple[float, float]]:
    """(PSNR, SSIM) of ``rep``'s repair of each view's renders against its ground truth; the
    repairs are appended to ``images`` when given."""
    from gsfix_online.core.metrics import psnr, ssim
    from gsfix_online.repair.outputs import read_png_rgb

    out = []
    for v in views:
        d = run / "views" / v["name"]
        gt = read_png_rgb(_gt(run, v["name"]))
        img = rep.repair(read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")).image
        out.append((psnr(img, gt), ssim(img, gt)))
        if images is not None:
            images.append(img)
    return out


def _region_sse(run: Path, name: str, img: Any) -> dict[str, list[float]]:
    """Squared error (8-bit levels, summed over pixels and channels) and pixel count of ``img``
    in each region class of view ``name`` (seen by both maps, the 3DGS map only, the mesh
    only, neither: the run's 3DGS alpha, and the mesh render where it is not black)."""
    import numpy as np

    from gsfix_online.repair.fallback import REGIONS, regions
    from gsfix_online.repair.outputs import read_png_rgb

    d = run / "views" / name
    gt = read_png_rgb(_gt(run, name)).astype(np.float64)
    alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
    region = regions(alpha, read_png_rgb(d / "mesh.png").any(axis=2))
    err = ((np.asarray(img, np.float64) - gt) ** 2).sum(axis=2)
    return {r: [float(err[region == i].sum()), int((region == i).sum())]
            for i, r in enumerate(REGIONS)}  # fmt: skip


def _half(run: Path, name: str, img: Any) -> Any:
    """``img`` and the run's mesh + Telea of view ``name``, half and half (8-bit)."""
    import numpy as np

    from gsfix_online.repair.outputs import read_png_rgb

    other = read_png_rgb(run / "views" / name / "mesh_inpaint.png").astype(np.float32)
    return np.clip(np.rint(0.5 * np.asarray(img, np.float32) + 0.5 * other), 0, 255).astype(
        np.uint8
    )


def _region_psnr(per_view: list[dict[str, list[float]]]) -> dict[str, float]:
    """Pooled PSNR per region class over views (regions no view has left out)."""
    import math

    out = {}
    for r in per_view[0]:
        sse = sum(v[r][0] for v in per_view)
        n = sum(v[r][1] for v in per_view)
        if n:
            out[r] = 10 * math.log10(255.0**2 * 3 * n / max(sse, 1e-12))
    return out


def _write_images(
    folder: Path, run: Path, views: list[dict[str, Any]], base: list[Any], tuned: list[Any]
) -> None:
    """One strip per view: 3DGS | mesh | mesh fill + Telea | untuned base | seed 0 | truth."""
    import numpy as np

    from gsfix_online.repair.outputs import read_png_rgb, write_png

    folder.mkdir(parents=True, exist_ok=True)
    for v, b, t in zip(views, base, tuned, strict=True):
        d = run / "views" / v["name"]
        strip = [read_png_rgb(d / f"{k}.png") for k in ("gs", "mesh", "inpaint")]
        gt = read_png_rgb(_gt(run, v["name"]))
        write_png(folder / f"{v['group']}_{v['name']}.png", np.concatenate([*strip, b, t, gt], 1))


def _params(keyframes: str, ck: str, seed: int, overrides: list[str]) -> Any:
    import gsfix_online.nodes.trainer as tn

    from gsfix_online.core.config import build, read_yaml

    base = read_yaml(GRAPH)["nodes"]["trainer"]["params"]
    return build(
        tn.Params,
        base=base,
        overrides=[
            f"checkpoint_dir={ck}",
            f"keyframe_dir={keyframes}",
            f"fixer.train.seed={seed}",
            *overrides,
        ],
    )


def _base(
    run: str, keyframes: str, overrides: list[str]
) -> tuple[list[tuple[float, float]], list[Any]]:
    """The untuned base (with the variant's model and inference settings) on the run's views:
    scores and repairs."""
    import torch

    torch.set_num_threads(1)
    from gsfix_online.repair.repairer import ViewRepairer

    with tempfile.TemporaryDirectory() as ck:
        rep = ViewRepairer(_params(keyframes, ck, 0, overrides).fixer)
        rep.load_base()
        images: list[Any] = []
        return _scores(rep, Path(run), _views(Path(run)), images), images


def _one_seed(run: str, keyframes: str, seed: int, overrides: list[str]) -> dict[str, Any]:
    """Fine-tune with ``seed`` until the run ends; repair and score the run's views."""
    import torch

    torch.set_num_threads(1)
    import gsfix_online.nodes.trainer as tn

    from gsfix_online.repair.repairer import ViewRepairer
    from gsfix_online.runtime import Message

    root = Path(run)
    with tempfile.TemporaryDirectory() as ck:
        params = _params(keyframes, ck, seed, overrides)
        # 1. The trainer node's service, its keyframes restored from disk, the final mesh
        t0 = time.perf_counter()
        svc = tn.TrainerService("trainer", params)
        mesh = {"kind": "mesh_written", "path": str(root / "mesh.ply"), "version": 1}
        svc.on_mesh(Message("mesh/tsdf", "map_event", meta=mesh))
        n_keyframes = len(svc.keyframes)
        # 2. Train until the run's end is announced (what `checkpoint: run` waits for)
        done = None
        while done is None:
            for msg in svc.work(0):
                if msg.meta.get("run_done"):
                    done = msg.meta
            if done is None and not svc.busy:
                raise RuntimeError(f"seed {seed}: the trainer went idle without ending a run")
        train_s = time.perf_counter() - t0
        # 3. Repair the run's views with the announced checkpoint
        rep = ViewRepairer(params.fixer)
        rep.load_checkpoint(done["path"], version=int(done["version"]))
        images: list[Any] = []
        views = _views(root)
        scores = _scores(rep, root, views, images)
    return {
        "seed": seed,
        "keyframes": n_keyframes,
        "steps": int(done["step"]),
        "train_s": train_s,
        "psnr_db_per_view": [p for p, _ in scores],
        "ssim_per_view": [s for _, s in scores],
        "region_sse_per_view": [
            _region_sse(root, v["name"], im) for v, im in zip(views, images, strict=True)
        ],
        # GSFixer's repair blended half and half with mesh + Telea (a far view's no-map parts)
        "region_sse_half_per_view": [
            _region_sse(root, v["name"], _half(root, v["name"], im))
            for v, im in zip(views, images, strict=True)
        ],
        "images": images if seed == 0 else None,
    }


def _group_summary(
    views: list[dict[str, Any]], seeds: list[dict[str, Any]], base: list[tuple[float, float]]
) -> dict[str, Any]:
    """Per group: each seed's mean PSNR/SSIM, their median, and the margins that matter."""
    out = {}
    for group in GROUPS:
        idx = [i for i, v in enumerate(views) if v["group"] == group]
        if not idx:
            continue

        def mean(xs: list[float]) -> float:
            return statistics.mean(xs[i] for i in idx)  # noqa: B023

        telea = statistics.mean(views[i]["inpaint"] for i in idx)
        ps = [mean(r["psnr_db_per_view"]) for r in seeds]
        ss = [mean(r["ssim_per_view"]) for r in seeds]
        out[group] = {
            "views": len(idx),
            "telea_psnr_db": telea,
            "run_output_psnr_db": statistics.mean(views[i]["output"] for i in idx),
            "base_psnr_db": mean([p for p, _ in base]),
            "base_ssim": mean([s for _, s in base]),
            "psnr_db_per_seed": ps,
            "psnr_db_median": statistics.median(ps),
            "psnr_db_min": min(ps),
            "psnr_db_max": max(ps),
            "ssim_median": statistics.median(ss),
            "margin_over_telea_db_median": statistics.median(ps) - telea,
            "gain_over_base_db_median": statistics.median(ps) - mean([p for p, _ in base]),
            "seeds_above_telea": sum(p > telea for p in ps),
        }
    return out


def _add_regions(
    summary: dict[str, Any],
    run: Path,
    views: list[dict[str, Any]],
    seeds: list[dict[str, Any]],
    base_images: list[Any],
) -> None:
    """Per group and region class: the seeds' median pooled PSNR, the untuned base's, the run's
    Telea (``inpaint.png``) and mesh + Telea (``mesh_inpaint.png``), and the pixel share."""
    from gsfix_online.repair.outputs import read_png_rgb

    base = [_region_sse(run, v["name"], im) for v, im in zip(views, base_images, strict=True)]
    fallbacks = {
        k: [
            _region_sse(run, v["name"], read_png_rgb(run / "views" / v["name"] / f"{k}.png"))
            for v in views
        ]  # fmt: skip
        for k in ("inpaint", "mesh_inpaint")
    }
    for group, s in summary.items():
        idx = [i for i, v in enumerate(views) if v["group"] == group]
        total = sum(n for i in idx for _, n in base[i].values())
        per_seed = [_region_psnr([r["region_sse_per_view"][i] for i in idx]) for r in seeds]
        half = [_region_psnr([r["region_sse_half_per_view"][i] for i in idx]) for r in seeds]
        ref = {k: _region_psnr([f[i] for i in idx]) for k, f in fallbacks.items()}
        b = _region_psnr([base[i] for i in idx])
        s["regions"] = {
            r: {
                "pixels_share": sum(base[i][r][1] for i in idx) / total,
                "fixed_median": statistics.median(p[r] for p in per_seed),
                "fixed_per_seed": [p[r] for p in per_seed],
                "half_mesh_inpaint_median": statistics.median(p[r] for p in half),
                "half_mesh_inpaint_per_seed": [p[r] for p in half],
                "base": b[r],
                **{k: v[r] for k, v in ref.items()},
            }
            for r in b
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a repair run's output folder (metrics.json, work/)")
    ap.add_argument("overrides", nargs="*", help="trainer KEY=VALUE overrides (a variant)")
    ap.add_argument("--keyframes", type=Path, help="saved keyframes (default RUN/work/keyframes)")
    ap.add_argument("--seeds", type=int, default=4, help="fine-tuning seeds 0..N-1")
    ap.add_argument("--jobs", type=int, default=2, help="seeds trained at once (1 thread each)")
    ap.add_argument("--images", type=Path, help="a folder for side-by-side PNGs of each view")
    ap.add_argument("--note", default="", help="what the run or the variant was, for the record")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/fixer_seeds_cpu.json"))
    args = ap.parse_args()
    keyframes = args.keyframes or args.run / "work" / "keyframes"
    if not any(keyframes.glob("kf_*.npz")):
        raise SystemExit(f"{keyframes}: no saved keyframes (kf_*.npz)")
    views = _views(args.run)

    # 1. The untuned base beside the first fine-tuning seeds, then one fine-tuning per seed
    t0 = time.perf_counter()
    run, kf = str(args.run), str(keyframes)
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        base_fut = pool.submit(_base, run, kf, args.overrides)
        futs = [pool.submit(_one_seed, run, kf, s, args.overrides) for s in range(args.seeds)]
        seeds = []
        for f in futs:
            r = f.result()
            seeds.append(r)
            print(
                f"seed {r['seed']}: {statistics.mean(r['psnr_db_per_view']):.2f} dB over "
                f"{len(views)} views after {r['steps']} steps ({r['train_s']:.0f} s)",
                flush=True,
            )
        base, base_images = base_fut.result()
    wall_s = time.perf_counter() - t0

    first = seeds[0].pop("images")
    for r in seeds[1:]:
        r.pop("images")
    if args.images is not None and first is not None:
        _write_images(args.images, args.run, views, base_images, first)

    # 2. Summary and the appended entry
    summary = _group_summary(views, seeds, base)
    _add_regions(summary, args.run, views, seeds, base_images)
    entry = {
        "command": "benchmarks/bench_fixer_seeds.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "threads_per_seed": 1, "jobs": args.jobs},
        "run": str(args.run),
        "keyframes": str(keyframes),
        "overrides": args.overrides,
        "note": args.note,
        "views": [{"name": v["name"], "group": v["group"]} for v in views],
        "wall_s": wall_s,
        "summary": summary,
        "base_per_view": [{"psnr_db": p, "ssim": s} for p, s in base],
        "per_seed": seeds,
    }
    old = json.loads(args.out.read_text()) if args.out.is_file() else []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps([*old, entry], indent=1) + "\n")
    for group, s in summary.items():
        print(
            f"{group} ({s['views']} views), {len(seeds)} seeds: median {s['psnr_db_median']:.2f} dB "
            f"(min {s['psnr_db_min']:.2f}, max {s['psnr_db_max']:.2f}); untuned base "
            f"{s['base_psnr_db']:.2f}; Telea {s['telea_psnr_db']:.2f} (margin "
            f"{s['margin_over_telea_db_median']:+.2f}, {s['seeds_above_telea']}/{len(seeds)} "
            f"seeds above); the run's output {s['run_output_psnr_db']:.2f}"
        )
    for group, s in summary.items():
        print(
            f"{group} per region, PSNR dB (median over seeds | base | Telea | mesh + Telea | "
            "median over seeds of half GSFixer, half mesh + Telea):"
        )
        for r, x in s["regions"].items():
            print(
                f"  {r:9s} {x['pixels_share']:5.1%} of pixels: {x['fixed_median']:.2f} | "
                f"{x['base']:.2f} | {x['inpaint']:.2f} | {x['mesh_inpaint']:.2f} | "
                f"{x['half_mesh_inpaint_median']:.2f}"
            )
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
