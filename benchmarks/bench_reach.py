"""How far the held-out frames' choice per region carries: finished repair runs recomposed.

For ``bench_variants.py`` case folders (runs with ``--holdout`` and novel views with ground
truth), every repaired view's output is composed again from the candidates the run saved
(``fixed.png``, ``inpaint.png``, ``mesh_inpaint.png``; no model runs) with:

- ``run``: the view's own output as the run delivered it;
- ``held-out``: the run's measured choice per region (``summary.fallback``) on every view, the
  rule before ``fallback.for_view``;
- ``fixed``, ``inpaint``, ``mesh_inpaint``: one candidate everywhere (``inpaint``, mesh fill +
  Telea, is the floor);
- ``--arm NAME:both=C,gs_only=C,mesh_only=C,neither=C``: any other choice per region (e.g. the
  trainer's, from the run's ``repair.log``); ``C@W`` blends GSFixer into fallback C with share W;
- ``own``: each repaired view's own recorded choice (``model.choice`` with ``choice_share``,
  GSFixer's share where a region blends it into a fallback); ``own-hard``: the choice the same
  measurements made with one candidate per region (``choice_hard``, the rule before blends).

Views the planner skipped keep the run's output in every arm but ``skipped-near``, where the
held-out frames among them take the run's measured choice per region with GSFixer's regions
given to the fallback measured better there (``RepairOutputs.finish_skipped``, for runs made
before it; in a run made after it ``run`` is that already), while repaired views keep the run's
output. Per group (``novel``: the user's
views, metres off the trajectory; ``holdout``: the held-out frames on it), the mean PSNR and
SSIM of each arm, and per view its keyframe distance and where its choice came from when the
run recorded them. Same maps and same GSFixer in every arm, so the arms differ by the choice alone.

    .venv/bin/python benchmarks/bench_reach.py CASE_DIR [CASE_DIR ...] [--out FILE]

(a run folder, e.g. ``outputs/demo/repair``, works too: without held-out frames every view is
in ``novel`` and ``held-out`` is the trainer's choice per region).

Results: ``benchmarks/results/reach_cpu.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._case import held_views  # noqa: E402
from gsfix_online.core.io import atomic_write_text  # noqa: E402
from gsfix_online.core.metrics import psnr, ssim  # noqa: E402
from gsfix_online.repair.fallback import (  # noqa: E402
    CANDIDATES,
    FALLBACKS,
    FEATHER_PX,
    REGIONS,
    Choice,
    compose,
    regions,
)
from gsfix_online.repair.outputs import read_png_rgb  # noqa: E402

# per repaired view: its own recorded choice recomposed (blends included), and that choice
# without blends (``choice_hard``: what the same measurement chose one candidate per region)
VIEW_ARMS = ("own", "own-hard")


def parse_arm(text: str) -> tuple[str, Choice]:
    """``NAME:both=C,gs_only=C,mesh_only=C,neither=C`` -> (NAME, its choice). A fallback C may
    carry GSFixer's share in it as ``C@W`` (``neither=mesh_inpaint@0.5``: half of each)."""
    name, _, spec = text.partition(":")
    per, share = {}, {}
    try:
        for kv in filter(None, spec.split(",")):
            r, c = kv.split("=", 1)
            c, at, w = c.partition("@")
            per[r] = c
            if at:
                share[r] = float(w)
        ok = set(per) == set(REGIONS) and set(per.values()) <= set(CANDIDATES)
        ok = ok and all(0.0 <= w <= 1.0 and per[r] in FALLBACKS for r, w in share.items())
    except ValueError:
        ok = False
    if not name or not ok:
        raise SystemExit(f"--arm {text!r}: give NAME:{','.join(r + '=C' for r in REGIONS)} "
                         f"with C one of {', '.join(CANDIDATES)} (a fallback as C@W: GSFixer's "
                         f"share W in [0, 1])")  # fmt: skip
    return name, Choice(per, {}, {}, 0, name, share)


def bench_case(case: Path, extra: dict[str, Choice] | None = None) -> dict[str, Any]:
    run = case / "run" if (case / "run").is_dir() else case  # a case folder or a run folder
    m = json.loads((run / "metrics.json").read_text())
    held = held_views(run)
    gt_dir = Path(m["summary"].get("ground_truth") or run / "work" / "gt")
    measured = Choice.from_json(json.dumps(m["summary"]["fallback"]))
    # a held-out frame is scored by the choice the other held-out frames measured (runs that
    # recorded it; a lone frame's is None and keeps the run's own output)
    without = {k: None if c is None else Choice.from_json(json.dumps(c))
               for k, c in (m["summary"].get("fallback_without") or {}).items()}  # fmt: skip
    arms = {"held-out": measured}
    arms.update({c: Choice(dict.fromkeys(REGIONS, c), {}, {}, 0, c) for c in CANDIDATES})
    arms.update(extra or {})
    rows = []
    for v in m["views"]:
        name = f"{v['view_id']:03d}"
        d, gt_path = run / "views" / name, gt_dir / f"{name}.png"
        if not gt_path.is_file():
            continue
        gt = read_png_rgb(gt_path)
        out: dict[str, float] = {}
        ss: dict[str, float] = {}

        def score(arm: str, img: np.ndarray) -> None:
            out[arm], ss[arm] = psnr(img, gt), ssim(img, gt)  # noqa: B023

        score("run", read_png_rgb(d / "output.png"))
        mine = without.get(name, measured)
        out["skipped-near"], ss["skipped-near"] = out["run"], ss["run"]
        if not v.get("repair") and v["view_id"] in held and (d / "mesh_inpaint.png").is_file():
            cands = {c: read_png_rgb(d / f"{c}.png") for c in FALLBACKS}
            alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
            region = regions(alpha, read_png_rgb(d / "mesh.png").any(axis=2))
            if mine is not None:
                score("skipped-near", compose(cands, region, mine.without_fixer(), FEATHER_PX))
        model = v.get("model", {})
        if (d / "fixed.png").is_file() and v.get("repair"):
            cands = {c: read_png_rgb(d / f"{c}.png") for c in CANDIDATES}
            alpha = read_png_rgb(d / "alpha.png")[..., 0].astype(np.float32) / 255.0
            region = regions(alpha, read_png_rgb(d / "mesh.png").any(axis=2))
            for arm, choice in arms.items():
                if arm == "held-out":
                    if mine is None:
                        out[arm], ss[arm] = out["run"], ss["run"]
                        continue
                    choice = mine
                score(arm, compose(cands, region, choice, FEATHER_PX))
            # the view's own choice as recorded (blends included), and without blends
            own = Choice(dict(model["choice"]), {}, {}, 0, "", dict(model.get("choice_share", {})),
                         hard=dict(model.get("choice_hard", {})))  # fmt: skip
            score("own", compose(cands, region, own, FEATHER_PX))
            score("own-hard", compose(cands, region, own.hardened(), FEATHER_PX))
        else:  # skipped: the run's output in every arm
            out.update(dict.fromkeys([*arms, *VIEW_ARMS], out["run"]))
            ss.update(dict.fromkeys([*arms, *VIEW_ARMS], ss["run"]))
        rows.append({
            "view": name, "group": "holdout" if v["view_id"] in held else "novel",
            "repair": bool(v.get("repair")),
            "keyframe_distance_m": model.get("keyframe_distance_m"),
            "choice_from": model.get("choice_from", ""), "choice": model.get("choice", {}),
            "psnr_db": out, "ssim": ss,
        })  # fmt: skip
    groups, groups_ssim = {}, {}
    for g in ("novel", "holdout"):
        sel = [r for r in rows if r["group"] == g]
        if sel:
            names = ["run", "skipped-near", *VIEW_ARMS, *arms]
            groups[g] = {a: float(np.mean([r["psnr_db"][a] for r in sel])) for a in names}
            groups_ssim[g] = {a: float(np.mean([r["ssim"][a] for r in sel])) for a in names}
    return {"case": case.name, "measured": measured.per_region, "groups": groups,
            "groups_ssim": groups_ssim, "views": rows}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cases", nargs="+", type=Path)
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).parent / "results" / "reach_cpu.json")  # fmt: skip
    ap.add_argument("--arm", action="append", default=[], type=parse_arm,
                    help="NAME:both=C,gs_only=C,mesh_only=C,neither=C (repeatable)")  # fmt: skip
    args = ap.parse_args()
    rows = [bench_case(c, dict(args.arm)) for c in args.cases]
    for r in rows:
        for g, arms in r["groups"].items():
            floor = arms["inpaint"]
            print(f"{r['case']:24s} {g:8s} " + "  ".join(
                f"{a} {p:.2f} ({p - floor:+.2f})" for a, p in arms.items()))  # fmt: skip
            print(f"{'':24s} {g:8s} SSIM " + "  ".join(
                f"{a} {x:.4f}" for a, x in r["groups_ssim"][g].items()))  # fmt: skip
    atomic_write_text(args.out, json.dumps({"argv": sys.argv[1:], "cases": rows}, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
