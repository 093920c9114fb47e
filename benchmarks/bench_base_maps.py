"""GSFixer base models on the degradations of our own maps: held-out scenes' novel views.

For each cached map-triplet scene (``gsfix-online fixer pretrain pretrain.maps.views=N`` writes
them to ``OUT/maps``; ``gsfix_online/jobs/map_corpus.py``), every novel view is repaired from
its TSDF-mesh render and its Gaussian-map render by each base model (untuned, as the repair
graph repairs: 1 DDIM step, 4 shifted grids) and scored against the noise-free ground truth
beside the baselines a user has without GSFixer: the raw 3DGS render, mesh fill (3DGS where its
alpha >= 0.5, else the mesh), and mesh fill + OpenCV Telea. Scores are whole-image PSNR/SSIM and
PSNR per region class (seen by both maps, the 3DGS map only, the mesh only, neither), and where
each method's error lies: each region's share of the pixels and of the squared error, and the
whole-view PSNR an exact region or a perfect flat fill there (the ground truth's mean colour)
would gain (``headroom``; ``inspection.metrics.region_headroom``). Scenes
built with ``pretrain.maps.holdout`` also hold frames of the trajectory kept out of mapping
(where the maps render well and a repair must keep them): those are summarised apart
(``holdout``), and the novel views are also composed as the repair node composes them from a
choice per region measured on those frames, with one candidate per region (``choice:NAME``)
and with blends of GSFixer into a fallback (``blend:NAME``; ``repair.fallback.choose``).

    .venv/bin/python benchmarks/bench_base_maps.py --maps OUT/maps --seeds 94-99 \\
        --bases stage2=DIR [--images DIR] --out benchmarks/results/base_maps_cpu.json

With ``--build`` the seeds' triplets missing from ``--maps`` are built first, as pretraining
builds its corpus (``--holdout``, ``--room-prob``; ``--workers`` processes).

The packaged base is always one of the models (``packaged``). Prints the median over views of
each method and of each model minus mesh fill + Telea.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._case import write_result  # noqa: E402

# the images --images draws after ground truth, 3DGS, mesh and mesh fill + Telea (per model)
ARMS = ("fixer", "choice", "blend")


def parse_seeds(spec: str) -> list[int]:
    out: list[int] = []
    for part in spec.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b) + 1) if b else [int(a)])
    return out


def scene_file(maps: Path, seed: int) -> Path:
    found = sorted(maps.glob(f"maps_v*_{seed:06d}_*.npz"))
    if len(found) != 1:
        raise SystemExit(f"{maps}: expected one map-triplet file for seed {seed}, got {len(found)}")
    return found[0]


def summarize(rows: list[dict[str, Any]], methods: list[str]) -> dict[str, Any]:
    """Medians over ``rows`` of each method: PSNR, SSIM, PSNR minus mesh fill + Telea, regions."""
    from gsfix_online.repair.fallback import REGIONS

    out: dict[str, Any] = {}
    for k in methods:
        out[k] = {
            "median_psnr_db": statistics.median(r[k]["psnr_db"] for r in rows),
            "median_ssim": statistics.median(r[k]["ssim"] for r in rows),
            "median_minus_fill_telea_db": statistics.median(
                r[k]["psnr_db"] - r["fill_telea"]["psnr_db"] for r in rows
            ),
            "regions": {
                reg: statistics.median(vals)
                for reg in REGIONS
                if (vals := [r[k]["regions"][reg] for r in rows if reg in r[k]["regions"]])
            },
            "headroom": {
                reg: {
                    key: statistics.median(h[key] for h in hs)
                    for key in ("error_share", "exact_gain_db", "mean_fill_gain_db")
                }
                for reg in REGIONS
                if (hs := [r[k]["headroom"][reg] for r in rows if reg in r[k]["headroom"]])
            },
        }
    out["pixel_share"] = {
        reg: statistics.mean(r["pixel_share"].get(reg, 0.0) for r in rows) for reg in REGIONS
    }
    return out


def add_choices(views: list[dict[str, Any]], models: dict[str, Any]) -> None:
    """Each novel view of a scene composed as the repair node composes views near its held-out
    frames: the choice per region measured on the scene's held-out frames (as they are; regions
    under 1 % of their pixels with the novel views' unmapped parts cut in), with one candidate per
    region (``choice:NAME``) and with blends of GSFixer into a fallback (``blend:NAME``)."""
    from gsfix_online.repair.fallback import (
        FEATHER_PX,
        HeldOutSample,
        baseline_candidates,
        choose,
        compose,
        measure,
    )

    held = [x for x in views if x["group"] == "holdout"]
    novel = [x for x in views if x["group"] == "novel"]
    samples = [HeldOutSample(x["gt"], x["gs"], x["alpha"], x["mesh"], x["valid"]) for x in held]
    shapes = [m for x in novel if (m := x["region"] == 3).any()]

    def cut(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
        return shapes[int(rng.integers(len(shapes)))]

    for k, model in models.items():

        def fn(gs: np.ndarray, mesh: np.ndarray, model: Any = model) -> np.ndarray:
            return model.repair(gs, mesh).image

        errors = measure(samples, fn, None, cuts=("none",))
        backup = measure(samples, fn, cut, cuts=("both", "gs", "mesh")) if shapes else None
        for arm, blend in (("choice", False), ("blend", True)):
            c = choose(errors, min_fraction=0.01, backup=backup, blend=blend)
            for x in novel:
                cands = baseline_candidates(x["gs"], x["alpha"], x["mesh"], x["valid"])
                cands["fixed"] = x["images"][f"fixer:{k}"]
                x["images"][f"{arm}:{k}"] = compose(cands, x["region"], c, FEATHER_PX)


def main() -> int:
    import dataclasses

    import torch

    from gsfix_online.core.config import profile
    from gsfix_online.core.metrics import region_headroom, region_scores
    from gsfix_online.fixer.config import FixerConfig
    from gsfix_online.repair.baselines import inpaint_telea, mesh_fill
    from gsfix_online.repair.fallback import REGIONS, regions
    from gsfix_online.repair.outputs import write_png
    from gsfix_online.repair.repairer import ViewRepairer

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--maps", type=Path, required=True, help="folder of maps_v*.npz")
    ap.add_argument("--seeds", default="94-99", help="scene seeds, e.g. 94-99 or 1,5,7")
    ap.add_argument("--bases", nargs="*", default=[], metavar="NAME=DIR")
    ap.add_argument("--images", type=Path, default=None,
                    help="PNGs of each view: truth, 3DGS, mesh, Telea, then each model's arms")  # fmt: skip
    ap.add_argument("--build", action="store_true",
                    help="build the seeds' map triplets missing from --maps first (pretraining's "
                         "corpus: 160x128, 8 novel views a scene)")  # fmt: skip
    ap.add_argument("--holdout", type=int, default=5, help="with --build: pretrain.maps.holdout")
    ap.add_argument("--room-prob", type=float, default=0.3, help="with --build: room share")
    ap.add_argument("--workers", type=int, default=2, help="with --build: processes")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bad = [b for b in args.bases if "=" not in b]
    if bad:
        raise SystemExit(f"--bases takes NAME=DIR, got {bad[0]!r}")

    if args.build:
        from gsfix_online.jobs.map_corpus import load_or_build_corpus
        from gsfix_online.jobs.pretrain import PretrainConfig

        pre = PretrainConfig()
        corpus = dataclasses.replace(pre.maps, views=8, holdout=args.holdout,
                                     workers=args.workers)  # fmt: skip
        t = time.perf_counter()
        load_or_build_corpus(
            parse_seeds(args.seeds), pre.width, pre.height, pre.grayscale_prob, corpus,
            args.maps, room_prob=args.room_prob,
            progress=lambda k, n, text: print(f"[{k}/{n}] {text}", flush=True),
        )  # fmt: skip
        print(f"map triplets ready in {time.perf_counter() - t:.1f} s ({args.workers} processes)")

    cfg = profile(FixerConfig, "repair_cpu.yaml")  # as the repair node repairs
    models: dict[str, ViewRepairer] = {"packaged": ViewRepairer(cfg)}
    models["packaged"].load_base()
    for spec in args.bases:
        name, path = spec.split("=", 1)
        models[name] = ViewRepairer(cfg)
        models[name].load_checkpoint(path, 0)

    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for seed in parse_seeds(args.seeds):
        with np.load(scene_file(args.maps, seed)) as z:
            gt_all, mesh_all, gs_all = z["gt"], z["mesh"], z["gs"]
            alpha_all, valid_all = z["alpha"], z["valid"]
            held_all = z["heldout"] if "heldout" in z else np.zeros(len(gt_all), bool)
        views = []
        for v in range(gt_all.shape[0]):
            gt, mesh, gs = gt_all[v], mesh_all[v], gs_all[v]
            alpha, valid = alpha_all[v].astype(np.float32) / 255.0, valid_all[v]
            fill = mesh_fill(gs, alpha, mesh, valid)
            images = {
                "gs": gs,
                "mesh_fill": fill.image,
                "fill_telea": inpaint_telea(fill.image, fill.missing),
                **{f"fixer:{k}": m.repair(gs, mesh).image for k, m in models.items()},
            }
            views.append({"gt": gt, "mesh": mesh, "gs": gs, "alpha": alpha, "valid": valid,
                          "region": regions(alpha, valid), "images": images,
                          "group": "holdout" if held_all[v] else "novel"})  # fmt: skip
        if held_all.any():
            add_choices(views, models)
        for v, x in enumerate(views):
            gt, images, region, group = x["gt"], x["images"], x["region"], x["group"]
            row: dict[str, Any] = {"seed": seed, "view": v, "group": group}
            for k, img in images.items():
                whole, by_region = region_scores(img, gt, region, REGIONS)
                room = region_headroom(img, gt, region, REGIONS)
                row[k] = {
                    "psnr_db": whole.psnr_db,
                    "ssim": whole.ssim,
                    "regions": {r: s.psnr_db for r, s in by_region.items()},
                    "headroom": {
                        r: {
                            "error_share": h.error_share,
                            "exact_gain_db": h.exact_gain_db,
                            "mean_fill_gain_db": h.mean_fill_gain_db,
                        }
                        for r, h in room.items()
                    },
                }
                row["pixel_share"] = {r: h.pixel_share for r, h in room.items()}
            rows.append(row)
            print(
                f"scene {seed} {group} view {v}: "
                + ", ".join(f"{k} {row[k]['psnr_db']:.2f}" for k in images)
                + f" ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
            if args.images is not None:
                arms = [im for k, im in images.items() if k.split(":")[0] in ARMS]
                write_png(args.images / f"s{seed}_v{v}.png", np.concatenate(
                    [gt, x["gs"], x["mesh"], images["fill_telea"], *arms], axis=1,
                ))  # fmt: skip

    novel = [r for r in rows if r["group"] == "novel"]
    held = [r for r in rows if r["group"] == "holdout"]

    def methods_of(group: list[dict[str, Any]]) -> list[str]:
        return [k for k in group[0] if k not in ("seed", "view", "group", "pixel_share")]

    summary: dict[str, Any] = {"views": len(novel), "scenes": len({r["seed"] for r in rows}),
                               **summarize(novel, methods_of(novel))}  # fmt: skip
    if held:
        summary["holdout"] = {"views": len(held), **summarize(held, methods_of(held))}
    write_result(args.out, __doc__, args.threads, summary, rows)
    for name, group, s in (("novel views", novel, summary),
                           ("held-out frames", held, summary.get("holdout"))):  # fmt: skip
        if not group:
            continue
        print(f"{len(group)} {name} of {summary['scenes']} scenes "
              "(medians; minus mesh fill + Telea):")  # fmt: skip
        methods = methods_of(group)
        for k in methods:
            print(f"  {k:18s} {s[k]['median_psnr_db']:6.2f} dB  SSIM {s[k]['median_ssim']:.3f}  "
                  f"{s[k]['median_minus_fill_telea_db']:+.2f} dB")  # fmt: skip
        print("  where the error is (pixel share; per method: error share, gain if exact / "
              "if flat-filled with the true mean colour, dB):")  # fmt: skip
        print("    pixels " + "  ".join(f"{r} {s['pixel_share'][r]:.2f}" for r in REGIONS))
        for k in methods:
            hr = s[k]["headroom"]
            print(f"    {k:18s} " + "  ".join(
                f"{r} {h['error_share']:.2f} {h['exact_gain_db']:+.2f}/{h['mean_fill_gain_db']:+.2f}"
                for r, h in hr.items()))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
