"""Online Gaussian mapping: per-frame growth and optimisation, keyframes, refinement, distillation.

Per posed RGB-D frame (:meth:`Mapper.process`), GSFusion-style:

1. render the map at the frame's pose (no grad);
2. grow Gaussians where the render does not explain the frame (:func:`growth.grow`) and add them;
3. select keyframes by novelty (:func:`keyframes.select_keyframe`) into a bounded
   :class:`~.keyframes.KeyframeStore`;
4. optimise: keyframes get ``kf_iters`` steps, other frames ``non_kf_iters`` steps on every
   ``non_kf_every``-th non-keyframe (the rest are grown but not optimised). Each step renders the
   current frame and ``replay_keyframes`` random past keyframes and minimises
   ``L1 + ssim_lambda * (1 - SSIM)`` on colour plus ``depth_weight * L1`` on valid depth;
5. densify and prune with gsplat's ``DefaultStrategy`` (its ops are plain torch and read our
   renderer's gsplat-compatible ``info``; only the current frame's view feeds its gradient
   statistics), plus :func:`prune.prune` every ``prune_every`` steps.

Two optional parts, off by default:

- ``exposure`` (:mod:`.exposure`): each frame's gain against the map is fitted in closed form
  before growth (which then compares the frame with the render in the frame's exposure and
  seeds canonical colours); keyframes keep theirs as parameters optimised with the map, and the
  canonical exposure is re-centred on the keyframes' mean gain at each keyframe;
- ``carve`` (:func:`.prune.carve_mask`): each keyframe's depth removes the Gaussians it saw
  through (floaters from pose error and depth noise).

Online steps render at ``1 / train_downscale`` of the frame resolution (the CPU budget);
:meth:`Mapper.refine` (unless ``refine_downscale``) and :meth:`Mapper.distill` render at full
resolution. Steps whose
gradients are not finite are skipped and counted. The mapper does no IO and reads no clock; the
node owns timing and files. Repaired views (:meth:`Mapper.distill`) go into the keyframe store
with depth 0 (invalid), so replay and refinement use them as extra observations.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F
from torch import Tensor

from gsfix_online.core.config import rng
from gsfix_online.core.se3 import pose_distances
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.mapping.splat.exposure import (
    ExposureConfig,
    apply_affine,
    fit_affine,
    invert_affine,
    prior_loss,
)
from gsfix_online.mapping.splat.gaussians import PARAM_KEYS, SH_C0, GaussianMap
from gsfix_online.mapping.splat.growth import GrowthConfig, GrowthResult, grow
from gsfix_online.mapping.splat.keyframes import (
    Keyframe,
    KeyframeConfig,
    KeyframeState,
    KeyframeStore,
    frame_from_dict,
    frame_to_dict,
    initialize_state,
    select_keyframe,
)
from gsfix_online.mapping.splat.poses import PoseConfig, clamp_, corrected, offsets
from gsfix_online.mapping.splat.poses import prior_loss as pose_prior_loss
from gsfix_online.mapping.splat.prune import (
    CarveConfig,
    PruneConfig,
    carve_mask,
    prune,
    push_behind,
)
from gsfix_online.mapping.splat.render import RenderOutput, render, resolve_backend

SSIM_WINDOW = 11
NEVER = 2**62  # a DefaultStrategy step count that is never reached (disables a schedule)
REPAIRED_FRAME_ID = "repaired"


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates per parameter (gsplat's trainer defaults)."""

    means: float = field(default=1.6e-4, metadata=rng(0, None, "times the scene scale, m"))
    scales: float = field(default=5e-3, metadata=rng(0, None, "log-scales"))
    quats: float = field(default=1e-3, metadata=rng(0, None, ""))
    opacities: float = field(default=5e-2, metadata=rng(0, None, "opacity logits"))
    sh0: float = field(default=2.5e-3, metadata=rng(0, None, ""))
    shN_ratio: float = field(default=1 / 20, metadata=rng(0, None, "shN rate = sh0 * this"))


@dataclass(frozen=True)
class DensifyConfig:
    """gsplat ``DefaultStrategy`` settings for online use (no opacity resets)."""

    enabled: bool = True
    grad_thresh: float = field(
        default=2e-4, metadata=rng(0, None, "mean 2D gradient (NDC) above which to clone/split")
    )
    grow_scale3d: float = field(
        default=0.01, metadata=rng(0, None, "clone below, split above this x scene scale")
    )
    refine_every: int = field(default=50, metadata=rng(1, None, "steps between refinements"))
    start_step: int = field(default=50, metadata=rng(0, None, "first step that may refine"))
    prune_opa: float = field(default=0.005, metadata=rng(0, 1, "opacity pruned at refinement"))


@dataclass(frozen=True)
class MapperConfig:
    """Online mapping: iterations per frame, losses, densification and the parts it composes."""

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
    polish_iters: int = field(default=40, metadata=rng(1, None, "steps per polished view"))
    polish_partners: int = field(
        default=2, metadata=rng(0, None, "other repaired views rendered in each polish step")
    )
    polish_rounds: int = field(default=2, metadata=rng(1, None, "polish rounds at most"))


@dataclass(frozen=True)
class PolishResult:
    """What :meth:`Mapper.polish` did: fidelity (PSNR dB inside each repaired view's mask, by
    keyframe id) before and after, and the views it polished."""

    before: dict[int, float]
    after: dict[int, float]
    polished: list[int]
    n_iters: int


@dataclass(frozen=True)
class FrameResult:
    """What :meth:`Mapper.process` did with one frame."""

    is_keyframe: bool
    reason: str  # keyframe reason: first, new_gaussians, low_overlap, none
    n_new_gaussians: int
    n_iters: int  # optimisation steps run (skipped non-finite steps included)
    loss: float  # mean loss of the steps run; NaN when none ran
    keyframe: Keyframe | None  # the stored keyframe (render and alpha after optimisation)
    # For a keyframe: the map's render at its pose before the frame changed the map (the one
    # growth compared against, training resolution). What the map predicted of a view it had
    # not seen, with the artefacts and holes of a novel view; GSFixer can train on it
    # (nodes/splat.py `keyframe_render`). Kept as rendered; :meth:`prior` resizes on request.
    prior_render: RenderOutput | None = None
    # [4, 4] the pose the frame was mapped at: the front end's, or where tracking moved it
    # (mapper.poses)
    pose: npt.NDArray[np.float64] | None = None

    def prior(
        self, height: int, width: int
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None:
        """The prior render at ``height`` x ``width``, bilinear: colour [H, W, C] in [0, 1] and
        alpha [H, W]; None for a frame that did not become a keyframe."""
        r = self.prior_render
        if r is None:
            return None
        color = _resize(r.color.clamp(0, 1), height, width)
        return color, _resize(r.alpha[..., None], height, width)[..., 0]


@dataclass(frozen=True)
class OptimResult:
    """Losses of a run of steps (:meth:`Mapper.refine`, :meth:`Mapper.distill`)."""

    n_iters: int
    loss_first: float
    loss_last: float
    keyframe_id: int = -1  # distill: the id of the repaired view in the keyframe store


@dataclass
class _View:
    """A training view prepared at some resolution (tensors on the map's device)."""

    color: Tensor  # [H, W, C] in [0, 1]
    depth: Tensor | None  # [H, W] m, 0 = invalid; None = no depth term
    K: Tensor  # [3, 3] px
    T_world_cam: Tensor  # [4, 4]
    mask: Tensor | None = None  # [H, W] bool: pixels that count; None = all
    affine: Tensor | None = None  # [2, C] the view's exposure (exposure.py); None = identity
    repaired: bool = False  # a repaired view (distillation), not an input keyframe
    pose: Tensor | None = None  # [6] the keyframe's pose correction (poses.py); None = as given


# ----------------------------------------------------------------------------------------------
# Pure math
# ----------------------------------------------------------------------------------------------


def photometric_loss(
    pred: Tensor,  # [H, W, C]
    target: Tensor,  # [H, W, C]
    ssim_lambda: float,
    l1_weight: float = 1.0,
    mask: Tensor | None = None,  # [H, W] bool
) -> Tensor:
    """``l1_weight * L1 + ssim_lambda * (1 - SSIM)`` (kornia SSIM, 11x11 Gaussian window)."""
    from kornia.metrics import ssim

    if mask is not None:
        m = mask[..., None].to(pred.dtype)
        pred, target = pred * m, target * m
        l1 = (pred - target).abs().sum() / (m.sum() * pred.shape[-1]).clamp_min(1.0)
    else:
        l1 = (pred - target).abs().mean()
    if ssim_lambda == 0:
        return l1_weight * l1
    s = ssim(pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], SSIM_WINDOW).mean()
    return l1_weight * l1 + ssim_lambda * (1.0 - s)


def downscale_view(view: _View, s: int) -> _View:
    """Area-average colour, strided depth and K for pixel centres at ``(i + 0.5) * s - 0.5``."""
    if s == 1:
        return view
    H, W = view.color.shape[0] // s * s, view.color.shape[1] // s * s
    color = F.avg_pool2d(view.color[:H, :W].permute(2, 0, 1)[None], s)[0].permute(1, 2, 0)
    off = (s - 1) // 2
    depth = None if view.depth is None else view.depth[off:H:s, off:W:s].contiguous()
    mask = None if view.mask is None else view.mask[off:H:s, off:W:s].contiguous()
    K = view.K.clone()
    K[0, 0] /= s
    K[1, 1] /= s
    K[0, 2] = (K[0, 2] + 0.5) / s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / s - 0.5
    return _View(color.contiguous(), depth, K, view.T_world_cam, mask, view.affine, view.repaired,
                 view.pose)  # fmt: skip


def _frame_view(frame: RGBDFrame, device: torch.device, use_depth: bool = True) -> _View:
    color = (
        torch.from_numpy(np.array(frame.color)).to(device).float() / 255.0
    )  # a copy: frames may be read-only views
    if color.ndim == 2:
        color = color[..., None]
    depth = torch.from_numpy(np.array(frame.depth)).to(device) if use_depth else None
    K = torch.as_tensor(frame.intrinsics.K, dtype=torch.float32, device=device)
    T = torch.as_tensor(frame.T_world_cam, dtype=torch.float32, device=device)
    return _View(color, depth, K, T)


# ----------------------------------------------------------------------------------------------
# Component
# ----------------------------------------------------------------------------------------------


class Mapper:
    """The Gaussian map, its optimizers, densification state and keyframes; see module doc."""

    def __init__(
        self, cfg: MapperConfig, channels: int = 3, device: str | torch.device | None = None
    ) -> None:
        self.cfg = cfg
        # the map lives where its renderer runs: cfg.backend (auto = CUDA when torch sees a GPU)
        self.device = torch.device(resolve_backend(cfg.backend) if device is None else device)
        self.gmap = GaussianMap(cfg.sh_degree, channels, self.device)
        self.kf_state: KeyframeState = initialize_state()
        self.store = KeyframeStore.from_config(cfg.keyframes)
        self.rng = np.random.default_rng(cfg.seed)
        self.scene_scale = cfg.scene_scale_m
        self.n_frames = 0
        # newest stamp mapped per camera (frame_id), saved in snapshots: the splat node skips
        # frames at or before it, which a restarted sender or a resent link delivers again
        self.last_stamp_ns: dict[str, int] = {}
        self.n_steps = 0
        self.n_nonfinite_steps = 0
        self.n_pruned = 0
        self.n_carved = 0  # Gaussians a keyframe's depth saw through (CarveConfig)
        self.n_pushed = 0  # distillation's seeds moved behind what other views see
        self.n_capped = 0  # Gaussians growth wanted but max_gaussians refused
        self._non_kf_seen = 0
        self._views: dict[int, _View] = {}  # kf_id -> full-resolution view
        # kf_id -> the pixels a repaired view is fitted on (distill's mask), in every pass
        self._repair_masks: dict[int, npt.NDArray[np.bool_]] = {}
        # repaired views fitted with an anchor (distill_anchor): their stored depth is the
        # anchor's surface, zero in their holes, so carving reads it as it is
        self._anchored: set[int] = set()
        # [N] bool, aligned with the map: Gaussians that distillation grew from a repaired
        # view's seed depth (a guess where no map holds anything); carved again after each fit
        self._seeded = torch.zeros(0, dtype=torch.bool, device=self.device)
        # kf_id -> [2, C] the keyframe's exposure (exposure.py), optimised with the map
        self.exposure: dict[int, Tensor] = {}
        self.exposure_opt: torch.optim.Optimizer | None = None
        # kf_id -> [6] the keyframe's pose correction (poses.py), optimised with the map
        self.poses: dict[int, Tensor] = {}
        self.pose_opt: torch.optim.Optimizer | None = None
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.strategy: Any = None
        self.strategy_state: dict[str, Any] = {}
        self._build_optimizers()

    # -- set-up ---------------------------------------------------------------------------------

    @property
    def channels(self) -> int:
        return self.gmap.channels

    def _build_optimizers(self) -> None:
        lr = self.cfg.lr
        rates = {
            "means": lr.means * max(self.scene_scale, 1e-6),
            "scales": lr.scales,
            "quats": lr.quats,
            "opacities": lr.opacities,
            "sh0": lr.sh0,
            "shN": lr.sh0 * lr.shN_ratio,
        }
        for key in PARAM_KEYS:
            self.gmap.params[key].requires_grad_(True)
        self.optimizers = {
            key: torch.optim.Adam(
                [{"params": [self.gmap.params[key]], "lr": rates[key], "name": key}], eps=1e-15
            )
            for key in PARAM_KEYS
        }
        if self.cfg.densify.enabled:
            from gsplat.strategy import DefaultStrategy

            d = self.cfg.densify
            self.strategy = DefaultStrategy(
                prune_opa=d.prune_opa,
                grow_grad2d=d.grad_thresh,
                grow_scale3d=d.grow_scale3d,
                refine_start_iter=d.start_step,
                refine_stop_iter=NEVER,
                reset_every=NEVER,  # opacity resets would wipe an online map
                refine_every=d.refine_every,
                refine_scale2d_stop_iter=0,
            )
            self.strategy.check_sanity(self.gmap.params, self.optimizers)
            self.strategy_state = self.strategy.initialize_state(
                scene_scale=max(self.scene_scale, 1e-6)
            )

    def _resize_strategy_state(self, keep: Tensor | None = None, n_new: int = 0) -> None:
        """Keep the strategy's per-Gaussian statistics (and which Gaussians distillation seeded)
        aligned with structural edits."""
        seeded = self._seeded  # the map has changed already: its length is the old one
        if keep is not None:
            seeded = (seeded[keep] if len(seeded) == len(keep)
                      else seeded.new_zeros(int(keep.sum())))  # fmt: skip
        self._seeded = torch.cat([seeded, seeded.new_zeros(n_new)]) if n_new else seeded
        for key in ("grad2d", "count", "radii"):
            v = self.strategy_state.get(key)
            if v is None:
                continue
            if keep is not None:
                v = v[keep]
            if n_new:
                v = torch.cat([v, v.new_zeros(n_new)])
            self.strategy_state[key] = v

    # -- rendering ------------------------------------------------------------------------------

    def render(
        self,
        T_world_cam: Tensor | npt.ArrayLike,  # [4, 4]
        K: Tensor | npt.ArrayLike,  # [3, 3] px
        width: int,
        height: int,
        keep: Tensor | None = None,  # [N] bool: render only these Gaussians; None = all
        frozen: bool = False,  # the map's tensors detached: gradients reach the pose alone
    ) -> RenderOutput:
        """Render the current map (differentiable when grad is enabled)."""
        g = self.gmap
        dev = self.device
        # torch.tensor copies: poses and K may be read-only views of received messages
        T = (
            T_world_cam
            if isinstance(T_world_cam, Tensor)
            else torch.tensor(np.asarray(T_world_cam))
        )
        Kt = K if isinstance(K, Tensor) else torch.tensor(np.asarray(K))
        T = T.to(device=dev, dtype=torch.float32)
        Kt = Kt.to(device=dev, dtype=torch.float32)
        if len(g) == 0 or (keep is not None and not bool(keep.any())):
            z = torch.zeros((height, width), device=dev)
            return RenderOutput(
                torch.zeros((height, width, self.channels), device=dev), z, z.clone()
            )
        tensors = (g.means, g.params["quats"], g.scales, g.opacities, g.sh)
        if frozen:
            tensors = tuple(t.detach() for t in tensors)
        if keep is not None:
            tensors = tuple(t[keep] for t in tensors)
        return render(
            *tensors, None, Kt, width, height,
            T_world_cam=T, backend=self.cfg.backend, sh_degree=g.sh_degree,
        )  # fmt: skip

    @torch.no_grad()
    def render_numpy(
        self, T_world_cam: npt.ArrayLike, K: npt.ArrayLike, width: int, height: int
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """(colour [H, W, C] clamped to [0, 1], depth [H, W] m, alpha [H, W]) as numpy."""
        out = self.render(T_world_cam, K, width, height)
        return (
            out.color.clamp(0, 1).cpu().numpy(),
            out.depth.cpu().numpy(),
            out.alpha.cpu().numpy(),
        )

    # -- optimisation ---------------------------------------------------------------------------

    def _view_loss(self, view: _View, lam: float, l1_weight: float) -> tuple[Tensor, RenderOutput]:
        H, W = view.color.shape[:2]
        T = view.T_world_cam
        if view.pose is not None:
            T = corrected(T, view.pose, self.scene_scale)
        out = self.render(T, view.K, W, H)
        pred = out.color
        if view.affine is not None:
            affine = view.affine
            if not self.cfg.exposure.bias:  # the bias row stays zero
                affine = torch.cat([affine[:1], torch.zeros_like(affine[1:])])
            pred = apply_affine(pred, out.alpha, affine)
        loss = photometric_loss(pred, view.color, lam, l1_weight, view.mask)
        if view.affine is not None and view.affine.requires_grad and self.cfg.exposure.prior > 0:
            loss = loss + self.cfg.exposure.prior * prior_loss(view.affine)
        if view.pose is not None and view.pose.requires_grad and self.cfg.poses.prior > 0:
            loss = loss + self.cfg.poses.prior * pose_prior_loss(view.pose)
        if view.depth is not None and self.cfg.depth_weight > 0:
            valid = view.depth > 0
            if view.mask is not None:
                valid &= view.mask
            if bool(valid.any()):
                loss = loss + self.cfg.depth_weight * (out.depth - view.depth)[valid].abs().mean()
        return loss, out

    def train_step(
        self, views: list[_View], lam: float | None = None, l1_weight: float = 1.0
    ) -> float:
        """One Adam step on the mean loss of ``views``; the first view feeds densification.

        Returns the loss; a step whose loss or gradients are not finite changes nothing and is
        counted in ``n_nonfinite_steps``.
        """
        assert views
        if len(self.gmap) == 0:
            return math.nan
        lam = self.cfg.ssim_lambda if lam is None else lam
        self.n_steps += 1
        opts = list(self.optimizers.values())
        for extra in (self.exposure_opt, self.pose_opt):
            if extra is not None:
                opts.append(extra)
        for opt in opts:
            opt.zero_grad(set_to_none=True)
        # With distill_freeze_mapped, repaired views' gradients reach only the seeded Gaussians:
        # their loss is back-propagated first and the other rows' gradients are cleared before
        # the keyframes' loss adds its own.
        freeze = self.cfg.distill_freeze_mapped and any(v.repaired for v in views)
        totals = {False: torch.zeros((), device=self.device)}
        if freeze:
            totals[True] = torch.zeros((), device=self.device)
        info = None
        for i, view in enumerate(views):
            loss, out = self._view_loss(view, lam, l1_weight)
            if i == 0:
                info = out.info
                if self.strategy is not None:
                    self.strategy.step_pre_backward(
                        self.gmap.params, self.optimizers, self.strategy_state, self.n_steps, info
                    )
            key = freeze and view.repaired
            totals[key] = totals[key] + loss / len(views)
        total = sum(totals.values(), torch.zeros((), device=self.device))
        params = [*self.gmap.params.values(), *self.exposure.values(), *self.poses.values()]
        kept: dict[str, Tensor] = {}
        if freeze:
            mapped = ~self.seeded()
            if totals[True].requires_grad:
                totals[True].backward()
            for p in self.gmap.params.values():
                if p.grad is not None:
                    p.grad[mapped] = 0.0
            if all(v.repaired for v in views):  # Adam's momentum must not move them either
                kept = {k: p.detach()[mapped].clone() for k, p in self.gmap.params.items()}
            if totals[False].requires_grad:
                totals[False].backward()
        else:
            total.backward()
        grads_ok = bool(torch.isfinite(total)) and all(
            p.grad is None or bool(torch.isfinite(p.grad).all()) for p in params
        )
        if not grads_ok:
            self.n_nonfinite_steps += 1
            for opt in opts:
                opt.zero_grad(set_to_none=True)
            return float(total.detach())
        for opt in opts:
            opt.step()
        for xi in self.poses.values():
            clamp_(xi, self.cfg.poses)
        if kept:
            with torch.no_grad():
                for k, v in kept.items():
                    self.gmap.params[k][mapped] = v
        if self.strategy is not None and info is not None:
            n_before = len(self.gmap)
            # gsplat edits every per-Gaussian tensor of its state with the map: which
            # Gaussians distillation seeded rides along through clones, splits and pruning
            self.strategy_state["seeded"] = self.seeded()
            self.strategy.step_post_backward(
                self.gmap.params, self.optimizers, self.strategy_state, self.n_steps, info
            )
            self._seeded = self.strategy_state.pop("seeded")
            assert len(self.gmap) == len(self.strategy_state["grad2d"]) or n_before == 0
        if self.n_steps % self.cfg.prune_every == 0:
            self._prune()
        return float(total.detach())

    def _prune(self) -> None:
        before = len(self.gmap)
        result = prune(self.gmap, self.cfg.prune, self.optimizers)
        if result.n_pruned:
            assert len(self.gmap) == before - result.n_pruned
            self._resize_strategy_state(keep=~result.mask)
            self.n_pruned += result.n_pruned

    def _posed(self, view: _View) -> Tensor:  # [4, 4] the view's pose with its correction
        if view.pose is None:
            return view.T_world_cam
        with torch.no_grad():
            return corrected(view.T_world_cam, view.pose, self.scene_scale)

    def _carve(self, view: _View) -> None:
        """Remove the Gaussians that this view's depth saw through (prune.carve_mask)."""
        if view.depth is None or not len(self.gmap):
            return
        g = self.gmap
        mask = carve_mask(
            g.means.detach(), g.params["scales"].detach(), view.depth, view.K, self._posed(view),
            self.cfg.carve,
        )  # fmt: skip
        self._remove_carved(mask)

    def seeded(self) -> Tensor:  # [N] bool
        """Which Gaussians distillation grew from a repaired view's seed depth (kept through
        growth, pruning, carving and densification)."""
        n = len(self.gmap)
        if len(self._seeded) != n:
            self._seeded = torch.zeros(n, dtype=torch.bool, device=self.device)
        return self._seeded

    def _carve_seeded(self) -> int:
        """Remove the Gaussians distillation seeded that a stored view sees through
        (prune.carve_mask with footprint); returns how many. The views are the input keyframes
        (their measured depth: free space the camera saw) and the repaired views (their seed
        depth where the map explained them, outside their distillation mask: the surface the
        maps agree on). A guessed seed in front of what another view sees would stand there as
        a floater, hiding the surface; it is judged at seeding and again after each fit, since
        fitting moves and grows it. Only seeded Gaussians are judged: a guess never removes
        what the input mapped, and one guess never removes another."""
        seeded = self.seeded()
        if not bool(seeded.any()):
            return 0
        g = self.gmap
        idx = torch.nonzero(seeded).squeeze(1)
        means, scales = g.means.detach()[idx], g.params["scales"].detach()[idx]
        seen = torch.zeros(len(idx), dtype=torch.bool, device=means.device)
        for depth, K, T in self._judging_views():
            seen |= carve_mask(means, scales, depth.to(means.device), K.to(means.device),
                               T.to(means.device), self.cfg.carve, footprint=True)  # fmt: skip
        mask = torch.zeros(len(g), dtype=torch.bool, device=means.device)
        mask[idx[seen]] = True
        return self._remove_carved(mask)

    def _judging_views(self) -> list[tuple[Tensor, Tensor, Tensor]]:
        """(depth [H, W], K, T_world_cam) of the stored views that judge distillation's seeds:
        the input keyframes (their measured depth: free space the camera saw) and the repaired
        views (their stored depth where the map explained them, outside their holes)."""
        views = []
        for kf in self.store:
            if kf.frame.frame_id == REPAIRED_FRAME_ID:
                d = np.array(kf.frame.depth, np.float32)
                holes = self._repair_masks.get(kf.kf_id)
                # only where the map explained that view: a guess in its holes must not move or
                # remove what another guess put there (an anchored view holds no depth there)
                if holes is not None and kf.kf_id not in self._anchored:
                    d[holes] = 0.0
                depth = torch.from_numpy(d)
                K = torch.as_tensor(kf.frame.intrinsics.K, dtype=torch.float32)
                T = torch.as_tensor(kf.frame.T_world_cam, dtype=torch.float32)
            else:
                view = self._keyframe_view(kf)
                if view.depth is None:
                    continue
                depth, K, T = view.depth, view.K, self._posed(view)
            if bool((depth > 0).any()):
                views.append((depth, K, T))
        return views

    def _remove_carved(self, mask: Tensor) -> int:  # [N] bool -> how many went
        n = int(mask.sum())
        if n:
            self.gmap.remove(mask, self.optimizers)
            self._resize_strategy_state(keep=~mask)
            self.n_carved += n
        return n

    def _keyframe_view(self, kf: Keyframe) -> _View:
        view = self._views.get(kf.kf_id)
        if view is None:
            repaired = kf.frame.frame_id == REPAIRED_FRAME_ID
            view = _frame_view(kf.frame, self.device, use_depth=not repaired)
            view.repaired = repaired
            view.affine = self.exposure.get(kf.kf_id)
            view.pose = self.poses.get(kf.kf_id)
            if kf.kf_id in self._repair_masks:
                view.mask = torch.from_numpy(self._repair_masks[kf.kf_id]).to(self.device)
            self._views[kf.kf_id] = view
        return view

    def _forget_views(self) -> None:
        live = set(self.store.ids)
        for kf_id in [k for k in self._views if k not in live]:
            del self._views[kf_id]
        for kf_id in [k for k in self._repair_masks if k not in live]:
            del self._repair_masks[kf_id]
        self._anchored &= live
        for params, opt in ((self.exposure, self.exposure_opt), (self.poses, self.pose_opt)):
            for kf_id in [k for k in params if k not in live]:
                p = params.pop(kf_id)
                assert opt is not None
                opt.param_groups = [g for g in opt.param_groups if g["params"][0] is not p]
                opt.state.pop(p, None)

    # -- exposure -------------------------------------------------------------------------------

    def _estimate_exposure(self, out: RenderOutput, view: _View) -> Tensor:  # [2, C]
        """The frame's exposure against the canonical map, in closed form (exposure.py): where
        the render is opaque, then again without the pixels that fit worst (new content,
        occlusions, moving light)."""
        e, C = self.cfg.exposure, self.channels
        pred, target = out.color.reshape(-1, C), view.color.reshape(-1, C)
        w = (out.alpha.reshape(-1) >= e.min_alpha).float()
        if float(w.mean()) < e.min_fraction:
            return torch.zeros((2, C), device=self.device)
        params = fit_affine(pred, target, w, e.ridge, e.max_log_gain, e.bias)
        resid = (apply_affine(pred, out.alpha.reshape(-1), params) - target).abs().mean(1)
        w2 = w * (resid <= 3.0 * resid[w > 0].median() + 1e-3).float()
        if float(w2.mean()) >= e.min_fraction:
            params = fit_affine(pred, target, w2, e.ridge, e.max_log_gain, e.bias)
        return params

    @torch.no_grad()
    def _recenter_exposure(self) -> None:
        """Move the canonical exposure to the keyframes' mean gain (an exact change of gauge:
        every colour times the mean gain, every keyframe's gain divided by it), so that renders
        of new views show the average exposure, as the TSDF's averaged colours do, rather than
        the first frame's."""
        if not self.exposure:
            return
        mu = torch.stack([p[0] for p in self.exposure.values()]).mean(0)  # [C] log-gain
        g = mu.exp()
        sh0, shN = self.gmap.params["sh0"], self.gmap.params["shN"]
        sh0.copy_(((sh0 * SH_C0 + 0.5) * g - 0.5) / SH_C0)
        shN.mul_(g)
        for p in self.exposure.values():
            p[0].sub_(mu)

    def _keep_exposure(self, kf_id: int, params: Tensor) -> Tensor:  # [2, C] -> leaf, grad
        p = params.detach().clone().requires_grad_(True)
        self.exposure[kf_id] = p
        self.exposure_opt = _with_param(self.exposure_opt, p, self.cfg.exposure.lr)
        return p

    # -- poses ----------------------------------------------------------------------------------

    def _keep_pose(self, kf_id: int, xi: Tensor) -> Tensor:  # [6] -> leaf, grad
        p = xi.detach().clone().to(self.device, torch.float32).requires_grad_(True)
        self.poses[kf_id] = p
        self.pose_opt = _with_param(self.pose_opt, p, self.cfg.poses.lr)
        return p

    def keyframe_pose(self, kf: Keyframe) -> npt.NDArray[np.float64]:  # [4, 4]
        """The keyframe's pose with its correction (the front end's pose when it has none)."""
        T = torch.as_tensor(kf.frame.T_world_cam, dtype=torch.float64)
        xi = self.poses.get(kf.kf_id)
        if xi is None:
            return T.numpy()
        with torch.no_grad():
            return corrected(T, xi.detach().double().cpu(), self.scene_scale).numpy()

    def pose_for(self, T_world_cam: npt.ArrayLike) -> npt.NDArray[np.float64]:  # [4, 4]
        """A pose in the front end's frame moved as the map was: by the world-frame correction
        ``T_corrected @ inv(T_given)`` of the nearest input keyframe (translation plus rotation
        at ``keyframes.rotation_weight_m``). The pose itself without corrections."""
        T = np.asarray(T_world_cam, np.float64)
        kfs = [kf for kf in self.store if kf.frame.frame_id != REPAIRED_FRAME_ID]
        if not self.poses or not kfs:
            return T.copy()
        d = pose_distances(T, np.stack([kf.frame.T_world_cam for kf in kfs]),
                           self.cfg.keyframes.rotation_weight_m)[0]  # fmt: skip
        kf = kfs[int(np.argmin(d))]
        if kf.kf_id not in self.poses:
            return T.copy()
        return self.keyframe_pose(kf) @ np.linalg.inv(kf.frame.T_world_cam) @ T

    def _last_correction(self) -> Tensor:  # [6] the newest input keyframe's, else zero
        for kf in reversed(list(self.store)):
            if kf.frame.frame_id != REPAIRED_FRAME_ID:
                xi = self.poses.get(kf.kf_id)
                return torch.zeros(6) if xi is None else xi.detach().cpu().clone()
        return torch.zeros(6)

    def _track_loss(self, view: _View, xi: Tensor, mask: Tensor) -> Tensor:
        """Photometric L1 plus depth L1 of the frozen map at the corrected pose, on ``mask``."""
        H, W = view.color.shape[:2]
        out = self.render(corrected(view.T_world_cam, xi, self.scene_scale), view.K, W, H,
                          frozen=True)  # fmt: skip
        loss = photometric_loss(out.color, view.color, 0.0, 1.0, mask)
        if view.depth is not None and self.cfg.depth_weight > 0:
            valid = mask & (view.depth > 0)
            if bool(valid.any()):
                loss = loss + self.cfg.depth_weight * (out.depth - view.depth)[valid].abs().mean()
        return loss + self.cfg.poses.prior * pose_prior_loss(xi)

    def _track(self, view: _View, xi0: Tensor) -> Tensor:  # [6]
        """The frame's correction fitted against the map alone (poses.py: tracking). It starts
        from the better of the front end's pose and the last keyframe's correction and is kept
        only where it explains the frame better than both by ``track_margin``: tracking on a
        map that is still coarse must not walk the poses away (each frame would start from the
        last one's error)."""
        c = self.cfg.poses
        zero = torch.zeros(6, device=self.device)
        xi0 = xi0.detach().to(self.device, torch.float32)
        H, W = view.color.shape[:2]
        with torch.no_grad():
            out = self.render(corrected(view.T_world_cam, xi0, self.scene_scale), view.K, W, H)
            mask = out.alpha > 0.9
            if c.track_iters == 0 or float(mask.float().mean()) < c.track_min_covered:
                return zero
            starts = {"given": (zero, float(self._track_loss(view, zero, mask)))}
            if bool(xi0.any()):
                starts["last"] = (xi0, float(self._track_loss(view, xi0, mask)))
        start, best = min(starts.values(), key=lambda s: s[1])
        xi = start.clone().requires_grad_(True)
        opt = torch.optim.Adam([xi], lr=c.track_lr, eps=1e-15)
        for _ in range(c.track_iters):
            opt.zero_grad(set_to_none=True)
            self._track_loss(view, xi, mask).backward()
            if xi.grad is None or not bool(torch.isfinite(xi.grad).all()):
                break
            opt.step()
            clamp_(xi, c)
        with torch.no_grad():
            tracked = float(self._track_loss(view, xi, mask))
        if tracked < (1.0 - c.track_margin) * best:
            return xi.detach()
        return start

    def pose_corrections(self) -> dict[int, tuple[float, float]]:
        """kf_id -> (translation m, rotation deg) of each corrected keyframe's correction."""
        out = {}
        for kf in self.store:
            if kf.kf_id in self.poses:
                T = torch.as_tensor(kf.frame.T_world_cam, dtype=torch.float64)
                out[kf.kf_id] = offsets(T, torch.from_numpy(self.keyframe_pose(kf)))
        return out

    def _add_gaussians(self, res: Any) -> int:
        m = min(len(res), self.cfg.max_gaussians - len(self.gmap))
        self.n_capped += len(res) - max(m, 0)
        if m <= 0:
            return 0
        self.gmap.add(
            res.means[:m], res.log_scales[:m], res.quats[:m], res.opacity_logits[:m],
            res.sh0[:m], optimizers=self.optimizers,
        )  # fmt: skip
        self._resize_strategy_state(n_new=m)
        return m

    # -- public steps ---------------------------------------------------------------------------

    def _check_size(self, height: int, width: int) -> None:
        """The SSIM loss pads by half its window (reflection needs more pixels than that) at
        ``train_downscale``: a smaller view failed inside kornia, in later refinement steps too
        (a 3x3 repaired view stopped the splat node; benchmarks/results/fault_findings.md)."""
        side = (SSIM_WINDOW // 2 + 1) * self.cfg.train_downscale
        if min(height, width) < side:
            raise ValueError(
                f"image must be at least {side}x{side} pixels (SSIM window {SSIM_WINDOW} at "
                f"train_downscale {self.cfg.train_downscale}), got {width}x{height}"
            )

    def process(self, frame: RGBDFrame) -> FrameResult:
        """Map one posed RGB-D frame (see the module doc for the steps)."""
        # 1. Check inputs and fix the scene scale on the first frame
        if not isinstance(frame, RGBDFrame):
            raise TypeError(f"frame must be an RGBDFrame, got {type(frame).__name__}")
        self._check_size(frame.height, frame.width)
        c = 1 if frame.is_gray else 3
        if c != self.channels:
            raise ValueError(
                f"frame has {c} channel(s) but the map has {self.channels}; build the Mapper with channels={c}"
            )
        if self.scene_scale <= 0:
            valid = frame.depth[frame.depth > 0]
            self.scene_scale = float(np.median(valid)) if valid.size else 1.0
            self._build_optimizers()
        self.n_frames += 1
        self.last_stamp_ns[frame.frame_id] = max(
            frame.stamp_ns, self.last_stamp_ns.get(frame.frame_id, frame.stamp_ns)
        )
        s = self.cfg.train_downscale
        full = _frame_view(frame, self.device)
        view = downscale_view(full, s)
        # 1b. With pose correction: track the frame against the map, then treat it as posed there
        xi = None
        given = frame
        if self.cfg.poses.enabled and len(self.gmap) and self.kf_state.n_keyframes >= 1:
            xi = self._track(downscale_view(view, self.cfg.poses.track_downscale),
                             self._last_correction())  # fmt: skip
            T = corrected(full.T_world_cam, xi, self.scene_scale).detach()
            frame = frame.with_pose(T.cpu().double().numpy())
            view = dataclasses.replace(view, T_world_cam=T)  # ``full`` keeps the given pose

        # 2. Render at the frame's pose (training resolution) and, with exposure compensation,
        #    in the frame's exposure; grow where it does not explain the frame, in the canonical
        #    exposure
        with torch.no_grad():
            H, W = view.color.shape[:2]
            out = self.render(view.T_world_cam, view.K, W, H)
            affine = self._estimate_exposure(out, view) if self.cfg.exposure.enabled else None
            shown = out.color if affine is None else apply_affine(out.color, out.alpha, affine)
        alpha = _upsample(out.alpha[..., None], s, frame.height, frame.width)[..., 0]
        rendered = _upsample(shown.clamp(0, 1), s, frame.height, frame.width)
        res = grow(frame, self.cfg.growth, alpha, rendered)
        if affine is not None and len(res):
            rgb = torch.from_numpy(res.sh0).to(self.device) * SH_C0 + 0.5
            canonical = invert_affine(rgb, affine).clamp(0, 1)
            res = dataclasses.replace(res, sh0=((canonical - 0.5) / SH_C0).cpu().numpy())
        n_new = self._add_gaussians(res)

        # 3. Keyframe selection
        decision = select_keyframe(frame, n_new, self.kf_state, self.cfg.keyframes)
        kf = None
        if decision.is_keyframe:
            kf, _ = self.store.add(given, n_new_gaussians=n_new)  # the front end's pose
            if affine is not None:
                affine = self._keep_exposure(kf.kf_id, affine)
            if self.cfg.poses.enabled and self.kf_state.n_keyframes > 1:  # the first is the gauge
                full.pose = view.pose = self._keep_pose(
                    kf.kf_id, torch.zeros(6) if xi is None else xi
                )
                # the correction applies on the given pose
                view = dataclasses.replace(view, T_world_cam=full.T_world_cam)
            self._views[kf.kf_id] = full
            self._forget_views()
            if affine is not None:
                self._recenter_exposure()
            if self.cfg.carve.enabled:
                self._carve(full)
            iters = self.cfg.kf_iters
        else:
            self._non_kf_seen += 1
            iters = self.cfg.non_kf_iters if self._non_kf_seen % self.cfg.non_kf_every == 0 else 0

        # 4. Optimise on this frame plus random past keyframes
        full.affine = view.affine = affine
        losses = []
        for _ in range(iters):
            replay = self.store.sample(self.cfg.replay_keyframes, self.rng, exclude_latest=True)
            views = [view] + [downscale_view(self._keyframe_view(k), s) for k in replay]
            losses.append(self.train_step(views))

        # 5. The keyframe's render and alpha after optimisation (what GSFixer trains on)
        if kf is not None:
            color, _, a = self.render_numpy(
                self.keyframe_pose(kf), frame.intrinsics.K, frame.width, frame.height
            )
            kf = self.store.update_render(kf.kf_id, color, a)
        loss = float(np.mean(losses)) if losses else math.nan
        prior = out if kf is not None else None
        return FrameResult(decision.is_keyframe, decision.reason, n_new, iters, loss, kf, prior,
                           frame.T_world_cam)  # fmt: skip

    def refine(self, iters: int | None = None, downscale: int | None = None) -> OptimResult:
        """Global refinement: ``iters`` steps over random keyframes at ``1 / downscale`` of their
        resolution (default ``refine_downscale``: full resolution)."""
        iters = self.cfg.refine_iters if iters is None else iters
        s = self.cfg.refine_downscale if downscale is None else downscale
        if s < 1:
            raise ValueError(f"downscale must be >= 1, got {s}")
        losses: list[float] = []
        if not len(self.store):
            return OptimResult(0, math.nan, math.nan)
        for _ in range(iters):
            kfs = self.store.sample(self.cfg.refine_views, self.rng, exclude_latest=False)
            losses.append(self.train_step([downscale_view(self._keyframe_view(k), s) for k in kfs]))
        if iters and self.cfg.carve.enabled and self.cfg.carve_seeds:
            self._carve_seeded()
        return OptimResult(
            iters, losses[0] if losses else math.nan, losses[-1] if losses else math.nan
        )

    def distill(
        self,
        image: npt.NDArray[np.uint8],  # [H, W, 3] RGB (or [H, W]) repaired view
        T_world_cam: npt.ArrayLike,  # [4, 4]
        K: npt.ArrayLike,  # [3, 3] px
        iters: int | None = None,
        mask: npt.NDArray[Any] | None = None,  # [H, W]: nonzero = repaired pixels; None = all
        stamp_ns: int = 0,
        depth: npt.NDArray[np.float32] | None = None,  # [H, W] m, 0 = unknown (mesh render)
    ) -> OptimResult:
        """Fit the map to a repaired view with ``(1-l) L1 + l (1-SSIM)``; keep it as a keyframe.

        With ``depth`` (the mesh render's), the map first grows where it does not explain the
        repaired view, as for a new frame: optimisation alone cannot fill holes, since no Gaussian
        lies there to move or recolour."""
        # 1. Check inputs; colour follows the map (a grayscale map takes the luma)
        img = np.asarray(image)
        if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
            raise ValueError(
                f"image must be uint8 [H, W, 3] or [H, W], got {img.dtype} {list(img.shape)}"
            )
        H, W = img.shape[:2]
        self._check_size(H, W)
        if self.channels == 1 and img.ndim == 3:
            img = np.rint(img.astype(np.float32) @ np.float32([0.299, 0.587, 0.114])).astype(
                np.uint8
            )
        elif self.channels == 3 and img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if mask is not None and np.asarray(mask).shape != (H, W):
            raise ValueError(f"mask must be [{H}, {W}], got {list(np.asarray(mask).shape)}")
        if depth is not None:
            depth = np.asarray(depth)
            if depth.dtype != np.float32 or depth.shape != (H, W):
                raise ValueError(
                    f"depth must be float32 [{H}, {W}] m, got {depth.dtype} {list(depth.shape)}"
                )
        intr = Intrinsics.from_K(K, width=W, height=H)
        seed_depth = np.zeros((H, W), np.float32) if depth is None else depth
        frame = make_frame(img, seed_depth, intr, T_world_cam, stamp_ns, frame_id=REPAIRED_FRAME_ID)

        # 2. The anchor: the map without distillation's seeds, where it renders a surface and the
        # repair leaves it be (outside the mask); fitted there, the seeds of other views that
        # veil it are pulled away. Inside the mask, the repair.
        if mask is not None and self.cfg.distill_anchor and len(self.gmap):
            with torch.no_grad():
                out = self.render(frame.T_world_cam, intr.K, W, H, keep=~self.seeded())
            color0 = out.color.clamp(0, 1).cpu().numpy()
            holes = np.asarray(mask) != 0
            anchored = (out.alpha.cpu().numpy() >= 0.5) & ~holes
            if self.channels == 1:
                color0 = color0[..., 0]
            anchor = np.rint(color0 * 255).astype(np.uint8)
            img = np.where(anchored[..., None] if img.ndim == 3 else anchored, anchor, img)
            # kept: the anchor's surface where anchored, for carving the seeds in front of it
            stored = make_frame(img, np.where(anchored, out.depth.cpu().numpy(), np.float32(0)),
                                intr, T_world_cam, stamp_ns, frame_id=REPAIRED_FRAME_ID)  # fmt: skip
            seed_depth = np.where(holes, seed_depth, np.float32(0))  # seeds only in the holes
            frame = make_frame(img, seed_depth, intr, T_world_cam, stamp_ns,
                               frame_id=REPAIRED_FRAME_ID)  # fmt: skip
            mask = holes | anchored
        else:
            stored = None

        # 3. Grow into the holes the mesh depth covers (no depth: nothing to seed)
        n_new = 0
        if depth is not None and np.any(frame.depth > 0):
            with torch.no_grad():
                color, _, alpha = self.render_numpy(frame.T_world_cam, intr.K, W, H)
            res = grow(frame, self.cfg.growth, alpha, color)
            if self.cfg.distill_push_seeds and len(res):
                res = self._pushed(res, frame.T_world_cam)
            n_new = self._add_gaussians(res)
            if n_new:
                self.seeded()[-n_new:] = True

        # 4. Keep it as an extra observation (without depth) in the keyframe store, with its
        # mask: the passes over keyframes and repaired views fit it only there too. Seeds in
        # front of what another view sees are carved (no floater there).
        kf, _ = self.store.add(frame if stored is None else stored, n_new_gaussians=n_new)
        if stored is not None:
            self._anchored.add(kf.kf_id)
        if n_new and self.cfg.carve.enabled and self.cfg.carve_seeds:
            n_new -= self._carve_seeded()
        if mask is not None:
            self._repair_masks[kf.kf_id] = np.asarray(mask) != 0
        self._views.pop(kf.kf_id, None)
        view = self._keyframe_view(kf)
        self._forget_views()

        # 5. Optimise on the repaired view
        iters = self.cfg.distill_iters if iters is None else iters
        lam = self.cfg.distill_lambda
        losses = [self.train_step([view], lam=lam, l1_weight=1.0 - lam) for _ in range(iters)]
        if self.cfg.carve.enabled and self.cfg.carve_seeds:
            self._carve_seeded()
        color, _, a = self.render_numpy(frame.T_world_cam, intr.K, W, H)
        self.store.update_render(kf.kf_id, color, a)
        first = losses[0] if losses else math.nan
        return OptimResult(iters, first, losses[-1] if losses else math.nan, kf.kf_id)

    def _pushed(self, res: GrowthResult, T_world_cam: npt.NDArray[np.float64]) -> GrowthResult:
        """``res`` with each seed moved along its own ray until no stored view sees it
        (``distill_push_seeds``; prune.push_behind)."""
        views = self._judging_views()
        if not views:
            return res
        means = torch.from_numpy(res.means)
        origin = torch.as_tensor(np.asarray(T_world_cam)[:3, 3], dtype=torch.float32)
        f = push_behind(means, origin, views, self.cfg.carve, self.cfg.distill_push_max)
        self.n_pushed += int((f > 1).sum())
        means = origin + f[:, None] * (means - origin)
        log_scales = torch.from_numpy(res.log_scales) + torch.log(f)[:, None]
        return dataclasses.replace(res, means=means.numpy().astype(np.float32),
                                   log_scales=log_scales.numpy().astype(np.float32))  # fmt: skip

    def forget_repairs(self) -> list[tuple[Keyframe, npt.NDArray[np.bool_] | None]]:
        """Undo distillation's additions: the repaired views leave the keyframe store and the
        Gaussians distillation seeded leave the map (what the passes changed in the input's
        Gaussians stays). Returns the repaired views, oldest first, each with the mask it was
        distilled with (None: the whole view). The map is then as the input built it, to
        distil again (e.g. the repairs of a better checkpoint)."""
        removed = []
        for kf in self.store:
            if kf.frame.frame_id != REPAIRED_FRAME_ID:
                continue
            mask = self._repair_masks.get(kf.kf_id)
            if mask is not None and kf.kf_id in self._anchored:
                mask = mask & (kf.frame.depth == 0)  # its mask is holes | anchor (with depth)
            removed.append((self.store.remove(kf.kf_id), mask))
        seeded = self.seeded()
        if bool(seeded.any()):
            self.gmap.remove(seeded, self.optimizers)
            self._resize_strategy_state(keep=~seeded)
        self._forget_views()
        return removed

    def fidelity(self) -> dict[int, float]:
        """Per repaired view (keyframe id): PSNR dB of the map's render against the image it
        was fitted to, inside its mask (exposure-corrected like the loss); inf if identical."""
        out: dict[int, float] = {}
        for kf in self.store:
            if kf.frame.frame_id != REPAIRED_FRAME_ID:
                continue
            view = self._keyframe_view(kf)
            H, W = view.color.shape[:2]
            with torch.no_grad():
                pred = self.render(view.T_world_cam, view.K, W, H).color.clamp(0, 1)
            err = (pred - view.color) ** 2
            if view.mask is not None:
                if not bool(view.mask.any()):
                    continue
                err = err[view.mask]
            mse = float(err.mean())
            out[kf.kf_id] = math.inf if mse == 0 else -10.0 * math.log10(mse)
        return out

    def polish(self, below_db: float | None = None) -> PolishResult:
        """Fit again the repaired views whose fidelity is under ``below_db`` (default
        ``polish_below_db``; 0: nothing): ``polish_iters`` steps each, every step with
        ``polish_partners`` random other repaired views, for up to ``polish_rounds`` rounds
        (a round polishes the views under the threshold when it starts)."""
        cfg = self.cfg
        below = cfg.polish_below_db if below_db is None else below_db
        before = self.fidelity() if below > 0 else {}
        after, polished, n = before, [], 0
        kfs = {kf.kf_id: kf for kf in self.store}
        lam = cfg.distill_lambda
        for _ in range(cfg.polish_rounds if below > 0 else 0):
            low = sorted(k for k, v in after.items() if v < below)
            if not low:
                break
            for k in low:
                others = [o for o in after if o != k]
                for _ in range(cfg.polish_iters):
                    pick = self.rng.choice(others, min(cfg.polish_partners, len(others)),
                                           replace=False) if others else []  # fmt: skip
                    views = [self._keyframe_view(kfs[k])]
                    views += [self._keyframe_view(kfs[int(o)]) for o in pick]
                    self.train_step(views, lam=lam, l1_weight=1.0 - lam)
                    n += 1
            polished += [k for k in low if k not in polished]
            after = self.fidelity()
        return PolishResult(before, after, polished, n)

    # -- snapshots ------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: map, optimizers, strategy, keyframes, counters, RNG."""
        last = self.kf_state.last_keyframe
        return {
            "version": 1,
            "map": self.gmap.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "strategy": {
                k: v.detach().cpu().clone() if isinstance(v, Tensor) else v
                for k, v in self.strategy_state.items()
            },
            "store": self.store.state_dict(),
            "last_keyframe": None if last is None else frame_to_dict(last),
            "kf_counts": (self.kf_state.n_frames, self.kf_state.n_keyframes),
            "counters": {
                "n_frames": self.n_frames,
                "n_steps": self.n_steps,
                "n_nonfinite_steps": self.n_nonfinite_steps,
                "n_pruned": self.n_pruned,
                "n_capped": self.n_capped,
                "n_carved": self.n_carved,
                "n_pushed": self.n_pushed,
                "non_kf_seen": self._non_kf_seen,
                "last_stamp_ns": dict(self.last_stamp_ns),
            },  # fmt: skip
            "scene_scale": self.scene_scale,
            "rng": json.dumps(self.rng.bit_generator.state),
            "exposure": {k: v.detach().cpu().clone() for k, v in self.exposure.items()},
            "poses": {k: v.detach().cpu().clone() for k, v in self.poses.items()},
            # bit-packed uint8 tensors: snapshots load with weights_only
            "repair_masks": {
                k: torch.from_numpy(np.packbits(m)) for k, m in self._repair_masks.items()
            },
            "repair_mask_shapes": {k: list(m.shape) for k, m in self._repair_masks.items()},
            "seeded": self.seeded().detach().cpu().clone(),
            "anchored": sorted(self._anchored),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if state.get("version") != 1:
            raise ValueError(f"mapper snapshot version must be 1, got {state.get('version')!r}")
        self.gmap = GaussianMap.from_state_dict(state["map"], self.device)
        self.scene_scale = float(state["scene_scale"])
        self._build_optimizers()
        for k, o in self.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        self.strategy_state.update(
            {
                k: v.to(self.device) if isinstance(v, Tensor) else v
                for k, v in state["strategy"].items()
            }
        )
        self.store = KeyframeStore.from_state_dict(state["store"])
        self._views = {}
        shapes = state.get("repair_mask_shapes", {})  # absent in older snapshots
        self._repair_masks = {
            int(k): np.unpackbits(np.asarray(b.numpy()), count=int(np.prod(shapes[k])))
            .reshape(shapes[k])
            .astype(bool)
            for k, b in state.get("repair_masks", {}).items()
        }
        self._anchored = {int(k) for k in state.get("anchored", [])}  # absent in older ones
        seeded = state.get("seeded")  # absent in older snapshots: none counts as seeded
        self._seeded = (seeded.to(self.device, torch.bool) if seeded is not None
                        else torch.zeros(len(self.gmap), dtype=torch.bool, device=self.device))  # fmt: skip
        self.exposure, self.exposure_opt = {}, None
        for kf_id, params in state.get("exposure", {}).items():  # absent in older snapshots
            self._keep_exposure(int(kf_id), params.to(self.device))
        self.poses, self.pose_opt = {}, None
        for kf_id, xi in state.get("poses", {}).items():  # absent in older snapshots
            self._keep_pose(int(kf_id), xi)
        self.kf_state = initialize_state()
        self.kf_state.n_frames, self.kf_state.n_keyframes = state["kf_counts"]
        if state["last_keyframe"] is not None:
            self.kf_state.last_keyframe = frame_from_dict(state["last_keyframe"])
        c = state["counters"]
        self.n_frames, self.n_steps = c["n_frames"], c["n_steps"]
        self.n_nonfinite_steps, self.n_pruned = c["n_nonfinite_steps"], c["n_pruned"]
        self.n_capped, self._non_kf_seen = c["n_capped"], c["non_kf_seen"]
        self.n_carved = c.get("n_carved", 0)  # absent in older snapshots
        self.n_pushed = c.get("n_pushed", 0)  # absent in older snapshots
        self.last_stamp_ns = dict(c.get("last_stamp_ns", {}))  # absent in older snapshots
        self.rng.bit_generator.state = json.loads(state["rng"])

    def stats(self) -> dict[str, float]:
        """Flat counters for the node's stats message."""
        return {
            "gaussians": len(self.gmap),
            "keyframes": len(self.store),
            "frames": self.n_frames,
            "steps": self.n_steps,
            "nonfinite_steps": self.n_nonfinite_steps,
            "pruned": self.n_pruned,
            "capped": self.n_capped,
            "carved": self.n_carved,
            "pushed": self.n_pushed,
            **self._pose_stats(),
        }

    def _pose_stats(self) -> dict[str, float]:
        if not self.cfg.poses.enabled:
            return {}
        c = list(self.pose_corrections().values())
        return {
            "pose_corrected": len(c),
            "pose_max_mm": 1000 * max((m for m, _ in c), default=0.0),
            "pose_max_deg": max((d for _, d in c), default=0.0),
        }


def _with_param(opt: torch.optim.Optimizer | None, p: Tensor, lr: float) -> torch.optim.Optimizer:
    """``opt`` with one more per-view parameter ``p`` (a new Adam at ``lr`` when None)."""
    if opt is None:
        return torch.optim.Adam([p], lr=lr, eps=1e-15)
    opt.add_param_group({"params": [p]})
    return opt


def _resize(x: Tensor, height: int, width: int) -> npt.NDArray[np.float32]:
    """[h, w, C] -> [height, width, C] numpy, bilinear (pixel centres aligned)."""
    if x.shape[:2] != (height, width):
        x = F.interpolate(
            x.permute(2, 0, 1)[None], size=(height, width), mode="bilinear", align_corners=False
        )[0].permute(1, 2, 0)
    return np.ascontiguousarray(x.cpu().numpy(), dtype=np.float32)


def _upsample(x: Tensor, s: int, height: int, width: int) -> npt.NDArray[np.float32]:
    """[h, w, C] -> [height, width, C] numpy by pixel repetition (edges padded)."""
    if s > 1:
        x = x.repeat_interleave(s, 0).repeat_interleave(s, 1)
    pad_h, pad_w = height - x.shape[0], width - x.shape[1]
    if pad_h or pad_w:
        x = F.pad(x.permute(2, 0, 1)[None], (0, pad_w, 0, pad_h), mode="replicate")[0].permute(
            1, 2, 0
        )
    return x.cpu().numpy()
