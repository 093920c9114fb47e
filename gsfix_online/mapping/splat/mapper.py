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
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from gsfix_online.core.types import RGBDFrame, make_frame
from gsfix_online.mapping.splat.carving import (
    Judge,
    carve_seeded,
    carve_view,
    judging_views,
    push_seeds,
)
from gsfix_online.mapping.splat.config import MapperConfig
from gsfix_online.mapping.splat.distill import anchor, repaired_frame
from gsfix_online.mapping.splat.exposure import apply_affine, invert_affine
from gsfix_online.mapping.splat.exposure_model import ExposureModel
from gsfix_online.mapping.splat.gaussians import (
    ORIGIN_OBSERVED,
    ORIGIN_REPAIRED,
    SH_C0,
    GaussianMap,
)
from gsfix_online.mapping.splat.growth import grow
from gsfix_online.mapping.splat.keyframes import (
    Keyframe,
    KeyframeState,
    KeyframeStore,
    frame_from_dict,
    frame_to_dict,
    initialize_state,
    prior_images,
    select_keyframe,
)
from gsfix_online.mapping.splat.optimize import (
    NEVER,
    DensifyConfig,
    LearningRates,
    MapOptimizer,
)
from gsfix_online.mapping.splat.pose_refiner import PoseRefiner
from gsfix_online.mapping.splat.poses import corrected
from gsfix_online.mapping.splat.provenance import seen_by, synthesised_share
from gsfix_online.mapping.splat.prune import project_points
from gsfix_online.mapping.splat.refine import PolishResult
from gsfix_online.mapping.splat.refine import fidelity as _fidelity
from gsfix_online.mapping.splat.refine import polish as _polish
from gsfix_online.mapping.splat.refine import refine as _refine
from gsfix_online.mapping.splat.render import resolve_backend
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import (
    REPAIRED_FRAME_ID,
    SSIM_WINDOW,
    TrainView,
    check_size,
    downscale_view,
    frame_view,
    photometric_loss,
    predicted_color,
    upsample,
    view_loss,
)

# The names this module has always exported (the parts now live in their own modules).
_View = TrainView
_frame_view = frame_view
# distill_split_px splits only where the map renders an opaque surface (the observed surfaces
# whose blur benchmarks/results/observed_blur_cpu.md traced), not at its holes' borders
SPLIT_ALPHA = 0.99

__all__ = [
    "NEVER", "REPAIRED_FRAME_ID", "SSIM_WINDOW", "DensifyConfig", "FrameResult",
    "LearningRates", "Mapper", "MapperConfig", "OptimResult", "PolishResult", "downscale_view",
    "photometric_loss",
]  # fmt: skip


@dataclass(frozen=True)
class FrameResult:
    """What :meth:`Mapper.process` did with one frame."""

    is_keyframe: bool
    reason: str  # keyframe reason: first, new_gaussians, low_overlap, none
    n_new_gaussians: int
    n_iters: int  # optimisation steps run (skipped non-finite steps included)
    loss: float  # mean loss of the steps run; NaN when none ran
    # the stored keyframe: its render and alpha after optimisation, and its prior, the map's
    # render at its pose before the frame changed the map (the one growth compared against, at
    # the training resolution): what the map predicted of a view it had not seen, with the
    # artefacts and holes of a novel view, which GSFixer trains on (services/splat.py
    # ``keyframe_render``)
    keyframe: Keyframe | None
    # [4, 4] the pose the frame was mapped at: the front end's, or where tracking moved it
    # (mapper.poses)
    pose: npt.NDArray[np.float64] | None = None

    def prior(
        self, height: int, width: int
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None:
        """The keyframe's prior at ``height`` x ``width``, bilinear: colour [H, W, C] in [0, 1]
        and alpha [H, W]; None for a frame that did not become a keyframe."""
        return None if self.keyframe is None else prior_images(self.keyframe, height, width)


@dataclass(frozen=True)
class OptimResult:
    """Losses of a run of steps (:meth:`Mapper.refine`, :meth:`Mapper.distill`)."""

    n_iters: int
    loss_first: float
    loss_last: float
    keyframe_id: int = -1  # distill: the id of the repaired view in the keyframe store


class _Part:
    """An attribute of the mapper that one of its parts holds (read and written through)."""

    def __init__(self, part: str, name: str) -> None:
        self.part, self.name = part, name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        return self if obj is None else getattr(getattr(obj, self.part), self.name)

    def __set__(self, obj: Any, value: Any) -> None:
        setattr(getattr(obj, self.part), self.name, value)


class Mapper:
    """The online Gaussian map: the facade over its parts (see module doc).

    ``optim`` (:class:`.optimize.MapOptimizer`) holds the map, its optimizers and densification;
    ``exposure_model`` (:class:`.exposure_model.ExposureModel`) and ``pose_refiner``
    (:class:`.pose_refiner.PoseRefiner`) the keyframes' exposures and pose corrections; the
    mapper holds the keyframes, the views prepared from them and what distillation added, and
    runs the mapping step (:meth:`process`), distillation (:meth:`distill`, inputs from
    :mod:`.distill`, carving from :mod:`.carving`) and the end-of-input refinement
    (:meth:`refine`, :meth:`polish`: :mod:`.refine`).
    """

    gmap = _Part("optim", "gmap")
    optimizers = _Part("optim", "optimizers")
    strategy = _Part("optim", "strategy")
    strategy_state = _Part("optim", "strategy_state")
    n_steps = _Part("optim", "n_steps")
    n_nonfinite_steps = _Part("optim", "n_nonfinite_steps")
    n_pruned = _Part("optim", "n_pruned")
    n_carved = _Part("optim", "n_carved")  # Gaussians a keyframe's depth saw through
    n_capped = _Part("optim", "n_capped")  # Gaussians growth wanted but max_gaussians refused
    exposure = _Part("exposure_model", "params")  # kf_id -> [2, C] the keyframe's exposure
    exposure_opt = _Part("exposure_model", "opt")
    poses = _Part("pose_refiner", "poses")  # kf_id -> [6] the keyframe's pose correction
    pose_opt = _Part("pose_refiner", "opt")

    def __init__(
        self, cfg: MapperConfig, channels: int = 3, device: str | torch.device | None = None
    ) -> None:
        self.cfg = cfg
        # the map lives where its renderer runs: cfg.backend (auto = CUDA when torch sees a GPU)
        self.device = torch.device(resolve_backend(cfg.backend) if device is None else device)
        self.optim = MapOptimizer(GaussianMap(cfg.sh_degree, channels, self.device), cfg.lr,
                                  cfg.densify, cfg.prune, cfg.prune_every, cfg.backend)  # fmt: skip
        self.exposure_model = ExposureModel(cfg.exposure, self.device)
        self.pose_refiner = PoseRefiner(cfg.poses, cfg.depth_weight, self.device)
        self.kf_state: KeyframeState = initialize_state()
        self.store = KeyframeStore.from_config(cfg.keyframes)
        self.rng = np.random.default_rng(cfg.seed)
        self.scene_scale = cfg.scene_scale_m
        self.n_frames = 0
        # newest stamp mapped per camera (frame_id), saved in snapshots: the splat node skips
        # frames at or before it, which a restarted sender or a resent link delivers again
        self.last_stamp_ns: dict[str, int] = {}
        self.n_pushed = 0  # distillation's seeds moved behind what other views see
        self.n_refilled = 0  # seeds grown again in repaired views' holes (refill), before carving
        self.n_split = 0  # input Gaussians split for repaired views that see them wide
        self._non_kf_seen = 0
        self._views: dict[int, TrainView] = {}  # kf_id -> full-resolution view
        # kf_id -> the pixels a repaired view is fitted on (distill's mask), in every pass
        self._repair_masks: dict[int, npt.NDArray[np.bool_]] = {}
        # repaired views fitted with an anchor (distill_anchor): their stored depth is the
        # anchor's surface, zero in their holes, so carving reads it as it is
        self._anchored: set[int] = set()
        # kf_id -> [H, W] m the depth a repaired view's seeds were grown at (0 = none), kept
        # with distill_veil_guard: it judges the seeds of other views (carving.judging_views)
        self._seed_depths: dict[int, npt.NDArray[np.float32]] = {}
        self._judge_depths: dict[int, tuple[tuple[Any, ...], Tensor]] = {}  # judging_views' own
        self._build_optimizers()

    # -- set-up ---------------------------------------------------------------------------------

    @property
    def channels(self) -> int:
        return self.gmap.channels

    def _build_optimizers(self) -> None:
        self.optim.build(self.scene_scale)

    def seeded(self) -> Tensor:  # [N] bool
        """Which Gaussians distillation grew from a repaired view's seed depth (kept through
        growth, pruning, carving and densification)."""
        return self.optim.seeded()

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
        return self.optim.render(T_world_cam, K, width, height, keep=keep, frozen=frozen)

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

    def synthesised_share(
        self, T_world_cam: npt.ArrayLike, K: npt.ArrayLike, width: int, height: int
    ) -> npt.NDArray[np.float32]:  # [H, W] in [0, 1]
        """Per pixel, the share of the render's colour that Gaussians grown from repaired views
        make (:func:`.provenance.synthesised_share`): what the map shows there was synthesised,
        not observed, though a render draws it."""
        return synthesised_share(self.gmap, T_world_cam, K, width, height, self.cfg.backend)

    # -- optimisation ---------------------------------------------------------------------------

    def _view_loss(
        self, view: TrainView, lam: float, l1_weight: float
    ) -> tuple[Tensor, RenderOutput]:
        H, W = view.color.shape[:2]
        T = view.T_world_cam
        if view.pose is not None:
            T = corrected(T, view.pose, self.scene_scale)
        out = self.render(T, view.K, W, H)
        cfg = self.cfg
        loss = view_loss(out, view, lam, l1_weight, cfg.depth_weight, cfg.exposure, cfg.poses.prior)
        return loss, out

    def train_step(
        self,
        views: list[TrainView],
        lam: float | None = None,
        l1_weight: float = 1.0,
        freeze_mapped: bool = False,
    ) -> float:
        """One Adam step on the mean loss of ``views`` (:meth:`.MapOptimizer.step`), the
        keyframes' exposures and pose corrections with the map; the first view feeds
        densification. Repaired views train only distillation's seeds with ``freeze_mapped``
        or ``distill_freeze_mapped``. A step whose loss or gradients are not finite changes
        nothing and is counted in ``n_nonfinite_steps``."""
        lam = self.cfg.ssim_lambda if lam is None else lam
        extra = [o for o in (self.exposure_opt, self.pose_opt) if o is not None]
        return self.optim.step(
            views, lambda v: self._view_loss(v, lam, l1_weight), extra,
            [*self.exposure.values(), *self.poses.values()],
            freeze_mapped=self.cfg.distill_freeze_mapped or freeze_mapped,
            after_update=self.pose_refiner.clamp,
        )  # fmt: skip

    def _posed(self, view: TrainView) -> Tensor:  # [4, 4] the view's pose with its correction
        if view.pose is None:
            return view.T_world_cam
        with torch.no_grad():
            return corrected(view.T_world_cam, view.pose, self.scene_scale)

    def _judging_views(self) -> list[Judge]:
        seeds = self._seed_depths if self.cfg.distill_veil_guard else None
        return judging_views(self.store, self._repair_masks, self._anchored, self._keyframe_view,
                             self._posed, seeds, self._judge_depths)  # fmt: skip

    def _carves_seeds(self) -> bool:
        """Whether distillation's seeds are carved after growth, fits and passes."""
        return self.cfg.distill_veil_guard or (self.cfg.carve.enabled and self.cfg.carve_seeds)

    def _carve_seeded(self) -> int:
        # the guard judges a seed by its centre: a large one in front of a surface veils it
        return carve_seeded(self.optim, self._judging_views(), self.cfg.carve,
                            whole=not self.cfg.distill_veil_guard)  # fmt: skip

    def _keyframe_view(self, kf: Keyframe) -> TrainView:
        view = self._views.get(kf.kf_id)
        if view is None:
            repaired = kf.frame.frame_id == REPAIRED_FRAME_ID
            view = frame_view(kf.frame, self.device, use_depth=not repaired)
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
        for kf_id in [k for k in self._seed_depths if k not in live]:
            del self._seed_depths[kf_id]
        self._anchored &= live
        self.exposure_model.forget(live)
        self.pose_refiner.forget(live)

    def _estimate_exposure(self, out: RenderOutput, view: TrainView) -> Tensor:  # [2, C]
        return self.exposure_model.estimate(out, view)

    # -- poses ----------------------------------------------------------------------------------

    def keyframe_pose(self, kf: Keyframe) -> npt.NDArray[np.float64]:  # [4, 4]
        """The keyframe's pose with its correction (the front end's pose when it has none)."""
        return self.pose_refiner.keyframe_pose(kf, self.scene_scale)

    def pose_for(self, T_world_cam: npt.ArrayLike) -> npt.NDArray[np.float64]:  # [4, 4]
        """A pose in the front end's frame moved as the map was: by the world-frame correction
        ``T_corrected @ inv(T_given)`` of the nearest input keyframe (translation plus rotation
        at ``keyframes.rotation_weight_m``). The pose itself without corrections."""
        return self.pose_refiner.pose_for(T_world_cam, self.store,
                                          self.cfg.keyframes.rotation_weight_m, self.scene_scale)  # fmt: skip

    def pose_corrections(self) -> dict[int, tuple[float, float]]:
        """kf_id -> (translation m, rotation deg) of each corrected keyframe's correction."""
        return self.pose_refiner.corrections(self.store, self.scene_scale)

    # -- public steps ---------------------------------------------------------------------------

    def _check_size(self, height: int, width: int) -> None:
        check_size(height, width, self.cfg.train_downscale)

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
        full = frame_view(frame, self.device)
        view = downscale_view(full, s)
        # 1b. With pose correction: track the frame against the map, then treat it as posed there
        xi = None
        given = frame
        if self.cfg.poses.enabled and len(self.gmap) and self.kf_state.n_keyframes >= 1:
            xi = self.pose_refiner.track(
                self.render, downscale_view(view, self.cfg.poses.track_downscale),
                self.pose_refiner.last_correction(self.store), self.scene_scale,
            )  # fmt: skip
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
        alpha = upsample(out.alpha[..., None], s, frame.height, frame.width)[..., 0]
        rendered = upsample(shown.clamp(0, 1), s, frame.height, frame.width)
        if view.depth is not None and len(self.gmap) and "depths" in out.info:
            # every Gaussian this frame saw counts it (its provenance: observations)
            self.gmap.observations[seen_by(out, view.depth)] += 1
        res = grow(frame, self.cfg.growth, alpha, rendered)
        if affine is not None and len(res):
            rgb = torch.from_numpy(res.sh0).to(self.device) * SH_C0 + 0.5
            canonical = invert_affine(rgb, affine).clamp(0, 1)
            res = dataclasses.replace(res, sh0=((canonical - 0.5) / SH_C0).cpu().numpy())
        n_new = self.optim.add(res, self.cfg.max_gaussians, ORIGIN_OBSERVED, observations=1)

        # 3. Keyframe selection
        decision = select_keyframe(frame, n_new, self.kf_state, self.cfg.keyframes)
        kf = None
        if decision.is_keyframe:
            kf, _ = self.store.add(given, n_new_gaussians=n_new)  # the front end's pose
            if affine is not None:
                affine = self.exposure_model.keep(kf.kf_id, affine)
            if self.cfg.poses.enabled and self.kf_state.n_keyframes > 1:  # the first is the gauge
                full.pose = view.pose = self.pose_refiner.keep(
                    kf.kf_id, torch.zeros(6) if xi is None else xi
                )
                # the correction applies on the given pose
                view = dataclasses.replace(view, T_world_cam=full.T_world_cam)
            self._views[kf.kf_id] = full
            self._forget_views()
            if affine is not None:
                self.exposure_model.recenter(self.gmap)
            if self.cfg.carve.enabled and full.depth is not None:
                carve_view(self.optim, full.depth, full.K, self._posed(full), self.cfg.carve)
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
            self.store.update_render(kf.kf_id, color, a)
            prior = torch.cat([out.color.clamp(0, 1), out.alpha[..., None]], dim=-1)
            kf = self.store.set_prior(kf.kf_id, prior.cpu().numpy())
        loss = float(np.mean(losses)) if losses else math.nan
        return FrameResult(decision.is_keyframe, decision.reason, n_new, iters, loss, kf,
                           frame.T_world_cam)  # fmt: skip

    def refine(self, iters: int | None = None, downscale: int | None = None) -> OptimResult:
        """Global refinement (:func:`.refine.refine`): ``iters`` steps over random keyframes at
        ``1 / downscale`` of their resolution (default ``refine_downscale``: full resolution)."""
        iters = self.cfg.refine_iters if iters is None else iters
        s = self.cfg.refine_downscale if downscale is None else downscale
        if s < 1:
            raise ValueError(f"downscale must be >= 1, got {s}")
        if not len(self.store):
            return OptimResult(0, math.nan, math.nan)
        losses = _refine(self.store, self._keyframe_view, self.train_step, self.rng, iters,
                         self.cfg.refine_views, s)  # fmt: skip
        if iters and self._carves_seeds():
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
        observed: npt.NDArray[Any] | None = None,  # [H, W]: nonzero = the mesh saw a surface
    ) -> OptimResult:
        """Fit the map to a repaired view with ``(1-l) L1 + l (1-SSIM)``; keep it as a keyframe.

        With ``depth`` (the mesh render's), the map first grows where it does not explain the
        repaired view, as for a new frame: optimisation alone cannot fill holes, since no Gaussian
        lies there to move or recolour. ``distill_split_px`` splits only on ``observed`` pixels
        (None: every repaired pixel): where the mesh never saw a surface, nothing backs a
        finer map."""
        # 1. Check inputs; colour follows the map (a grayscale map takes the luma)
        rv = repaired_frame(image, T_world_cam, K, self.channels, self.cfg.train_downscale, mask,
                            stamp_ns, depth)  # fmt: skip
        frame = rv.frame
        H, W, intr = frame.height, frame.width, frame.intrinsics
        if observed is not None and np.shape(observed) != (H, W):
            raise ValueError(f"observed must be [{H}, {W}], got {list(np.shape(observed))}")

        # 2. The anchor: the map without distillation's seeds, where it renders a surface and the
        # repair leaves it be (outside the mask); fitted there, the seeds of other views that
        # veil it are pulled away. Inside the mask, the repair.
        if rv.mask is not None and self.cfg.distill_anchor and len(self.gmap):
            with torch.no_grad():
                out = self.render(frame.T_world_cam, intr.K, W, H, keep=~self.seeded())
            rv = anchor(rv, out)
            frame = rv.frame

        # 3. Grow into the holes the mesh depth covers (no depth: nothing to seed); split the
        # input's Gaussians that are wider than the view's pixels where it repairs them
        n_new = self._seed(frame) if depth is not None and np.any(frame.depth > 0) else 0
        if self.cfg.distill_split_px > 0 and mask is not None:
            where = np.asarray(mask) != 0
            self._split_wide(frame, where if observed is None else where & (observed != 0))

        # 4. Keep it as an extra observation (without depth) in the keyframe store, with its
        # mask: the passes over keyframes and repaired views fit it only there too. Seeds in
        # front of what another view sees are carved (no floater there).
        kf, _ = self.store.add(frame if rv.stored is None else rv.stored, n_new_gaussians=n_new)
        if rv.stored is not None:
            self._anchored.add(kf.kf_id)
        if self.cfg.distill_veil_guard and np.any(frame.depth > 0):
            self._seed_depths[kf.kf_id] = frame.depth  # its seeds' depth, in its holes
        if n_new and self._carves_seeds():
            self._carve_seeded()
        if rv.mask is not None:
            self._repair_masks[kf.kf_id] = rv.mask
        self._views.pop(kf.kf_id, None)
        view = self._keyframe_view(kf)
        self._forget_views()

        # 5. Optimise on the repaired view
        iters = self.cfg.distill_iters if iters is None else iters
        lam = self.cfg.distill_lambda
        losses = [self.train_step([view], lam=lam, l1_weight=1.0 - lam) for _ in range(iters)]
        if self._carves_seeds():
            self._carve_seeded()
        color, _, a = self.render_numpy(frame.T_world_cam, intr.K, W, H)
        self.store.update_render(kf.kf_id, color, a)
        first = losses[0] if losses else math.nan
        return OptimResult(iters, first, losses[-1] if losses else math.nan, kf.kf_id)

    def _seed(self, frame: RGBDFrame, min_share: float = 0.0) -> int:
        """Grow distillation's seeds where the map does not explain a repaired view (``frame``,
        its seed depth as depth), as for input frames but for the repaired views' own
        thresholds where set; moved behind what other views see with the veil guard, bounded
        by ``distill_scale_growth``; none unless their cells cover ``min_share`` of the view.
        Returns how many were added."""
        H, W, K = frame.height, frame.width, frame.intrinsics.K
        with torch.no_grad():
            color, _, alpha = self.render_numpy(frame.T_world_cam, K, W, H)
        own = {"error_thresh": self.cfg.distill_error_thresh,
               "var_thresh": self.cfg.distill_var_thresh}  # fmt: skip
        gcfg = dataclasses.replace(
            self.cfg.growth, **{k: v for k, v in own.items() if v is not None}
        )
        res = grow(frame, gcfg, alpha, color)
        if not len(res) or int((res.cells[:, 2] * res.cells[:, 3]).sum()) < min_share * H * W:
            return 0
        if self.cfg.distill_push_seeds or self.cfg.distill_veil_guard:
            res, n_pushed = push_seeds(res, frame.T_world_cam, self._judging_views(),
                                       self.cfg.carve, self.cfg.distill_push_max)  # fmt: skip
            self.n_pushed += n_pushed
        return self.optim.add(res, self.cfg.max_gaussians, ORIGIN_REPAIRED,
                              scale_growth=self.cfg.distill_scale_growth)  # fmt: skip

    def _split_wide(self, frame: RGBDFrame, where: npt.NDArray[np.bool_]) -> int:
        """Split the Gaussians the input mapped that a repaired view sees wider than
        ``distill_split_px`` of its pixels (largest sigma times focal length over depth), whose
        centre projects onto ``where`` ([H, W]) where the map renders an opaque surface
        (``SPLIT_ALPHA``), no farther than 5 % behind it; up to ``distill_split_rounds``
        rounds, within ``max_gaussians`` (the widest first). Returns how many were split
        (``n_split`` counts them)."""
        H, W, K = frame.height, frame.width, frame.intrinsics.K
        cfg, total, dev = self.cfg, 0, self.device
        K_t = torch.as_tensor(np.asarray(K), dtype=torch.float32, device=dev)
        T_t = torch.as_tensor(np.asarray(frame.T_world_cam), dtype=torch.float32, device=dev)
        where_t = torch.as_tensor(where, device=dev)
        for _ in range(cfg.distill_split_rounds):
            g = self.gmap
            with torch.no_grad():
                out = self.render(frame.T_world_cam, K, W, H)
                z, u, v = project_points(g.means, K_t, T_t)
                on = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
                u, v = u.clamp(0, W - 1), v.clamp(0, H - 1)
                d = out.depth[v, u]
                on &= where_t[v, u] & (out.alpha[v, u] >= SPLIT_ALPHA) & (d > 0) & (z <= 1.05 * d)
                sigma_px = g.scales.amax(1) * float(K[0, 0]) / z.clamp_min(1e-6)
                pick = on & (sigma_px > cfg.distill_split_px) & ~self.seeded()
                room = max(cfg.max_gaussians - len(g), 0)
                if int(pick.sum()) > room:  # the widest first
                    widest = torch.topk(torch.where(pick, sigma_px, -math.inf), room).indices
                    pick = torch.zeros_like(pick)
                    pick[widest] = True
            n = self.optim.split(pick, int(self.rng.integers(2**31)))
            total += n
            if not n:
                break
        self.n_split += total
        return total

    def refill(self, min_share: float = 0.0) -> dict[int, int]:
        """Seed again the holes that have opened in the repaired views since they were
        distilled: where a view's seed depth (kept with the veil guard) has a surface and the
        map now renders too little of it (growth's ``alpha_thresh``) or renders it far from the
        view's image (its ``error_thresh``, as distillation grows), in views where such cells
        cover at least ``min_share`` of the view. A view gets no seed where the map
        explained it when it came; in a bounded map (``distill_scale_growth``) what covered
        it then may have shrunk away. Returns the seeds grown per repaired view (keyframe id;
        views that got none left out); ``n_refilled`` counts them, ``n_carved`` what carving
        then removes."""
        grown = {}
        for kf in [k for k in self.store if k.kf_id in self._seed_depths]:
            f = kf.frame
            n = self._seed(make_frame(f.color, self._seed_depths[kf.kf_id], f.intrinsics,
                                      f.T_world_cam, f.stamp_ns, frame_id=REPAIRED_FRAME_ID),
                           min_share)  # fmt: skip
            if n:
                grown[kf.kf_id] = n
        if grown and self._carves_seeds():
            self._carve_seeded()
        self.n_refilled += sum(grown.values())
        return grown

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
            self.optim.remove(seeded)
        self._forget_views()
        return removed

    def fidelity(self) -> dict[int, float]:
        """Per repaired view (keyframe id): PSNR dB of the map's render against the image it
        was fitted to, inside its mask; inf if identical (:func:`.refine.fidelity`)."""
        return _fidelity(self.store, self._keyframe_view, self.render)

    def _observed(self) -> list[Keyframe]:
        """The stored input keyframes (not repaired views), in store order."""
        return [kf for kf in self.store if kf.frame.frame_id != REPAIRED_FRAME_ID]

    def observed_ids(self) -> list[int]:
        """The ids of the stored input keyframes (not repaired views), in store order."""
        return [kf.kf_id for kf in self._observed()]

    def nearest_observed(self, T_world_cam: npt.ArrayLike, n: int) -> list[int]:
        """The ids of the ``n`` input keyframes (not repaired views) whose camera centres lie
        nearest the pose's, nearest first."""
        centre = np.asarray(T_world_cam, np.float64)[:3, 3]
        observed = self._observed()
        dist = [float(np.linalg.norm(kf.frame.T_world_cam[:3, 3] - centre)) for kf in observed]
        return [observed[i].kf_id for i in np.argsort(dist, kind="stable")[:n]]

    @torch.no_grad()
    def observed_psnr(self, kf_ids: list[int], downscale: int = 1) -> dict[int, float]:
        """Per input keyframe asked for (those still stored): PSNR dB of the map's render at
        its corrected pose, in its exposure (what the mapping loss compares), against the
        frame's colour over the whole image, both at 1/``downscale`` of the frame's size (the
        frame area-averaged); inf if identical."""
        by_id = {kf.kf_id: kf for kf in self._observed()}
        out: dict[int, float] = {}
        for kf_id in kf_ids:
            if kf_id not in by_id:
                continue
            view = downscale_view(self._keyframe_view(by_id[kf_id]), downscale)
            H, W = view.color.shape[:2]
            res = self.render(self._posed(view), view.K, W, H)
            pred = predicted_color(res, view, self.cfg.exposure).clamp(0, 1)
            mse = float(((pred - view.color) ** 2).mean())
            out[kf_id] = math.inf if mse == 0 else -10.0 * math.log10(mse)
        return out

    def polish(self, below_db: float | None = None) -> PolishResult:
        """Fit again the repaired views whose fidelity is under ``below_db`` (default
        ``polish_below_db``; 0: nothing): up to ``polish_iters`` steps each (fewer once it
        reaches ``polish_until_db``), every step with ``polish_partners`` random other
        repaired views and ``polish_keyframes`` random input keyframes, for up to
        ``polish_rounds`` rounds (:func:`.refine.polish`); with ``polish_refill`` it first
        seeds the holes opened since the views were distilled (:meth:`refill`) and polishes
        the views that got seeds whatever their fidelity."""
        cfg = self.cfg
        below = cfg.polish_below_db if below_db is None else below_db
        refilled = self.refill(cfg.polish_refill_share) if cfg.polish_refill and below > 0 else {}
        keyframes = list(self.store)
        by_id = {kf.kf_id: kf for kf in keyframes}

        def measure_one(kf_id: int) -> float:
            return _fidelity([by_id[kf_id]], self._keyframe_view, self.render)[kf_id]

        inputs = self._observed()

        def observed() -> list[TrainView]:
            n = min(cfg.polish_keyframes, len(inputs))
            pick = np.sort(self.rng.choice(len(inputs), n, replace=False)) if n else []
            return [downscale_view(self._keyframe_view(inputs[i]), cfg.refine_downscale)
                    for i in pick]  # fmt: skip

        res = _polish(
            keyframes, self._keyframe_view,
            lambda views, lam, l1: self.train_step(views, lam=lam, l1_weight=l1,
                                                   freeze_mapped=cfg.polish_freeze_mapped),
            self.fidelity, self.rng, below, cfg.polish_rounds, cfg.polish_iters,
            cfg.polish_partners, cfg.distill_lambda, cfg.polish_until_db,
            cfg.polish_check_every, measure_one, observed if cfg.polish_keyframes else None,
            force=refilled,
        )  # fmt: skip
        return dataclasses.replace(res, refilled=refilled)

    # -- snapshots ------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: map, optimizers, strategy, keyframes, counters, RNG."""
        last, last_T = self.kf_state.last_keyframe, self.kf_state.last_T_world_cam
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
            "kf_path_m": self.kf_state.path_m,
            "kf_last_pose": None if last_T is None else torch.from_numpy(last_T.copy()),
            "counters": {
                "n_frames": self.n_frames,
                "n_steps": self.n_steps,
                "n_nonfinite_steps": self.n_nonfinite_steps,
                "n_pruned": self.n_pruned,
                "n_capped": self.n_capped,
                "n_carved": self.n_carved,
                "n_pushed": self.n_pushed,
                "n_refilled": self.n_refilled,
                "n_split": self.n_split,
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
            "anchored": sorted(self._anchored),
            "seed_depths": {k: torch.from_numpy(d.copy()) for k, d in self._seed_depths.items()},
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
        self._judge_depths = {}
        shapes = state.get("repair_mask_shapes", {})  # absent in older snapshots
        self._repair_masks = {
            int(k): np.unpackbits(np.asarray(b.numpy()), count=int(np.prod(shapes[k])))
            .reshape(shapes[k])
            .astype(bool)
            for k, b in state.get("repair_masks", {}).items()
        }
        self._anchored = {int(k) for k in state.get("anchored", [])}  # absent in older ones
        self._seed_depths = {int(k): d.numpy().astype(np.float32)
                             for k, d in state.get("seed_depths", {}).items()}  # fmt: skip
        seeded = state.get("seeded")  # older snapshots kept distillation's seeds beside the map
        if "origin" not in state["map"] and seeded is not None:
            self.gmap.origin[seeded.to(self.device, torch.bool)] = ORIGIN_REPAIRED
        self.exposure, self.exposure_opt = {}, None
        for kf_id, params in state.get("exposure", {}).items():  # absent in older snapshots
            self.exposure_model.keep(int(kf_id), params.to(self.device))
        self.poses, self.pose_opt = {}, None
        for kf_id, xi in state.get("poses", {}).items():  # absent in older snapshots
            self.pose_refiner.keep(int(kf_id), xi)
        self.kf_state = initialize_state()
        self.kf_state.n_frames, self.kf_state.n_keyframes = state["kf_counts"]
        # the path so far (the share rule's gate); absent in older snapshots
        self.kf_state.path_m = float(state.get("kf_path_m", 0.0))
        if state.get("kf_last_pose") is not None:
            self.kf_state.last_T_world_cam = state["kf_last_pose"].numpy()
        if state["last_keyframe"] is not None:
            self.kf_state.last_keyframe = frame_from_dict(state["last_keyframe"])
        c = state["counters"]
        self.n_frames, self.n_steps = c["n_frames"], c["n_steps"]
        self.n_nonfinite_steps, self.n_pruned = c["n_nonfinite_steps"], c["n_pruned"]
        self.n_capped, self._non_kf_seen = c["n_capped"], c["non_kf_seen"]
        self.n_carved = c.get("n_carved", 0)  # absent in older snapshots
        self.n_pushed = c.get("n_pushed", 0)  # absent in older snapshots
        self.n_refilled = c.get("n_refilled", 0)
        self.n_split = c.get("n_split", 0)  # absent in older snapshots
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
            "refilled": self.n_refilled,
            "split": self.n_split,
            **self.pose_refiner.stats(self.store, self.scene_scale),
        }
