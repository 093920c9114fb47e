"""The exposure model (exposure_model.py): identity leaves the image alone, a known gain is
recovered, re-centring is an exact change of gauge, forgotten keyframes leave the optimiser."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from gsfix_online.mapping.splat.exposure import ExposureConfig, apply_affine
from gsfix_online.mapping.splat.exposure_model import ExposureModel
from gsfix_online.mapping.splat.mapper import Mapper
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import TrainView, frame_view
from tests.mapping.splat.test_mapper import (
    CFG,
    H,
    W,
    one_thread,  # noqa: F401 -- autouse: one torch thread
    plane_frame,
)


def _pair(gain: float) -> tuple[RenderOutput, TrainView]:
    g = torch.Generator().manual_seed(0)
    color = 0.2 + 0.6 * torch.rand(H, W, 3, generator=g)
    out = RenderOutput(color, torch.full((H, W), 2.0), torch.ones(H, W))
    view = TrainView((color * gain).clamp(0, 1), None, torch.eye(3), torch.eye(4))
    return out, view


def test_identity_parameters_leave_the_image_unchanged() -> None:
    out, view = _pair(1.0)
    model = ExposureModel(ExposureConfig(enabled=True), torch.device("cpu"))
    params = model.estimate(out, view)
    torch.testing.assert_close(params, torch.zeros(2, 3), atol=1e-4, rtol=0)
    torch.testing.assert_close(apply_affine(out.color, out.alpha, torch.zeros(2, 3)), out.color)


def test_a_known_gain_is_recovered() -> None:
    out, view = _pair(1.2)
    params = ExposureModel(ExposureConfig(enabled=True, ridge=0.0), torch.device("cpu")).estimate(
        out, view
    )
    torch.testing.assert_close(params[0].exp(), torch.full((3,), 1.2), atol=2e-3, rtol=0)


def test_recentring_keeps_every_keyframe_render_and_zeroes_the_mean_gain() -> None:
    torch.manual_seed(0)
    mapper = Mapper(CFG)
    f = plane_frame()
    mapper.process(f)
    model = ExposureModel(ExposureConfig(enabled=True), mapper.device)
    model.keep(0, torch.tensor([[0.2] * 3, [0.0] * 3]))
    model.keep(1, torch.tensor([[-0.1] * 3, [0.0] * 3]))
    shown = {}
    for k, p in model.params.items():
        out = mapper.render(f.T_world_cam, f.intrinsics.K, W, H)
        shown[k] = apply_affine(out.color, out.alpha, p).detach()
    model.recenter(mapper.gmap)
    mu = torch.stack([p[0] for p in model.params.values()]).mean(0)
    torch.testing.assert_close(mu, torch.zeros(3), atol=1e-6, rtol=0)
    for k, p in model.params.items():
        out = mapper.render(f.T_world_cam, f.intrinsics.K, W, H)
        # exact up to the colour clamp at 0 (none here: the plane's colours are mid-range)
        torch.testing.assert_close(apply_affine(out.color, out.alpha, p).detach(), shown[k],
                                   atol=1e-5, rtol=1e-5)  # fmt: skip


def test_forgotten_keyframes_leave_the_optimiser() -> None:
    model = ExposureModel(ExposureConfig(enabled=True), torch.device("cpu"))
    for k in range(3):
        model.keep(k, torch.zeros(2, 3))
    assert model.opt is not None and len(model.opt.param_groups) == 3
    model.forget({1})
    assert list(model.params) == [1] and len(model.opt.param_groups) == 1
    assert model.opt.param_groups[0]["params"][0] is model.params[1]


def test_the_mapper_view_carries_the_kept_exposure() -> None:
    torch.manual_seed(0)
    mapper = Mapper(dataclasses.replace(CFG, exposure=ExposureConfig(enabled=True)))
    res = mapper.process(plane_frame())
    assert res.is_keyframe and set(mapper.exposure) == {0}
    assert mapper.exposure is mapper.exposure_model.params
    assert frame_view(plane_frame(), mapper.device).affine is None
    assert np.isfinite(float(mapper.exposure[0].detach().sum()))
