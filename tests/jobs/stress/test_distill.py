"""Stress properties of the mapper's optimisation and distillation (gsfix_online/mapping/splat/
mapper.py), and a long run of optimisation steps on extreme frames."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.jobs.stress import properties
from gsfix_online.jobs.stress.runner import assert_property
from gsfix_online.jobs.stress.splat import stress_mapper_config
from gsfix_online.mapping.splat.mapper import DensifyConfig, Mapper

STEPS = 300  # ~90 ms a step on 2 loaded cores; gsfix-online stress runs thousands

PROPS = [p for p in properties("splat") if p.name in ("splat.mapper_steps", "splat.distill")]


@pytest.mark.parametrize("prop", PROPS, ids=lambda p: p.name)
def test_property_holds(prop):
    assert_property(prop)


def test_hundreds_of_steps_10km_out_on_depths_from_1mm_to_1km_stay_finite():
    rng = np.random.default_rng(0)
    w, h = 8, 6
    K = Intrinsics(8.0, 8.0, 4.0, 3.0, w, h)
    cfg = dataclasses.replace(stress_mapper_config(), densify=DensifyConfig(), prune_every=50)
    mapper = Mapper(cfg)
    for i in range(3):
        depth = (2.0 * np.exp(2.0 * rng.standard_normal((h, w)))).clip(1e-3, 1e3)
        T = np.eye(4)
        T[:3, 3] = [1e4, 0.0, 0.01 * i]
        color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        mapper.process(make_frame(color, depth.astype(np.float32), K, T, 10**9 * (i + 1)))
    res = mapper.refine(STEPS)
    assert mapper.n_nonfinite_steps == 0
    for key, p in mapper.gmap.params.items():
        assert torch.isfinite(p).all(), key
    assert res.loss_last < res.loss_first  # it still optimises
