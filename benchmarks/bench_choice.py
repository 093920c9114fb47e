"""Which held-out measurement makes the per-region choice that serves novel views best.

For finished repair runs with ``--holdout`` and novel views with ground truth: GSFixer (the
run's checkpoint, the repair graph's inference settings) repairs every held-out frame and every
repaired novel view again from the run's own renders; the choice per region is measured on the
held-out frames (their camera images) in several ways, and the outputs composed with each
choice (and with the run's own, ``run``) are scored against ground truth per group:

- ``cuts``: procedural holes cut into the renders (the fixer's mask generator);
- ``none``: the frames as they are, a region measured from 500 px on;
- ``none_frac``: the same, a region measured only from 1 % of the pixels on (else the best
  candidate over all pixels);
- ``hybrid``: ``none_frac``, regions under 1 % measured by ``cuts``;
- ``views``: the holes of the repaired novel views (what neither map holds there) cut in;
- ``hybrid_views``: ``none_frac``, regions under 1 % measured by ``views`` (what the repair
  node does);
- ``prior``: ``none_frac`` with GSFixer wherever neither map holds anything.

    .venv/bin/python benchmarks/bench_choice.py RUN [RUN ...]

Results: ``benchmarks/results/choice_cpu.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import psnr  # noqa: E402
from gsfix_online.repair.fallback import (  # noqa: E402
    FEATHER_PX,
    Choice,
    HeldOutSample,
    baseline_candidates,
    choose,
    compose,
    measure,
    regions,
)
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402

CUTS = {"cuts": ("none", "both", "gs", "mesh"), "none": ("none",)}


def bench_run(run: Path, n_novel: int) -> dict[str, Any]:
    from gsfix_online.core.config import profile
    from gsfix_online.fixer.config import FixerConfig
    from gsfix_online.fixer.masks import procedural_mask
    from gsfix_online.repair.repairer import ViewRepairer

    m = json.loads((run / "metrics.json").read_text())
    views = m["views"]
    step = max(int(v["model"]["step"]) for v in views if v.get("repair"))
    fixer = profile(FixerConfig, "repair_cpu.yaml")  # as the repair node repairs
    rep = ViewRepairer(fixer)
    rep.load_checkpoint(str(run / "work" / "checkpoints" / f"step_{step:06d}"), 1)
    run_choice = next(v["model"]["choice"] for v in views if v.get("repair"))
    data = {}
    for v in views:
        name = f"{v['view_id']:03d}"
        d, gt_path = run / "views" / name, run / "work" / "gt" / f"{name}.png"
        if not gt_path.is_file() or not (d / "gs.png").is_file():
            continue
        gs, mesh = read_png_rgb(d / "gs.png"), read_png_rgb(d / "mesh.png")
        alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
        valid = mesh.any(axis=2)
        data[int(v["view_id"])] = {
            "gt": read_png_rgb(gt_path), "gs": gs, "mesh": mesh, "alpha": alpha, "valid": valid,
            "repair": bool(v.get("repair")), "fixed": rep.repair(gs, mesh).image,
        }  # fmt: skip
    held = [k for k in data if k >= n_novel]  # the command puts them after the user's
    samples = [HeldOutSample(data[k]["gt"], data[k]["gs"], data[k]["alpha"], data[k]["mesh"],
                             data[k]["valid"]) for k in held]  # fmt: skip

    def holes(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
        return procedural_mask(rng, h, w, fixer.masks)

    choices = {"run": Choice(dict(run_choice), {}, {}, 0, "")}
    errors = {name: measure(samples, lambda g, me: rep.repair(g, me).image, holes, cuts=cuts)
              for name, cuts in CUTS.items()}  # fmt: skip
    for name in CUTS:
        choices[name] = choose(errors[name])
    choices["none_frac"] = choose(errors["none"], min_fraction=0.01)
    choices["hybrid"] = choose(errors["none"], min_fraction=0.01, backup=errors["cuts"])
    # holes with the shapes of the views to repair: each cut takes the part of a repaired view
    # that neither map holds
    targets = [regions(data[k]["alpha"], data[k]["valid"]) == 3 for k in data
               if k not in held and data[k]["repair"]]  # fmt: skip
    targets = [t for t in targets if t.any()]
    if targets:

        def transplant(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
            return targets[int(rng.integers(len(targets)))]

        errors["views"] = measure(samples, lambda g, me: rep.repair(g, me).image, transplant,
                                  cuts=("both", "gs", "mesh"))  # fmt: skip
        choices["views"] = choose(errors["views"])
        choices["hybrid_views"] = choose(errors["none"], min_fraction=0.01,
                                         backup=errors["views"])  # fmt: skip
    prior = dict(choices["none_frac"].per_region)
    if errors["none"].pixels["neither"] < 0.01 * sum(errors["none"].pixels.values()):
        prior["neither"] = "fixed"
    choices["prior"] = Choice(prior, {}, {}, 0, "")
    result: dict[str, Any] = {"run": str(run), "held_out": held,
                              "choices": {k: c.per_region for k, c in choices.items()}}  # fmt: skip
    for group, ids in (("holdout", held), ("novel", [k for k in data if k not in held])):
        ids = [k for k in ids if data[k]["repair"]]  # the views the repair node composes
        for cname, c in choices.items():
            vals = []
            for k in ids:
                x = data[k]
                cands = baseline_candidates(x["gs"], x["alpha"], x["mesh"], x["valid"])
                cands["fixed"] = x["fixed"]
                out = compose(cands, regions(x["alpha"], x["valid"]), c, FEATHER_PX)
                vals.append(psnr(out, x["gt"]))
            result.setdefault(group, {})[cname] = {
                "mean_psnr_db": float(np.mean(vals)) if vals else None,
                "views": len(vals),
            }
        for base in ("inpaint", "mesh_inpaint", "fixed"):
            vals = []
            for k in ids:
                x = data[k]
                cands = baseline_candidates(x["gs"], x["alpha"], x["mesh"], x["valid"])
                img = x["fixed"] if base == "fixed" else cands[base]
                vals.append(psnr(img, x["gt"]))
            result[group][base] = {"mean_psnr_db": float(np.mean(vals)) if vals else None}
    print(json.dumps({k: result[k] for k in ("run", "choices", "holdout", "novel")}, indent=1))
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).parent / "results" / "choice_cpu.json")  # fmt: skip
    ap.add_argument("--novel", type=int, default=8, help="the user's views come first")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    rows = [bench_run(r, args.novel) for r in args.runs]
    atomic_write_text(args.out, json.dumps({"argv": sys.argv[1:], "runs": rows}, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
