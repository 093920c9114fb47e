"""The exposure model: each keyframe's affine colour, fitted in closed form and optimised.

:class:`ExposureModel` holds the per-keyframe exposure parameters (:mod:`.exposure`, a
``[2, C]`` tensor each) and their Adam. A new frame's exposure against the canonical map comes
in closed form (:meth:`~ExposureModel.estimate`); a keyframe keeps it as a parameter optimised
with the map (:meth:`~ExposureModel.keep`); the canonical exposure is re-centred on the
keyframes' mean gain (:meth:`~ExposureModel.recenter`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from gsfix_online.mapping.splat.exposure import ExposureConfig, apply_affine, fit_affine
from gsfix_online.mapping.splat.gaussians import SH_C0, GaussianMap
from gsfix_online.mapping.splat.optimize import drop_params, with_param
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import TrainView


class ExposureModel:
    """kf_id -> [2, C] exposure, optimised with the map (one Adam for them all)."""

    def __init__(self, cfg: ExposureConfig, device: torch.device) -> None:
        self.cfg = cfg
        self.device = device
        self.params: dict[int, Tensor] = {}
        self.opt: torch.optim.Optimizer | None = None

    def estimate(self, out: RenderOutput, view: TrainView) -> Tensor:  # [2, C]
        """The frame's exposure against the canonical map, in closed form (exposure.py): where
        the render is opaque, then again without the pixels that fit worst (new content,
        occlusions, moving light)."""
        e, C = self.cfg, out.color.shape[-1]
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

    def keep(self, kf_id: int, params: Tensor) -> Tensor:  # [2, C] -> leaf, grad
        """Keep a keyframe's exposure as a parameter optimised with the map."""
        p = params.detach().clone().requires_grad_(True)
        self.params[kf_id] = p
        self.opt = with_param(self.opt, p, self.cfg.lr)
        return p

    @torch.no_grad()
    def recenter(self, gmap: GaussianMap) -> None:
        """Move the canonical exposure to the keyframes' mean gain (an exact change of gauge:
        every colour times the mean gain, every keyframe's gain divided by it), so that renders
        of new views show the average exposure, as the TSDF's averaged colours do, rather than
        the first frame's."""
        if not self.params:
            return
        mu = torch.stack([p[0] for p in self.params.values()]).mean(0)  # [C] log-gain
        g = mu.exp()
        sh0, shN = gmap.params["sh0"], gmap.params["shN"]
        sh0.copy_(((sh0 * SH_C0 + 0.5) * g - 0.5) / SH_C0)
        shN.mul_(g)
        for p in self.params.values():
            p[0].sub_(mu)

    def forget(self, live: set[int]) -> None:
        """Drop the exposures of keyframes that left the store."""
        drop_params(self.params, self.opt, live)

    def reset(self) -> None:
        self.params, self.opt = {}, None
