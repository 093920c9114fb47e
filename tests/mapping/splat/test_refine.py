"""The end-of-input refinement (refine.py): passes lower the loss, fidelity is PSNR inside the
mask, polish lifts the repaired views under its threshold and does nothing at 0."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gsfix_online.mapping.splat.mapper import Mapper
from gsfix_online.mapping.splat.refine import fidelity, polish, refine
from gsfix_online.mapping.splat.views import TrainView
from tests.mapping.splat.test_mapper import (
    CFG,
    H,
    K,
    W,
    one_thread,  # noqa: F401 -- autouse: one torch thread
    plane_frame,
)


def _mapped(repaired: int = 0) -> Mapper:
    torch.manual_seed(0)
    m = Mapper(CFG)
    for i in range(2):
        m.process(plane_frame(0.1 * i, i))
    for j in range(repaired):
        pose = plane_frame(0.03 + 0.04 * j).T_world_cam
        color, _, _ = m.render_numpy(pose, K.K, W, H)
        img = np.rint(np.clip(color * 0.6 + 0.3, 0, 1) * 255).astype(np.uint8)
        mask = np.zeros((H, W), bool)
        mask[:, : W // 2] = True
        m.distill(img, pose, K.K, iters=2, mask=mask)
    return m


def test_refinement_passes_lower_the_loss() -> None:
    m = _mapped()
    losses = refine(m.store, m._keyframe_view, m.train_step, m.rng, 12, 2, 1)
    assert len(losses) == 12 and np.mean(losses[-3:]) < np.mean(losses[:3]), losses


def test_fidelity_is_psnr_inside_the_mask() -> None:
    m = _mapped(repaired=1)
    (kf,) = [kf for kf in m.store if kf.frame.frame_id == "repaired"]
    view = m._keyframe_view(kf)
    assert view.mask is not None and int(view.mask.sum()) == H * (W // 2)

    def same(T, K_, w, h):  # noqa: ANN001, ANN202 -- a render equal to the image inside the mask
        out = m.render(T, K_, w, h)
        out.color = torch.where(view.mask[..., None], view.color, 1.0 - view.color)
        return out

    assert fidelity(m.store, m._keyframe_view, same) == {kf.kf_id: math.inf}
    db = fidelity(m.store, m._keyframe_view, m.render)[kf.kf_id]
    with torch.no_grad():
        pred = m.render(view.T_world_cam, view.K, W, H).color.clamp(0, 1)
    mse = float(((pred - view.color) ** 2)[view.mask].mean())
    assert db == pytest.approx(-10 * math.log10(mse))


def test_polish_lifts_views_under_the_threshold_and_nothing_at_zero() -> None:
    m = _mapped(repaired=2)
    calls: list[int] = []

    def step(views: list[TrainView], lam: float, l1: float) -> float:
        calls.append(len(views))
        return m.train_step(views, lam=lam, l1_weight=l1)

    args = (list(m.store), m._keyframe_view, step, m.fidelity, m.rng)
    off = polish(*args, 0.0, 2, 5, 1, 0.2)
    assert off.n_iters == 0 and off.before == {} and not calls
    res = polish(*args, 100.0, 1, 5, 1, 0.2)  # every view is under 100 dB: one round each
    assert res.polished == sorted(res.before) and len(res.polished) == 2
    assert res.n_iters == 10 and calls == [2] * 10  # each step with its one partner
    assert np.mean(list(res.after.values())) > np.mean(list(res.before.values())), res


def test_polish_fits_the_observed_views_it_is_given_in_every_step() -> None:
    m = _mapped(repaired=2)
    sizes: list[list[int]] = []
    observed = [m._keyframe_view(kf) for kf in m.store if kf.frame.frame_id != "repaired"]

    def step(views: list[TrainView], lam: float, l1: float) -> float:
        sizes.append([v.color.shape[1] for v in views])
        return m.train_step(views, lam=lam, l1_weight=l1)

    args = (list(m.store), m._keyframe_view, step, m.fidelity, m.rng)
    res = polish(*args, 100.0, 1, 3, 1, 0.2, observed=lambda: observed[:1])
    assert res.n_iters == 6 and len(sizes) == 6
    assert all(len(s) == 3 for s in sizes)  # the polished view, its partner, one input keyframe


def test_polish_stops_a_view_once_it_reaches_until_db() -> None:
    """With ``until_db`` a view's fit is measured every ``check_every`` steps and stops at
    the first check that finds it there; a view that never gets there takes every step."""
    from types import SimpleNamespace

    kfs = [SimpleNamespace(kf_id=k) for k in (3, 7, 9)]
    steps = {3: 0, 7: 0, 9: 0}
    checks: list[tuple[int, int]] = []

    def step(views: list[int], lam: float, l1: float) -> float:  # views: their keyframe ids
        steps[views[0]] += 1  # the polished view comes first
        return 0.0

    def measure_one(k: int) -> float:  # view 3 gains 1 dB a step from 20; view 7 stays at 10
        checks.append((k, steps[k]))
        return 20.0 + steps[k] if k == 3 else 10.0

    def measure() -> dict[int, float]:
        return {3: 20.0 + steps[3], 7: 10.0, 9: 40.0}  # view 9 is above the threshold

    rng = np.random.default_rng(0)
    res = polish(kfs, lambda kf: kf.kf_id, step, measure, rng, 25.0, 1, 30, 1, 0.2,
                 until_db=33.0, check_every=5, measure_one=measure_one)  # fmt: skip
    # view 3: checked after 5, 10 and 15 steps, at 25, 30 and 35 dB: stops at the third
    assert steps == {3: 15, 7: 30, 9: 0} and res.n_iters == 45 and res.polished == [3, 7]
    assert [c for c in checks if c[0] == 3] == [(3, 5), (3, 10), (3, 15)]
    assert [c for c in checks if c[0] == 7] == [(7, i) for i in range(5, 30, 5)]
    # without until_db every polished view takes every step, and nothing is measured between
    steps.update({3: 0, 7: 0})
    checks.clear()
    res = polish(kfs, lambda kf: kf.kf_id, step, measure, rng, 25.0, 1, 30, 1, 0.2,
                 measure_one=measure_one)  # fmt: skip
    assert steps == {3: 30, 7: 30, 9: 0} and checks == [] and res.n_iters == 60
    with pytest.raises(ValueError, match="measure_one"):
        polish(kfs, lambda kf: kf.kf_id, step, measure, rng, 25.0, 1, 30, 1, 0.2, until_db=33.0)


def test_polish_takes_the_forced_views_in_its_first_round_only() -> None:
    """A view in ``force`` (just given new seeds) is polished in the first round although it
    is above the threshold, and not again in later rounds unless it falls under it."""
    from types import SimpleNamespace

    kfs = [SimpleNamespace(kf_id=k) for k in (3, 9)]
    steps = {3: 0, 9: 0}

    def step(views: list[int], lam: float, l1: float) -> float:
        steps[views[0]] += 1
        return 0.0

    def measure() -> dict[int, float]:  # view 3 stays under the threshold, view 9 above it
        return {3: 10.0, 9: 40.0}

    rng = np.random.default_rng(0)
    res = polish(kfs, lambda kf: kf.kf_id, step, measure, rng, 25.0, 2, 4, 1, 0.2, force={9})
    assert steps == {3: 8, 9: 4} and res.n_iters == 12 and res.polished == [3, 9]
    steps.update({3: 0, 9: 0})
    res = polish(kfs, lambda kf: kf.kf_id, step, measure, rng, 25.0, 2, 4, 1, 0.2)
    assert steps == {3: 8, 9: 0} and res.polished == [3]
