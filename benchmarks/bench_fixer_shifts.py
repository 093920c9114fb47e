"""Block artefacts of GSFixer's repairs, and what averaging over shifted codec grids does.

The embedded GSFixer works on pixel-unshuffle latents (4x4 blocks); its errors follow that grid.
``fixer.inference.shifts`` = k repairs each view on k codec grids shifted diagonally by 1/k of a
block and averages them (cycle spinning). For every repaired view of finished repair runs, this
benchmark repairs the view again from the run's own renders (``views/NNN/gs.png``, ``mesh.png``)
with the run's fine-tuned checkpoint (the one its metrics name), for each k, and scores:

- the block ratio (``inspection.metrics.block_gradient_ratio``: gradient energy across the 4-px
  boundaries over that inside blocks) against the ground truth's own ratio: within 5 % is the
  goal;
- PSNR and SSIM against the ground truth (``work/gt/NNN.png``), and seconds per view.

    .venv/bin/python benchmarks/bench_fixer_shifts.py outputs/bv/tank_s0/run ... --shifts 1 2 4

Results: ``benchmarks/results/fixer_shifts_cpu.json`` (per view and medians).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import block_gradient_ratio, scores  # noqa: E402
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402


def _checkpoint(run: Path, step: int) -> Path:
    path = run / "work" / "checkpoints" / f"step_{step:06d}"
    if not path.is_dir():
        raise SystemExit(f"{run}: the checkpoint of step {step} is not in work/checkpoints")
    return path


def bench_run(
    run: Path, shifts: list[int], block: int, checkpoint: Path | None, all_views: bool
) -> list[dict[str, Any]]:
    """Every repaired view of ``run`` (``all_views``: every view with renders), with the
    checkpoint its metrics name (or ``checkpoint``)."""
    import dataclasses

    from gsfix_online.core.config import profile
    from gsfix_online.fixer.config import FixerConfig
    from gsfix_online.repair.repairer import ViewRepairer

    if (run / "metrics.json").is_file() and checkpoint is None:
        metrics = json.loads((run / "metrics.json").read_text())
        views = [(f"{v['view_id']:03d}", int(v["model"]["step"])) for v in metrics["views"]
                 if v.get("repair") or all_views]  # fmt: skip
    elif checkpoint is not None:
        views = [(d.name, -1) for d in sorted((run / "views").iterdir())]
    else:
        raise SystemExit(f"{run}: no metrics.json; name the checkpoint (--checkpoint)")
    repair = profile(FixerConfig, "repair_cpu.yaml")  # the repair node's, k grids each
    rows = []
    repairers: dict[tuple[int, int], ViewRepairer] = {}
    for name, step in views:
        gt_path = run / "work" / "gt" / f"{name}.png"
        d = run / "views" / name
        if not gt_path.is_file() or not (d / "gs.png").is_file():
            continue
        gt = read_png_rgb(gt_path)
        gs, mesh = read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")
        row: dict[str, Any] = {
            "run": str(run),
            "view": name,
            "model": str(checkpoint) if checkpoint is not None else step,
            "gt_ratio": block_gradient_ratio(gt, block),
            "shifts": {},
        }
        for k in shifts:
            inference = dataclasses.replace(repair.inference, shifts=k)
            key = (step, k)
            if key not in repairers:
                rep = ViewRepairer(dataclasses.replace(repair, inference=inference))
                if checkpoint is not None:
                    rep.load_checkpoint(str(checkpoint), 1)
                elif step > 0:
                    rep.load_checkpoint(str(_checkpoint(run, step)), 1)
                else:
                    rep.load_base()
                repairers[key] = rep
            t0 = time.perf_counter()
            out = repairers[key].repair(gs, mesh).image
            sec = time.perf_counter() - t0
            s = scores(out, gt)
            ratio = block_gradient_ratio(out, block)
            row["shifts"][str(k)] = {
                "psnr_db": s.psnr_db,
                "ssim": s.ssim,
                "ratio": ratio,
                "ratio_rel": ratio / row["gt_ratio"],
                "seconds": sec,
            }
        rows.append(row)
        print(
            f"{run.name} view {name}: gt ratio {row['gt_ratio']:.3f}; "
            + "; ".join(
                f"k={k}: {r['psnr_db']:.2f} dB ratio x{r['ratio_rel']:.3f} {r['seconds']:.2f} s"
                for k, r in row["shifts"].items()
            ),
            flush=True,
        )
    return rows


def main() -> int:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="finished repair run folders")
    ap.add_argument("--shifts", nargs="+", type=int, default=[1, 2, 4])
    ap.add_argument("--block", type=int, default=4, help="the codec's block, px")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--checkpoint", type=Path, default=None, help="default: the run's own")
    ap.add_argument("--all-views", action="store_true", help="skipped views too")
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "fixer_shifts_cpu.json"
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = [
        r
        for run in args.runs
        for r in bench_run(run, args.shifts, args.block, args.checkpoint, args.all_views)
    ]
    if not rows:
        raise SystemExit("no repaired view with ground truth in these runs")
    summary = {}
    for k in map(str, args.shifts):
        rs = [r["shifts"][k] for r in rows]
        summary[k] = {
            "median_psnr_db": statistics.median(r["psnr_db"] for r in rs),
            "median_ssim": statistics.median(r["ssim"] for r in rs),
            "median_ratio_rel": statistics.median(r["ratio_rel"] for r in rs),
            "max_ratio_dev": max(abs(r["ratio_rel"] - 1) for r in rs),
            "views_within_5pct": sum(abs(r["ratio_rel"] - 1) <= 0.05 for r in rs),
            "median_seconds": statistics.median(r["seconds"] for r in rs),
        }
    result = {
        "about": __doc__.split("\n")[0],
        "argv": sys.argv[1:],
        "machine": {"platform": platform.platform(), "threads": args.threads},
        "views": len(rows),
        "summary": summary,
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(result, indent=1))
    for k, s in summary.items():
        print(
            f"shifts {k}: {s['median_psnr_db']:.2f} dB, SSIM {s['median_ssim']:.3f}, block ratio "
            f"x{s['median_ratio_rel']:.3f} of the ground truth's (worst {s['max_ratio_dev']:.1%}, "
            f"{s['views_within_5pct']}/{len(rows)} within 5 %), {s['median_seconds']:.2f} s/view"
        )
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
