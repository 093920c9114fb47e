"""What distillation changed in the input keyframes' renders, at full size, from a run's snapshots.

A repair run keeps the map of the input's end as ``RUN/repair/work/map.pt.prev`` (the snapshot
before the final one: no repaired view in it) and the final map as ``map.pt``. For every input
keyframe both hold, this renders the keyframe at its corrected pose and in its exposure
(:meth:`Mapper.observed_psnr`) and prints the PSNR change's median and worst, and how many
keyframes lost more than 0.1 dB; and the same over the repaired views' neighbours (the keyframes
``metrics.json`` ``keyframes_kept`` names beside a view: issue 43's "neighbouring keyframes"). The
in-run measure (``keyframes_kept``) starts from the map at the first repaired view instead. The
run's files are only read.

    .venv/bin/python benchmarks/keyframes_change.py RUN [RUN ...] [--downscale 1] \\
        [--json benchmarks/results/polish_keyframes_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def change(run: Path, downscale: int) -> dict[str, Any]:
    """The run's keyframes' PSNR dB in the input's map and the final map, and the summary."""
    import yaml

    from gsfix_online.core.config import build
    from gsfix_online.mapping.splat.mapper import MapperConfig
    from gsfix_online.services.splat import load_snapshot

    graph = yaml.safe_load((run / "repair/work/graph.yaml").read_text())
    cfg = build(MapperConfig, base=graph["nodes"]["splat"]["params"]["mapper"])
    before = load_snapshot(cfg, run / "repair/work/map.pt.prev")
    after = load_snapshot(cfg, run / "repair/work/map.pt")
    if len(before.store) != len(before.observed_ids()):
        raise SystemExit(f"{run}: map.pt.prev holds repaired views: not the map of the input's end")
    ids = [i for i in before.observed_ids() if i in set(after.observed_ids())]
    a, b = before.observed_psnr(ids, downscale), after.observed_psnr(ids, downscale)
    d = np.array([b[i] - a[i] for i in ids])
    kept = json.loads((run / "repair/metrics.json").read_text()).get("keyframes_kept") or {}
    near = sorted({int(r["keyframe_id"]) for r in kept.get("keyframes", []) if r["view_id"] >= 0})
    dn = np.array([b[i] - a[i] for i in near if i in a])
    return {
        "keyframes": len(ids),
        "median_change_db": float(np.median(d)),
        "worst_change_db": float(d.min()),
        "lost_over_0.1_db": int((d < -0.1).sum()),
        "neighbours": len(dn),
        "neighbours_median_change_db": float(np.median(dn)) if len(dn) else None,
        "neighbours_worst_change_db": float(dn.min()) if len(dn) else None,
        "neighbours_lost_over_0.1_db": int((dn < -0.1).sum()),
        "before_db": {str(i): a[i] for i in ids},
        "after_db": {str(i): b[i] for i in ids},
    }


def main() -> int:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="gsfix-online demo --out folders")
    ap.add_argument("--downscale", type=int, default=1, help="render at 1/n of the frame size")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None, help="add the figures to this file's runs")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    out = {}
    for run in a.runs:
        r = out[run.name] = change(run, a.downscale)
        print(f"{run.name}: {r['keyframes']} keyframes, change {r['median_change_db']:+.2f} dB "
              f"(median), worst {r['worst_change_db']:+.2f}, {r['lost_over_0.1_db']} lost "
              f"over 0.1 dB; neighbours {r['neighbours']}: {r['neighbours_median_change_db']:+.2f}"
              f", worst {r['neighbours_worst_change_db']:+.2f}, "
              f"{r['neighbours_lost_over_0.1_db']} lost")  # fmt: skip
    if a.json is not None:
        data = json.loads(a.json.read_text()) if a.json.is_file() else {}
        for name, r in out.items():
            data.setdefault(name, {})[f"keyframes_change_downscale_{a.downscale}"] = {
                k: v for k, v in r.items() if not k.endswith("_db") or "change" in k
            }
        a.json.write_text(json.dumps(data, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
