"""The Gaussian mapper's parameters (:class:`MapperConfig`): one frozen section composed of its
parts' configs. The shipped 2-core policy is ``configs/profiles/mapper_cpu.yaml``; these
defaults are the plain component defaults it starts from."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from gsfix_online.core.config import rng
from gsfix_online.mapping.splat.exposure import ExposureConfig
from gsfix_online.mapping.splat.growth import GrowthConfig
from gsfix_online.mapping.splat.keyframes import KeyframeConfig
from gsfix_online.mapping.splat.optimize import DensifyConfig, LearningRates
from gsfix_online.mapping.splat.poses import PoseConfig
from gsfix_online.mapping.splat.prune import CarveConfig, PruneConfig


@dataclass(frozen=True)
class MapperConfig:
    """Online mapping: iterations per frame, losses, densification and the parts it composes."""

    # 0: one colour per Gaussian. Degree 1 was measured on the tank and the room (seed 1): it did
    # not keep views that invent one surface differently apart (room view 004 -0.87 dB under its
    # output), and the tank's final map fell 0.16 dB under its output, with a dark blotch where
    # sparsely seen Gaussians took a colour no view gave them (benchmarks/results/sh_degree_cpu.md)
    sh_degree: int = field(default=0, metadata=rng(0, 3, "SH degree of the map's colour"))
    backend: Literal["auto", "cpu", "cuda"] = "auto"
    kf_iters: int = field(default=4, metadata=rng(0, None, "optimisation steps per keyframe"))
    non_kf_iters: int = field(default=1, metadata=rng(0, None, "steps per optimised non-keyframe"))
    non_kf_every: int = field(
        default=3, metadata=rng(1, None, "optimise every n-th non-keyframe; others only grow")
    )
    replay_keyframes: int = field(
        default=1, metadata=rng(0, None, "random past keyframes rendered in each step")
    )
    train_downscale: int = field(
        default=2, metadata=rng(1, 8, "online steps render at 1/n of the frame resolution")
    )
    ssim_lambda: float = field(default=0.2, metadata=rng(0, 1, "weight of 1 - SSIM"))
    depth_weight: float = field(default=0.1, metadata=rng(0, None, "weight of depth L1, per m"))
    refine_iters: int = field(default=300, metadata=rng(0, None, "steps of refine() by default"))
    refine_views: int = field(default=2, metadata=rng(1, None, "keyframes per refinement step"))
    refine_downscale: int = field(
        default=1, metadata=rng(1, 8, "refine() renders at 1/n of the keyframe resolution")
    )
    distill_iters: int = field(default=20, metadata=rng(0, None, "steps per repaired view"))
    distill_lambda: float = field(
        default=0.2, metadata=rng(0, 1, "distillation loss (1-l) L1 + l (1-SSIM)")
    )
    scene_scale_m: float = field(
        default=0.0, metadata=rng(0, None, "scene scale, m; 0 = first frame's median depth")
    )
    max_gaussians: int = field(default=300_000, metadata=rng(1, None, "growth stops here"))
    prune_every: int = field(default=100, metadata=rng(1, None, "steps between prune() calls"))
    seed: int = 0
    lr: LearningRates = field(default_factory=LearningRates)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    growth: GrowthConfig = field(default_factory=GrowthConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    prune: PruneConfig = field(default_factory=PruneConfig)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    poses: PoseConfig = field(default_factory=PoseConfig)
    carve: CarveConfig = field(default_factory=CarveConfig)
    # With ``carve``: distillation's seeds (guessed depth) that a stored view sees through are
    # removed, at seeding and after each fit and pass (Mapper._carve_seeded). Off here: alone,
    # on the room with every degradation (40 frames, seed 0) it cost the final map 0.9 dB at
    # novel views, while on the tank it removed a veil that cost one view 7 dB where both maps
    # cover it (benchmarks/results/variants_carve_cpu.json). With distill_anchor it removed
    # that veil but opened black holes in other views' holes (variants_anchor_cpu.json).
    carve_seeds: bool = False
    # Repaired views (distillation) train only the Gaussians distillation seeded: what the
    # input mapped moves only for input keyframes. A repaired view is a guess in its holes;
    # without this its fit pulls mapped Gaussians at the holes' borders out of place. Off:
    # distilling the same views into the same map (tank:real, 12 views, with the anchor, 6
    # passes and polish) it cost -0.21 dB at the novel views and gained +0.27 at the held-out
    # frames (benchmarks/bench_distill.py; benchmarks/results/distill_freeze_cpu.json).
    distill_freeze_mapped: bool = False
    # A repaired view is fitted on its whole image: inside its mask on the repair, elsewhere on
    # the map's own render there without distillation's seeds (its anchor). Seeds grown for one
    # view that stand in front of what another view's map rendered are then pulled away by
    # that view's fit; with the mask alone, nothing held them (a veil over the tank's novel
    # views: the final map 0.6 dB below mesh fill + Telea, one view 3.9 dB).
    distill_anchor: bool = False
    # Distillation's seeds stand at a guessed depth in the holes (the mesh's, inpainted where it
    # has no surface). A seed that another stored view sees (in front of the surface that view
    # measured or rendered) moves away from its camera along its own ray, scaled with the
    # distance, to the first place no stored view sees it (prune.push_behind, up to
    # ``distill_push_max`` times as far): its own view renders it on the same pixels, and the
    # others no longer see it as a veil over their surfaces. Off: distilling the same views
    # into the same maps (benchmarks/bench_distill.py; tank:real and room:real, 12 views each,
    # with the anchor, 6 passes and polish) it moved 1443 and 121 seeds and the final map
    # -0.05 and 0.00 dB at the novel views (benchmarks/results/distill_push_cpu.json): the
    # anchor and polish already pull such veils away.
    distill_push_seeds: bool = False
    # The veil guard: distillation keeps no Gaussian that a stored view sees through. Each
    # repaired view judges with the depth its seeds were grown at (the mesh's in its holes) beside
    # the input keyframes' measured depth and the anchors (carving.judging_views); a view's new
    # seeds move back along their own rays until no judge sees them (as distill_push_seeds), and
    # after growth, each fit and each run of passes the seeds a judge still sees through are
    # removed (as carve_seeds, with carve's margins whether or not carve is enabled). Without
    # it, on the demo's view 001 the seeds that view 005 grew at 1.4 m from its camera stood
    # 0.14-0.6 m in front of view 001's camera, where its mesh lies 2.4 m away: a veil over the
    # lower half of its final render (sharpness 0.39 of its output).
    distill_veil_guard: bool = False
    # Detail seeds: a repaired view's quadtree cell gets a seed (at the mesh depth, in the view's
    # mask) where the map's render differs from the repair by more than this mean |error|
    # (colour in [0, 1]); None: ``growth.error_thresh``, as for input frames. Off: at 0.01 the
    # demo's map grew 71k -> 93k Gaussians and its renders of the repaired views kept more of
    # the output's fine texture (median sharpness ratio 0.86 -> 0.89-0.91), not enough for
    # the 0.9 bound on most views, for 40-55 s more (benchmarks/results/detail_seeds_cpu.md).
    distill_error_thresh: float | None = field(
        default=None, metadata=rng(0, 1, "seed a repaired view's cell above this mean |error|")
    )
    # A repaired view's quadtree cells split while their colour variance is above this; None:
    # ``growth.var_thresh``, as for input frames. The CPU profile splits input frames finer than
    # repaired views: with both at 0.0005, tank seed 1's view 000 showed a dark hole where its
    # seeds in GSFixer's part did not cover (benchmarks/results/fine_seeds_cpu.md).
    distill_var_thresh: float | None = field(
        default=None, metadata=rng(0, None, "split a repaired view's cell above this variance")
    )
    # A seed grown for a repaired view keeps to its footprint: its scale (every axis) stays at
    # most this many times the scale it was grown at (the cell it fills), through every fit,
    # pass and polish step. Without a bound, the seeds of views that look at one wall from near
    # grew to sigmas of 0.3-0.66 m and veiled other views of it (room seed 1, view 004: the
    # seeds at 1.6-2.0 m from its camera, in front of the wall's 2.7 m, covered its top-left
    # wall at alpha 0.93). 0: unbounded.
    distill_scale_growth: float = field(
        default=0.0,
        metadata=rng(0, None, "a repaired view's seed grows to this x its scale; 0 = off"),
    )
    # A repaired view that looks at an observed surface closer than the input frames did sees
    # the input's Gaussians there wider than its pixels (benchmarks/results/observed_blur_cpu.md:
    # 1.2-2.3 times closer where the final map lost the output's detail). Before its fit, every
    # Gaussian the input mapped whose centre lies on the view's repaired pixels where the mesh
    # saw a surface (distill's ``observed``) and the map renders one opaque (alpha 0.99), at
    # that surface, and whose largest sigma spans more than this many of the view's pixels, is
    # split in two (scales / 1.6), up to ``distill_split_rounds`` times. 0: off
    # (benchmarks/results/split_wide_cpu.md).
    distill_split_px: float = field(
        default=0.0, metadata=rng(0, None, "split mapped Gaussians wider than this, view px")
    )
    distill_split_rounds: int = field(
        default=1, metadata=rng(1, 8, "split rounds per repaired view at most")
    )
    distill_push_max: float = field(
        default=3.0, metadata=rng(1, 100, "farthest push, as a multiple of the seed's distance")
    )
    # Polish (Mapper.polish): a repaired view whose render is further than this from what it
    # was fitted to (PSNR dB inside its mask) gets ``polish_iters`` more steps, each with
    # ``polish_partners`` other repaired views, so that it is not won back at their cost;
    # up to ``polish_rounds`` rounds. 0 = off. On tank:real (40 frames, seed 0) a view veiled
    # by seeds grown for another view was 18.6 dB from its target and 2.1 dB below its output
    # against the ground truth; alone, its fit lifted it and dropped the other view 1.3 dB.
    polish_below_db: float = field(
        default=0.0, metadata=rng(0, 100, "repaired views under this fidelity get polished")
    )
    # Before polishing, seed again the holes that opened in the repaired views since they were
    # distilled (Mapper.refill): a view gets no seed where the map explained it when it came,
    # and with ``distill_scale_growth`` what covered it then may shrink away.
    polish_refill: bool = False
    polish_refill_share: float = field(
        default=0.0, metadata=rng(0, 1, "refill a view whose open holes cover this share of it")
    )
    polish_iters: int = field(default=40, metadata=rng(1, None, "steps per polished view"))
    polish_partners: int = field(
        default=2, metadata=rng(0, None, "other repaired views rendered in each polish step")
    )
    polish_rounds: int = field(default=2, metadata=rng(1, None, "polish rounds at most"))
    # Random input keyframes fitted in each polish step beside the repaired views (at
    # ``refine_downscale``, as the passes fit them), so that polish does not move what the
    # frames observed. 0: none.
    polish_keyframes: int = field(
        default=2, metadata=rng(0, None, "input keyframes rendered in each polish step")
    )
    # In polish, repaired views train only the Gaussians distillation seeded (as
    # ``distill_freeze_mapped`` does everywhere): what the input mapped moves only for the
    # input keyframes polish fits beside them. Polish fits a view again where its seeds left
    # holes or other views' seeds veil it; neither is fixed by moving what the frames observed.
    polish_freeze_mapped: bool = False
    # A polished view's fit stops once the map renders it this close to its target (PSNR dB
    # inside its mask), measured every ``polish_check_every`` steps; 0: all ``polish_iters``.
    # Off: at 30 dB (the error that moves a view 18 dB from the truth by 0.27 dB at most) the
    # demo took 70 polish steps, not 120, and the room 190, not 200 over more views; the wall
    # time went +10 s and -44 s, but the repaired views' sharpness ratios fell (views under
    # issue 43's 0.9 bound: demo 6 against 5, room 3 against 0), since every polish step also
    # fits two partner views (benchmarks/results/polish_until_cpu.md).
    polish_until_db: float = field(
        default=0.0, metadata=rng(0, 100, "a polished view stops at this fidelity")
    )
    polish_check_every: int = field(
        default=10, metadata=rng(1, None, "polish steps between fidelity checks")
    )

    def validate(self) -> None:
        if self.polish_refill and not self.distill_veil_guard:
            raise ValueError(
                "polish_refill needs distill_veil_guard: the guard keeps the seed depths it refills"
            )

    def __post_init__(self) -> None:
        self.validate()
