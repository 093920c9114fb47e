"""A finished run read back for the benchmarks that rework its map (``bench_polish.py``,
``bench_distill.py``): the run's graph, its views with their ground truth, and the map's renders
there scored against it. A case is a ``bench_variants.py`` case folder (``CASE/run``,
``CASE/scene``) or a demo run (``gsfix-online demo --out RUN``: ``RUN/repair``, ``RUN/scene``,
scored at the scene's novel views, each also against the output the run delivered there)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt


@dataclass
class Case:
    path: Path
    graph: dict[str, Any]  # work/graph.yaml's nodes
    mapper: dict[str, Any]  # the splat node's mapper settings, on the CPU
    held: set[int]  # indices of the held-out frames among the views
    intrinsics: Any  # Intrinsics of the views
    poses: list[npt.NDArray[np.float64]]  # [4, 4] per view, in work/views.txt's order
    gts: list[npt.NDArray[np.uint8]]  # [H, W, 3] per view
    reference: dict[str, dict[str, float]]  # group -> inpaint / output / final PSNR of the run
    outputs: list[npt.NDArray[np.uint8] | None] | None = None  # per view, what the run delivered

    @property
    def run(self) -> Path:
        demo = self.path / "repair"
        return demo if demo.is_dir() else self.path / "run"


def held_views(run: Path) -> set[int]:
    """Indices of a repair run's held-out frames among its views (``--holdout``: the repair
    node's ``holdout_views`` [first, stop) in ``work/graph.yaml``); empty without them."""
    from gsfix_online.core.config import read_yaml

    graph = run / "work" / "graph.yaml"
    if not graph.is_file():
        return set()
    first_stop = read_yaml(graph)["nodes"]["repair"]["params"].get("holdout_views") or []
    return set(range(*first_stop)) if first_stop else set()


def read_demo_case(path: Path) -> Case:
    """A demo run: its scene's novel views and their truth, and per view the output the run
    delivered (``repair/views/NNN/output.png``; None where the view was not repaired)."""
    from gsfix_online.core.config import read_yaml
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.views import read_views
    from gsfix_online.sources.tum import read_intrinsics_json

    run, novel = path / "repair", path / "scene" / "novel"
    intr, _ = read_intrinsics_json(novel / "intrinsics.json")
    poses = [v.T_world_cam for v in read_views(novel / "views.txt")]
    gts = [read_png_rgb(novel / "color" / f"{i:03d}.png", intr.width, intr.height)
           for i in range(len(poses))]  # fmt: skip
    metrics = json.loads((run / "metrics.json").read_text())
    outputs: list[npt.NDArray[np.uint8] | None] = [None] * len(poses)
    for v in metrics["views"]:
        if v.get("origin") == "file" and v.get("repair") and v["view_id"] < len(poses):
            outputs[v["view_id"]] = read_png_rgb(run / v["files"]["output"], intr.width,
                                                 intr.height)  # fmt: skip
    stages = metrics["summary"]["stages"]
    graph = read_yaml(run / "work" / "graph.yaml")["nodes"]
    return Case(
        path=path,
        graph=graph,
        mapper={**graph["splat"]["params"].get("mapper", {}), "backend": "cpu"},
        held=set(),
        intrinsics=intr,
        poses=poses,
        gts=gts,
        reference={
            "novel": {
                "inpaint": stages["mesh_inpaint"]["psnr_db"],
                "output": stages["output"]["psnr_db"],
                "final": stages["final"]["psnr_db"],
            }
        },  # fmt: skip
        outputs=outputs,
    )


def read_case(path: Path) -> Case:
    from gsfix_online.core.config import read_yaml

    if (path / "repair" / "metrics.json").is_file():
        return read_demo_case(path)
    from gsfix_online.repair.outputs import read_png_rgb
    from gsfix_online.repair.views import read_views
    from gsfix_online.sources.tum import read_intrinsics_json

    run = path / "run"
    graph = read_yaml(run / "work" / "graph.yaml")["nodes"]
    intr, _ = read_intrinsics_json(path / "scene" / "novel" / "intrinsics.json")
    poses = [v.T_world_cam for v in read_views(run / "work" / "views.txt")]  # file order
    gts = [read_png_rgb(run / "work" / "gt" / f"{i:03d}.png", intr.width, intr.height)
           for i in range(len(poses))]  # fmt: skip
    metrics = json.loads((run / "metrics.json").read_text())["summary"]["groups"]
    return Case(
        path=path,
        graph=graph,
        mapper={**graph["splat"]["params"].get("mapper", {}), "backend": "cpu"},
        held=held_views(run),
        intrinsics=intr,
        poses=poses,
        gts=gts,
        reference={
            g: {s: metrics[g][s]["psnr_db"] for s in ("inpaint", "output", "final")}
            for g in metrics
        },  # fmt: skip
    )


def score_map(mapper: Any, case: Case, images: Path | None = None) -> dict[str, Any]:
    """PSNR dB of the map's render at each view against its ground truth; the mean over the
    novel views and over the held-out frames. With ``images``, the renders go there as
    ``NNN.png`` (view index)."""
    import torch

    from gsfix_online.core.metrics import psnr, sharpness
    from gsfix_online.repair.outputs import write_png

    intr, per_view = case.intrinsics, []
    against: dict[int, tuple[float, float]] = {}
    for i, (T, gt) in enumerate(zip(case.poses, case.gts, strict=True)):
        with torch.no_grad():
            r = mapper.render(T, intr.K, intr.width, intr.height)
        img = np.rint(r.color.clamp(0, 1).numpy() * 255).astype(np.uint8)
        if img.shape[-1] == 1:
            img = np.repeat(img, 3, axis=-1)
        per_view.append(psnr(img, gt))
        if images is not None:
            write_png(images / f"{i:03d}.png", img)
        out = None if case.outputs is None else case.outputs[i]
        if out is not None:  # issue 43's per-view bounds: final - output dB, sharpness ratio
            against[i] = (per_view[-1] - psnr(out, gt),
                          sharpness(img) / max(sharpness(out), 1e-12))  # fmt: skip
    novel = [p for i, p in enumerate(per_view) if i not in case.held]
    hold = [p for i, p in enumerate(per_view) if i in case.held]
    return {"views": per_view, "novel_db": float(np.mean(novel)),
            "holdout_db": float(np.mean(hold)) if hold else float("nan"),
            "vs_output": {f"{i:03d}": {"db": d, "sharpness": r}
                          for i, (d, r) in against.items()}}  # fmt: skip


def write_result(path: Path, doc: str | None, threads: int, summary: Any, rows: list[Any]) -> None:
    """A benchmark's JSON: what it is (the docstring's first line), its arguments, the machine,
    its summary and rows; written atomically."""
    import platform
    import sys

    from gsfix_online.core.io import atomic_write_text

    result = {
        "about": (doc or "").split("\n")[0],
        "argv": sys.argv[1:],
        "machine": {"platform": platform.platform(), "threads": threads},
        "summary": summary,
        "rows": rows,
    }
    atomic_write_text(path, json.dumps(result, indent=1, default=float))
