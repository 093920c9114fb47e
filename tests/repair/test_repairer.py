"""seed_depth and distill_mask: what a repaired view gives distillation (seed depth, fitted pixels)."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.repair.repairer import distill_mask, seed_depth


def test_seed_depth_keeps_the_mesh_and_fills_empty_parts_within_range():
    h, w = 40, 60
    ramp = np.tile(np.linspace(1.0, 3.0, w, dtype=np.float32), (h, 1))  # [H, W] m
    valid = np.ones((h, w), bool)
    valid[:, 20:35] = False  # a band no map holds
    valid[:8] = False
    only_mesh = seed_depth(ramp, valid, fill_empty=False)
    assert only_mesh.dtype == np.float32
    np.testing.assert_array_equal(only_mesh[valid], ramp[valid])
    assert (only_mesh[~valid] == 0).all()
    filled = seed_depth(ramp, valid, fill_empty=True)
    np.testing.assert_array_equal(filled[valid], ramp[valid])  # the mesh is never changed
    inside = filled[~valid]
    assert (inside >= 1.0).all() and (inside <= 3.0).all()  # no overshoot beyond the border
    # inside the band the fill sits between the depths on either side of it
    row = filled[20, 20:35]
    assert ramp[20, 19] - 0.05 <= row.min() and row.max() <= ramp[20, 35] + 0.05
    # nothing to fill from (no surface at all) and nothing missing: returned as they are
    assert (seed_depth(ramp, np.zeros_like(valid), True) == 0).all()
    np.testing.assert_array_equal(seed_depth(ramp, np.ones_like(valid), True), ramp)


def test_distill_mask_covers_the_holes_of_the_map_and_a_band_around_them():
    alpha = np.ones((20, 30), np.float32)
    alpha[5:8, 10:12] = 0.2  # a hole
    alpha[0, 0] = 0.5  # at the threshold: covered
    m = distill_mask(alpha, 0.5, "holes", dilate_px=2)
    assert m.dtype == np.uint8 and set(np.unique(m)) == {0, 255}
    want = np.zeros((20, 30), bool)
    want[3:10, 8:14] = True
    np.testing.assert_array_equal(m == 255, want)
    np.testing.assert_array_equal(distill_mask(alpha, 0.5, "holes", 0) == 255, alpha < 0.5)
    assert distill_mask(alpha, 0.5, "all") is None
    with pytest.raises(ValueError, match="'holes', 'delivered' or 'all'"):
        distill_mask(alpha, 0.5, "edges")


def test_delivered_mask_adds_the_covered_pixels_the_choice_replaced():
    alpha = np.ones((20, 30), np.float32)
    alpha[5:8, 10:12] = 0.2  # a hole
    rep = np.zeros((20, 30), bool)
    rep[15:, 20:] = True  # e.g. GSFixer chosen where both maps cover the view
    m = distill_mask(alpha, 0.5, "delivered", dilate_px=0, replaced=rep)
    np.testing.assert_array_equal(m == 255, (alpha < 0.5) | rep)
    want = np.zeros((20, 30), bool)
    want[3:10, 8:14] = want[13:, 18:] = True  # both widened by 2 px
    np.testing.assert_array_equal(distill_mask(alpha, 0.5, "delivered", 2, rep) == 255, want)
    # nothing replaced: the holes mask
    np.testing.assert_array_equal(distill_mask(alpha, 0.5, "delivered", 2, np.zeros_like(rep)),
                                  distill_mask(alpha, 0.5, "holes", 2))  # fmt: skip
    with pytest.raises(ValueError, match="needs replaced"):
        distill_mask(alpha, 0.5, "delivered")
    with pytest.raises(ValueError, match="needs replaced"):
        distill_mask(alpha, 0.5, "delivered", replaced=rep[:10])
