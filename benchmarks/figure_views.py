"""Side-by-side figure of repaired views (:mod:`gsfix_online.jobs.figure`): ground truth, the
run's best classical baseline, 3DGS, mesh, GSFixer, delivered output, final map render and the
output's provenance, one row per view, each image tile labelled with its PSNR.

    .venv/bin/python benchmarks/figure_views.py outputs/demo/repair --views 0 3 5 \\
        --gt outputs/demo/scene/novel/color \\
        --out docs/repair_views.png

The images are the run's own files (``views/NNN/*.png``); ground truth from ``--gt DIR/NNN.png``
(default: the run's ``work/gt``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gsfix_online.jobs.figure import write_views_figure  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a finished repair run folder")
    ap.add_argument("--gt", type=Path, default=None, help="ground truth NNN.png (default work/gt)")
    ap.add_argument("--views", nargs="+", type=int, default=None, help="default: repaired ones")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scale", type=float, default=1.0, help="resize the figure (area average)")
    args = ap.parse_args()
    w, h = write_views_figure(args.run, args.out, args.gt, args.views, args.scale)
    print(f"-> {args.out} ({w}x{h})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
