"""Does fine-tuning help? GSFixer's repairs with the packaged base against the run's checkpoint.

For every view of finished repair runs that has renders and a ground truth (the user's novel
views and the held-out frames), this benchmark repairs the view again from the run's own renders
(``views/NNN/gs.png``, ``mesh.png``) twice, with the packaged base model and with the checkpoint
the run repaired with (its metrics name it), both as the repair graph does (1 DDIM step, 4
shifted grids), and scores each against the ground truth, whole and per region class (the run's
``alpha.png`` for the 3DGS map; a non-black ``mesh.png`` pixel for the mesh).

    .venv/bin/python benchmarks/bench_finetune_gain.py RUN [RUN ...] --alphas 1 0.75 0.5 \\
        --out benchmarks/results/finetune_wise_cpu.json

``--bases NAME=DIR``: other base checkpoints (e.g. one pretrained on a GPU) repaired beside the
packaged base, as ``base:NAME``, so a candidate base is judged on the same views.

``--alphas``: the checkpoint also moved back towards the base, ``base + a (tuned - base)``
(weight-space ensembling, WiSE-FT; the trainer's ``fixer.train.wise_alpha``). A run made with
``wise_alpha`` < 1 saved such a checkpoint already: ``a`` then applies on top of it.

Prints per run and group (novel views, held-out frames) the median PSNR of each model and the
fine-tuned minus base gain per region.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._case import write_result  # noqa: E402
from gsfix_online.core.metrics import region_scores  # noqa: E402
from gsfix_online.repair.fallback import REGIONS, regions  # noqa: E402
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402

GT_DIR: Path | None = None  # --gt: every run's ground truth; default the run's work/gt


def gt_dir(run: Path) -> Path:
    return GT_DIR or run / "work" / "gt"


def _key(alpha: float) -> str:
    return "tuned" if alpha == 1.0 else f"tuned@{alpha:g}"


def _views(run: Path) -> tuple[list[tuple[str, int, str]], int]:
    """(name, checkpoint step, group) of each view with renders; the run's checkpoint step."""
    metrics = json.loads((run / "metrics.json").read_text())
    held = run / "work" / "holdout" / "views.txt"  # held-out frames follow the user's views
    n_held = (sum(1 for line in held.read_text().splitlines()
                  if line.strip() and not line.startswith("#")) if held.is_file() else 0)  # fmt: skip
    n_user = len(metrics["views"]) - n_held
    steps = [int(v["model"]["step"]) for v in metrics["views"] if v.get("repair")]
    step = max(set(steps), key=steps.count) if steps else 0
    out = []
    for v in metrics["views"]:
        name = f"{v['view_id']:03d}"
        group = "novel" if v["view_id"] < n_user else "holdout"
        if (run / "views" / name / "gs.png").is_file() and (gt_dir(run) / f"{name}.png").is_file():
            out.append((name, step, group))
    return out, step


def _mixed(base: Any, tuned: Any, alpha: float) -> Any:
    """A repairer whose U-Net is base + alpha (tuned - base) (WiSE-FT; 1 = the checkpoint)."""
    import copy

    import torch

    rep = copy.deepcopy(tuned)
    sb, st = base.bundle.model.state_dict(), tuned.bundle.model.state_dict()
    with torch.no_grad():
        rep.bundle.model.load_state_dict({
            k: torch.lerp(sb[k].float(), v.float(), alpha).to(v.dtype) if v.is_floating_point()
            else v for k, v in st.items()
        })  # fmt: skip
    return rep


def bench_run(
    run: Path, alphas: list[float], bases: dict[str, str] | None = None
) -> list[dict[str, Any]]:
    from gsfix_online.core.config import profile
    from gsfix_online.fixer.config import FixerConfig
    from gsfix_online.repair.repairer import ViewRepairer

    views, step = _views(run)
    if step <= 0:
        raise SystemExit(f"{run}: its views were repaired with no fine-tuned checkpoint")
    cfg = profile(FixerConfig, "repair_cpu.yaml")  # as the repair node repairs
    base, tuned = ViewRepairer(cfg), ViewRepairer(cfg)
    base.load_base()
    tuned.load_checkpoint(str(run / "work" / "checkpoints" / f"step_{step:06d}"), 1)
    others = {}
    for name, path in (bases or {}).items():
        others[f"base:{name}"] = ViewRepairer(cfg)
        others[f"base:{name}"].load_checkpoint(path, 0)
    models = {"base": base, **others, **{_key(a): _mixed(base, tuned, a) for a in alphas}}
    rows = []
    for name, _, group in views:
        d = run / "views" / name
        gt = read_png_rgb(gt_dir(run) / f"{name}.png")
        gs, mesh = read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")
        alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
        region = regions(alpha, mesh.max(axis=2) > 0)
        row: dict[str, Any] = {"run": str(run), "view": name, "group": group, "step": step}
        for key, rep in models.items():
            whole, by_region = region_scores(rep.repair(gs, mesh).image, gt, region, REGIONS)
            row[key] = {"psnr_db": whole.psnr_db, "ssim": whole.ssim,
                        "regions": {r: {"psnr_db": s.psnr_db, "mse": s.mse, "pixels": s.pixels}
                                    for r, s in by_region.items()}}  # fmt: skip
        rows.append(row)
        print(
            f"{run.parent.name}/{run.name} {group} view {name}: "
            + ", ".join(f"{k} {row[k]['psnr_db']:.2f} dB" for k in models),
            flush=True,
        )
    return rows


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per run and group: median PSNR/SSIM of each model, and the pixel-weighted mean squared
    error per region as PSNR (base, tuned)."""
    out = []
    for run in dict.fromkeys(r["run"] for r in rows):
        for group in ("novel", "holdout"):
            rs = [r for r in rows if r["run"] == run and r["group"] == group]
            if not rs:
                continue
            s: dict[str, Any] = {"run": run, "group": group, "views": len(rs)}
            for key in [k for k in rs[0] if k.startswith(("base", "tuned"))]:
                s[key] = {
                    "median_psnr_db": statistics.median(r[key]["psnr_db"] for r in rs),
                    "median_ssim": statistics.median(r[key]["ssim"] for r in rs),
                    "regions": {},
                }
                for reg in REGIONS:
                    px = [r[key]["regions"][reg] for r in rs if reg in r[key]["regions"]]
                    n = sum(p["pixels"] for p in px)
                    if n:
                        mse = sum(p["pixels"] * p["mse"] for p in px) / n
                        s[key]["regions"][reg] = {"psnr_db": -10 * np.log10(mse), "pixels": n}
            out.append(s)
    return out


def main() -> int:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="finished repair run folders")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--gt",
        type=Path,
        default=None,
        help="ground truth NNN.png (default: each run's work/gt; the demo's: "
        "outputs/demo/scene/novel/color)",
    )
    ap.add_argument(
        "--alphas",
        nargs="+",
        type=float,
        default=[1.0],
        help="also the checkpoint moved back to the base: base + a (tuned - base)",
    )
    ap.add_argument(
        "--bases", nargs="*", default=[], metavar="NAME=DIR", help="other base checkpoints"
    )
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "finetune_gain_cpu.json"
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    global GT_DIR
    GT_DIR = args.gt
    bad = [b for b in args.bases if "=" not in b]
    if bad:
        raise SystemExit(f"--bases takes NAME=DIR, got {bad[0]!r}")
    bases = dict(b.split("=", 1) for b in args.bases)
    rows = [r for run in args.runs for r in bench_run(run, args.alphas, bases)]
    summary = summarize(rows)
    write_result(args.out, __doc__, args.threads, summary, rows)
    for s in summary:
        for key in [k for k in s if k.startswith(("tuned", "base:"))]:
            gains = ", ".join(
                f"{reg} {s[key]['regions'][reg]['psnr_db'] - s['base']['regions'][reg]['psnr_db']:+.2f}"
                for reg in REGIONS if reg in s[key]["regions"]
            )  # fmt: skip
            print(f"{s['run']} {s['group']} ({s['views']} views): base "
                  f"{s['base']['median_psnr_db']:.2f} dB / {s['base']['median_ssim']:.3f}, {key} "
                  f"{s[key]['median_psnr_db']:.2f} / {s[key]['median_ssim']:.3f}; per region "
                  f"{gains}")  # fmt: skip
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
