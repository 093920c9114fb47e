"""Carving (carving.py): what a view's depth sees through goes, what lies behind stays; seeds
are judged by the stored views and pushed behind what they see."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsfix_online.mapping.splat.carving import carve_seeded, carve_view, push_seeds
from gsfix_online.mapping.splat.gaussians import ORIGIN_REPAIRED, GaussianMap
from gsfix_online.mapping.splat.growth import GrowthResult
from gsfix_online.mapping.splat.optimize import DensifyConfig, LearningRates, MapOptimizer
from gsfix_online.mapping.splat.prune import CarveConfig, PruneConfig
from gsfix_online.mapping.splat.views import frame_view
from tests.mapping.splat.test_mapper import Z, plane_frame

CARVE = CarveConfig(enabled=True)


def _map(zs: list[float]) -> MapOptimizer:
    """Gaussians of 5 mm on the camera's axis at depths ``zs`` (the plane camera at x = 0)."""
    opt = MapOptimizer(GaussianMap(0, 3, "cpu"), LearningRates(), DensifyConfig(enabled=False),
                       PruneConfig(), 1000, "cpu")  # fmt: skip
    n = len(zs)
    opt.gmap.add(
        np.array([[0.0, 0.0, z] for z in zs], np.float32), np.full((n, 3), np.log(0.005), np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.zeros(n, np.float32),
        np.zeros((n, 1, 3), np.float32),
    )  # fmt: skip
    opt.build(Z)
    return opt


def _judge() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    v = frame_view(plane_frame(), torch.device("cpu"))
    assert v.depth is not None
    return v.depth, v.K, v.T_world_cam


def test_a_view_carves_what_it_saw_through_and_keeps_what_lies_behind() -> None:
    opt = _map([1.0, Z, 2.5])  # in front of the plane (z = 2), on it, behind it
    depth, K, T = _judge()
    assert carve_view(opt, depth, K, T, CARVE) == 1 and opt.n_carved == 1
    np.testing.assert_allclose(opt.gmap.means[:, 2].detach().numpy(), [Z, 2.5])


def test_only_seeded_gaussians_are_judged() -> None:
    opt = _map([1.0, 1.2, Z])
    opt.gmap.origin[1] = ORIGIN_REPAIRED  # the seed at 1.2 m; the mapped one at 1 m is left alone
    assert carve_seeded(opt, [_judge()], CARVE) == 1
    np.testing.assert_allclose(opt.gmap.means[:, 2].detach().numpy(), [1.0, Z])
    assert not bool(opt.seeded().any())


def test_seeds_are_pushed_along_their_ray_behind_what_a_view_sees() -> None:
    # a seed grown from a camera 1 m to the side, at 1.5 m: the plane camera sees through it
    origin = np.array([1.0, 0.0, 0.0])
    T = np.eye(4)
    T[:3, 3] = origin
    seed = np.float32([[0.0, 0.0, 1.5]])
    res = GrowthResult(seed, np.full((1, 3), np.log(0.005), np.float32),
                       np.float32([[1, 0, 0, 0]]), np.zeros(1, np.float32),
                       np.zeros((1, 1, 3), np.float32), np.zeros((1, 4), np.int32), 1, 0, 0)  # fmt: skip
    pushed, n = push_seeds(res, T, [_judge()], CARVE, 3.0)
    assert n == 1
    d0 = seed[0] - origin
    d1 = pushed.means[0] - origin
    cos = float(d0 @ d1 / np.linalg.norm(d0) / np.linalg.norm(d1))
    assert cos == pytest.approx(1.0, abs=1e-6)  # on its own ray
    assert np.linalg.norm(d1) > np.linalg.norm(d0) and pushed.means[0, 2] > Z  # behind the plane
    assert pushed.log_scales[0, 0] > res.log_scales[0, 0]  # scaled with the distance
    same, n = push_seeds(res, T, [], CARVE, 3.0)
    assert same is res and n == 0
