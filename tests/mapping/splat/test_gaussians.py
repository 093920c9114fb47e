"""GaussianMap: activations, add/remove/select with optimizer state, state-dict snapshots."""

from __future__ import annotations

import math

import pytest
import torch

from gsfix_online.mapping.splat.gaussians import (
    ORIGIN_OBSERVED,
    ORIGIN_REPAIRED,
    PARAM_KEYS,
    SH_C0,
    GaussianMap,
    GaussianMapError,
    normalize_quats,
    rgb_to_sh0,
    sh0_to_rgb,
)


def random_map(n: int = 10, sh_degree: int = 1, channels: int = 3, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    return GaussianMap.from_tensors(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 3, generator=g) - 3,
        torch.randn(n, 4, generator=g),
        torch.randn(n, generator=g),
        torch.randn(n, 1, channels, generator=g),
        torch.randn(n, k - 1, channels, generator=g),
        sh_degree=sh_degree,
    )


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
@pytest.mark.parametrize("channels", [1, 3])
def test_shapes_and_activations(sh_degree: int, channels: int) -> None:
    gmap = random_map(7, sh_degree, channels)
    k = (sh_degree + 1) ** 2
    assert len(gmap) == 7
    assert gmap.params["shN"].shape == (7, k - 1, channels)
    assert gmap.sh.shape == (7, k, channels)
    torch.testing.assert_close(gmap.scales, torch.exp(gmap.params["scales"]))
    torch.testing.assert_close(gmap.opacities, torch.sigmoid(gmap.params["opacities"]))
    torch.testing.assert_close(gmap.quats.norm(dim=-1), torch.ones(7))


def test_empty_map() -> None:
    gmap = GaussianMap(sh_degree=3, channels=1)
    assert len(gmap) == 0
    assert gmap.params["shN"].shape == (0, 15, 1)
    assert gmap.sh.shape == (0, 16, 1)


def test_quaternion_normalisation_in_graph() -> None:
    q = torch.tensor([[2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    q.requires_grad_(True)
    out = normalize_quats(q)
    torch.testing.assert_close(
        out.detach(), torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]])
    )
    out[:, 1].sum().backward()
    assert torch.isfinite(q.grad).all()
    torch.testing.assert_close(q.grad[1], torch.zeros(4))  # the zero quaternion gets no gradient
    # d(q/|q|)/dq for q = (2, 0, 0, 0): the x component's derivative is 1/|q| = 0.5
    torch.testing.assert_close(q.grad[0], torch.tensor([0.0, 0.5, 0.0, 0.0]))


def test_gradcheck_normalize_quats() -> None:
    q = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(normalize_quats, (q,))


def test_sh0_rgb_round_trip() -> None:
    rgb = torch.tensor([0.0, 0.5, 1.0])
    torch.testing.assert_close(sh0_to_rgb(rgb_to_sh0(rgb)), rgb)
    assert rgb_to_sh0(torch.tensor(0.5 + SH_C0)).item() == pytest.approx(1.0)


def test_add_remove_select() -> None:
    gmap = random_map(5)
    idx = gmap.add(
        torch.ones(2, 3),
        torch.zeros(2, 3),
        torch.tensor([[1.0, 0, 0, 0]] * 2),
        torch.zeros(2),
        torch.zeros(2, 1, 3),
    )
    assert idx.tolist() == [5, 6] and len(gmap) == 7
    assert torch.equal(gmap.params["shN"][5:], torch.zeros(2, 3, 3))  # default higher bands
    sub = gmap.select(torch.tensor([0, 6]))
    assert torch.equal(sub.means[1], torch.ones(3))
    mask = torch.zeros(7, dtype=torch.bool)
    mask[[1, 5]] = True
    before = gmap.means.detach().clone()
    assert gmap.remove(mask) == 2
    assert torch.equal(gmap.means.detach(), before[~mask])


def test_add_keeps_optimizer_state() -> None:
    gmap = random_map(4, sh_degree=0)
    opts = {k: torch.optim.Adam([gmap.params[k]], lr=1e-2) for k in PARAM_KEYS}
    loss = sum((gmap.params[k] ** 2).sum() for k in PARAM_KEYS)
    loss.backward()
    for o in opts.values():
        o.step()
    avg = opts["means"].state[gmap.params["means"]]["exp_avg"].clone()
    gmap.add(
        torch.zeros(1, 3),
        torch.zeros(1, 3),
        torch.ones(1, 4),
        torch.zeros(1),
        torch.zeros(1, 1, 3),
        optimizers=opts,
    )
    state = opts["means"].state[gmap.params["means"]]
    assert opts["means"].param_groups[0]["params"][0] is gmap.params["means"]
    assert torch.equal(state["exp_avg"][:4], avg)
    assert torch.equal(state["exp_avg"][4], torch.zeros(3))
    mask = torch.tensor([True, False, False, False, False])
    gmap.remove(mask, optimizers=opts)
    state = opts["means"].state[gmap.params["means"]]
    assert torch.equal(state["exp_avg"], torch.cat([avg[1:], torch.zeros(1, 3)]))
    # the optimizer still steps on the new parameters
    gmap.params["means"].grad = torch.ones_like(gmap.params["means"])
    opts["means"].step()


@pytest.mark.parametrize("channels", [1, 3])
def test_state_dict_round_trip(channels: int) -> None:
    gmap = random_map(6, sh_degree=2, channels=channels)
    state = gmap.state_dict()
    back = GaussianMap.from_state_dict(state)
    assert (back.sh_degree, back.channels) == (2, channels)
    for k in PARAM_KEYS:
        assert torch.equal(back.params[k], gmap.params[k])
    other = GaussianMap()
    other.load_state_dict(state)
    assert torch.equal(other.params["shN"], gmap.params["shN"])


def add_one(gmap: GaussianMap, n: int = 1, **override: torch.Tensor | float) -> None:
    """Add ``n`` valid Gaussians to a colour map, with some inputs replaced by ``override``."""
    args = {
        "means": torch.zeros(n, 3),
        "log_scales": torch.zeros(n, 3),
        "quats": torch.ones(n, 4),
        "opacity_logits": torch.zeros(n),
        "sh0": torch.zeros(n, 1, 3),
    }
    gmap.add(**{**args, **override})


def test_validation_messages() -> None:
    gmap = GaussianMap(sh_degree=1, channels=3)
    with pytest.raises(GaussianMapError, match=r"log_scales must be \[2, 3\], got \[2, 2\]"):
        add_one(gmap, 2, log_scales=torch.zeros(2, 2))
    with pytest.raises(GaussianMapError, match="means contains NaN"):
        add_one(gmap, means=torch.full((1, 3), float("nan")))
    with pytest.raises(GaussianMapError, match=r"sh0 must be \[1, 1, 3\]"):
        add_one(gmap, sh0=torch.zeros(1, 1, 1))
    with pytest.raises(GaussianMapError, match="means must be floating point"):
        add_one(gmap, means=torch.zeros(1, 3, dtype=torch.int64))
    with pytest.raises(GaussianMapError, match="sh_degree must be"):
        GaussianMap(sh_degree=5)
    with pytest.raises(GaussianMapError, match="channels must be 1"):
        GaussianMap(channels=2)
    with pytest.raises(GaussianMapError, match=r"mask must be a bool tensor \[0\]"):
        gmap.remove(torch.zeros(3, dtype=torch.bool))
    with pytest.raises(GaussianMapError, match="state dict lacks sh_degree"):
        GaussianMap.from_state_dict({k: torch.zeros(0) for k in PARAM_KEYS})


def test_provenance_follows_add_remove_select_and_snapshots() -> None:
    gmap = random_map(4)
    assert gmap.origin.tolist() == [ORIGIN_OBSERVED] * 4 and gmap.observations.tolist() == [0] * 4
    add_one(gmap, 2)
    gmap.add(torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2, 4), torch.zeros(2),
             torch.zeros(2, 1, 3), origin=ORIGIN_REPAIRED, observations=torch.tensor([3, 4]))  # fmt: skip
    assert gmap.origin.dtype == torch.uint8 and gmap.observations.dtype == torch.int32
    assert gmap.origin.tolist() == [0, 0, 0, 0, 0, 0, 1, 1]
    assert gmap.repaired().tolist() == [False] * 6 + [True] * 2
    assert gmap.observations.tolist() == [0, 0, 0, 0, 0, 0, 3, 4]
    assert gmap.select(torch.tensor([6, 0])).observations.tolist() == [3, 0]
    mask = torch.zeros(8, dtype=torch.bool)
    mask[[0, 6]] = True
    gmap.remove(mask)
    assert gmap.origin.tolist() == [0] * 5 + [1] and gmap.observations.tolist() == [0] * 5 + [4]
    back = GaussianMap.from_state_dict(gmap.state_dict())
    assert torch.equal(back.origin, gmap.origin) and torch.equal(
        back.observations, gmap.observations
    )
    # a snapshot from before provenance: every Gaussian observed, never counted
    old = {k: v for k, v in gmap.state_dict().items() if k not in ("origin", "observations")}
    assert GaussianMap.from_state_dict(old).origin.tolist() == [0] * 6


def test_a_scale_bound_follows_add_remove_select_and_snapshots() -> None:
    gmap = random_map(3)
    assert torch.isinf(gmap.max_log_scale).all() and gmap.max_log_scale.dtype == torch.float32
    add_one(gmap, 2, max_log_scale=torch.tensor([-1.0, -2.0]))
    assert gmap.max_log_scale.tolist()[3:] == [-1.0, -2.0]
    assert gmap.select(torch.tensor([4, 0])).max_log_scale.tolist() == [-2.0, math.inf]
    mask = torch.zeros(5, dtype=torch.bool)
    mask[3] = True
    gmap.remove(mask)
    assert gmap.max_log_scale.tolist() == [math.inf] * 3 + [-2.0]
    back = GaussianMap.from_state_dict(gmap.state_dict())
    assert torch.equal(back.max_log_scale, gmap.max_log_scale)
    # a snapshot from before the bound: nothing bounded
    old = {k: v for k, v in gmap.state_dict().items() if k != "max_log_scale"}
    assert torch.isinf(GaussianMap.from_state_dict(old).max_log_scale).all()
    with pytest.raises(GaussianMapError, match="max_log_scale must not be NaN"):
        add_one(gmap, max_log_scale=math.nan)
    with pytest.raises(
        GaussianMapError, match=r"max_log_scale must be a number or \[2\], got \[3\]"
    ):
        add_one(gmap, 2, max_log_scale=torch.zeros(3))


def test_provenance_validation_messages() -> None:
    gmap = GaussianMap(sh_degree=0, channels=3)
    with pytest.raises(GaussianMapError, match=r"origin must lie in \[0, 1\], got \[2, 2\]"):
        add_one(gmap, origin=2)
    with pytest.raises(GaussianMapError, match=r"observations must be \[2\], got \[3\]"):
        add_one(gmap, 2, observations=torch.tensor([1, 2, 3]))
    with pytest.raises(GaussianMapError, match="origin must be an integer or integer"):
        add_one(gmap, origin=torch.tensor([0.5]))
    with pytest.raises(GaussianMapError, match=r"observations must be \[0\], got \[2\]"):
        gmap.set_meta({"origin": torch.zeros(0), "observations": torch.zeros(2)})
    assert len(gmap) == 0 and len(gmap.origin) == 0
