"""Pruning thresholds: transparent, huge, tiny, non-finite, too large on screen."""

from __future__ import annotations

import math

import pytest
import torch

from gsfix_online.core.config import ConfigError, build
from gsfix_online.mapping.splat.gaussians import PARAM_KEYS, GaussianMap
from gsfix_online.mapping.splat.mapper import Mapper
from gsfix_online.mapping.splat.prune import (
    CarveConfig,
    PruneConfig,
    carve_mask,
    hidden_mask,
    prune,
    prune_mask,
    push_behind,
)

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


# ----------------------------------------------------------------------------------------------
# Free-space carving
# ----------------------------------------------------------------------------------------------

CARVE = CarveConfig(enabled=True, margin_m=0.05, margin_rel=0.1, window_px=5, extent_sigmas=2.0)
CW, CH, CF = 40, 30, 30.0
CK = torch.tensor([[CF, 0, (CW - 1) / 2], [0, CF, (CH - 1) / 2], [0, 0, 1.0]])


def plane_depth() -> torch.Tensor:  # [H, W]: a wall at 2 m, a box at 1 m in the right quarter
    d = torch.full((CH, CW), 2.0)
    d[:, 30:] = 1.0
    d[0:3, 0:3] = 0.0  # no depth measured here
    return d


def test_carve_mask_analytic() -> None:
    def at(u: float, v: float, z: float) -> list[float]:  # a point seen at pixel (u, v), depth z
        return [(u - CK[0, 2].item()) / CF * z, (v - CK[1, 2].item()) / CF * z, z]

    points = {
        "on the wall": (at(10, 15, 2.0), 0.01, False),
        "within the margin": (at(10, 15, 1.8), 0.01, False),  # 2 m - 0.2 m margin
        "floater": (at(10, 15, 1.0), 0.01, True),
        "large, reaching the wall": (at(10, 15, 1.6), 0.1, False),  # 1.6 + 2 sigma = 1.8
        "behind the wall (occluded)": (at(10, 15, 3.0), 0.01, False),
        "near the box's edge": (at(28, 15, 1.5), 0.01, False),  # the box is within 2 px
        "in front of the box": (at(35, 15, 0.5), 0.01, True),
        "no depth there": (at(1, 1, 1.0), 0.01, False),
        "outside the image": (at(-5, 15, 1.0), 0.01, False),
        "behind the camera": ([0.0, 0.0, -1.0], 0.01, False),
    }
    means = torch.tensor([p for p, _, _ in points.values()])
    log_scales = torch.log(torch.tensor([[s, s / 2, s / 4] for _, s, _ in points.values()]))
    mask = carve_mask(means, log_scales, plane_depth(), CK, torch.eye(4), CARVE)
    want = [c for _, _, c in points.values()]
    assert mask.tolist() == want, dict(zip(points, mask.tolist(), strict=True))


def test_carve_mask_footprint_judges_near_gaussians_just_outside_the_image() -> None:
    """A Gaussian close to the camera, centred just left of the image, covers much of it: with
    ``footprint`` it is judged at the nearest image pixel (the wall at 2 m is behind it, so it
    is carved); a small one there, which does not reach the image, is not."""

    def at(u: float, v: float, z: float) -> list[float]:
        return [(u - CK[0, 2].item()) / CF * z, (v - CK[1, 2].item()) / CF * z, z]

    means = torch.tensor([at(-20, 15, 0.3), at(-20, 15, 0.3), at(10, 15, 1.0)])
    sig = torch.tensor([[0.1, 0.1, 0.1], [0.005, 0.005, 0.005], [0.01, 0.01, 0.01]])
    # the first reaches 2 sigma = 0.2 m = 20 px at 0.3 m: into the image from 20 px outside
    plain = carve_mask(means, sig.log(), plane_depth(), CK, torch.eye(4), CARVE)
    near = carve_mask(means, sig.log(), plane_depth(), CK, torch.eye(4), CARVE, footprint=True)
    assert plain.tolist() == [False, False, True]
    assert near.tolist() == [True, False, True]


def test_carve_mask_any_pose() -> None:
    """The same floater in world coordinates is found from a moved camera."""
    from gsfix_online.core.se3 import look_at

    T = torch.tensor(look_at([1.0, 2.0, 0.5], [3.0, 1.0, 1.5]), dtype=torch.float32)
    p_cam = torch.tensor([[0.1, -0.05, 1.0], [0.1, -0.05, 2.0]])
    means = p_cam @ T[:3, :3].T + T[:3, 3]
    mask = carve_mask(means, torch.full((2, 3), math.log(0.01)), plane_depth(), CK, T, CARVE)
    assert mask.tolist() == [True, False]


def test_mapper_carves_a_floater_seen_through_by_keyframes() -> None:
    """A floater half-way to a textured plane that later keyframes see through is removed; the
    plane's Gaussians stay."""
    import dataclasses

    from tests.mapping.splat.test_mapper import CFG as MCFG
    from tests.mapping.splat.test_mapper import plane_frame

    every = dataclasses.replace(MCFG.keyframes, min_new_gaussians=0, min_overlap=0.95)
    cfg = dataclasses.replace(MCFG, kf_iters=0, keyframes=every, carve=CARVE)
    mapper = Mapper(cfg)
    mapper.process(plane_frame(0.0, 0))
    n_plane = len(mapper.gmap)
    floater = torch.tensor([[0.05, 0.02, 1.0]])  # on the line of sight of the next views
    mapper.gmap.add(
        floater, torch.full((1, 3), math.log(0.02)), torch.tensor([[1.0, 0, 0, 0]]),
        torch.tensor([2.0]), torch.zeros(1, 1, 3), optimizers=mapper.optimizers,
    )  # fmt: skip
    res = mapper.process(plane_frame(0.3, 1))  # 6 px over: a keyframe that sees the floater
    assert res.is_keyframe and mapper.n_carved == 1
    means = mapper.gmap.means.detach()
    assert not bool(((means - floater).norm(dim=1) < 1e-6).any())
    assert len(mapper.gmap) == n_plane + res.n_new_gaussians  # nothing of the plane went
    assert mapper.stats()["carved"] == 1


def test_hidden_mask_analytic() -> None:
    def at(u: float, v: float, z: float) -> list[float]:
        return [(u - CK[0, 2].item()) / CF * z, (v - CK[1, 2].item()) / CF * z, z]

    points = {  # margin: max(0.05, 0.1 x 2 m) = 0.2 m behind the wall at 2 m
        "in front of the wall": (at(10, 15, 1.0), False),
        "on the wall": (at(10, 15, 2.0), False),
        "within the margin behind": (at(10, 15, 2.15), False),
        "behind the wall by the margin": (at(10, 15, 2.25), True),
        "behind the box": (at(35, 15, 1.5), True),  # box at 1 m: margin 0.1 m
        "no depth there": (at(1, 1, 1.0), True),
        "outside the image": (at(-5, 15, 1.0), True),
        "behind the camera": ([0.0, 0.0, -1.0], True),
    }
    pts = torch.tensor([p for p, _ in points.values()])
    got = hidden_mask(pts, plane_depth(), CK, torch.eye(4), CARVE)
    assert got.tolist() == [h for _, h in points.values()], dict(
        zip(points, got.tolist(), strict=True)
    )
    # any leading shape: [S, M, 3] -> [S, M]
    assert hidden_mask(pts.expand(3, -1, -1), plane_depth(), CK, torch.eye(4), CARVE).shape == (
        3, len(points),
    )  # fmt: skip


def test_push_behind_moves_seeds_along_their_ray_until_no_view_sees_them() -> None:
    """A second camera 1 m to the left of the judging one, both looking along +z at the wall
    (2 m; the box at 1 m on the right). Seeds on the second camera's rays: one at 1 m, in front
    of the wall, goes just past wall + margin (2.2 m: factor 2.2), one already behind the wall stays
    (1), one whose ray never enters the judging view's image stays (1)."""
    origin = torch.tensor([-1.0, 0.0, 0.0])
    seeds = torch.tensor(
        [
            [-0.6, 0.0, 1.0],  # ray crosses the judging view's free space in front of the wall
            [-0.2, 0.0, 2.5],  # behind the wall already
            [-3.0, 0.0, 1.0],  # out of the judging view's image at every factor
        ]
    )
    views = [(plane_depth(), CK, torch.eye(4))]
    f = push_behind(seeds, origin, views, CARVE, max_factor=3.0, n_steps=200)
    moved = origin + f[:, None] * (seeds - origin)
    assert f[1].item() == 1.0 and f[2].item() == 1.0
    # the first lands past 2.2 m (wall + 0.2 m margin), on the first grid step beyond it
    z = moved[0, 2].item()
    step = 3.0 ** (1 / 199)
    assert 2.2 <= z < 2.2 * step + 1e-6, z
    assert bool(hidden_mask(moved, plane_depth(), CK, torch.eye(4), CARVE).all())
    # seen at every factor (a wall far behind): left where it was
    far = torch.full((CH, CW), 50.0)
    assert push_behind(seeds[:1], origin, [(far, CK, torch.eye(4))], CARVE).item() == 1.0
    # no views: nothing moves
    assert push_behind(seeds, origin, [], CARVE).tolist() == [1.0, 1.0, 1.0]


def test_nearest_surface_filters_once_per_depth_and_again_after_a_change() -> None:
    from gsfix_online.mapping.splat.prune import nearest_surface

    d = torch.full((9, 12), 3.0)
    d[4, 6] = 1.0
    d[0, :] = 0.0  # unmeasured
    a = nearest_surface(d, 5)
    assert nearest_surface(d, 5) is a  # the same tensor: filtered once
    assert float(a[2:7, 4:9].max()) == 1.0 and float(a[4, 9]) == 3.0  # a 5x5 min around (4, 6)
    assert float(a[0, 0]) == 3.0  # unmeasured pixels take their measured neighbours
    assert torch.isinf(nearest_surface(torch.zeros(4, 4), 3)).all()  # none measured
    assert float(nearest_surface(d, 3)[4, 8]) == 3.0  # another window, another filter
    d[8, 0] = 0.5  # changed in place: filtered again
    b = nearest_surface(d, 5)
    assert b is not a and float(b[7, 1]) == 0.5
    assert float(nearest_surface(d.clone(), 5)[7, 1]) == 0.5
