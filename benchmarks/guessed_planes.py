"""How far from the true surface repaired views seed what the mesh never saw.

For each demo-layout run given (``RUN/repair/mesh.ply``, the scene's novel views and their true
depth in ``RUN/scene/novel``), per novel view, over the pixels where the mesh render has no
surface and the truth has one: the median relative error of the seed depth
(:func:`gsfix_online.repair.repairer.seed_depth`) against the true z-depth,

- ``inpainted``: Navier-Stokes inpainting of the mesh depth (``seed_depth`` without a guess);
- ``planes``: the mesh's planes extended (:mod:`gsfix_online.mapping.mesh_planes`), unguarded,
  inpainting where no plane bounds the ray;
- ``seeds``: what the repair graph seeds: the planes within ``GUESS_RANGE`` of the inpainted
  depth, else inpainting.

    .venv/bin/python benchmarks/guessed_planes.py RUN1 RUN2 ... [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gsfix_online.mapping.mesh import read_mesh
from gsfix_online.mapping.mesh_planes import PlaneGuessConfig, fit_planes, guessed_depth
from gsfix_online.mapping.mesh_render import MeshRenderer
from gsfix_online.repair.repairer import seed_depth
from gsfix_online.scene.generate import DEPTH_SCALE
from gsfix_online.sources.tum import read_intrinsics_json, read_pose_list

ARMS = ("inpainted", "planes", "seeds")


def rel_error(depth: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    k = where & (depth > 0)
    return float(np.median(np.abs(depth[k] - truth[k]) / truth[k])) if k.any() else float("nan")


def run_rows(run: Path, cfg: PlaneGuessConfig) -> list[dict[str, Any]]:
    novel = run / "scene" / "novel"
    mesh = read_mesh(run / "repair" / "mesh.ply")
    renderer, planes = MeshRenderer(mesh), fit_planes(mesh, cfg)
    K, _ = read_intrinsics_json(novel / "intrinsics.json")
    rows = []
    for i, T in enumerate(read_pose_list(novel / "views.txt").poses):
        truth = cv2.imread(str(novel / "depth" / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
        truth = truth.astype(np.float32) / DEPTH_SCALE
        r = renderer.render(T, K)
        unseen = ~r.valid & (truth > 0)
        guess = guessed_depth(planes, T, K, r.valid)
        inpainted = seed_depth(r.depth_m, r.valid, True)
        arms = {
            "inpainted": inpainted,
            "planes": np.where(~r.valid & (guess > 0), guess, inpainted),
            "seeds": seed_depth(r.depth_m, r.valid, True, guess),
        }
        rows.append({"view": i, "unseen": float(unseen.mean()), "n_planes": len(planes)}
                    | {a: rel_error(d, truth, unseen) for a, d in arms.items()})  # fmt: skip
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--json", type=Path, help="also write the rows here")
    args = p.parse_args()
    cfg = PlaneGuessConfig()
    out: dict[str, Any] = {"command": " ".join(sys.argv), "guess": cfg.__dict__, "runs": {}}
    print("| run | view | unseen | planes | " + " | ".join(ARMS) + " |")
    print("|---|---:|---:|---:|" + "---:|" * len(ARMS))
    for run in args.runs:
        rows = run_rows(run, cfg)
        out["runs"][str(run)] = rows
        for r in rows:
            cells = " | ".join(f"{100 * r[a]:.1f} %" for a in ARMS)
            print(
                f"| {run.name} | {r['view']:03d} | {r['unseen']:.2f} | {r['n_planes']} | {cells} |"
            )
        med = {a: statistics.median(r[a] for r in rows) for a in ARMS}
        print(
            f"| {run.name} | median | | | "
            + " | ".join(f"{100 * med[a]:.1f} %" for a in ARMS)
            + " |"
        )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
