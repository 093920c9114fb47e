"""Distillation settings compared on the same map: a finished run's repaired views distilled
again into the map its input built, once per arm, and the final renders scored against the
ground truth.

An online run's final map moves 0.5-0.8 dB between runs of one input (node timing changes the
keyframes), more than most distillation changes are worth; here every arm starts from one map
and distils the same views, so the difference is the setting's alone. Per case folder of
``benchmarks/bench_variants.py``:

1. load the run's last map snapshot (``work/map.pt``) with the splat node's mapper settings
   (``work/graph.yaml``) and take distillation out of it (``Mapper.forget_repairs``: its
   repaired views and the Gaussians it seeded; what the passes changed in the input's
   Gaussians stays);
2. per arm (mapper settings over the run's), distil each repaired view as the splat node does:
   ``Mapper.distill`` with its delivered mask and the seed depth of the run's final mesh, then
   ``splat.distill_passes`` passes over the keyframes, then polish (``mapper.polish_below_db``);
   with ``--at-end`` the passes and polish follow the last view only;
3. score the map's renders at every view of ``work/views.txt`` against ``work/gt``, novel
   views and held-out frames apart, beside the run's own mesh fill + Telea and output.

    .venv/bin/python benchmarks/bench_distill.py CASE_DIR... \\
        --arm shipped --arm push:distill_push_seeds=true --out benchmarks/results/distill_cpu.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse_arm(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME[:KEY=VALUE,...]`` -> (name, mapper overrides); values are YAML scalars."""
    import yaml

    name, _, rest = text.partition(":")
    overrides: dict[str, Any] = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise SystemExit(f"--arm {text!r}: {item!r} is not KEY=VALUE")
        overrides[key] = yaml.safe_load(value)
    return name, overrides


def main() -> int:
    import numpy as np
    import torch

    from benchmarks._case import read_case, score_map
    from gsfix_online.core.config import build
    from gsfix_online.core.io import atomic_write_text
    from gsfix_online.mapping.mesh import read_mesh
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.mapping.splat.mapper import Mapper, MapperConfig
    from gsfix_online.repair.repairer import seed_depth
    from gsfix_online.services.splat import load_snapshot

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cases", type=Path, nargs="+", help="bench_variants case folders")
    ap.add_argument(
        "--arm",
        action="append",
        default=[],
        metavar="NAME[:KEY=VALUE,...]",
        help="mapper settings over the run's (repeatable; default: the run's only)",
    )
    ap.add_argument("--passes", type=int, default=None, help="distill_passes (default: run's)")
    ap.add_argument("--at-end", action="store_true",
                    help="the passes and polish once, after the last view (as a graph whose "
                         "repairs arrive faster than their passes), not after each view")  # fmt: skip
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--images", type=Path, default=None,
                    help="write each arm's renders to IMAGES/CASE/ARM/NNN.png")  # fmt: skip
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    arms = [parse_arm(a) for a in args.arm] or [("run", {})]

    rows = []
    for path in args.cases:
        case = read_case(path)
        run, graph, run_cfg = case.run, case.graph, case.mapper
        splat = graph["splat"]["params"]
        passes = splat.get("distill_passes", 2) if args.passes is None else args.passes
        seed_empty = graph["repair"]["params"].get("seed_empty", True)

        # 1. The map the input built, and the repaired views to distil again
        built = load_snapshot(build(MapperConfig, base=run_cfg), run / "work" / "map.pt")
        views = built.forget_repairs()
        state = built.state_dict()
        mesh = MeshRenderer(read_mesh(run / "mesh.ply"))
        jobs = []
        for kf, mask in views:
            f = kf.frame
            holes = np.ones(f.depth.shape, bool) if mask is None else mask
            r = mesh.render(f.T_world_cam, f.intrinsics)
            jobs.append((f.color, f.T_world_cam, f.intrinsics.K, holes,
                         seed_depth(r.depth_m, r.valid, seed_empty)))  # fmt: skip

        ref = case.reference
        m0 = Mapper(build(MapperConfig, base=run_cfg))
        m0.load_state_dict(state)
        row: dict[str, Any] = {"case": str(path), "run": ref, "views": len(jobs),
                               "passes": passes, "built": score_map(m0, case), "arms": {}}  # fmt: skip
        print(f"{path}: {len(jobs)} repaired views; the input's map: novel "
              f"{row['built']['novel_db']:.2f} dB, held-out {row['built']['holdout_db']:.2f}; "
              f"mesh fill + Telea {ref['novel']['inpaint']:.2f}, "
              f"{ref.get('holdout', {}).get('inpaint', float('nan')):.2f}", flush=True)  # fmt: skip

        # 2. Each arm distils the same views into the same map
        for name, overrides in arms:
            cfg = build(MapperConfig, base={**run_cfg, **overrides})
            m = Mapper(cfg)
            m.load_state_dict(state)
            t0 = time.perf_counter()
            for color, T, K, holes, depth in jobs:
                m.distill(color, T, K, mask=holes, depth=depth)
                if not args.at_end:
                    m.refine(passes * -(-len(m.store) // cfg.refine_views))
                    if cfg.polish_below_db > 0:
                        m.polish()
            if args.at_end:
                m.refine(passes * -(-len(m.store) // cfg.refine_views))
                if cfg.polish_below_db > 0:
                    m.polish()
            seconds = time.perf_counter() - t0
            where = None if args.images is None else args.images / path.name / name
            s = score_map(m, case, where)
            row["arms"][name] = {"overrides": overrides, "seconds": seconds,
                                 "gaussians": len(m.gmap), "pushed": m.n_pushed,
                                 "fidelity": {str(k): v for k, v in m.fidelity().items()},
                                 **s}  # fmt: skip
            print(f"  {name}: novel {s['novel_db']:.2f} dB, held-out {s['holdout_db']:.2f} "
                  f"({seconds:.0f} s, {m.n_pushed} seeds pushed, {len(m.gmap)} Gaussians)",
                  flush=True)  # fmt: skip
            for view, b in s["vs_output"].items():
                flag = " x" if b["db"] < -0.3 or b["sharpness"] < 0.9 else ""
                print(f"    view {view}: final - output {b['db']:+.2f} dB, "
                      f"sharpness {b['sharpness']:.2f}{flag}", flush=True)  # fmt: skip
        rows.append(row)

    # 3. Medians over the cases, against the first arm and the floor
    first = arms[0][0]
    summary = {}
    for name, _ in arms:
        summary[name] = {
            f"{g}_vs_{first}_db": statistics.median(
                r["arms"][name][f"{g}_db"] - r["arms"][first][f"{g}_db"] for r in rows)
            for g in ("novel", "holdout")
        } | {
            f"{g}_vs_inpaint_db": statistics.median(
                r["arms"][name][f"{g}_db"] - r["run"][key]["inpaint"] for r in rows)
            for g, key in (("novel", "novel"), ("holdout", "holdout"))
            if all(key in r["run"] for r in rows)
        }  # fmt: skip
    print(json.dumps(summary, indent=1))
    if args.out:
        atomic_write_text(args.out, json.dumps({"runs": rows, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
