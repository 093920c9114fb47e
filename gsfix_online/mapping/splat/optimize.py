"""The map and its optimisation: Adam per parameter, gsplat densification, pruning, one step.

:class:`MapOptimizer` holds the Gaussian map with what changes it: one Adam per parameter,
gsplat's ``DefaultStrategy`` and its per-Gaussian statistics (kept aligned, with the map's
per-Gaussian provenance, through every structural edit), and the counters of what it did. Its
:meth:`~MapOptimizer.step` runs one Adam step on the mean loss of some views; the caller says
how each view is scored (:func:`.views.view_loss` at the view's pose) and which per-view
parameters (exposure, pose corrections) step with the map. It does no IO and reads no clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from gsfix_online.core.config import rng
from gsfix_online.mapping.splat.gaussians import (
    META_DTYPES,
    ORIGIN_OBSERVED,
    PARAM_KEYS,
    UNBOUNDED,
    GaussianMap,
)
from gsfix_online.mapping.splat.growth import GrowthResult
from gsfix_online.mapping.splat.prune import PruneConfig, prune
from gsfix_online.mapping.splat.render import Backend, render
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import TrainView

NEVER = 2**62  # a DefaultStrategy step count that is never reached (disables a schedule)


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


ViewLoss = Callable[[TrainView], tuple[Tensor, RenderOutput]]


class MapOptimizer:
    """The Gaussian map, its optimizers and densification state; see module doc."""

    def __init__(
        self,
        gmap: GaussianMap,
        lr: LearningRates,
        densify: DensifyConfig,
        prune_cfg: PruneConfig,
        prune_every: int,
        backend: Backend,
    ) -> None:
        self.gmap = gmap
        self.lr, self.densify, self.prune_cfg = lr, densify, prune_cfg
        self.prune_every, self.backend = prune_every, backend
        self.device = gmap.device
        self.n_steps = 0
        self.n_nonfinite_steps = 0
        self.n_pruned = 0
        self.n_carved = 0  # Gaussians a keyframe's depth saw through (CarveConfig)
        self.n_capped = 0  # Gaussians growth wanted but max_gaussians refused
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.strategy: Any = None
        self.strategy_state: dict[str, Any] = {}

    def build(self, scene_scale: float) -> None:
        """(Re)build the optimizers and the strategy for the current map and scene scale."""
        lr = self.lr
        rates = {
            "means": lr.means * max(scene_scale, 1e-6),
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
        if self.densify.enabled:
            from gsplat.strategy import DefaultStrategy

            d = self.densify
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
            self.strategy_state = self.strategy.initialize_state(scene_scale=max(scene_scale, 1e-6))

    # -- structure ------------------------------------------------------------------------------

    def resize_state(self, keep: Tensor | None = None, n_new: int = 0) -> None:
        """Keep the strategy's per-Gaussian statistics aligned with structural edits."""
        for key in ("grad2d", "count", "radii"):
            v = self.strategy_state.get(key)
            if v is None:
                continue
            if keep is not None:
                v = v[keep]
            if n_new:
                v = torch.cat([v, v.new_zeros(n_new)])
            self.strategy_state[key] = v

    @torch.no_grad()
    def bound_scales(self) -> None:
        """Clamp every bounded Gaussian's log-scales to its ``max_log_scale`` (gaussians doc)."""
        cap = self.gmap.max_log_scale
        if cap.numel() and bool(torch.isfinite(cap).any()):
            s = self.gmap.params["scales"]
            s.copy_(torch.minimum(s, cap[:, None]))

    def seeded(self) -> Tensor:  # [N] bool, a copy
        """Which Gaussians distillation grew from a repaired view's seed depth (a guess where
        no map holds anything; their origin, kept through growth, pruning, carving and
        densification)."""
        return self.gmap.repaired()

    def add(
        self, res: GrowthResult, max_gaussians: int, origin: int = ORIGIN_OBSERVED,
        observations: int = 0, scale_growth: float = 0.0,
    ) -> int:  # fmt: skip
        """Add grown Gaussians up to ``max_gaussians`` in all, with their origin and how many
        input frames saw them (growth from a frame: that one), their scales bounded by
        ``scale_growth`` times their grown scale (0: unbounded); returns how many were added."""
        m = min(len(res), max_gaussians - len(self.gmap))
        self.n_capped += len(res) - max(m, 0)
        if m <= 0:
            return 0
        self.gmap.add(
            res.means[:m], res.log_scales[:m], res.quats[:m], res.opacity_logits[:m],
            res.sh0[:m], optimizers=self.optimizers, origin=origin, observations=observations,
            max_log_scale=res.log_scales[:m].max(axis=1) + math.log(scale_growth)
            if scale_growth > 0 else UNBOUNDED,
        )  # fmt: skip
        self.resize_state(n_new=m)
        return m

    def remove(self, mask: Tensor) -> None:  # [N] bool
        """Remove Gaussians (not counted)."""
        self.gmap.remove(mask, self.optimizers)
        self.resize_state(keep=~mask)

    def split(self, mask: Tensor, seed: int) -> int:  # [N] bool -> how many were split
        """Split each chosen Gaussian in two as gsplat's densification does (children drawn
        from the parent, scales / 1.6, Adam's moments zeroed); the children keep the parent's
        provenance and scale bound and go to the end of the map. ``seed`` draws the children
        (the global torch RNG is left as it was). Not counted."""
        from gsplat.strategy.ops import split

        n = int(mask.sum())
        if not n:
            return 0
        state = {**self.strategy_state, **self.gmap.meta}
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            split(self.gmap.params, self.optimizers, state, mask)
        self.gmap.set_meta({k: state.pop(k) for k in META_DTYPES})
        self.strategy_state.update(state)
        return n

    def remove_carved(self, mask: Tensor) -> int:  # [N] bool -> how many went
        n = int(mask.sum())
        if n:
            self.remove(mask)
            self.n_carved += n
        return n

    def prune(self) -> None:
        before = len(self.gmap)
        result = prune(self.gmap, self.prune_cfg, self.optimizers)
        if result.n_pruned:
            assert len(self.gmap) == before - result.n_pruned
            self.resize_state(keep=~result.mask)
            self.n_pruned += result.n_pruned

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
            return RenderOutput(torch.zeros((height, width, g.channels), device=dev), z, z.clone())
        tensors = (g.means, g.params["quats"], g.scales, g.opacities, g.sh)
        if frozen:
            tensors = tuple(t.detach() for t in tensors)
        if keep is not None:
            tensors = tuple(t[keep] for t in tensors)
        return render(
            *tensors, None, Kt, width, height,
            T_world_cam=T, backend=self.backend, sh_degree=g.sh_degree,
        )  # fmt: skip

    # -- one step -------------------------------------------------------------------------------

    def step(
        self,
        views: Sequence[TrainView],
        loss_of: ViewLoss,  # a view -> (its loss, the render it scored)
        extra_optimizers: Sequence[torch.optim.Optimizer] = (),  # per-view parameters' Adams
        extra_params: Sequence[Tensor] = (),  # their parameters (checked for finite gradients)
        freeze_mapped: bool = False,  # repaired views train only the seeded Gaussians
        after_update: Callable[[], None] | None = None,  # right after the Adam steps
    ) -> float:
        """One Adam step on the mean loss of ``views``; the first view feeds densification.

        Returns the loss; a step whose loss or gradients are not finite changes nothing and is
        counted in ``n_nonfinite_steps``.
        """
        assert views
        if len(self.gmap) == 0:
            return math.nan
        self.n_steps += 1
        opts = [*self.optimizers.values(), *extra_optimizers]
        for opt in opts:
            opt.zero_grad(set_to_none=True)
        # With freeze_mapped, repaired views' gradients reach only the seeded Gaussians: their
        # loss is back-propagated first and the other rows' gradients are cleared before the
        # keyframes' loss adds its own.
        freeze = freeze_mapped and any(v.repaired for v in views)
        totals = {False: torch.zeros((), device=self.device)}
        if freeze:
            totals[True] = torch.zeros((), device=self.device)
        info = None
        for i, view in enumerate(views):
            loss, out = loss_of(view)
            if i == 0:
                info = out.info
                if self.strategy is not None:
                    self.strategy.step_pre_backward(
                        self.gmap.params, self.optimizers, self.strategy_state, self.n_steps, info
                    )
            key = freeze and view.repaired
            totals[key] = totals[key] + loss / len(views)
        total = sum(totals.values(), torch.zeros((), device=self.device))
        params = [*self.gmap.params.values(), *extra_params]
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
        if after_update is not None:
            after_update()
        if kept:
            with torch.no_grad():
                for k, v in kept.items():
                    self.gmap.params[k][mapped] = v
        self.bound_scales()
        if self.strategy is not None and info is not None:
            n_before = len(self.gmap)
            # gsplat edits every per-Gaussian tensor of its state with the map: the
            # Gaussians' provenance rides along through clones, splits and pruning
            self.strategy_state.update(self.gmap.meta)
            self.strategy.step_post_backward(
                self.gmap.params, self.optimizers, self.strategy_state, self.n_steps, info
            )
            self.gmap.set_meta({k: self.strategy_state.pop(k) for k in META_DTYPES})
            assert len(self.gmap) == len(self.strategy_state["grad2d"]) or n_before == 0
        if self.n_steps % self.prune_every == 0:
            self.prune()
        return float(total.detach())


def with_param(opt: torch.optim.Optimizer | None, p: Tensor, lr: float) -> torch.optim.Optimizer:
    """``opt`` with one more per-view parameter ``p`` (a new Adam at ``lr`` when None)."""
    if opt is None:
        return torch.optim.Adam([p], lr=lr, eps=1e-15)
    opt.add_param_group({"params": [p]})
    return opt


def drop_params(
    params: dict[int, Tensor], opt: torch.optim.Optimizer | None, live: set[int]
) -> None:
    """Remove the per-view parameters of views no longer in ``live`` (and their Adam state)."""
    for kf_id in [k for k in params if k not in live]:
        p = params.pop(kf_id)
        assert opt is not None
        opt.param_groups = [g for g in opt.param_groups if g["params"][0] is not p]
        opt.state.pop(p, None)
