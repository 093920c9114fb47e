"""The map optimiser (optimize.py): a step lowers the loss, bad steps change nothing, growth is
capped, and which Gaussians were seeded stays aligned with the map."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from gsfix_online.mapping.splat.exposure import ExposureConfig
from gsfix_online.mapping.splat.gaussians import ORIGIN_REPAIRED, GaussianMap
from gsfix_online.mapping.splat.growth import grow
from gsfix_online.mapping.splat.optimize import DensifyConfig, LearningRates, MapOptimizer
from gsfix_online.mapping.splat.prune import PruneConfig
from gsfix_online.mapping.splat.views import downscale_view, frame_view, view_loss
from tests.mapping.splat.test_mapper import (
    CFG,
    H,
    W,
    one_thread,  # noqa: F401 -- autouse: one torch thread
    plane_frame,
)


def _grown(max_gaussians: int = 100_000, densify: bool = False) -> tuple[MapOptimizer, object]:
    torch.manual_seed(0)
    opt = MapOptimizer(GaussianMap(0, 3, "cpu"), LearningRates(), DensifyConfig(enabled=densify),
                       PruneConfig(), 1000, "cpu")  # fmt: skip
    opt.build(2.0)
    f = plane_frame()
    res = grow(f, CFG.growth, np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.float32))
    opt.add(res, max_gaussians)
    return opt, f


def _loss_of(opt: MapOptimizer):  # noqa: ANN202
    def loss_of(v):  # noqa: ANN001, ANN202
        out = opt.render(v.T_world_cam, v.K, v.color.shape[1], v.color.shape[0])
        return view_loss(out, v, 0.2, 1.0, 0.1, ExposureConfig(), 0.0), out

    return loss_of


def test_steps_lower_the_loss_of_a_grown_plane() -> None:
    opt, f = _grown()
    view = frame_view(f, opt.device)
    losses = [opt.step([view], _loss_of(opt)) for _ in range(15)]
    assert opt.n_steps == 15 and opt.n_nonfinite_steps == 0
    assert losses[-1] < 0.8 * losses[0], losses


def test_a_step_with_non_finite_gradients_changes_nothing() -> None:
    opt, f = _grown()
    view = frame_view(f, opt.device)
    before = {k: p.detach().clone() for k, p in opt.gmap.params.items()}

    def nan_loss(v):  # noqa: ANN001, ANN202
        loss, out = _loss_of(opt)(v)
        return loss * math.nan, out

    opt.step([view], nan_loss)
    assert opt.n_nonfinite_steps == 1
    assert all(torch.equal(before[k], p.detach()) for k, p in opt.gmap.params.items())


def test_growth_is_capped_and_counted() -> None:
    opt, _ = _grown(max_gaussians=10)
    assert len(opt.gmap) == 10 and opt.n_capped > 0


def test_provenance_follows_removal_and_densification() -> None:
    opt, f = _grown(densify=True)
    opt.strategy = dataclasses.replace(opt.strategy, refine_start_iter=0, refine_every=1,
                                       grow_grad2d=0.0)  # fmt: skip
    n = len(opt.gmap)
    opt.gmap.origin[: n // 2] = ORIGIN_REPAIRED
    opt.gmap.observations[:] = torch.where(opt.seeded(), 7, 3).int()
    gone = torch.zeros(n, dtype=torch.bool)
    gone[::3] = True
    assert opt.remove_carved(gone) == int(gone.sum()) and opt.n_carved == int(gone.sum())
    assert int(opt.seeded().sum()) == int((~gone[: n // 2]).sum())
    view = downscale_view(frame_view(f, opt.device), 1)
    opt.step([view], _loss_of(opt))  # every Gaussian is cloned or split
    assert len(opt.gmap) > n - int(gone.sum()) and len(opt.seeded()) == len(opt.gmap)
    assert 0 < int(opt.seeded().sum()) < len(opt.gmap)
    # a clone or a split keeps its parent's observation count
    seeded = opt.seeded()
    assert (opt.gmap.observations[seeded] == 7).all() and (
        opt.gmap.observations[~seeded] == 3
    ).all()


def test_a_bounded_seed_grows_to_its_bound_and_no_further() -> None:
    torch.manual_seed(0)
    opt = MapOptimizer(GaussianMap(0, 3, "cpu"), LearningRates(scales=0.05), DensifyConfig(enabled=False),
                       PruneConfig(), 1000, "cpu")  # fmt: skip
    opt.build(2.0)
    f = plane_frame()
    res = grow(f, CFG.growth, np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.float32))
    n = opt.add(res, 100_000)  # unbounded, as from an input frame
    opt.add(res, 100_000, ORIGIN_REPAIRED, scale_growth=1.5)
    grown = torch.from_numpy(res.log_scales).max(1).values
    bound = opt.gmap.max_log_scale
    assert torch.isinf(bound[:n]).all()
    assert torch.allclose(bound[n:], grown + math.log(1.5))

    def wider(v):  # noqa: ANN001, ANN202 -- a loss that rewards every Gaussian for growing
        out = opt.render(v.T_world_cam, v.K, v.color.shape[1], v.color.shape[0])
        return -opt.gmap.params["scales"].sum() + 0.0 * out.color.sum(), out

    view = frame_view(f, opt.device)
    for _ in range(20):  # Adam: about 0.05 a step, 1 in all
        opt.step([view], wider)
    s = opt.gmap.params["scales"].detach()
    # the bounded ones stand at their bound on every axis; the others grew past it
    assert torch.allclose(s[n:], bound[n:, None].expand(-1, 3))
    assert (s[:n].max(1).values > grown + math.log(1.5) + 0.1).all()
