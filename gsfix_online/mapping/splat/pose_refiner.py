"""Pose refinement: each keyframe's SE(3) correction, tracking of new frames, corrected poses.

:class:`PoseRefiner` holds the per-keyframe corrections (:mod:`.poses`, a ``[6]`` tensor each)
and their Adam. A new frame is first tracked against the frozen map
(:meth:`~PoseRefiner.track`); a keyframe keeps its correction as a parameter optimised with the
map (:meth:`~PoseRefiner.keep`); a pose given by the user takes the correction of the nearest
input keyframe (:meth:`~PoseRefiner.pose_for`). The scene scale is passed in: corrections are
stored in its units.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from gsfix_online.core.se3 import pose_distances
from gsfix_online.mapping.splat.keyframes import Keyframe
from gsfix_online.mapping.splat.optimize import drop_params, with_param
from gsfix_online.mapping.splat.poses import PoseConfig, clamp_, corrected, offsets, prior_loss
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID, TrainView, photometric_loss

# (T_world_cam [4, 4], K [3, 3], width, height, frozen=) -> the map's render
Render = Callable[..., RenderOutput]


class PoseRefiner:
    """kf_id -> [6] pose correction, optimised with the map (one Adam for them all)."""

    def __init__(self, cfg: PoseConfig, depth_weight: float, device: torch.device) -> None:
        self.cfg = cfg
        self.depth_weight = depth_weight  # per m, as the map's loss
        self.device = device
        self.poses: dict[int, Tensor] = {}
        self.opt: torch.optim.Optimizer | None = None

    def keep(self, kf_id: int, xi: Tensor) -> Tensor:  # [6] -> leaf, grad
        """Keep a keyframe's correction as a parameter optimised with the map."""
        p = xi.detach().clone().to(self.device, torch.float32).requires_grad_(True)
        self.poses[kf_id] = p
        self.opt = with_param(self.opt, p, self.cfg.lr)
        return p

    def clamp(self) -> None:
        """Keep every correction within its limits (after each optimiser step)."""
        for xi in self.poses.values():
            clamp_(xi, self.cfg)

    def forget(self, live: set[int]) -> None:
        """Drop the corrections of keyframes that left the store."""
        drop_params(self.poses, self.opt, live)

    def reset(self) -> None:
        self.poses, self.opt = {}, None

    # -- corrected poses ------------------------------------------------------------------------

    def keyframe_pose(self, kf: Keyframe, scene_scale: float) -> npt.NDArray[np.float64]:
        """[4, 4] the keyframe's pose with its correction (the front end's when it has none)."""
        T = torch.as_tensor(kf.frame.T_world_cam, dtype=torch.float64)
        xi = self.poses.get(kf.kf_id)
        if xi is None:
            return T.numpy()
        with torch.no_grad():
            return corrected(T, xi.detach().double().cpu(), scene_scale).numpy()

    def pose_for(
        self,
        T_world_cam: npt.ArrayLike,  # [4, 4] in the front end's frame
        keyframes: Iterable[Keyframe],
        rotation_weight_m: float,
        scene_scale: float,
    ) -> npt.NDArray[np.float64]:  # [4, 4]
        """A pose in the front end's frame moved as the map was: by the world-frame correction
        ``T_corrected @ inv(T_given)`` of the nearest input keyframe (translation plus rotation
        at ``rotation_weight_m``). The pose itself without corrections."""
        T = np.asarray(T_world_cam, np.float64)
        kfs = [kf for kf in keyframes if kf.frame.frame_id != REPAIRED_FRAME_ID]
        if not self.poses or not kfs:
            return T.copy()
        d = pose_distances(T, np.stack([kf.frame.T_world_cam for kf in kfs]),
                           rotation_weight_m)[0]  # fmt: skip
        kf = kfs[int(np.argmin(d))]
        if kf.kf_id not in self.poses:
            return T.copy()
        return self.keyframe_pose(kf, scene_scale) @ np.linalg.inv(kf.frame.T_world_cam) @ T

    def last_correction(self, keyframes: Iterable[Keyframe]) -> Tensor:  # [6]
        """The newest input keyframe's correction, else zero."""
        for kf in reversed(list(keyframes)):
            if kf.frame.frame_id != REPAIRED_FRAME_ID:
                xi = self.poses.get(kf.kf_id)
                return torch.zeros(6) if xi is None else xi.detach().cpu().clone()
        return torch.zeros(6)

    def corrections(
        self, keyframes: Iterable[Keyframe], scene_scale: float
    ) -> dict[int, tuple[float, float]]:
        """kf_id -> (translation m, rotation deg) of each corrected keyframe's correction."""
        out = {}
        for kf in keyframes:
            if kf.kf_id in self.poses:
                T = torch.as_tensor(kf.frame.T_world_cam, dtype=torch.float64)
                out[kf.kf_id] = offsets(T, torch.from_numpy(self.keyframe_pose(kf, scene_scale)))
        return out

    def stats(self, keyframes: Iterable[Keyframe], scene_scale: float) -> dict[str, float]:
        if not self.cfg.enabled:
            return {}
        c = list(self.corrections(keyframes, scene_scale).values())
        return {
            "pose_corrected": len(c),
            "pose_max_mm": 1000 * max((m for m, _ in c), default=0.0),
            "pose_max_deg": max((d for _, d in c), default=0.0),
        }

    # -- tracking -------------------------------------------------------------------------------

    def track_loss(
        self, render: Render, view: TrainView, xi: Tensor, mask: Tensor, scene_scale: float
    ) -> Tensor:
        """Photometric L1 plus depth L1 of the frozen map at the corrected pose, on ``mask``."""
        H, W = view.color.shape[:2]
        out = render(corrected(view.T_world_cam, xi, scene_scale), view.K, W, H, frozen=True)
        loss = photometric_loss(out.color, view.color, 0.0, 1.0, mask)
        if view.depth is not None and self.depth_weight > 0:
            valid = mask & (view.depth > 0)
            if bool(valid.any()):
                loss = loss + self.depth_weight * (out.depth - view.depth)[valid].abs().mean()
        return loss + self.cfg.prior * prior_loss(xi)

    def track(
        self, render: Render, view: TrainView, xi0: Tensor, scene_scale: float
    ) -> Tensor:  # [6]
        """The frame's correction fitted against the map alone (poses.py: tracking). It starts
        from the better of the front end's pose and the last keyframe's correction (``xi0``)
        and is kept only where it explains the frame better than both by ``track_margin``:
        tracking on a map that is still coarse must not walk the poses away (each frame would
        start from the last one's error)."""
        c = self.cfg
        zero = torch.zeros(6, device=self.device)
        xi0 = xi0.detach().to(self.device, torch.float32)
        H, W = view.color.shape[:2]

        def loss(xi: Tensor) -> Tensor:
            return self.track_loss(render, view, xi, mask, scene_scale)

        with torch.no_grad():
            out = render(corrected(view.T_world_cam, xi0, scene_scale), view.K, W, H)
            mask = out.alpha > 0.9
            if c.track_iters == 0 or float(mask.float().mean()) < c.track_min_covered:
                return zero
            starts = {"given": (zero, float(loss(zero)))}
            if bool(xi0.any()):
                starts["last"] = (xi0, float(loss(xi0)))
        start, best = min(starts.values(), key=lambda s: s[1])
        xi = start.clone().requires_grad_(True)
        opt = torch.optim.Adam([xi], lr=c.track_lr, eps=1e-15)
        for _ in range(c.track_iters):
            opt.zero_grad(set_to_none=True)
            loss(xi).backward()
            if xi.grad is None or not bool(torch.isfinite(xi.grad).all()):
                break
            opt.step()
            clamp_(xi, c)
        with torch.no_grad():
            tracked = float(loss(xi))
        if tracked < (1.0 - c.track_margin) * best:
            return xi.detach()
        return start
