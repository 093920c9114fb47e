"""Polishing a finished run's final map (``Mapper.polish``): the map's views against the ground
truth before and after, for each threshold.

Loads the run's last map snapshot (``work/map.pt``, which holds the repaired views with their
masks) with the splat node's mapper settings from ``work/graph.yaml``, polishes a copy per
threshold, and scores the renders at every view of ``work/views.txt`` against ``work/gt``:
novel views and held-out frames (the repair node's ``holdout_views``) apart. Takes the case
folders of ``benchmarks/bench_variants.py``:

    .venv/bin/python benchmarks/bench_polish.py CASE_DIR... --below 22 30 \\
        --out benchmarks/results/polish_cpu.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    import numpy as np
    import torch

    from gsfix_online.config_schema import atomic_write_text, build, read_yaml
    from gsfix_online.inspection.metrics import psnr
    from gsfix_online.mapping.splat.mapper import Mapper, MapperConfig
    from gsfix_online.mapping.splat.service import load_snapshot
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.views import read_views
    from gsfix_online.sources.tum import read_intrinsics_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cases", type=Path, nargs="+", help="bench_variants case folders")
    ap.add_argument("--below", type=float, nargs="+", default=[22.0], help="thresholds, dB")
    ap.add_argument("--iters", type=int, default=None, help="polish_iters (default: the run's)")
    ap.add_argument("--rounds", type=int, default=None, help="polish_rounds (default: the run's)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    rows = []
    for case in args.cases:
        run = case / "run"
        graph = read_yaml(run / "work" / "graph.yaml")["nodes"]
        mapper_cfg = {**graph["splat"]["params"].get("mapper", {}), "backend": "cpu"}
        for key, value in (("polish_iters", args.iters), ("polish_rounds", args.rounds)):
            if value is not None:
                mapper_cfg[key] = value
        cfg = build(MapperConfig, base=mapper_cfg)
        first_stop = graph["repair"]["params"].get("holdout_views", [])  # [first, stop)
        held = set(range(*first_stop)) if first_stop else set()
        intr, _ = read_intrinsics_json(case / "scene" / "novel" / "intrinsics.json")
        poses = [v.T_world_cam for v in read_views(run / "work" / "views.txt")]  # file order
        gts = [read_png_rgb(run / "work" / "gt" / f"{i:03d}.png", intr.width, intr.height)
               for i in range(len(poses))]  # fmt: skip

        def score(m: Mapper, poses=poses, gts=gts, intr=intr) -> list[float]:
            out = []
            for T, gt in zip(poses, gts, strict=True):
                with torch.no_grad():
                    r = m.render(T, intr.K, intr.width, intr.height)
                img = np.rint(r.color.clamp(0, 1).numpy() * 255).astype(np.uint8)
                if img.shape[-1] == 1:
                    img = np.repeat(img, 3, axis=-1)
                out.append(psnr(img, gt))
            return out

        def groups(per_view: list[float], held=held) -> dict[str, float]:
            novel = [p for i, p in enumerate(per_view) if i not in held]
            hold = [p for i, p in enumerate(per_view) if i in held]
            return {"novel_db": float(np.mean(novel)),
                    "holdout_db": float(np.mean(hold)) if hold else float("nan")}  # fmt: skip

        base = load_snapshot(cfg, run / "work" / "map.pt")
        before = score(base)
        metrics = json.loads((run / "metrics.json").read_text())["summary"]["groups"]
        ref = {g: {s: metrics[g][s]["psnr_db"] for s in ("inpaint", "output", "final")}
               for g in metrics}  # fmt: skip
        row = {"case": str(case), "before": {"views": before, **groups(before)}, "run": ref,
               "polished": {}}  # fmt: skip
        print(f"{case}: final map novel {row['before']['novel_db']:.2f} dB, held-out "
              f"{row['before']['holdout_db']:.2f} (mesh fill + Telea {ref['novel']['inpaint']:.2f}, "
              f"{ref.get('holdout', {}).get('inpaint', float('nan')):.2f})")  # fmt: skip
        for below in args.below:
            m = load_snapshot(cfg, run / "work" / "map.pt")
            res = m.polish(below_db=below)
            after = score(m)
            row["polished"][str(below)] = {
                "views": after, **groups(after), "polished_kf": res.polished,
                "steps": res.n_iters,
                "fidelity_before": {str(k): v for k, v in res.before.items()},
                "fidelity_after": {str(k): v for k, v in res.after.items()},
            }  # fmt: skip
            p = row["polished"][str(below)]
            print(
                f"  below {below:g} dB: {len(res.polished)} views polished in {res.n_iters} "
                f"steps; novel {p['novel_db']:.2f} dB, held-out {p['holdout_db']:.2f}"
            )
        rows.append(row)
    gains = {b: statistics.median(r["polished"][str(b)]["novel_db"] - r["before"]["novel_db"]
                                  for r in rows) for b in args.below}  # fmt: skip
    print("median gain at the novel views:", {f"{b:g}": round(g, 2) for b, g in gains.items()})
    if args.out:
        atomic_write_text(args.out, json.dumps({"runs": rows, "median_novel_gain_db": gains},
                                               indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
