"""GSFixer's own repair at *every* held-out frame of finished ``--holdout`` repair runs, per mode.

A run's ``metrics.json`` scores GSFixer (``fixed``) only at the held-out frames the planner sent
to repair (the others the map explains are skipped), so two runs compare on a few views. Here
each run's final checkpoint (``work/checkpoints``, the one its repair node used) repairs all its
held-out frames from the renders the planner decided them with (``views/NNN/gs.png``,
``mesh.png``; mode ``mesh+gs+ref`` also ``ref_warp.png``, its pixels taken as the non-black
ones, and the mesh's as the non-black ones of ``mesh.png``), and is scored against
``work/gt/NNN.png`` beside the run's ``ref_inpaint`` and its best classical stage. A
``mesh+gs+ref`` checkpoint is also run without its warp (``no_warp``: the mesh render in the
reference slot), which shows how much of its repair the warp carries; and the packaged base.

    .venv/bin/python benchmarks/bench_fixer_ref_mode.py RUN... --out OUT.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _case import held_views, write_result  # noqa: E402


def _scores(run: Path, threads: int) -> dict[str, Any]:
    import torch

    from gsfix_online.core.config import read_yaml
    from gsfix_online.core.metrics import psnr
    from gsfix_online.fixer.config import FixerConfig
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.repairer import ViewRepairer

    torch.set_num_threads(threads)
    graph = read_yaml(run / "work" / "graph.yaml")["nodes"]["repair"]["params"]
    from gsfix_online.core.config import build

    fixer = build(FixerConfig, base=graph.get("fixer", {}))
    mode = fixer.model.mode
    rep = ViewRepairer(fixer)
    rep.load_checkpoint(str(run / "work" / "checkpoints"), version=1)
    base = ViewRepairer(dataclasses.replace(fixer, model=dataclasses.replace(fixer.model, path="")))
    base.load_base()
    metrics = json.loads((run / "metrics.json").read_text())
    summary = metrics["summary"]
    rows = []
    for vid in sorted(held_views(run)):
        d = run / "views" / f"{vid:03d}"
        gs, mesh = read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")
        h, w = gs.shape[:2]
        gt = read_png_rgb(run / "work" / "gt" / f"{vid:03d}.png", w, h)
        ref = read_png_rgb(d / "ref_warp.png") if (d / "ref_warp.png").is_file() else None
        valid = None if ref is None else ref.any(axis=2)
        row: dict[str, Any] = {"view": vid, "ref_coverage": None if valid is None else
                               float(valid.mean())}  # fmt: skip
        row["fixed"] = psnr(rep.repair(gs, mesh, ref, valid).image, gt)
        row["base"] = psnr(base.repair(gs, mesh, ref, valid).image, gt)
        if "ref" in rep.bundle.model.conditions:
            row["no_warp"] = psnr(rep.repair(gs, mesh).image, gt)
        for stage in ("ref_inpaint", "output", summary["best_classical"]["stage"]):
            if (d / f"{stage}.png").is_file():
                row[stage] = psnr(read_png_rgb(d / f"{stage}.png"), gt)
        rows.append(row)
    keys = sorted({k for r in rows for k in r if k not in ("view", "ref_coverage")})
    med = {k: float(np.median([r[k] for r in rows if r.get(k) is not None])) for k in keys}
    hold = summary["groups"]["holdout"]
    return {
        "run": str(run),
        "mode": mode,
        "step": rep.step,
        "median_psnr_db": med,
        "metrics_holdout": {k: hold[k] for k in ("fixed", "output", "ref_inpaint") if k in hold},
        "best_classical": summary["best_classical"],
        "rows": rows,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    results = []
    for run in args.runs:
        r = _scores(run, args.threads)
        results.append(r)
        m = r["median_psnr_db"]
        print(f"{run.name} ({r['mode']}, step {r['step']}): " + ", ".join(
            f"{k} {v:.2f}" for k, v in m.items()))  # fmt: skip
    summary = {r["run"]: r["median_psnr_db"] for r in results}
    write_result(args.out, __doc__, args.threads, summary, results)


if __name__ == "__main__":
    main()
