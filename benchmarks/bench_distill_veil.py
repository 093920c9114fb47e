"""Veils of distillation, per view: a demo run's repaired views distilled again into the map
its input built, once per arm, and every repaired view and its neighbouring keyframes scored.

The final map must render every repaired view no blurrier than the 2D output delivered there
(sharpness ratio: mean gradient magnitude of the final render over the output's, >= 0.9) and
no more than 0.3 dB below it against the ground truth; the input keyframes nearest each
repaired view must not lose more than 0.1 dB (against their own observed colour). Per run
folder of ``gsfix-online demo`` (``DEMO/repair``, ``DEMO/scene``):

1. the map at the end of the input: ``repair/work/map.pt.prev`` (the splat node's snapshot
   after its last input frame and refinement, before any repaired view arrived; checked to
   hold no distillation seed), with the node's mapper settings (``repair/work/graph.yaml``);
2. the repaired views in the order the node distilled them, from the final snapshot
   (``repair/work/map.pt``: each one's image and hole mask, ``Mapper.forget_repairs``), the
   seed depth from the run's mesh (``repair/mesh.ply``) as the repair node computes it, and
   where the mesh saw a surface from the view's region (``views/NNN/provenance.npz``);
3. per arm (mapper settings over the run's): each view distilled as the splat node does
   (``Mapper.distill``, then ``splat.distill_passes`` passes, then polish), and the renders
   scored: PSNR against ``scene/novel/color/NNN.png`` beside the run's ``output.png``, the
   sharpness ratio, and the neighbouring keyframes' PSNR before and after.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_distill_veil.py outputs/demo \\
        --arm before:distill_veil.enabled=false --arm after \\
        --out benchmarks/results/distill_veil_cpu.json --images /tmp/veil_images
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SHARPNESS_MIN = 0.9  # final render / output, mean gradient magnitude
BELOW_OUTPUT_MAX_DB = 0.3  # final render at most this far below the output
KEYFRAME_LOSS_MAX_DB = 0.1  # the neighbouring keyframes' renders lose at most this
NEIGHBOURS = 2  # input keyframes per repaired view, nearest camera centres


def parse_arm(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME[:KEY=VALUE,...]`` -> (name, mapper overrides); dotted keys nest
    (``growth.scale_mult=0.5``), values are YAML scalars (bench_distill.parse_arm)."""
    from benchmarks.bench_distill import parse_arm as parse_flat

    name, flat = parse_flat(text)
    overrides: dict[str, Any] = {}
    for key, value in flat.items():
        node = overrides
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return name, overrides


def score(
    m: Any,  # Mapper
    scored: list[tuple[Any, ...]],  # (view, T, K, gt, output) per repaired view with a gt
    keyframes: list[tuple[Any, ...]],  # (T, K, colour) per input keyframe
    near: list[int],  # the keyframes to score
    where: Path | None,  # the renders go here as NNN.png
) -> dict[str, Any]:
    """PSNR of the map's render and its sharpness ratio at each view; PSNR at the keyframes."""
    import numpy as np

    from gsfix_online.core.metrics import psnr, sharpness
    from gsfix_online.repair.outputs import write_png

    out: dict[str, Any] = {"views": {}, "keyframes": {}}
    for name, T, K, gt, output in scored:
        H, W = gt.shape[:2]
        color, _, _ = m.render_numpy(T, K, W, H)
        img = np.rint(color * 255).astype(np.uint8)
        out["views"][name] = {
            "output_db": psnr(output, gt), "final_db": psnr(img, gt),
            "sharpness": sharpness(img) / sharpness(output),
        }  # fmt: skip
        if where is not None:
            where.mkdir(parents=True, exist_ok=True)
            write_png(where / f"{name}.png", img)
    for i in near:
        T, K, color = keyframes[i]
        H, W = color.shape[:2]
        c, _, _ = m.render_numpy(T, K, W, H)
        out["keyframes"][str(i)] = psnr(np.rint(c * 255).astype(np.uint8), color)
    return out


def main() -> int:
    import numpy as np
    import torch

    from gsfix_online.core.config import build, deep_merge, read_yaml
    from gsfix_online.core.io import atomic_write_text
    from gsfix_online.mapping.mesh import read_mesh
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.mapping.splat.mapper import REPAIRED_FRAME_ID, Mapper, MapperConfig
    from gsfix_online.repair.fallback import MESH_SAW
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.repairer import seed_depth
    from gsfix_online.services.splat import load_snapshot

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("demos", type=Path, nargs="+", help="gsfix-online demo output folders")
    ap.add_argument("--arm", action="append", default=[], metavar="NAME[:KEY=VALUE,...]",
                    help="mapper settings over the run's (repeatable; default: the run's)")  # fmt: skip
    ap.add_argument("--passes", type=int, default=None, help="distill_passes (default: run's)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--images", type=Path, default=None,
                    help="each arm's renders as IMAGES/DEMO/ARM/NNN.png")  # fmt: skip
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    arms = [parse_arm(a) for a in args.arm] or [("run", {})]

    rows = []
    for demo in args.demos:
        run = demo / "repair"
        graph = read_yaml(run / "work" / "graph.yaml")["nodes"]
        run_cfg = {**graph["splat"]["params"].get("mapper", {}), "backend": "cpu"}
        passes = graph["splat"]["params"].get("distill_passes", 2)
        passes = passes if args.passes is None else args.passes
        seed_empty = graph["repair"]["params"].get("seed_empty", True)
        views = json.loads((run / "metrics.json").read_text())["views"]

        # 1. The map at the end of the input
        built = load_snapshot(build(MapperConfig, base=run_cfg), run / "work" / "map.pt.prev")
        if bool(built.seeded().any()) or any(
            kf.frame.frame_id == REPAIRED_FRAME_ID for kf in built.store
        ):
            raise SystemExit(f"{run}/work/map.pt.prev holds repaired views: not the input's map")
        state = built.state_dict()
        keyframes = [(kf.frame.T_world_cam, kf.frame.intrinsics.K, kf.frame.color)
                     for kf in built.store]  # fmt: skip

        # 2. The repaired views, in the order they were distilled, with their seed depth
        final = load_snapshot(build(MapperConfig, base=run_cfg), run / "work" / "map.pt")
        mesh = MeshRenderer(read_mesh(run / "mesh.ply"))
        jobs, sizes = [], {}
        for kf, mask in final.forget_repairs():
            f = kf.frame
            name = next((v["view"] for v in views if np.allclose(
                np.reshape(v["camera"]["T_world_cam"], (4, 4)), f.T_world_cam, atol=1e-5)),
                f"kf{kf.kf_id}")  # fmt: skip
            r = mesh.render(f.T_world_cam, f.intrinsics)
            holes = np.ones(f.depth.shape, bool) if mask is None else mask
            # where the mesh saw a surface, as the splat node reads it from the view's region
            prov = run / "views" / name / "provenance.npz"
            observed = r.valid
            if prov.is_file():
                with np.load(prov) as z:
                    observed = np.isin(z["region"], MESH_SAW)
            jobs.append((name, f.color, f.T_world_cam, f.intrinsics.K, holes,
                         seed_depth(r.depth_m, r.valid, seed_empty), observed))  # fmt: skip
            sizes[name] = (f.height, f.width)
        scored = []  # (view, T, K, gt, output) of the repaired views with a ground truth
        for name, _, T, K, *_ in jobs:
            gt_path = demo / "scene" / "novel" / "color" / f"{name}.png"
            out_path = run / "views" / name / "output.png"
            if gt_path.is_file() and out_path.is_file():
                H, W = sizes[name]
                scored.append(
                    (name, T, K, read_png_rgb(gt_path, W, H), read_png_rgb(out_path, W, H))
                )
        # the input keyframes nearest each scored view
        centres = np.array([T[:3, 3] for T, _, _ in keyframes])
        near = sorted({int(i) for _, T, *_ in scored
                       for i in np.argsort(np.linalg.norm(centres - T[:3, 3], axis=1))[:NEIGHBOURS]})  # fmt: skip

        m0 = Mapper(build(MapperConfig, base=run_cfg))
        m0.load_state_dict(state)
        row: dict[str, Any] = {"demo": str(demo), "passes": passes, "order": [j[0] for j in jobs],
                               "input": score(m0, scored, keyframes, near, None), "arms": {}}  # fmt: skip
        print(f"{demo}: {len(jobs)} repaired views ({', '.join(row['order'])}), "
              f"{len(scored)} with ground truth, {len(near)} neighbouring keyframes", flush=True)  # fmt: skip

        # 3. Each arm distils the same views into the same map
        for name, overrides in arms:
            cfg = build(MapperConfig, base=deep_merge(copy.deepcopy(run_cfg), overrides))
            m = Mapper(cfg)
            m.load_state_dict(state)
            t0 = time.perf_counter()
            for view, color, T, K, holes, depth, observed in jobs:
                m.distill(color, T, K, mask=holes, depth=depth, observed=observed)
                m.refine(passes * -(-len(m.store) // cfg.refine_views))
                if cfg.polish_below_db > 0:
                    m.polish()
                print(f"    {name}: {view} distilled ({time.perf_counter() - t0:.0f} s, "
                      f"{int(m.seeded().sum())} seeded)", flush=True)  # fmt: skip
            seconds = time.perf_counter() - t0
            where = None if args.images is None else args.images / demo.name / name
            s = score(m, scored, keyframes, near, where)
            kf_change = [s["keyframes"][k] - row["input"]["keyframes"][k] for k in s["keyframes"]]
            s.update(seconds=seconds, gaussians=len(m.gmap), seeded=int(m.seeded().sum()),
                     stats=m.stats(), overrides=overrides,
                     keyframe_change_db={"min": min(kf_change), "median": statistics.median(kf_change)})  # fmt: skip
            row["arms"][name] = s
            print(f"  {name} ({seconds:.0f} s, {len(m.gmap)} Gaussians, {s['seeded']} seeded):")
            for v, r in s["views"].items():
                ok = (r["sharpness"] >= SHARPNESS_MIN
                      and r["final_db"] >= r["output_db"] - BELOW_OUTPUT_MAX_DB)  # fmt: skip
                print(f"    {v}: output {r['output_db']:.2f} dB, final {r['final_db']:.2f} "
                      f"({r['final_db'] - r['output_db']:+.2f}), sharpness {r['sharpness']:.2f}"
                      f"{'' if ok else '  FAILS'}")  # fmt: skip
            print(f"    keyframes: change min {min(kf_change):+.2f} dB, median "
                  f"{statistics.median(kf_change):+.2f}", flush=True)  # fmt: skip
        rows.append(row)

    if args.out:
        atomic_write_text(args.out, json.dumps({"runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
