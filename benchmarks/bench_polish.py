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
    import torch

    from benchmarks._case import read_case, score_map
    from gsfix_online.core.config import build
    from gsfix_online.core.io import atomic_write_text
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.services.splat import load_snapshot

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
    for path in args.cases:
        case = read_case(path)
        run = case.run
        mapper_cfg = dict(case.mapper)
        for key, value in (("polish_iters", args.iters), ("polish_rounds", args.rounds)):
            if value is not None:
                mapper_cfg[key] = value
        cfg = build(MapperConfig, base=mapper_cfg)
        base = load_snapshot(cfg, run / "work" / "map.pt")
        ref = case.reference
        row = {"case": str(path), "before": score_map(base, case), "run": ref, "polished": {}}
        print(f"{path}: final map novel {row['before']['novel_db']:.2f} dB, held-out "
              f"{row['before']['holdout_db']:.2f} (mesh fill + Telea {ref['novel']['inpaint']:.2f}, "
              f"{ref.get('holdout', {}).get('inpaint', float('nan')):.2f})")  # fmt: skip
        for below in args.below:
            m = load_snapshot(cfg, run / "work" / "map.pt")
            res = m.polish(below_db=below)
            row["polished"][str(below)] = {
                **score_map(m, case), "polished_kf": res.polished,
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
