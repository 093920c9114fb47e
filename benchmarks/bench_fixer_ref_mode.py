"""GSFixer's own repair at *every* held-out frame of finished ``--holdout`` repair runs, each
run's renders repaired by every run's fine-tuned checkpoint (one per condition mode).

A run's ``metrics.json`` scores GSFixer (``fixed``) only at the held-out frames the planner sent
to repair (the others the map explains are skipped), and two runs differ in their maps too.
Here each run's final checkpoint (``work/checkpoints``, the one its repair node used) repairs
the held-out frames of *every* run given, from the renders the planner decided them with
(``views/NNN/gs.png``, ``mesh.png``; mode ``mesh+gs+ref`` also ``ref_warp.png``, its pixels
taken as the non-black ones), scored against ``work/gt/NNN.png`` beside the run's
``ref_inpaint``, ``output`` and best classical stage: the modes compare on the same renders.
Also: the packaged base (in mode ``mesh+gs+ref`` widened by a zero slot, checked against the
``mesh+gs`` base: ``base_max_abs_diff``), a ``mesh+gs+ref`` checkpoint without its warp
(``<name>:no_warp``: the mesh render in the reference slot), and each checkpoint's repair of its
own run against the run's ``fixed.png`` (``fixed_vs_run_max_abs_diff``: 0 = reproduced).
With ``--splits``, the base before any fine-tuning with other starts of the reference slot
(``base_split<s>``: the share ``s`` of the mesh slot's weights moved to it; 1 = the warp takes
the mesh render's place): what the zero start gives up, before fine-tuning.

    .venv/bin/python benchmarks/bench_fixer_ref_mode.py RUN... [--renders RUN...] \\
        [--splits 0.5 1] --out OUT.json
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


def _repairer(run: Path | None, fixer: Any) -> Any:
    """The run's final checkpoint (None: the packaged base in the run's mode)."""
    from gsfix_online.repair.repairer import ViewRepairer

    rep = ViewRepairer(fixer)
    if run is None:
        rep.load_base()
    else:
        rep.load_checkpoint(str(run / "work" / "checkpoints"), version=1)
    return rep


def _fixer(run: Path) -> Any:
    from gsfix_online.core.config import build, read_yaml
    from gsfix_online.fixer.config import FixerConfig

    graph = read_yaml(run / "work" / "graph.yaml")["nodes"]["repair"]["params"]
    return build(FixerConfig, base=graph.get("fixer", {}))


def main() -> None:
    import torch

    from gsfix_online.core.metrics import psnr
    from gsfix_online.fixer.config import MODE_CONDITIONS
    from gsfix_online.repair.outputs import read_png_rgb

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--splits", type=float, nargs="*", default=[])
    ap.add_argument(
        "--renders",
        type=Path,
        nargs="*",
        default=None,
        help="runs whose held-out renders are scored (default: every RUN)",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    fixers = {run.name: _fixer(run) for run in args.runs}
    reps = {run.name: _repairer(run, fixers[run.name]) for run in args.runs}
    modes = {name: rep.bundle.model.mode for name, rep in reps.items()}
    fx0 = next(iter(fixers.values()))
    base_cfg = {m: dataclasses.replace(fx0, model=dataclasses.replace(fx0.model, path="", mode=m))
                for m in ("mesh+gs", "mesh+gs+ref")}  # fmt: skip
    bases = {m: _repairer(None, c) for m, c in base_cfg.items()}
    for share in args.splits:  # the mesh slot's weights shared with the (zero) reference slot
        rep = _repairer(None, base_cfg["mesh+gs+ref"])
        w, c = rep.bundle.model.unet.conv_in.weight, rep.bundle.model.latent_channels
        i_mesh, i_ref = (MODE_CONDITIONS["mesh+gs+ref"].index(k) for k in ("mesh", "ref"))
        with torch.no_grad():
            mesh_w = w[:, i_mesh * c : (i_mesh + 1) * c].clone()
            w[:, i_ref * c : (i_ref + 1) * c] = share * mesh_w
            w[:, i_mesh * c : (i_mesh + 1) * c] = (1 - share) * mesh_w
        bases[f"split{share:g}"] = rep
    results, base_diff = [], 0
    for run in args.runs if args.renders is None else args.renders:
        # a run still distilling has no metrics.json yet: its views' images score all the same
        done = (run / "metrics.json").is_file()
        classical = (json.loads((run / "metrics.json").read_text())["summary"]["best_classical"]
                     ["stage"] if done else "ref_inpaint")  # fmt: skip
        rows = []
        for vid in sorted(held_views(run)):
            d = run / "views" / f"{vid:03d}"
            gs, mesh = read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")
            h, w = gs.shape[:2]
            gt = read_png_rgb(run / "work" / "gt" / f"{vid:03d}.png", w, h)
            ref = read_png_rgb(d / "ref_warp.png")
            valid = ref.any(axis=2)
            row: dict[str, Any] = {"view": vid, "ref_coverage": float(valid.mean())}
            for name, rep in reps.items():
                img = rep.repair(gs, mesh, ref, valid).image
                row[name] = psnr(img, gt)
                if "ref" in rep.bundle.model.conditions:
                    row[f"{name}:no_warp"] = psnr(rep.repair(gs, mesh).image, gt)
                if name == run.name and (d / "fixed.png").is_file():
                    ran = read_png_rgb(d / "fixed.png").astype(int)
                    row["fixed_vs_run_max_abs_diff"] = int(np.abs(img.astype(int) - ran).max())
            b0 = bases["mesh+gs"].repair(gs, mesh).image
            b1 = bases["mesh+gs+ref"].repair(gs, mesh, ref, valid).image
            base_diff = max(base_diff, int(np.abs(b0.astype(int) - b1.astype(int)).max()))
            row["base"] = psnr(b0, gt)
            for k in (k for k in bases if k.startswith("split")):
                row[f"base_{k}"] = psnr(bases[k].repair(gs, mesh, ref, valid).image, gt)
            for stage in dict.fromkeys(("ref_inpaint", "output", classical)):
                if done or (d / f"{stage}.png").is_file():
                    row[stage] = psnr(read_png_rgb(d / f"{stage}.png"), gt)
            rows.append(row)
        keys = [k for k in rows[0] if k not in ("view", "ref_coverage") and "diff" not in k
                and all(k in r for r in rows)]  # fmt: skip
        med = {k: float(np.median([r[k] for r in rows])) for k in keys}
        mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
        diffs = [r["fixed_vs_run_max_abs_diff"] for r in rows if "fixed_vs_run_max_abs_diff" in r]
        results.append({
            "run": str(run), "mode": modes.get(run.name), "best_classical": classical,
            "median_psnr_db": med, "mean_psnr_db": mean,
            "fixed_vs_run_max_abs_diff": max(diffs, default=None), "rows": rows,
        })  # fmt: skip
        print(f"renders of {run.name} ({modes.get(run.name)}), median / mean PSNR dB over "
              f"{len(rows)} held-out frames; own fixed.png reproduced to max |diff| "
              f"{max(diffs, default=None)}:")  # fmt: skip
        for k in keys:
            print(f"  {k:28s} {med[k]:6.2f} / {mean[k]:6.2f}")
    print(f"the base widened by a zero slot against the mesh+gs base: max |diff| {base_diff}")
    steps = {name: rep.step for name, rep in reps.items()}  # the checkpoints' optimizer steps
    print("checkpoint steps:", steps)
    summary_out = {"modes": modes, "steps": steps, "base_max_abs_diff": base_diff,
                   "median_psnr_db": {r["run"]: r["median_psnr_db"] for r in results}}  # fmt: skip
    write_result(args.out, __doc__, args.threads, summary_out, results)


if __name__ == "__main__":
    main()
