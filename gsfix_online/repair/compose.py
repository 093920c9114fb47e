"""One repaired view, composed: the choice it follows, its regions, the delivered image and what
distillation fits. The graph's repair node and the map server's on-demand repair both call
:func:`compose_view`, so a view repaired either way follows the same rules (``fallback``'s:
the held-out frames' choice near the keyframes, the mesh first beyond them, ``far_regions``).

:class:`ComposeRules` names the settings, which the repair node's ``Params`` and the map
server's ``ServerConfig`` inherit."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import rng
from gsfix_online.repair.fallback import (
    FAR_GS_ONLY_HOLES,
    FAR_NEITHER_SHARE,
    FEATHER_PX,
    FLAT,
    FLAT_RING_STD,
    GS_ONLY,
    Choice,
    compose,
    far_regions,
    for_view,
    regions,
    replaced,
)
from gsfix_online.repair.provenance import GS_REPAIRED_SHARE
from gsfix_online.repair.repairer import distill_mask


@dataclass(frozen=True)
class ComposeRules:
    """How a repaired view is composed and what distillation fits. The repair node's ``Params``
    and the map server's ``ServerConfig`` inherit these settings: one name, default and range."""

    # What distillation fits to: "holes", the pixels the 3DGS map does not explain (alpha below
    # the fixer's threshold), widened by ``distill_dilate_px``; "all", the whole repaired view.
    # Holes only keeps what the map renders well where it is observed: on the tank (54 frames,
    # 9 repaired views) held-out frames lost 0.15 dB instead of 0.55, and novel views gained
    # 5.80 dB instead of 5.68 (offline on one map, commit 3e7f9fc; that script was not kept).
    # The passes keep the mask too (benchmarks/results/variants_passes_masked_cpu.md).
    # "delivered": the holes, and where the choice per region replaced the 3DGS render by
    # GSFixer or the mesh (fallback.replaced), so the map renders what the view delivered.
    distill_mask: Literal["holes", "delivered", "all"] = "holes"
    distill_dilate_px: int = field(default=3, metadata=rng(0, 64, "holes mask widening, px"))
    feather_px: float = field(
        default=FEATHER_PX, metadata=rng(0, 64, "blend across region seams of the output, px")
    )
    # A region may blend GSFixer into its fallback by the share that measured best
    # (fallback.choose). Off by default: it gained on tank:drift seed 1 (novel views +0.27 dB)
    # and lost on room:real seed 3 (-0.76), where the trainer's cut-hole measurement blended
    # mesh + Telea into the no-map parts of far views that GSFixer alone repaired best
    # (benchmarks/results/blend_maps_cpu.md)
    blend: bool = False
    # GSFixer's share where neither map covers a view beyond the held-out frames' reach (or
    # any view without them), blended into mesh + Telea (fallback.FAR_NEITHER_SHARE: no
    # measurement the run has predicts which is nearer the truth there; half and half gained
    # 0.16 and 0.80 dB at the novel views of tank:drift and room:real). 1: GSFixer alone;
    # 0: mesh + Telea alone. With ``blend`` the trainer's measured choice applies instead.
    far_neither_share: float = field(
        default=FAR_NEITHER_SHARE, metadata=rng(0, 1, "GSFixer's share in far no-map parts")
    )
    # Where the output around such a hole varies by under this standard deviation of luma
    # (8-bit levels), mesh + Telea fills it alone (fallback.FLAT_RING_STD). 0: never.
    flat_hole_std: float = field(
        default=FLAT_RING_STD, metadata=rng(0, 255, "far no-map holes this flat around: Telea")
    )
    # Which pixels that only the 3DGS map covers a far view repairs as holes, not showing the
    # 3DGS render (fallback.FAR_GS_ONLY_HOLES): "grown" (what other views' repairs grew), "all"
    # or "none"
    far_gs_only_holes: Literal["grown", "all", "none"] = FAR_GS_ONLY_HOLES

    def rules(self) -> ComposeRules:
        """These settings alone, out of a configuration that inherits them."""
        return ComposeRules(**{f.name: getattr(self, f.name) for f in fields(ComposeRules)})


@dataclass(frozen=True)
class ComposedView:
    image: npt.NDArray[np.uint8]  # [H, W, 3] what the view delivers
    region: npt.NDArray[np.uint8]  # [H, W] index into fallback.REGIONS, or FLAT
    choice: Choice  # the choice per region it followed
    source: str  # where that choice comes from (fallback.for_view)
    mask: npt.NDArray[np.uint8] | None  # [H, W] 255 where distillation fits it; None: all

    @property
    def flat_holes(self) -> bool:
        return bool((self.region == FLAT).any())


def compose_view(
    candidates: dict[str, npt.NDArray[np.uint8]],  # baseline_candidates' and "fixed"
    gs_alpha: npt.NDArray[np.floating],  # [H, W] the 3DGS render's opacity
    mesh_valid: npt.NDArray[np.bool_],  # [H, W] the mesh has a surface there
    alpha_min: float,  # the fixer's alpha threshold
    distance_m: float | None,  # the view's keyframe distance (planner.keyframe_distance)
    near: Choice | None,  # measured at the held-out frames; None without them
    reach_m: float | None,  # the farthest held-out frame's keyframe distance
    trainer: Choice,  # measured by the trainer
    rules: ComposeRules,
    synthesised: npt.NDArray[np.floating] | None = None,  # [H, W] render's share from repairs
) -> ComposedView:
    """The view's choice (:func:`.fallback.for_view`), its regions (a far view's by
    :func:`.fallback.far_regions`), the composed image and the distillation mask. A far view's
    observed 3DGS-only pixels composed as holes (``far_gs_only_holes="all"``) stay out of the
    mask, the holes' widening band included: the map keeps what its keyframes saw there."""
    region = regions(gs_alpha, mesh_valid, alpha_min)
    choice, source = for_view(distance_m, near, reach_m, trainer, blend=rules.blend,
                              neither_share=rules.far_neither_share)  # fmt: skip
    observed = None  # a far view's observed 3DGS-only pixels composed as holes
    if source == "mesh first":  # 3DGS-only holes; flat holes: mesh + Telea
        grown = None if synthesised is None else np.asarray(synthesised) >= GS_REPAIRED_SHARE
        holes = None
        if rules.far_gs_only_holes == "all":
            holes = region == GS_ONLY
            observed = holes if grown is None else holes & ~grown
        elif rules.far_gs_only_holes == "grown":
            holes = grown
        region = far_regions(region, candidates, choice, rules.feather_px, rules.flat_hole_std,
                             holes)  # fmt: skip
    image = compose(candidates, region, choice, rules.feather_px)
    mask = distill_mask(gs_alpha, alpha_min, rules.distill_mask, rules.distill_dilate_px,
                        replaced(region, choice), synthesised)  # fmt: skip
    if mask is not None and observed is not None:
        # (with "all", tank seed 1, one run each: the final map 17.48 -> 17.49 dB, the same;
        # benchmarks/results/far_views_three_seeds_cpu.md)
        mask[observed] = 0
    return ComposedView(image, region, choice, source, mask)
