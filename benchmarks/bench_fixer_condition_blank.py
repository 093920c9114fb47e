"""GSFixer's 3DGS condition with the map's faint parts blanked: finished runs' views repaired again.

GSFixer takes a view's 3DGS render as it is, composited over black. Where the map's alpha is
low (a floater seen from a far view, the map's frayed edges), GSFixer is shown a faint shape on
black, and it may repair that shape into a solid one: on tank seed 1's view 004 a pale rounded
rectangle that neither map's surface has. This repairs every scored view of finished repair runs
again with the run's own checkpoint (``work/checkpoints/step_NNNNNN``, the step the view's
``metrics.json`` names) from the run's own renders (``views/NNN/gs.png``, ``alpha.png``,
``mesh.png``), once as the run did (``rerun``: must reproduce ``fixed.png``) and once with the
3DGS render blanked to black where its alpha is under ``--alpha`` (``masked``: what GSFixer sees
of a hole in training), recomposes the output from the run's choice (``bench_seams.recompose``,
``detail:8``) and scores GSFixer alone and the output against the ground truth, over the view
and over the pixels no map covers.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_fixer_condition_blank.py \\
        t1=/work/runs/t1/repair:/work/runs/t1/scene/novel/color --alpha 0.5 \\
        --out benchmarks/results/fixer_condition_blank_cpu.json
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

from benchmarks.bench_seams import load, recompose  # noqa: E402
from gsfix_online.core.config import build, read_yaml  # noqa: E402
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import masked_scores, psnr, scores  # noqa: E402
from gsfix_online.fixer.config import FixerConfig  # noqa: E402
from gsfix_online.repair.fallback import GS_ONLY, NEITHER  # noqa: E402
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402
from gsfix_online.repair.repairer import ViewRepairer  # noqa: E402

ARM = "detail:8"  # the compose rule the repair node uses (fallback.BLEND_DETAIL_PX)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="NAME=REPAIR_DIR:GT_DIR")
    ap.add_argument("--alpha", type=float, default=0.5, help="blank the 3DGS render under this")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    rows: list[dict[str, Any]] = []
    for spec in args.runs:
        name, _, dirs = spec.partition("=")
        run, gt_dir = (Path(p) for p in dirs.split(":"))
        graph = read_yaml(run / "work" / "graph.yaml")["nodes"]
        cfg = build(FixerConfig, base=graph["repair"]["params"]["fixer"])
        steps = {v["view"]: (v.get("model") or {}).get("step")
                 for v in json.loads((run / "metrics.json").read_text())["views"]}  # fmt: skip
        fixer, loaded = ViewRepairer(cfg), None
        for x in load(name, run, gt_dir):
            step = steps[x["view"]]
            if step != loaded:
                if step:
                    fixer.load_checkpoint(str(run / "work" / "checkpoints" / f"step_{step:06d}"), 1)
                else:
                    fixer.load_base()
                loaded = step
            d = run / "views" / x["view"]
            gs, mesh = read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")
            alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
            blanked = np.where((alpha >= args.alpha)[..., None], gs, 0).astype(np.uint8)
            # the 3DGS-only pixels the run composed as holes (fallback.far_regions: another
            # repaired view's Gaussians make them), from the output's provenance
            synth = np.load(d / "provenance.npz")["synthesised"].astype(np.float32) >= 0.5
            grown = (x["region"] == GS_ONLY) & synth
            x = {**x, "region": np.where(grown, NEITHER, x["region"]).astype(np.uint8)}
            unseen = np.where(grown[..., None], 0, gs).astype(np.uint8)
            row: dict[str, Any] = {
                "run": name,
                "view": x["view"],
                "grown_share": float(grown.mean()),
            }
            nei = x["region"] == NEITHER
            ran = recompose(x, ARM)
            row["recompose_vs_output_db"] = psnr(ran, x["output"])
            rerun = fixer.repair(gs, mesh).image
            row["rerun_vs_run_fixed_db"] = psnr(rerun, x["c"]["fixed"])
            for arm, fixed in (("run", x["c"]["fixed"]),
                               ("rerun", rerun),
                               ("masked", fixer.repair(blanked, mesh).image),
                               ("unseen", fixer.repair(unseen, mesh).image)):  # fmt: skip
                out = recompose({**x, "c": {**x["c"], "fixed": fixed}}, ARM)
                for what, img in (("fixed", fixed), ("output", out)):
                    s = scores(img, x["gt"])
                    row[f"{arm}_{what}_db"], row[f"{arm}_{what}_ssim"] = s.psnr_db, s.ssim
                    if nei.sum() >= 200:
                        row[f"{arm}_{what}_neither_db"] = masked_scores(img, x["gt"], {"n": nei})[
                            "n"
                        ].psnr_db
            row["blanked_share"] = float(((alpha < args.alpha) & (gs.max(axis=2) > 8)).mean())
            rows.append(row)
            print(f"{name} {x['view']}: GSFixer {row['run_fixed_db']:.2f} -> "
                  f"{row['masked_fixed_db']:.2f} masked, {row['unseen_fixed_db']:.2f} unseen; "
                  f"output {row['run_output_db']:.2f} -> {row['masked_output_db']:.2f}, "
                  f"{row['unseen_output_db']:.2f} dB (grown {row['grown_share']:.1%}; "
                  f"recomposed vs output {row['recompose_vs_output_db']:.1f} dB, rerun vs run "
                  f"{row['rerun_vs_run_fixed_db']:.1f} dB; faint pixels blanked "
                  f"{row['blanked_share']:.1%})", flush=True)  # fmt: skip
    summary: dict[str, dict[str, float]] = {}
    for name in dict.fromkeys(r["run"] for r in rows):
        mine = [r for r in rows if r["run"] == name]
        summary[name] = {k: statistics.median(r[k] for r in mine if k in r)
                         for k in mine[0] if k not in ("run", "view")}  # fmt: skip
    print(
        "\n| run | views | GSFixer: run / rerun / masked | output: run / rerun / masked | "
        "output SSIM: rerun / masked | no-map output: rerun / masked | unseen: GSFixer / output "
        "/ SSIM |\n|---|---|---|---|---|---|---|"
    )
    for name, s in summary.items():
        n = sum(r["run"] == name for r in rows)
        print(f"| {name} | {n} | {s['run_fixed_db']:.2f} / {s['rerun_fixed_db']:.2f} / "
              f"{s['masked_fixed_db']:.2f} | {s['run_output_db']:.2f} / {s['rerun_output_db']:.2f} / "
              f"{s['masked_output_db']:.2f} | {s['rerun_output_ssim']:.3f} / "
              f"{s['masked_output_ssim']:.3f} | {s.get('rerun_output_neither_db', float('nan')):.2f} / "
              f"{s.get('masked_output_neither_db', float('nan')):.2f} | {s['unseen_fixed_db']:.2f} / "
              f"{s['unseen_output_db']:.2f} / {s['unseen_output_ssim']:.3f} |")  # fmt: skip
    if args.out:
        atomic_write_text(args.out, json.dumps({"alpha": args.alpha, "arm": ARM, "views": rows,
                                                "medians": summary}, indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
