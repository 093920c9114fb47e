"""Fine-tuning seed spread: how far GSFixer's 2D repairs sit above the OpenCV baseline when only
the fine-tuning seed changes.

A demo (or repair) run decides its GSFixer-vs-Telea margin with one fine-tuning run, and that
margin moves with the seed of the masks, crops, noise and timesteps. This benchmark replays the
fine-tuning of the repair graph's trainer node on the keyframes a demo saved, once per seed:

- the trainer node's own service (``nodes/trainer.py``) with the graph's trainer parameters
  (``configs/graphs/repair.yaml``) plus any ``KEY=VALUE`` overrides (to compare a variant);
- trained until it announces the end of its run, as the repair node waits for it
  (``checkpoint: run``); the announced checkpoint repairs the run's novel views from exactly the
  renders the run's repair node had (``repair/views/NNN/gs.png``, ``mesh.png``);
- scored against ground truth next to the run's own baselines (``inpaint.png``,
  ``mesh_fill.png``).

The mesh is the run's final ``repair/mesh.ply`` (the live trainer saw the TSDF mesh grow while
the log was mapped; its one run starts after mapping, on about the final mesh). The demo must
have saved its keyframes::

    flock /tmp/gsfix-bench.lock .venv/bin/gsfix-online demo \\
        'demo.extra_overrides=["trainer.keyframe_dir=outputs/demo_keyframes"]' --out outputs/demo
    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_fixer_seeds.py outputs/demo \\
        outputs/demo_keyframes --seeds 4 --jobs 2

Results: ``benchmarks/results/fixer_seeds_cpu.json`` (one entry per invocation, appended).
"""

from __future__ import annotations

import argparse
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
from gsfix_online.config_schema import atomic_write_text  # noqa: E402

GRAPH = Path(__file__).resolve().parents[1] / "configs" / "graphs" / "repair.yaml"


def _views(run: Path) -> list[dict[str, Any]]:
    """The run's repaired ground-truth views, as its own table counts them."""
    metrics = json.loads((run / "repair" / "metrics.json").read_text())
    views = [v for v in metrics["views"] if v["origin"] == "file" and v["repair"]]
    if not views or "inpaint" not in views[0]["metrics"]:
        raise SystemExit(f"{run}: no repaired views scored against ground truth")
    return views


def _one_seed(run: str, keyframes: str, seed: int, overrides: list[str]) -> dict[str, Any]:
    """Fine-tune with ``seed`` until the run ends; repair and score the run's views."""
    import torch

    torch.set_num_threads(1)
    import nodes.trainer as tn
    from gsfix_online.config_schema import build, read_yaml
    from gsfix_online.inspection.metrics import psnr
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.repairer import ViewRepairer
    from gsfix_online.runtime import Message

    root = Path(run)
    base = read_yaml(GRAPH)["nodes"]["trainer"]["params"]
    with tempfile.TemporaryDirectory() as ck:
        params = build(
            tn.Params,
            base=base,
            overrides=[
                f"checkpoint_dir={ck}",
                f"keyframe_dir={keyframes}",
                f"fixer.train.seed={seed}",
                *overrides,
            ],
        )
        # 1. The trainer node's service, its keyframes restored from disk, the final mesh
        t0 = time.perf_counter()
        svc = tn.TrainerService("trainer", params)
        mesh = {"path": str(root / "repair" / "mesh.ply"), "version": 1}
        svc.on_mesh(Message("mesh/tsdf", "checkpoint", meta=mesh))
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
        scores = []
        for v in _views(root):
            d = root / "repair" / "views" / v["view"]
            gt = read_png_rgb(root / "scene" / "novel" / "color" / f"{v['view_id']:03d}.png")
            scores.append(
                psnr(rep.repair(read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")).image, gt)
            )
    return {
        "seed": seed,
        "keyframes": n_keyframes,
        "steps": int(done["step"]),
        "train_s": train_s,
        "psnr_db_per_view": scores,
        "psnr_db": statistics.mean(scores),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a demo output folder (scene/, repair/)")
    ap.add_argument("keyframes", type=Path, help="the keyframe folder that run saved")
    ap.add_argument("overrides", nargs="*", help="trainer KEY=VALUE overrides (a variant)")
    ap.add_argument("--seeds", type=int, default=4, help="fine-tuning seeds 0..N-1")
    ap.add_argument("--jobs", type=int, default=2, help="seeds trained at once (1 thread each)")
    ap.add_argument("--note", default="", help="what the run or the variant was, for the record")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/fixer_seeds_cpu.json"))
    args = ap.parse_args()
    if not any(args.keyframes.glob("kf_*.npz")):
        raise SystemExit(f"{args.keyframes}: no saved keyframes (kf_*.npz)")

    # 1. The run's own figures: its baselines and its GSFixer output
    views = _views(args.run)

    def mean_of(stage: str) -> float:
        return statistics.mean(v["metrics"][stage]["psnr_db"] for v in views)

    telea, fill, run_fixed = mean_of("inpaint"), mean_of("mesh_fill"), mean_of("fixed")

    # 2. One fine-tuning per seed
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = [
            pool.submit(_one_seed, str(args.run), str(args.keyframes), s, args.overrides)
            for s in range(args.seeds)
        ]
        seeds = []
        for f in futs:
            r = f.result()
            seeds.append(r)
            print(
                f"seed {r['seed']}: {r['psnr_db']:.2f} dB after {r['steps']} steps "
                f"({r['train_s']:.0f} s); Telea {telea:.2f} dB",
                flush=True,
            )
    wall_s = time.perf_counter() - t0

    # 3. Summary and the appended entry
    ps = [r["psnr_db"] for r in seeds]
    summary = {
        "seeds": len(ps),
        "psnr_db_median": statistics.median(ps),
        "psnr_db_mean": statistics.mean(ps),
        "psnr_db_sd": statistics.stdev(ps) if len(ps) > 1 else 0.0,
        "psnr_db_min": min(ps),
        "psnr_db_max": max(ps),
        "margin_over_telea_db_median": statistics.median(ps) - telea,
        "seeds_above_telea": sum(p > telea for p in ps),
        "seeds_above_mesh_fill": sum(p > fill for p in ps),
    }
    entry = {
        "command": "benchmarks/bench_fixer_seeds.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "threads_per_seed": 1, "jobs": args.jobs},
        "run": str(args.run),
        "keyframes": str(args.keyframes),
        "overrides": args.overrides,
        "note": args.note,
        "views": len(views),
        "run_telea_psnr_db": telea,
        "run_mesh_fill_psnr_db": fill,
        "run_fixed_psnr_db": run_fixed,
        "wall_s": wall_s,
        "summary": summary,
        "per_seed": seeds,
    }
    old = json.loads(args.out.read_text()) if args.out.is_file() else []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps([*old, entry], indent=1) + "\n")
    print(
        f"{len(ps)} seeds: median {summary['psnr_db_median']:.2f} dB "
        f"(min {summary['psnr_db_min']:.2f}, max {summary['psnr_db_max']:.2f}, "
        f"sd {summary['psnr_db_sd']:.2f}); the run: {run_fixed:.2f}; Telea {telea:.2f}, "
        f"mesh fill {fill:.2f}; above Telea: {summary['seeds_above_telea']}/{len(ps)} -> {args.out}"
    )


if __name__ == "__main__":
    main()
