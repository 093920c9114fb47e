"""Mesh renders that hold every integrated frame, against the remesh policy's mesh.

Until the TSDF component refreshed its mesh for every render (``gsfix_online/mapping/
tsdf_service.py``), a render came from the mesh the remesh policy last extracted. The policy
counts new blocks, and frames that lift voxels over ``mesh_weight_threshold`` add surface without
adding blocks, so a finished run's views were rendered from a mesh that lacked its last frames.

This benchmark takes finished repair runs made before the change and renders each view again
from the run's final mesh (``RUN/mesh.ply``, written when the run ended, from every frame):

- coverage: the share of each view's pixels with a surface, in the run's render and the fresh one;
- PSNR against the ground truth of the mesh-based candidates with either render: mesh + Telea
  (``mesh_inpaint``), mesh fill + Telea (``inpaint``), and GSFixer repaired with the run's own
  checkpoint (1 DDIM step on 4 grids, as the graph repairs); the run's own images are the
  "run" rows, recomputed from the run's renders where the run did not keep them.

Usage::

    .venv/bin/python benchmarks/bench_mesh_fresh.py RUN... [--out F]

RUN is a repair run's output folder with ground truth (``--holdout`` or ``--views-gt``), e.g. the
``run`` folder of a ``bench_variants.py`` case. Results: ``benchmarks/results/mesh_fresh_cpu.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._case import held_views  # noqa: E402
from gsfix_online.core.io import atomic_write_text  # noqa: E402

STAGES = ("mesh_inpaint", "inpaint", "fixed")


def _run(run: Path) -> dict[str, Any]:
    import cv2

    from gsfix_online.core.config import profile
    from gsfix_online.core.metrics import scores
    from gsfix_online.core.types import Intrinsics
    from gsfix_online.fixer.config import FixerConfig
    from gsfix_online.mapping.mesh import read_mesh
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.repair.baselines import inpaint_telea, mesh_fill
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.repairer import ViewRepairer

    renderer = MeshRenderer(read_mesh(run / "mesh.ply"))
    rep = ViewRepairer(profile(FixerConfig, "repair_cpu.yaml"))  # as the repair node repairs
    ck = run / "work" / "checkpoints"
    rep.load_checkpoint(str(ck / (ck / "latest").read_text().strip()), 1)
    held = held_views(run)
    metrics = json.loads((run / "metrics.json").read_text())
    rows = []
    for v in metrics["views"]:
        name, vid = v["view"], int(v["view_id"])
        gt_file = run / "work" / "gt" / f"{name}.png"
        if not gt_file.is_file():
            continue
        d = run / "views" / name
        cam = v["camera"]
        K = np.asarray(cam["K"], np.float64).reshape(3, 3)
        T = np.asarray(cam["T_world_cam"], np.float64).reshape(4, 4)
        fresh = renderer.render(T, Intrinsics.from_K(K, int(cam["width"]), int(cam["height"])))
        gt = read_png_rgb(gt_file)
        gs = read_png_rgb(d / "gs.png")
        alpha = cv2.imread(str(d / "alpha.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
        stale_rgb = read_png_rgb(d / "mesh.png")
        stale_valid = stale_rgb.max(axis=2) > 0  # the run's render: black where no surface
        row: dict[str, Any] = {
            "view": name, "group": "holdout" if vid in held else "novel",
            "coverage": {"run": float(stale_valid.mean()), "fresh": float(fresh.valid.mean())},
        }  # fmt: skip
        for arm, rgb, valid in (
            ("run", stale_rgb, stale_valid),
            ("fresh", fresh.rgb(), fresh.valid),
        ):
            fill = mesh_fill(gs, alpha, rgb, valid)
            ims = {
                "mesh_inpaint": inpaint_telea(rgb, ~valid),
                "inpaint": inpaint_telea(fill.image, fill.missing),
                "fixed": rep.repair(gs, rgb).image,
            }
            row[arm] = {k: scores(im, gt).psnr_db for k, im in ims.items()}
        rows.append(row)
        print(f"{run.parent.name} {name} ({row['group']}): coverage "
              f"{row['coverage']['run']:.3f} -> {row['coverage']['fresh']:.3f}; " + ", ".join(
                  f"{k} {row['run'][k]:.2f} -> {row['fresh'][k]:.2f}" for k in STAGES),
              flush=True)  # fmt: skip
    summary: dict[str, Any] = {}
    for group in ("novel", "holdout"):
        rs = [r for r in rows if r["group"] == group]
        if not rs:
            continue
        summary[group] = {
            "views": len(rs),
            "coverage_mean": {a: float(np.mean([r["coverage"][a] for r in rs])) for a in ("run", "fresh")},
            **{
                f"{k}_{stat}": {a: float(f([r[a][k] for r in rs])) for a in ("run", "fresh")}
                for k in STAGES
                for stat, f in (("mean", np.mean), ("median", statistics.median))
            },
        }  # fmt: skip
    return {"run": str(run), "summary": summary, "views": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/mesh_fresh_cpu.json"))
    a = ap.parse_args()
    import torch

    torch.set_num_threads(a.threads)
    results = [_run(r) for r in a.runs]
    for res in results:
        print(res["run"])
        for group, s in res["summary"].items():
            print(f"  {group} ({s['views']} views): coverage {s['coverage_mean']['run']:.3f} -> "
                  f"{s['coverage_mean']['fresh']:.3f}; " + ", ".join(
                      f"{k} {s[f'{k}_mean']['run']:.2f} -> {s[f'{k}_mean']['fresh']:.2f}"
                      for k in STAGES) + " (means, dB)")  # fmt: skip
    doc = {
        "benchmark": "bench_mesh_fresh",
        "command": "benchmarks/bench_mesh_fresh.py " + " ".join(map(str, a.runs)),
        "machine": {"cpus": 2, "platform": platform.platform(), "threads": a.threads},
        "results": results,
    }
    atomic_write_text(a.out, json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
