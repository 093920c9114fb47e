"""Held-out frames of a mapped sequence: does the Gaussian map generalise to views a few
centimetres off its training views, as well as the TSDF mesh does?

Every ``K``-th frame (``i % K == K // 2``) of a sequence is held out; the others are mapped as the
repair graph maps them: :class:`~gsfix_online.mapping.splat.mapper.Mapper` with the graph's
mapper policy (``configs/profiles/mapper_cpu.yaml``, which its splat node extends; one torch thread)
and the TSDF at 2 cm. At each held-out frame, rendered at the pose the system has for it (the
estimated pose when poses drift), four images are scored against the frame's real image (PSNR,
SSIM):

- ``gs``: the raw 3DGS render;
- ``gs_telea``: the 3DGS render with its low-alpha (< 0.5) holes filled by OpenCV Telea;
- ``mesh_telea``: the mesh render with its holes filled by Telea;
- ``fill_telea``: the repair baseline, mesh fill (3DGS where alpha >= 0.5, else the mesh) + Telea.

Per view it also scores regions: pixels both maps cover (3DGS vs mesh on the same pixels), near
and far ones (depth below / above ``--near-m``), and the 3DGS low-alpha pixels.

Inputs are the synthetic ship tank or, with ``--family room``, the furnished room (generated in
memory) in variants that mimic a real log: pose drift, depth noise, exposure changes between
frames, motion blur, grayscale, and all together (``real``); or any recorded input
(``--input SRC``, read with its own poses). Medians are taken over the views of a run, then over
seeds. ``--set mapper.KEY=VALUE`` changes the mapper params, ``--refine N`` adds N refinement
steps after the stream (what the graph would run when the input ends), ``--images DIR`` writes
side-by-side PNGs (real | 3DGS | alpha | mesh + Telea | 3DGS + Telea) of the first views of each
run.

    flock /tmp/gsfix-bench.lock .venv/bin/python benchmarks/bench_heldout_map.py \
        [--family tank|room] [--variants clean drift ...] [--seeds 0 1] [--frames 80] \
        [--width 320 --height 240] \
        [--refine 0] [--set mapper.KEY=VALUE ...] [--tag NAME] [--out JSON] [--images DIR]

Results: ``benchmarks/results/heldout_map_cpu.json`` (one entry per ``--tag``; a run adds or
replaces its tag).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
METHODS = ("gs", "gs_telea", "mesh_telea", "fill_telea")

# Variants of the ship tank that mimic what a real log does to the map. ``scene``: ShipTankConfig
# fields; ``exposure``: sigma of the per-frame log gain (auto-exposure; plus a 3 % white balance
# wobble); ``blur``: mean motion-blur length, px at 320 px width (0 to twice this, random
# direction, per frame).
VARIANTS: dict[str, dict[str, Any]] = {
    "clean": {},
    "drift": {"scene": {"pose_drift": 0.02, "pose_noise": 0.005, "pose_noise_deg": 0.3}},
    "depth_noise": {"scene": {"depth_noise": 0.012, "dropout": 0.08}},
    "exposure": {"exposure": 0.2},
    "blur": {"blur": 2.0},
    "gray": {"scene": {"grayscale": True}},
    "real": {
        "scene": {
            "pose_drift": 0.02, "pose_noise": 0.005, "pose_noise_deg": 0.3,
            "depth_noise": 0.012, "dropout": 0.08,
        },
        "exposure": 0.2,
        "blur": 2.0,
    },
}  # fmt: skip


# ----------------------------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------------------------


def exposure_gains(n: int, sigma: float, channels: int, rng: np.random.Generator) -> np.ndarray:
    """[n, channels] per-frame gains: a mean-reverting random walk of the log gain (auto-exposure
    hunting) with std ``sigma``, times a small per-channel white-balance wobble."""
    log_g = np.zeros(n)
    a = 0.0
    for i in range(n):
        a = 0.8 * a + rng.normal(0.0, sigma * 0.6)
        log_g[i] = a
    wb = rng.normal(0.0, 0.03, (n, channels)) if channels == 3 else np.zeros((n, 1))
    return np.exp(log_g[:, None] + wb)


def motion_blur(img: np.ndarray, length_px: float, angle: float) -> np.ndarray:
    """A line-kernel motion blur of ``length_px`` pixels at ``angle`` radians."""
    import cv2

    if length_px < 1.0:
        return img
    k = int(math.ceil(length_px)) | 1
    kernel = np.zeros((k, k), np.float32)
    c = (k - 1) / 2
    for t in np.linspace(-length_px / 2, length_px / 2, 4 * k):
        x, y = c + t * math.cos(angle), c + t * math.sin(angle)
        kernel[int(round(y)), int(round(x))] += 1.0
    kernel /= kernel.sum()
    return cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)


def scene_frames(
    variant: str, seed: int, n_frames: int, width: int, height: int, family: str = "tank"
) -> Iterator[tuple[Any, np.ndarray | None]]:
    """(frame, exact depth or None) of the generated scene (``family``: the ship tank or the
    room) in ``variant``; the frame carries the estimated pose when the variant drifts."""
    from gsfix_online.core.types import make_frame
    from gsfix_online.scene import ShipTankConfig
    from gsfix_online.scene.generate import build_scene, iter_samples

    spec = VARIANTS[variant]
    cfg = dataclasses.replace(
        ShipTankConfig(), family=family, seed=seed, n_frames=n_frames, width=width,
        height=height, n_novel=0, **spec.get("scene", {}),
    )  # fmt: skip
    scene = build_scene(cfg)
    pose = "estimated" if scene.has_estimate else "gt"
    rng = np.random.default_rng([seed, 0xE7])
    channels = 1 if cfg.grayscale else 3
    gains = exposure_gains(n_frames, spec.get("exposure", 0.0), channels, rng)
    blur = spec.get("blur", 0.0) * width / 320
    for s in iter_samples(scene):
        f = s.frame(scene.intrinsics, noisy=True, pose=pose)
        color = f.color
        if spec.get("exposure", 0.0) > 0:
            g = gains[s.index] if color.ndim == 3 else gains[s.index, 0]
            color = np.clip(np.rint(color.astype(np.float32) * g), 0, 255).astype(np.uint8)
        if blur > 0:
            color = motion_blur(color, rng.uniform(0, 2 * blur), rng.uniform(0, math.pi))
        if color is not f.color:
            f = make_frame(color, f.depth, f.intrinsics, f.T_world_cam, f.stamp_ns,
                           frame_id=f.frame_id, seq=f.seq)  # fmt: skip
        yield f, s.depth_gt


def source_frames(
    path: str, max_frames: int, pose_file: str = ""
) -> Iterator[tuple[Any, np.ndarray | None]]:
    from gsfix_online.sources import SourceConfig, open_source

    for f in open_source(SourceConfig(path=path, max_frames=max_frames, pose_file=pose_file)):
        yield f, None


# ----------------------------------------------------------------------------------------------
# Scoring
# ----------------------------------------------------------------------------------------------


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(x) * 255.0), 0, 255).astype(np.uint8)


def _region_psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float | None:
    from gsfix_online.core.metrics import psnr

    if mask.mean() < 0.02:  # fewer than 2 % of the pixels: no figure
        return None
    return psnr(pred, target, mask)


def _gain_matched_psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float | None:
    """PSNR on ``mask`` after the least-squares gain per channel that maps ``pred`` to
    ``target`` there: the map's quality without the held-out frame's own exposure, which no
    map can know."""
    if mask.mean() < 0.02:
        return None
    x = pred.reshape(*mask.shape, -1)[mask].astype(np.float64)
    y = target.reshape(*mask.shape, -1)[mask].astype(np.float64)
    g = (x * y).sum(0) / np.maximum((x * x).sum(0), 1e-9)
    mse = float(((np.clip(x * g, 0, 255) - y) ** 2).mean()) / 255.0**2
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def score_view(
    gs_color: np.ndarray,  # [H, W(, 1|3)] float in [0, 1]
    gs_alpha: np.ndarray,  # [H, W]
    gs_depth: np.ndarray,  # [H, W] m
    mesh: Any,  # MeshRender
    real: np.ndarray,  # [H, W(, 3)] uint8
    depth: np.ndarray | None,  # [H, W] m, the view's depth (for near / far), or None
    near_m: float,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    from gsfix_online.core.metrics import scores
    from gsfix_online.repair.baselines import inpaint_telea, mesh_fill

    gs = _u8(gs_color)
    if real.ndim == 2:
        gs = gs.reshape(real.shape)
    mesh_c = mesh.color
    hole = gs_alpha < 0.5
    images = {
        "gs": gs,
        "gs_telea": inpaint_telea(gs, hole),
        "mesh_telea": inpaint_telea(mesh_c, ~mesh.valid),
    }
    fill = mesh_fill(gs, gs_alpha.astype(np.float32), mesh_c, mesh.valid)
    images["fill_telea"] = inpaint_telea(fill.image, fill.missing)
    out: dict[str, Any] = {}
    for k, img in images.items():
        s = scores(img, real)
        out[k] = {"psnr": s.psnr_db, "ssim": s.ssim}
    both = ~hole & mesh.valid
    reg: dict[str, Any] = {
        "alpha_cover": float((~hole).mean()),
        "mesh_cover": float(mesh.valid.mean()),
        "both_gs": _region_psnr(gs, real, both),
        "both_mesh": _region_psnr(mesh_c, real, both),
        "both_gs_gain": _gain_matched_psnr(gs, real, both),
        "both_mesh_gain": _gain_matched_psnr(mesh_c, real, both),
        "low_alpha_gs_telea": _region_psnr(images["gs_telea"], real, hole),
        "low_alpha_mesh_telea": _region_psnr(images["mesh_telea"], real, hole),
    }
    if depth is not None:
        near = both & (depth > 0) & (depth < near_m)
        far = both & (depth >= near_m)
        reg.update({
            "near_gs": _region_psnr(gs, real, near), "near_mesh": _region_psnr(mesh_c, real, near),
            "far_gs": _region_psnr(gs, real, far), "far_mesh": _region_psnr(mesh_c, real, far),
        })  # fmt: skip
    # 3DGS surface well in front of the mesh's (floaters): share and quality there
    d = mesh.depth_m
    front = both & (gs_depth < d - np.maximum(0.1, 0.05 * d))
    reg["front_fraction"] = float(front.mean())
    reg["front_gs"] = _region_psnr(gs, real, front)
    reg["front_mesh"] = _region_psnr(mesh_c, real, front)
    out["regions"] = reg
    return out, images


def side_by_side(real: np.ndarray, images: dict[str, np.ndarray], alpha: np.ndarray) -> np.ndarray:
    def rgb(x: np.ndarray) -> np.ndarray:
        return np.repeat(x[..., None], 3, axis=2) if x.ndim == 2 else x

    a = _u8(alpha)
    return np.concatenate(
        [rgb(real), rgb(images["gs"]), rgb(a), rgb(images["mesh_telea"]), rgb(images["gs_telea"])],
        axis=1,
    )


# ----------------------------------------------------------------------------------------------
# One run
# ----------------------------------------------------------------------------------------------


def mapper_config(sets: list[str]) -> Any:
    """The repair graph's mapper policy (configs/profiles/mapper_cpu.yaml), plus
    ``mapper.KEY=VALUE`` overrides."""
    from gsfix_online.core.config import build, configs_dir, read_yaml
    from gsfix_online.mapping.splat.mapper import MapperConfig

    base = read_yaml(configs_dir() / "profiles" / "mapper_cpu.yaml")
    over = []
    for s in sets:
        if not s.startswith("mapper."):
            raise SystemExit(f"--set takes mapper.KEY=VALUE, got {s!r}")
        over.append(s[len("mapper.") :])
    return build(MapperConfig, base=base, overrides=over)


def run_one(
    frames: Iterator[tuple[Any, np.ndarray | None]],
    K: int,
    mapper_cfg: Any,
    refine: list[int],
    near_m: float,
    images_dir: Path | None,
    n_images: int,
    name: str,
) -> dict[str, Any]:
    import torch

    from gsfix_online.core.metrics import psnr
    from gsfix_online.mapping.mesh_render import MeshRenderer
    from gsfix_online.mapping.splat.mapper import Mapper
    from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume
    from gsfix_online.repair.outputs import write_png

    torch.manual_seed(0)
    mapper = None
    tsdf = TsdfVolume(TsdfConfig(voxel_size=0.02, depth_max=5.0))  # the repair graph's
    held: list[tuple[Any, np.ndarray | None]] = []
    train: list[Any] = []  # the training frame before each held-out one (fit, not generalisation)
    map_s = tsdf_s = 0.0
    n_mapped = 0
    for i, (f, depth_gt) in enumerate(frames):
        if i % K == K // 2:
            held.append((f, depth_gt))
            continue
        if i % K == K // 2 - 1:
            train.append(f)
        if mapper is None:
            mapper = Mapper(mapper_cfg, channels=1 if f.is_gray else 3)
        t0 = time.perf_counter()
        mapper.process(f)
        map_s += time.perf_counter() - t0
        t0 = time.perf_counter()
        tsdf.integrate(f)
        tsdf_s += time.perf_counter() - t0
        n_mapped += 1
    assert mapper is not None and held, "no frames to map or none held out"
    t0 = time.perf_counter()
    renderer = MeshRenderer(tsdf.extract_mesh())
    tsdf_s += time.perf_counter() - t0
    mesh_renders = [renderer.render(f.T_world_cam, f.intrinsics) for f, _ in held]

    stages: dict[str, Any] = {}
    done = 0
    for total in [0, *refine]:
        t0 = time.perf_counter()
        if total > done:
            mapper.refine(total - done)
            done = total
        refine_s = time.perf_counter() - t0
        views = []
        for j, ((f, depth_gt), mesh) in enumerate(zip(held, mesh_renders, strict=True)):
            color, gs_depth, alpha = mapper.render_numpy(  # moved as the map was (poses)
                mapper.pose_for(f.T_world_cam), f.intrinsics.K, f.width, f.height
            )
            depth = depth_gt if depth_gt is not None else (f.depth if f.depth.any() else None)
            sc, imgs = score_view(color, alpha, gs_depth, mesh, f.color, depth, near_m)
            sc["seq"] = int(f.seq)
            views.append(sc)
            if images_dir is not None and j < n_images:
                write_png(images_dir / f"{name}_r{total}_{j}.png",
                          side_by_side(f.color, imgs, alpha))  # fmt: skip
        fit = []
        for f in train:
            T = mapper.pose_for(f.T_world_cam)
            color, _, _ = mapper.render_numpy(T, f.intrinsics.K, f.width, f.height)
            gs = _u8(color).reshape(f.color.shape)
            fit.append(psnr(gs, f.color))
        stages[f"refine_{total}"] = {
            "refine_s": refine_s,  # the steps since the previous stage, not the total
            "train_gs_psnr": _median(fit),
            "gaussians": len(mapper.gmap),
            "views": views,
            "median": summarize(views),
        }
    return {
        "frames_mapped": n_mapped,
        "held_out": len(held),
        "map_s": map_s,
        "tsdf_s": tsdf_s,
        "keyframes": len(mapper.store),
        "mapper_stats": mapper.stats(),
        "stages": stages,
    }


def _median(xs: list[float | None]) -> float | None:
    v = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else None


def summarize(views: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for m in METHODS:
        out[m] = {k: _median([v[m][k] for v in views]) for k in ("psnr", "ssim")}
    out["regions"] = {k: _median([v["regions"].get(k) for v in views]) for k in views[0]["regions"]}
    return out


def combine(runs: list[dict[str, Any]], stage: str) -> dict[str, Any]:
    """Median over seeds of the per-run medians."""
    meds = [r["stages"][stage]["median"] for r in runs]
    out: dict[str, Any] = {}
    for m in METHODS:
        out[m] = {k: _median([x[m][k] for x in meds]) for k in ("psnr", "ssim")}
    out["regions"] = {k: _median([x["regions"].get(k) for x in meds]) for k in meds[0]["regions"]}
    out["map_s"] = _median([r["map_s"] for r in runs])
    out["refine_s"] = _median([r["stages"][stage]["refine_s"] for r in runs])
    out["train_gs_psnr"] = _median([r["stages"][stage]["train_gs_psnr"] for r in runs])
    out["gaussians"] = _median([r["stages"][stage]["gaussians"] for r in runs])
    out["keyframes"] = _median([r["keyframes"] for r in runs])
    return out


def _fmt(x: float | None, nd: int = 2) -> str:
    return "  -  " if x is None else f"{x:.{nd}f}"


def table(summary: dict[str, dict[str, Any]]) -> str:
    head = ("| variant | stage | " + " | ".join(METHODS)
            + " | both: gs / mesh | train gs | map s | gaussians |")  # fmt: skip
    lines = [head, "|" + "---|" * (len(METHODS) + 6)]
    for variant, stages in summary.items():
        for stage, s in stages.items():
            cells = [f"{_fmt(s[m]['psnr'])} / {_fmt(s[m]['ssim'], 3)}" for m in METHODS]
            r = s["regions"]
            lines.append(
                f"| {variant} | {stage} | " + " | ".join(cells)
                + f" | {_fmt(r.get('both_gs'))} / {_fmt(r.get('both_mesh'))}"
                + f" | {_fmt(s['train_gs_psnr'])} | {_fmt(s['map_s'], 0)} | {_fmt(s['gaussians'], 0)} |"
            )  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--variants", nargs="+", default=["clean", "real"], choices=sorted(VARIANTS))
    p.add_argument("--input", default="", help="a recorded input instead of the ship tank")
    p.add_argument("--family", default="tank", choices=["tank", "room"],
                   help="the generated scene: the ship tank or the furnished room")  # fmt: skip
    p.add_argument("--pose-file", default="", help="with --input: its pose list (e.g. a TUM "
                   "folder's estimated.txt; default the format's own)")  # fmt: skip
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--frames", type=int, default=80, help="tank frames (all of them are mapped "
                   "or held out); with --input: at most this many, 0 = all")  # fmt: skip
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("-K", type=int, default=10, help="hold out frames with i %% K == K // 2")
    p.add_argument("--refine", type=int, nargs="*", default=[],
                   help="also score after this many refinement steps (cumulative)")  # fmt: skip
    p.add_argument("--set", action="append", default=[], help="mapper.KEY=VALUE")
    p.add_argument("--near-m", type=float, default=1.5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--tag", default="graph", help="name of this configuration in the JSON")
    p.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "heldout_map_cpu.json"))
    p.add_argument("--images", default="", help="folder for side-by-side PNGs")
    p.add_argument("--n-images", type=int, default=3)
    args = p.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    mcfg = mapper_config(args.set)
    images = Path(args.images) if args.images else None
    if images is not None:
        images.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    runs: dict[str, list[dict[str, Any]]] = {}
    inputs = [("input", 0)] if args.input else [(v, s) for v in args.variants for s in args.seeds]
    for variant, seed in inputs:
        t0 = time.perf_counter()
        frames = (
            source_frames(args.input, args.frames, args.pose_file)
            if args.input
            else scene_frames(variant, seed, args.frames, args.width, args.height, args.family)
        )
        name = f"{args.tag}_{variant}_s{seed}"
        r = run_one(frames, args.K, mcfg, sorted(args.refine), args.near_m, images,
                    args.n_images, name)  # fmt: skip
        r.update({"variant": variant, "seed": seed, "wall_s": time.perf_counter() - t0})
        runs.setdefault(variant, []).append(r)
        m = r["stages"]["refine_0"]["median"]
        print(
            f"{variant} seed {seed}: " + ", ".join(f"{k} {_fmt(m[k]['psnr'])}" for k in METHODS)
            + f"; both gs/mesh {_fmt(m['regions']['both_gs'])}/{_fmt(m['regions']['both_mesh'])}"
            + f" (gain-matched {_fmt(m['regions']['both_gs_gain'])}"
            + f"/{_fmt(m['regions']['both_mesh_gain'])})"
            + f"; train gs {_fmt(r['stages']['refine_0']['train_gs_psnr'])}"
            + f"; map {r['map_s']:.0f} s, {r['wall_s']:.0f} s",
            flush=True,
        )  # fmt: skip
    stages = ["refine_0", *(f"refine_{n}" for n in sorted(args.refine))]
    summary = {v: {s: combine(rs, s) for s in stages} for v, rs in runs.items()}
    print(table(summary))

    out = Path(args.out)
    doc: dict[str, Any] = json.loads(out.read_text()) if out.is_file() else {}
    doc.setdefault("about", __doc__.split("\n")[0])
    doc.setdefault("runs", {})
    doc["runs"][args.tag] = {
        "command": "benchmarks/bench_heldout_map.py " + " ".join(argv or sys.argv[1:]),
        "machine": {
            "python": sys.version.split()[0],
            "platform": platform.platform(),
            "threads": args.threads,
        },  # fmt: skip
        "input": args.input or {"tank": "ship tank", "room": "room"}[args.family],
        "frames": args.frames,
        "resolution": [args.width, args.height],
        "K": args.K,
        "mapper": dataclasses.asdict(mcfg),
        "variants": {v: VARIANTS.get(v, {}) for v in runs},
        "summary": summary,
        "table": table(summary),
        "wall_s": time.perf_counter() - t_all,
        "runs": runs,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1, default=float))
    print(f"wrote {out} [{args.tag}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
