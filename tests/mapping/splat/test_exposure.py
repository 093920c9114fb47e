"""Per-view exposure compensation: the closed-form fit, the affine colour, and the mapper with it."""

from __future__ import annotations

import dataclasses
import io
import math

import numpy as np
import pytest
import torch

from gsfix_online.core.types import RGBDFrame, make_frame
from gsfix_online.mapping.splat.exposure import (
    ExposureConfig,
    apply_affine,
    fit_affine,
    identity,
    invert_affine,
)
from gsfix_online.mapping.splat.mapper import Mapper, _frame_view
from tests.mapping.splat.test_mapper import CFG, H, W, plane_frame

EXPOSED = dataclasses.replace(CFG, exposure=ExposureConfig(enabled=True))


@pytest.fixture(autouse=True, scope="module")
def one_thread():  # tiny images: two OpenMP threads only add barrier waits
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def scaled(frame: RGBDFrame, gain: float) -> RGBDFrame:
    color = np.clip(np.rint(frame.color * gain), 0, 255).astype(np.uint8)
    return make_frame(
        color, frame.depth, frame.intrinsics, frame.T_world_cam, frame.stamp_ns, seq=frame.seq
    )


@pytest.mark.parametrize("channels", [1, 3])
def test_fit_recovers_gain_and_bias(channels: int) -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.rand((500, channels), generator=g)
    gain, bias = torch.linspace(0.7, 1.4, channels), torch.linspace(-0.05, 0.05, channels)
    y = x * gain + bias
    w = torch.ones(500)
    p = fit_affine(x, y, w, ridge=0.0, bias=True)
    torch.testing.assert_close(p[0].exp(), gain, atol=1e-5, rtol=0)
    torch.testing.assert_close(p[1], bias, atol=1e-5, rtol=0)
    p = fit_affine(x, x * gain, w, ridge=0.0, bias=False)  # gain alone: exact, bias stays 0
    torch.testing.assert_close(p[0].exp(), gain, atol=1e-5, rtol=0)
    assert bool((p[1] == 0).all())


def test_fit_weights_ridge_and_clamp() -> None:
    x = torch.rand((200, 3), generator=torch.Generator().manual_seed(1))
    y = x * 1.2
    y[:50] = 1.0  # outliers with zero weight do not count
    w = torch.ones(200)
    w[:50] = 0
    torch.testing.assert_close(fit_affine(x, y, w, 0.0, bias=False)[0].exp(), torch.full((3,), 1.2))
    # the ridge pulls towards the identity; a huge ridge returns it
    shrunk = fit_affine(x, y, w, 0.5, bias=False)[0].exp()
    assert bool(((shrunk > 1.0) & (shrunk < 1.2)).all())
    torch.testing.assert_close(fit_affine(x, y, w, 1e9)[0], torch.zeros(3), atol=1e-6, rtol=0)
    # gains beyond exp(max_log_gain) are clamped
    assert fit_affine(x, 10 * x, torch.ones(200), 0.0, max_log_gain=1.0)[0].max() <= 1.0 + 1e-6


def test_affine_round_trip_and_identity() -> None:
    c = torch.rand((4, 5, 3))
    a = torch.rand((4, 5))
    torch.testing.assert_close(apply_affine(c, a, identity(3)), c)
    p = torch.tensor([[0.2, -0.1, 0.05], [0.03, 0.0, -0.02]])
    # one opaque Gaussian of colour c renders as gain * c + bias; invert_affine undoes it
    shown = apply_affine(c, torch.ones((4, 5)), p)
    torch.testing.assert_close(invert_affine(shown, p), c, atol=1e-6, rtol=0)
    # composited: alpha-weighted bias, black background stays black
    torch.testing.assert_close(
        apply_affine(torch.zeros(1, 3), torch.zeros(1), p), torch.zeros(1, 3)
    )


def test_mapper_recovers_a_known_gain() -> None:
    """A frame 1.3x brighter than the map reads as log-gain log(1.3), and the map's colour does
    not take it on: growth and steps see the frame through its gain."""
    mapper = Mapper(EXPOSED)
    for i in range(4):
        mapper.process(plane_frame(0.05 * i, i))
    bright = scaled(plane_frame(0.1, 5), 1.3)
    view = _frame_view(bright, mapper.device)
    with torch.no_grad():
        out = mapper.render(view.T_world_cam, view.K, W, H)
    est = mapper._estimate_exposure(out, view)
    np.testing.assert_allclose(est[0].numpy(), math.log(1.3), atol=0.03)
    assert bool((est[1] == 0).all())  # gain alone by default


def test_sequence_with_exposure_changes_keeps_canonical_colour() -> None:
    """Frames alternating 0.75x / 1.25x of the true plane: with compensation the map renders the
    plane at its mean exposure (the keyframes' mean log-gain is the gauge); the per-keyframe
    gains follow the frames'."""
    gains = [1.0, 0.75, 1.25, 0.75, 1.25, 1.0]
    every = dataclasses.replace(CFG.keyframes, min_new_gaussians=0, min_overlap=1.0)
    mapper = Mapper(dataclasses.replace(EXPOSED, keyframes=every))
    for i, g in enumerate(gains):
        assert mapper.process(scaled(plane_frame(0.2 * i, i), g)).is_keyframe
    logs = torch.stack([p[0].mean() for p in mapper.exposure.values()]).detach()
    # the gauge (re-centred at each keyframe; the steps after the last one move it a little)
    assert len(logs) == len(gains) and abs(float(logs.mean())) < 0.01
    mapper.refine(30)
    logs = torch.stack([p[0].mean() for p in mapper.exposure.values()]).detach()
    want = np.log(gains) - np.log(gains).mean()
    np.testing.assert_allclose(logs.numpy() - float(logs.mean()), want, atol=0.08)
    f = plane_frame(0.5, 9)
    color, _, alpha = mapper.render_numpy(f.T_world_cam, f.intrinsics.K, W, H)
    m = alpha > 0.9
    target = f.color / 255.0 * math.exp(np.log(gains).mean())  # the mean exposure
    assert abs(float(color[m].mean() / target[m].mean()) - 1.0) < 0.05


def test_snapshot_keeps_exposures() -> None:
    mapper = Mapper(EXPOSED)
    for i, g in enumerate([1.0, 1.2, 0.9]):
        mapper.process(scaled(plane_frame(0.1 * i, i), g))
    buf = io.BytesIO()
    torch.save(mapper.state_dict(), buf)
    buf.seek(0)
    restored = Mapper(EXPOSED)
    restored.load_state_dict(torch.load(buf, weights_only=True))
    assert restored.exposure.keys() == mapper.exposure.keys()
    for k, p in mapper.exposure.items():
        torch.testing.assert_close(restored.exposure[k], p.detach())
    restored.refine(2)  # its exposures are optimised like the original's


def test_off_by_default_changes_nothing() -> None:
    """Without compensation no exposure parameters exist and frames map as before."""
    mapper = Mapper(CFG)
    for i in range(3):
        mapper.process(scaled(plane_frame(0.1 * i, i), 1.0 + 0.1 * i))
    assert mapper.exposure == {} and mapper.exposure_opt is None
