"""The end-of-input refinement: global passes over the keyframes, and polish of repaired views.

Once the input has ended the map gets :func:`refine` (steps over random stored views, repaired
views included, at some resolution), and, after distillation, :func:`polish`: each repaired
view whose render is still far from what it was fitted to (:func:`fidelity`, PSNR inside its
mask) gets more steps, each with some other repaired views so that it is not won back at their
cost. The functions take the step and the views from the caller (:class:`Mapper`): they hold no
state but the losses and fidelities they return.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from gsfix_online.mapping.splat.keyframes import Keyframe, KeyframeStore
from gsfix_online.mapping.splat.render_output import RenderOutput
from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID, TrainView, downscale_view

# (views, ssim_lambda, l1_weight) -> the step's loss (MapOptimizer.step with the mapper's loss)
Step = Callable[[list[TrainView], float, float], float]
KeyframeView = Callable[[Keyframe], TrainView]


@dataclass(frozen=True)
class PolishResult:
    """What :meth:`Mapper.polish` did: fidelity (PSNR dB inside each repaired view's mask, by
    keyframe id) before and after, and the views it polished."""

    before: dict[int, float]
    after: dict[int, float]
    polished: list[int]
    n_iters: int
    refilled: dict[int, int] = field(default_factory=dict)  # seeds grown first, by keyframe id


def refine(
    store: KeyframeStore,
    keyframe_view: KeyframeView,
    step: Callable[[list[TrainView]], float],
    rng: np.random.Generator,
    iters: int,
    views_per_step: int,
    downscale: int,
) -> list[float]:
    """``iters`` steps, each over ``views_per_step`` random stored views at ``1 / downscale``
    of their resolution; returns the losses."""
    losses: list[float] = []
    for _ in range(iters):
        kfs = store.sample(views_per_step, rng, exclude_latest=False)
        losses.append(step([downscale_view(keyframe_view(k), downscale) for k in kfs]))
    return losses


def fidelity(
    keyframes: Iterable[Keyframe],
    keyframe_view: KeyframeView,
    render: Callable[[torch.Tensor, torch.Tensor, int, int], RenderOutput],
) -> dict[int, float]:
    """Per repaired view (keyframe id): PSNR dB of the map's render against the image it
    was fitted to, inside its mask; inf if identical."""
    out: dict[int, float] = {}
    for kf in keyframes:
        if kf.frame.frame_id != REPAIRED_FRAME_ID:
            continue
        view = keyframe_view(kf)
        H, W = view.color.shape[:2]
        with torch.no_grad():
            pred = render(view.T_world_cam, view.K, W, H).color.clamp(0, 1)
        err = (pred - view.color) ** 2
        if view.mask is not None:
            if not bool(view.mask.any()):
                continue
            err = err[view.mask]
        mse = float(err.mean())
        out[kf.kf_id] = math.inf if mse == 0 else -10.0 * math.log10(mse)
    return out


def polish(
    keyframes: Sequence[Keyframe],
    keyframe_view: KeyframeView,
    step: Step,
    measure: Callable[[], dict[int, float]],  # the repaired views' fidelity now
    rng: np.random.Generator,
    below_db: float,  # 0: nothing
    rounds: int,
    iters: int,
    partners: int,
    lam: float,  # the distillation loss' SSIM weight
    until_db: float = 0.0,  # 0: always ``iters`` steps
    check_every: int = 10,
    measure_one: Callable[[int], float] | None = None,  # one view's fidelity now, by keyframe id
    observed: Callable[[], list[TrainView]] | None = None,  # input keyframes to fit in each step
    force: Collection[int] = (),  # keyframe ids polished in the first round whatever their fidelity
) -> PolishResult:
    """Fit again the repaired views whose fidelity is under ``below_db``: ``iters`` steps
    each, every step with ``partners`` random other repaired views, for up to ``rounds``
    rounds (a round polishes the views under the threshold when it starts). With
    ``until_db``, a view's fit stops early once its fidelity, measured every ``check_every``
    steps, reaches it. With ``observed``, every step also fits the input keyframes it returns,
    so that a polished view does not move what the frames observed. The views in ``force``
    (e.g. just given new seeds, which no step has fitted) are polished in the first round too."""
    if until_db > 0 and measure_one is None:
        raise ValueError("polish until_db needs measure_one, to measure a view between steps")
    before = measure() if below_db > 0 else {}
    after, polished, n = before, [], 0
    kfs = {kf.kf_id: kf for kf in keyframes}
    for r in range(rounds if below_db > 0 else 0):
        low = sorted(k for k, v in after.items() if v < below_db or (r == 0 and k in force))
        if not low:
            break
        for k in low:
            others = [o for o in after if o != k]
            for i in range(iters):
                if until_db > 0 and i > 0 and i % check_every == 0 and measure_one(k) >= until_db:  # type: ignore[misc]
                    break
                pick = rng.choice(others, min(partners, len(others)),
                                  replace=False) if others else []  # fmt: skip
                views = [keyframe_view(kfs[k])]
                views += [keyframe_view(kfs[int(o)]) for o in pick]
                views += observed() if observed is not None else []
                step(views, lam, 1.0 - lam)
                n += 1
        polished += [k for k in low if k not in polished]
        after = measure()
    return PolishResult(before, after, polished, n)
