"""Tests for gsfix_online/fixer/model.py: conv_in widening, the GSFixer wrapper."""

from __future__ import annotations

import pytest
import torch

from gsfix_online.fixer.model import (
    GSFixer,
    merge_condition_slots,
    select_conditions,
    widen_conv_in,
)
from tests.fixer.conftest import TOL, tiny_sd2_unet


@pytest.mark.parametrize("n_conditions", [1, 2])
def test_widened_conv_in_reproduces_pretrained_response_on_identical_inputs(n_conditions):
    unet = tiny_sd2_unet(seed=3).eval()
    x = torch.randn(2, 4, 16, 24, generator=torch.Generator().manual_seed(0))
    t = torch.tensor([10, 700])
    emb = torch.randn(2, 5, 16, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        ref = unet(x, t, encoder_hidden_states=emb).sample
        widen_conv_in(unet, n_conditions)
        out = unet(x.repeat(1, n_conditions + 1, 1, 1), t, encoder_hidden_states=emb).sample
    assert unet.conv_in.in_channels == 4 * (n_conditions + 1)
    assert unet.config.in_channels == 4 * (n_conditions + 1)
    torch.testing.assert_close(out, ref, **TOL[torch.float32])


def test_widened_weights_are_copies_divided_by_count():
    unet = tiny_sd2_unet()
    w0 = unet.conv_in.weight.detach().clone()
    widen_conv_in(unet, 2)
    w = unet.conv_in.weight.detach()
    for k in range(3):
        torch.testing.assert_close(w[:, 4 * k : 4 * (k + 1)], w0 / 3)


def test_widened_unet_save_load_round_trip(tmp_path):
    from diffusers import UNet2DConditionModel

    unet = widen_conv_in(tiny_sd2_unet(), 2)
    unet.save_pretrained(tmp_path / "u")
    again = UNet2DConditionModel.from_pretrained(tmp_path / "u", local_files_only=True)
    assert again.conv_in.in_channels == 12
    torch.testing.assert_close(again.conv_in.weight, unet.conv_in.weight)


def test_gsfixer_rejects_unwidened_unet():
    with pytest.raises(ValueError, match="needs 12"):
        GSFixer(tiny_sd2_unet(), "mesh+gs", 4, torch.zeros(1, 2, 16))


@pytest.mark.parametrize(("mode", "n"), [("mesh+gs", 2), ("gs", 1), ("mesh", 1)])
def test_gsfixer_forward_shape_per_mode(mode, n):
    unet = widen_conv_in(tiny_sd2_unet(), n)
    model = GSFixer(unet, mode, 4, torch.zeros(1, 3, 16))
    out = model(torch.randn(2, 4 * n, 8, 8), torch.randn(2, 4, 8, 8), torch.tensor([1, 2]))
    assert out.shape == (2, 4, 8, 8)
    assert model.multiple == 2


def test_select_conditions_order_and_missing():
    zm, zg = torch.zeros(1, 2, 3, 3), torch.ones(1, 2, 3, 3)
    both = select_conditions("mesh+gs", zm, zg)
    assert torch.equal(both[:, :2], zm) and torch.equal(both[:, 2:], zg)
    assert torch.equal(select_conditions("gs", None, zg), zg)
    with pytest.raises(ValueError, match="needs the mesh"):
        select_conditions("mesh+gs", None, zg)


def test_merged_condition_slots_reproduce_the_wide_response_on_repeated_inputs():
    unet = widen_conv_in(tiny_sd2_unet(seed=4), 2).eval()
    g = torch.Generator().manual_seed(0)
    z, zt = torch.randn(2, 4, 16, 24, generator=g), torch.randn(2, 4, 16, 24, generator=g)
    t = torch.tensor([10, 700])
    emb = torch.randn(2, 5, 16, generator=g)
    with torch.no_grad():
        ref = unet(torch.cat([z, z, zt], 1), t, encoder_hidden_states=emb).sample
        merge_condition_slots(unet, 4)
        out = unet(torch.cat([z, zt], 1), t, encoder_hidden_states=emb).sample
    assert unet.conv_in.in_channels == 8 and unet.config.in_channels == 8
    torch.testing.assert_close(out, ref, **TOL[torch.float32])
    with pytest.raises(ValueError, match="mesh\\+gs U-Net has 12"):
        merge_condition_slots(unet, 4)


def test_residual_output_adds_the_last_condition():
    unet = widen_conv_in(tiny_sd2_unet(), 2).eval()
    plain = GSFixer(unet, "mesh+gs", 4, torch.zeros(1, 3, 16))
    res = GSFixer(unet, "mesh+gs", 4, torch.zeros(1, 3, 16), residual=True)
    g = torch.Generator().manual_seed(0)
    cond, zt = torch.randn(1, 8, 8, 8, generator=g), torch.randn(1, 4, 8, 8, generator=g)
    t = torch.tensor([5])
    with torch.no_grad():
        torch.testing.assert_close(res(cond, zt, t), plain(cond, zt, t) + cond[:, 4:])
