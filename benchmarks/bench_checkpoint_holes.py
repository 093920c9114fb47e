"""Which of a run's GSFixer checkpoints repairs best, and does the trainer's held-out holes error
(``trainer.select_by: holes``) rank them so? For each checkpoint:

- at the run's 8 novel views (the demo's ``scene/novel/color`` truth), GSFixer on the run's own
  saved renders (``views/NNN/gs.png``, ``mesh.png``): PSNR over the view, and over the pixels
  the output drew from GSFixer (``provenance.npz`` source ``fixer``: far views' no-map holes),
  with the mean colour error there;
- at the run's held-out keyframes (``work/keyframes`` split ``holdout`` in the trainer's
  ``policy.json``; the run's final mesh rendered at each), ``fallback.measure`` with holes cut
  into both renders, as the trainer measures it (``TrainerService.holes_error``: one codec
  grid): GSFixer's mean squared error in the holes (8-bit levels), and mesh + Telea's beside it.

    .venv/bin/python benchmarks/bench_checkpoint_holes.py DEMO_RUN [CHECKPOINT...] [--base] [--samples 4]

DEMO_RUN is a ``gsfix-online demo --out`` folder; CHECKPOINT a ``work/checkpoints/step_N``
folder of any run on the same scene.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    import torch

    from gsfix_online.core.config import profile
    from gsfix_online.core.types import Intrinsics
    from gsfix_online.fixer.config import FixerConfig
    from gsfix_online.fixer.masks import procedural_mask
    from gsfix_online.mapping.mesh import read_mesh
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.repair.fallback import HeldOutSample, measure
    from gsfix_online.repair.repairer import ViewRepairer

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a gsfix-online demo output folder")
    ap.add_argument("checkpoints", type=Path, nargs="*")
    ap.add_argument("--base", action="store_true", help="the packaged base model first")
    ap.add_argument("--samples", type=int, default=4, help="held-out keyframes (select_samples)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    def rgb(p: Path) -> np.ndarray:
        return cv2.imread(str(p))[..., ::-1].copy()

    work = args.run / "repair" / "work"
    split = json.loads((work / "checkpoints" / "policy.json").read_text())["policy"]["split"]
    held = [int(k) for k, v in split.items() if v == "holdout"][: args.samples]
    meshes = MeshRenderer(read_mesh(args.run / "repair" / "mesh.ply"))
    samples = []
    for kid in held:
        with np.load(work / "keyframes" / f"kf_{kid:08d}.npz") as z:
            h, w = z["depth"].shape
            r = meshes.render(z["T_world_cam"], Intrinsics.from_K(z["K"], w, h))
            samples.append(HeldOutSample(z["color"], z["gs_render"],
                                         z["gs_alpha"].astype(np.float32), r.rgb(),
                                         np.asarray(r.valid, bool)))  # fmt: skip
    fx = profile(FixerConfig, "repair_cpu.yaml")
    views = sorted((args.run / "scene" / "novel" / "color").glob("*.png"))
    print(f"{len(views)} novel views, {len(samples)} held-out keyframes")
    one_grid = dataclasses.replace(fx, inference=dataclasses.replace(fx.inference, shifts=1))
    for ck in ([None] if args.base else []) + list(args.checkpoints):
        rep, rep1 = ViewRepairer(fx), ViewRepairer(one_grid)
        for r in (rep, rep1):
            r.load_base() if ck is None else r.load_checkpoint(str(ck), version=1)
        ck = ck or "the packaged base"
        psnr, err, shift = [], [], []
        for gt_path in views:
            d = args.run / "repair" / "views" / gt_path.stem
            gt = rgb(gt_path).astype(np.float64)
            out = rep.repair(rgb(d / "gs.png"), rgb(d / "mesh.png")).image.astype(np.float64)
            fixer = np.load(d / "provenance.npz")["source"] == 2
            psnr.append(10 * np.log10(255**2 / np.mean((out - gt) ** 2)))
            err.append(((out - gt) ** 2)[fixer].mean(-1))
            shift.append((out - gt)[fixer].mean(0))
        e = np.concatenate(err).mean()
        holes = measure(samples, lambda gs, mesh, rep=rep1: rep.repair(gs, mesh).image,
                        lambda g, h, w: procedural_mask(g, h, w, fx.masks), seed=fx.train.seed,
                        alpha_min=fx.masks.alpha_threshold, cuts=("both",))  # fmt: skip
        n = holes.pixels["neither"]
        print(f"{ck}: novel views {np.mean(psnr):.2f} dB, GSFixer's pixels "
              f"{10 * np.log10(255**2 / e):.2f} dB (colour error {np.round(np.mean(shift, 0), 1)}); "
              f"held-out holes error {holes.sse['neither']['fixed'] / n:.0f} "
              f"(mesh + Telea {holes.sse['neither']['mesh_inpaint'] / n:.0f}, {n} px)", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
