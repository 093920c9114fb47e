"""DDIM steps against repair accuracy: the checkpoints a demo (or repair) run kept, each repairing
the run's novel views with 1, 2, 4 and 8 DDIM steps, scored against ground truth next to the
run's own OpenCV-inpainting baseline (mesh fill + Telea, from its metrics.json).

The inputs are exactly what the run's repair node had: ``repair/views/NNN/gs.png`` and
``mesh.png``; ground truth ``scene/novel/color/NNN.png``. Views the planner skipped are left out,
as in the run's table. Run it on a finished demo::

    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_fixer_steps.py outputs/demo

Results: ``benchmarks/results/fixer_steps_cpu.json`` (one entry per run, appended).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import psnr  # noqa: E402
from gsfix_online.fixer.config import FixerConfig  # noqa: E402
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402
from gsfix_online.repair.repairer import ViewRepairer  # noqa: E402

STEPS = (1, 2, 4, 8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a demo output folder (scene/, repair/)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/fixer_steps_cpu.json"))
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    metrics = json.loads((args.run / "repair" / "metrics.json").read_text())
    views = [v for v in metrics["views"] if v["origin"] == "file" and v["repair"]]
    telea = statistics.mean(v["metrics"]["inpaint"]["psnr_db"] for v in views)
    used = statistics.mean(v["metrics"]["fixed"]["psnr_db"] for v in views)
    data = []
    for v in views:
        d = args.run / "repair" / "views" / v["view"]
        gt = read_png_rgb(args.run / "scene" / "novel" / "color" / f"{v['view_id']:03d}.png")
        data.append((read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png"), gt))
    ckpts = sorted((args.run / "repair" / "work" / "checkpoints").glob("step_*"))
    rows = []
    for ck in ckpts:
        row = {"checkpoint": ck.name}
        for steps in STEPS:
            base = FixerConfig()
            cfg = dataclasses.replace(
                base, inference=dataclasses.replace(base.inference, steps=steps)
            )
            rep = ViewRepairer(cfg)
            rep.load_checkpoint(str(ck), version=1)
            scores = [psnr(rep.repair(gs, mesh).image, gt) for gs, mesh, gt in data]
            row[f"psnr_db_{steps}_steps"] = statistics.mean(scores)
        rows.append(row)
        print(ck.name, {k: round(x, 2) for k, x in row.items() if k != "checkpoint"}, flush=True)
    entry = {
        "run": str(args.run),
        "views": len(views),
        "telea_psnr_db": telea,
        "run_fixed_psnr_db": used,
        "checkpoints": rows,
        "machine": f"{platform.processor() or platform.machine()}, 1 torch thread",
    }
    old = json.loads(args.out.read_text()) if args.out.is_file() else []
    atomic_write_text(args.out, json.dumps([*old, entry], indent=2))
    print(f"Telea {telea:.2f} dB; the run's GSFixer {used:.2f} dB; written to {args.out}")


if __name__ == "__main__":
    main()
