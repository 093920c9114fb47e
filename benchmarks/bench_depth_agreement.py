"""Where both maps cover a novel view, is the 3DGS render wrong where its depth disagrees with
the mesh's? Bins the pixels of a finished run's novel views by (3DGS depth - mesh depth) / mesh
depth and scores both renders against the ground truth in each bin.

The 3DGS render is the run's final map without distillation's seeds (``Mapper.render(keep=)``),
the mesh render is the run's TSDF mesh ray-cast by Open3D; ground truth is the run's
``work/gt``. Run it on a case folder of ``benchmarks/bench_variants.py``:

    .venv/bin/python benchmarks/bench_depth_agreement.py CASE_DIR [--group holdout] [--out FILE.json]

``--group holdout`` scores the run's held-out input frames (``repair --holdout``) instead of
its novel views.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._case import held_views  # noqa: E402

BINS = [-1.0, -0.3, -0.1, -0.03, 0.03, 0.1, 0.3, 10.0]


def main() -> int:
    import open3d as o3d
    import torch
    from PIL import Image

    from gsfix_online.core.io import atomic_write_text
    from gsfix_online.mapping.mesh import TriMesh
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.repair.views import read_views
    from gsfix_online.services.splat import load_snapshot
    from gsfix_online.sources.tum import read_intrinsics_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case", type=Path, help="a bench_variants case folder (scene/, run/)")
    ap.add_argument("--group", choices=("novel", "holdout"), default="novel")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    run = args.case / "run"
    mapper = load_snapshot(MapperConfig(backend="cpu"), run / "work" / "map.pt")
    mesh = o3d.io.read_triangle_mesh(str(run / "work" / "mesh" / "mesh.ply"))
    colors = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255), 0, 255).astype(np.uint8)
    renderer = MeshRenderer(TriMesh(np.asarray(mesh.vertices, np.float32),
                                    np.asarray(mesh.triangles, np.int32), colors))  # fmt: skip
    intr, _ = read_intrinsics_json(args.case / "scene" / "novel" / "intrinsics.json")
    # in file order: a pose list sorted by time would interleave the held-out frames
    poses = [v.T_world_cam for v in read_views(run / "work" / "views.txt")]
    n = len(list((args.case / "scene" / "novel" / "color").glob("*.png")))
    which = range(n) if args.group == "novel" else sorted(held_views(run))
    acc = np.zeros((len(BINS) - 1, 3))  # pixels, SSE 3DGS, SSE mesh
    for i in which:
        T = poses[i]
        gt = np.asarray(Image.open(run / "work" / "gt" / f"{i:03d}.png").convert("RGB"), np.float32)
        with torch.no_grad():
            out = mapper.render(T, intr.K, intr.width, intr.height, keep=~mapper.seeded())
        gs = out.color.clamp(0, 1).numpy() * 255
        m = renderer.render(T, intr)
        both = (out.alpha.numpy() >= 0.5) & m.valid
        rel = (out.depth.numpy() - m.depth_m) / np.maximum(m.depth_m, 1e-3)
        err_gs = ((gs - gt) ** 2).mean(-1)
        err_mesh = ((m.rgb().astype(np.float32) - gt) ** 2).mean(-1)
        idx = np.digitize(rel, BINS[1:-1])
        for b in range(len(BINS) - 1):
            sel = both & (idx == b)
            acc[b] += (sel.sum(), err_gs[sel].sum(), err_mesh[sel].sum())
    rows = []
    for b, (px, sg, sm) in enumerate(acc):
        if px:
            rows.append({"rel_depth": [BINS[b], BINS[b + 1]], "share": px / acc[:, 0].sum(),
                         "psnr_gs_db": 10 * np.log10(255**2 * px / sg),
                         "psnr_mesh_db": 10 * np.log10(255**2 * px / sm)})  # fmt: skip
            r = rows[-1]
            print(f"(3DGS - mesh) / mesh depth in [{BINS[b]:+.2f}, {BINS[b + 1]:+.2f}): "
                  f"{r['share']:5.1%} of the pixels both cover; 3DGS {r['psnr_gs_db']:.2f} dB, "
                  f"mesh {r['psnr_mesh_db']:.2f} dB")  # fmt: skip
    if args.out:
        atomic_write_text(args.out, json.dumps({"case": str(args.case), "group": args.group, "views": len(which), "bins": rows},
                                               indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
