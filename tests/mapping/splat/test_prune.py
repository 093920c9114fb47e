"""Pruning thresholds: transparent, huge, tiny, non-finite, too large on screen."""

from __future__ import annotations

import math

import pytest
import torch

from gsfix_online.config_schema import ConfigError, build
from gsfix_online.mapping.splat.gaussians import PARAM_KEYS, GaussianMap
from gsfix_online.mapping.splat.prune import PruneConfig, prune, prune_mask

CFG = PruneConfig(min_opacity=0.01, max_scale_m=0.5, min_scale_m=1e-4, max_radius_px=100.0)


def logit(p: float) -> float:
    return math.log(p / (1 - p))


def make_map(opacities: list[float], max_scales: list[float]) -> GaussianMap:
    n = len(opacities)
    largest = torch.tensor(max_scales, dtype=torch.float64)[:, None]
    log_scales = torch.log(largest * torch.tensor([0.5, 1.0, 0.25], dtype=torch.float64)).float()
    return GaussianMap.from_tensors(
        torch.arange(3 * n, dtype=torch.float32).reshape(n, 3),
        log_scales,
        torch.tensor([[1.0, 0, 0, 0]] * n),
        torch.tensor([logit(p) for p in opacities], dtype=torch.float32),
        torch.zeros(n, 1, 3),
        sh_degree=1,
    )


def test_thresholds_per_reason() -> None:
    #                   keep   transp  huge  tiny  keep(at max) keep(at min opacity-ish)
    opac = [0.5, 0.005, 0.5, 0.5, 0.5, 0.02]
    scales = [0.01, 0.01, 0.6, 5e-5, 0.5 * 0.999, 0.01]
    gmap = make_map(opac, scales)
    res = prune(gmap, CFG)
    assert res.mask.tolist() == [False, True, True, True, False, False]
    assert (res.n_transparent, res.n_huge, res.n_tiny, res.n_nonfinite) == (1, 1, 1, 0)
    assert res.n_pruned == 3 and len(gmap) == 3
    # the survivors are rows 0, 4, 5 in order
    assert gmap.means[:, 0].tolist() == [0.0, 12.0, 15.0]


def test_scale_uses_largest_axis() -> None:
    # one axis tiny, another normal: a flat disc, not a tiny Gaussian
    log_scales = torch.log(
        torch.tensor([[1e-7, 1e-2, 1e-2], [1e-7, 1e-7, 1e-7], [1e-2, 1e-2, 2.0]])
    )
    res = prune_mask(torch.zeros(3), log_scales, CFG)
    assert res.mask.tolist() == [False, True, True]
    assert (res.n_tiny, res.n_huge) == (1, 1)


def test_extreme_values_do_not_overflow() -> None:
    logits = torch.tensor([-1e4, 1e4, 0.0])
    log_scales = torch.tensor([[0.0] * 3, [-1e4] * 3, [1e4] * 3]) + math.log(0.01)
    res = prune_mask(logits, log_scales, CFG)
    assert res.mask.tolist() == [True, True, True]
    assert (res.n_transparent, res.n_tiny, res.n_huge) == (1, 1, 1)


def test_nonfinite_and_screen_radius() -> None:
    gmap = make_map([0.5] * 4, [0.01] * 4)
    with torch.no_grad():
        gmap.params["sh0"][1, 0, 2] = float("nan")
        gmap.params["quats"][2, 0] = float("inf")
    res = prune(gmap, CFG, radii_px=torch.tensor([10.0, 10.0, 10.0, 101.0]))
    assert (res.n_nonfinite, res.n_large_on_screen, res.n_pruned) == (2, 1, 3)
    assert len(gmap) == 1 and torch.isfinite(gmap.params["sh0"]).all()
    off = PruneConfig(max_radius_px=0.0)
    gmap = make_map([0.5], [0.01])
    assert prune(gmap, off, radii_px=torch.tensor([1e6])).n_pruned == 0


def test_prune_updates_optimizer_state() -> None:
    gmap = make_map([0.5, 0.001, 0.5], [0.01] * 3)
    opts = {k: torch.optim.Adam([gmap.params[k]], lr=1e-3) for k in PARAM_KEYS}
    sum((gmap.params[k] ** 2).sum() for k in PARAM_KEYS).backward()
    for o in opts.values():
        o.step()
    prune(gmap, CFG, optimizers=opts)
    assert opts["opacities"].state[gmap.params["opacities"]]["exp_avg"].shape == (2,)


def test_empty_map_and_validation() -> None:
    assert prune(GaussianMap(), CFG).n_pruned == 0
    with pytest.raises(ValueError, match=r"radii_px must be \[2\]"):
        prune(make_map([0.5, 0.5], [0.01] * 2), CFG, radii_px=torch.zeros(3))
    with pytest.raises(ConfigError, match="min_scale_m 2.0 must be below max_scale_m 1.0"):
        build(PruneConfig, overrides=["min_scale_m=2.0"])
