"""The knobs that trade run time for error, with the graph overrides that turn them.

Each :class:`Knob` names the ``NODE.KEY`` override(s) of ``configs/graphs/repair.yaml`` it sets
(several keys get the same value, e.g. the threads of every torch node), the values a sweep tries
beside its default (the graph's value, read from the graph), and the stage of the run it changes. A run of the sweep is a set
of knob values; every knob left out keeps the graph's default.

:data:`QUICK` is what ``gsfix-online bench --quick`` sweeps: the knobs that move time or error
most, two values each beside the default, on a small tank (:data:`QUICK_SCENE`) with a short
fine-tuning run (:data:`QUICK_BASE`), so that it fits in about 11 minutes on 2 cores.
:data:`NOT_SWEPT` lists what the issue asks for that no graph override reaches yet, and why.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Literal

Stage = Literal["map", "mesh", "finetune", "repair", "distill", "all"]


@dataclass(frozen=True)
class Knob:
    name: str  # the column in the results
    keys: tuple[str, ...]  # NODE.KEY overrides that all get the knob's value
    values: tuple[Any, ...]  # tried beside the default in the full sweep
    stage: Stage  # what it changes
    help: str

    @property
    def default(self) -> Any:
        """The repair graph's value of the knob's first key, as its node runs with it."""
        node, *path = self.keys[0].split(".")
        value = graph_params()[node]
        for key in path:
            value = value[key]
        return value

    def overrides(self, value: Any) -> list[str]:
        return [f"{k}={format_value(value)}" for k in self.keys]


@functools.cache
def graph_params() -> dict[str, dict[str, Any]]:
    """Every node's params in the repair graph, in full (its profiles, then the node defaults)."""
    from gsfix_online.core.config import to_dict
    from gsfix_online.jobs.repair_run import DEFAULT_GRAPH
    from gsfix_online.runtime.graph import load_graph, node_params

    graph = load_graph(DEFAULT_GRAPH)
    return {name: to_dict(node_params(entry)) for name, entry in graph.nodes.items()}


def format_value(value: Any) -> str:
    """A value as a YAML override (``true``, ``0.02``, ``[1, 2]``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return str(value)


KNOBS: dict[str, Knob] = {
    k.name: k
    for k in (
        Knob("voxel_m", ("tsdf.tsdf.voxel_size",), (0.01, 0.04), "mesh",
             "TSDF voxel size, m"),
        Knob("train_downscale", ("splat.mapper.train_downscale",), (1, 4), "map",
             "3DGS online steps render at 1/n of the processing resolution"),
        Knob("kf_iters", ("splat.mapper.kf_iters",), (1, 4, 8), "map",
             "3DGS steps per keyframe"),
        Knob("non_kf_iters", ("splat.mapper.non_kf_iters",), (0, 2), "map",
             "3DGS steps per optimised non-keyframe"),
        Knob("kf_overlap", ("splat.mapper.keyframes.min_overlap",), (0.5, 0.85), "map",
             "keyframe threshold: a frame that overlaps the last keyframe less is a keyframe"),
        Knob("seed_var", ("splat.mapper.growth.var_thresh",), (0.002, 0.0001), "map",
             "3DGS seeding: a quadtree cell of an input frame splits while its colour "
             "variance is above this (lower: finer seeds, more Gaussians)"),
        Knob("refine_steps", ("splat.refine_at_input_end",), (0, 300), "map",
             "3DGS refinement steps over the keyframes when the input ends"),
        Knob("finetune_steps", ("trainer.policy.max_steps_per_run",), (150, 1200),
             "finetune", "GSFixer fine-tuning steps (at most; patience may stop earlier)"),
        Knob("ddim_steps", ("repair.fixer.inference.steps",), (2, 4), "repair",
             "DDIM steps of GSFixer"),
        Knob("distill_iters", ("splat.mapper.distill_iters",), (5, 50), "distill",
             "distillation steps per repaired view"),
        Knob("distill_passes", ("splat.distill_passes",), (0, 2, 10), "distill",
             "passes over keyframes and repaired views after each repair"),
        Knob("hole_fraction", ("planner.skip.hole_fraction",), (0.0, 0.1), "repair",
             "planner: repair when more of the surface than this is holes"),
        Knob("disagree_fraction", ("planner.skip.disagree_fraction",), (0.0, 0.2),
             "repair", "planner: repair when more of the surface than this disagrees"),
        Knob("empty_fraction", ("planner.skip.empty_fraction",), (0.0, 0.2), "repair",
             "planner: repair when more of the image than this is empty in both maps"),
        Knob("threads", ("splat.threads", "repair.threads"), (2,), "all",
             "torch threads of the splat and repair nodes"),
    )
}  # fmt: skip

# ``--quick``: the scene, the base every quick run starts from, and the knobs it sweeps.
# 20 frames and 5 knobs, 11 runs of 46-68 s: 10 min 42 s on 2 idle cores (2026-11-30,
# benchmarks/results/bench_quick_cpu.md). 30 frames with DDIM steps as a knob took 47-77 s a run
QUICK_SCENE = {"width": 160, "height": 120, "n_frames": 20, "views": 3}
# --skips: the scene its recorded table was measured on (benchmarks/results/bench_skips_cpu.md)
SKIPS_SCENE = {"width": 160, "height": 120, "n_frames": 30, "views": 3}
# A fine-tuning run of 20 steps instead of 600 (600 alone take ~2.5 min on 2 idle cores); every
# other value is the repair graph's default.
QUICK_BASE = ["trainer.policy.max_steps_per_run=20"]
QUICK: dict[str, tuple[Any, ...]] = {
    "kf_iters": (1, 4),
    "voxel_m": (0.01, 0.04),
    # runs shorter than trainer.policy.eval_every (20) now end with a checkpoint too
    "finetune_steps": (40, 60),
    "distill_passes": (0, 2),  # beside the graph's 6
    # the input frames' seeding (the graph's 0.0005 against the 0.002 it had before, and finer;
    # on the full demo: benchmarks/results/fine_seeds_cpu.md)
    "seed_var": (0.002, 0.0001),
}  # DDIM steps (1, 2, 4) moved final PSNR by 0.27 dB at most (bench_quick11_cpu.json): full sweep only
QUICK_DEFAULTS = {"finetune_steps": 20}  # the quick base's values where it differs

NOT_SWEPT = {
    "processing resolution": "source.max_width sets it (benchmarks/bench_resolution.py "
    "measures it on a recorded input); the bench's scenes are generated at 160x120, below any "
    "width worth sweeping, and the 3DGS training resolution is swept (train_downscale)",
    "trainer threads": "the trainer node has no threads parameter (torch's default)",
}


def check_values(values: dict[str, Any]) -> None:
    """One-line error for a knob name the table does not hold."""
    unknown = sorted(set(values) - set(KNOBS))
    if unknown:
        raise ValueError(f"unknown knob(s) {', '.join(unknown)}; known: {', '.join(KNOBS)}")


def overrides_for(values: dict[str, Any]) -> list[str]:
    """The graph overrides of a run's knob values (knobs in table order)."""
    check_values(values)
    return [o for name, k in KNOBS.items() if name in values for o in k.overrides(values[name])]


def one_at_a_time(
    sweep: dict[str, tuple[Any, ...]], defaults: dict[str, Any] | None = None
) -> list[dict[str, Any]]:
    """The runs of a one-at-a-time sweep: the default run ({}), then each knob at each value
    that differs from its default, the others at theirs."""
    check_values(dict(sweep))
    defaults = {**{n: k.default for n, k in KNOBS.items()}, **(defaults or {})}
    runs: list[dict[str, Any]] = [{}]
    for name, values in sweep.items():
        runs += [{name: v} for v in values if v != defaults[name]]
    return runs


__all__ = [
    "KNOBS", "NOT_SWEPT", "QUICK", "QUICK_BASE", "QUICK_DEFAULTS", "QUICK_SCENE", "SKIPS_SCENE", "Knob",
    "format_value", "one_at_a_time", "overrides_for",
]  # fmt: skip
