"""How many fused frames a voxel needs before it is meshed (``tsdf.mesh_weight_threshold``).

For each procedural scene (family, variant, camera, seed; generated here, none of them a scene the
defaults were tuned on), the input is fused into one TSDF volume per threshold exactly as the
tsdf node fuses it (every posed frame, the held-out ones left out as ``--holdout`` leaves them
out, the poses the input carries: estimated ones for ``drift`` and ``real``), and the final mesh
is rendered at the scene's novel views and at its held-out frames. Per view and threshold:

- ``coverage``: the share of pixels with a surface;
- ``depth_ok``: the share of those whose depth is within 5 cm + 2 % of the true depth (the
  ground truth's depth at the view; novel views are rendered at the input's pose frame, so
  drift shows here as it does in every render a user gets);
- ``mesh_psnr_db``: PSNR of the mesh colour on the covered pixels;
- ``mesh_telea_psnr_db``: PSNR of the whole view after OpenCV Telea fills the uncovered pixels
  (the mesh-only fallback a user could always have).

Usage::

    .venv/bin/python benchmarks/bench_mesh_threshold.py [--cases tank room:real ...]
        [--seeds 21 22] [--thresholds 1 2 3] [--frames 40] [--holdout 10] [--work DIR]
        [--out benchmarks/results/mesh_threshold_cpu.json]

Results: ``benchmarks/results/mesh_threshold_cpu.json`` (per case, the medians over seeds of the
per-view means).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from gsfix_online.core.io import atomic_write_text  # noqa: E402

CLI = [sys.executable, "-m", "gsfix_online.apps.cli"]
DEFAULT_CASES = ["tank", "tank:drift", "tank:noisy-depth", "tank:real", "tank:real+gray",
                 "room", "room:drift", "room:noisy-depth", "room:real", "room:real+gray"]  # fmt: skip


def _scene(case: str, seed: int, frames: int, work: Path) -> Path:
    parts = case.split(":")
    out = work / f"{case.replace(':', '_').replace('+', '-')}_s{seed}"
    if not (out / "log.mcap").is_file():
        kind = {"tank": "ship-tank", "room": "room"}[parts[0]]
        cmd = [*CLI, "scene", kind, f"scene.seed={seed}", f"scene.n_frames={frames}"]
        if len(parts) > 1 and parts[1]:
            cmd += ["--variant", parts[1].replace("+", ",")]
        if len(parts) > 2:
            cmd += ["--camera", parts[2]]
        subprocess.run([*cmd, "--out", str(out)], check=True, cwd=ROOT,
                       stdout=subprocess.DEVNULL)  # fmt: skip
    return out


def _views(scene: Path, holdout: int) -> list[dict[str, Any]]:
    """Novel views and held-out frames: pose (input frame), intrinsics, true colour and depth."""
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.views import read_views
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.base import read_depth_png
    from gsfix_online.sources.replay import is_held_out
    from gsfix_online.sources.tum import read_intrinsics_json

    intr, scale = read_intrinsics_json(scene / "novel" / "intrinsics.json")
    views = []
    for i, v in enumerate(read_views(scene / "novel" / "views.txt")):
        views.append({"group": "novel", "T": v.T_world_cam, "intr": intr,
                      "gt": read_png_rgb(scene / "novel" / "color" / f"{i:03d}.png",
                                         intr.width, intr.height),
                      "depth": read_depth_png(scene / "novel" / "depth" / f"{i:03d}.png", scale)})  # fmt: skip
    for i, f in enumerate(open_source(SourceConfig(path=str(scene / "log.mcap")))):
        if is_held_out(i, holdout):
            views.append({"group": "holdout", "T": f.T_world_cam, "intr": f.intrinsics,
                          "gt": read_png_rgb(scene / "gt" / "color" / f"{i:06d}.png",
                                             f.width, f.height),
                          "depth": read_depth_png(scene / "gt" / "depth" / f"{i:06d}.png", scale)})  # fmt: skip
    return views


def _score(mesh: Any, views: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    from gsfix_online.core.metrics import psnr, scores
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.repair.baselines import inpaint_telea

    renderer = MeshRenderer(mesh)
    per: dict[str, list[dict[str, float]]] = {}
    for v in views:
        r = renderer.render(v["T"], v["intr"])
        rgb, gt, valid = r.rgb(), v["gt"], r.valid
        true_d = v["depth"]
        has = valid & (true_d > 0)
        ok = np.abs(r.depth_m - true_d) <= 0.05 + 0.02 * true_d
        row = {
            "coverage": float(valid.mean()),
            "depth_ok": float((ok & has).sum() / max(has.sum(), 1)),
            "mesh_psnr_db": psnr(rgb, gt, valid) if valid.any() else float("nan"),
            "mesh_telea_psnr_db": scores(inpaint_telea(rgb, ~valid), gt).psnr_db,
        }
        per.setdefault(v["group"], []).append(row)
    return {g: {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]}
            for g, rows in per.items()}  # fmt: skip


def run_scene(scene: Path, thresholds: list[float], holdout: int) -> dict[str, Any]:
    from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume
    from gsfix_online.sources import SourceConfig, open_source
    from gsfix_online.sources.replay import is_held_out

    # one volume; meshes at each threshold come from the same fused voxels
    vol = TsdfVolume(TsdfConfig(voxel_size=0.02, depth_max=5.0))
    for i, f in enumerate(open_source(SourceConfig(path=str(scene / "log.mcap")))):
        if not is_held_out(i, holdout):
            vol.integrate(f)
    views = _views(scene, holdout)
    out = {}
    for t in thresholds:
        vol.cfg = dataclasses.replace(vol.cfg, mesh_weight_threshold=t)
        out[f"{t:g}"] = _score(vol.extract_mesh(), views)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=DEFAULT_CASES)
    ap.add_argument("--seeds", nargs="+", type=int, default=[21, 22])
    ap.add_argument("--thresholds", nargs="+", type=float, default=[1.0, 2.0, 3.0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--holdout", type=int, default=10)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_mesh_threshold"))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/mesh_threshold_cpu.json")
    a = ap.parse_args()
    t0 = time.monotonic()
    cases: dict[str, Any] = {}
    for case in a.cases:
        runs = {}
        for seed in a.seeds:
            t1 = time.monotonic()
            runs[seed] = run_scene(_scene(case, seed, a.frames, a.work), a.thresholds, a.holdout)
            print(f"{case} seed {seed}: " + "; ".join(
                f"thr {t}: " + ", ".join(f"{g} cov {s['coverage']:.3f} depth_ok {s['depth_ok']:.3f} "
                                         f"mesh+Telea {s['mesh_telea_psnr_db']:.2f}"
                                         for g, s in r.items()) for t, r in runs[seed].items())
                  + f" ({time.monotonic() - t1:.0f} s)", flush=True)  # fmt: skip
        med: dict[str, Any] = {}
        for t in runs[a.seeds[0]]:
            med[t] = {g: {k: statistics.median(runs[s][t][g][k] for s in a.seeds)
                          for k in runs[a.seeds[0]][t][g]} for g in runs[a.seeds[0]][t]}  # fmt: skip
        cases[case] = {"median_over_seeds": med, "per_seed": runs}
    result = {
        "command": "benchmarks/bench_mesh_threshold.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform()},
        "frames": a.frames, "holdout": a.holdout, "seeds": a.seeds, "thresholds": a.thresholds,
        "wall_s": time.monotonic() - t0,
        "cases": cases,
    }  # fmt: skip
    atomic_write_text(a.out, json.dumps(result, indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
