"""ViewRepairer on grayscale renders; seed_depth and distill_mask: what a repaired view gives
distillation (seed depth, fitted pixels)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gsfix_online.fixer.config import FixerConfig, InferenceConfig
from gsfix_online.repair.repairer import ViewRepairer, distill_mask, seed_depth


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


def test_seed_depth_takes_the_guessed_surface_where_there_is_one():
    h, w = 40, 60
    ramp = np.tile(np.linspace(1.0, 3.0, w, dtype=np.float32), (h, 1))
    valid = np.ones((h, w), bool)
    valid[:, 20:35] = False  # inpainted, the band is 1.6-2.2 m
    inpainted = seed_depth(ramp, valid, True)
    guessed = np.zeros((h, w), np.float32)
    guessed[:15, 20:35] = 3.0  # a plane behind the inpainted surface, within GUESS_RANGE
    guessed[15:25, 20:35] = 9.0  # a plane more than GUESS_RANGE behind: not believed
    seeds = seed_depth(ramp, valid, True, guessed)
    np.testing.assert_array_equal(seeds[valid], ramp[valid])  # the mesh is never changed
    assert (seeds[:15, 20:35] == 3.0).all()
    np.testing.assert_array_equal(seeds[15:, 20:35], inpainted[15:, 20:35])
    # without fill_empty nothing is seeded off the mesh, guess or not
    assert (seed_depth(ramp, valid, False, guessed)[~valid] == 0).all()
    # a view the mesh does not see at all has only the guess to go by
    assert (seed_depth(ramp, np.zeros_like(valid), True, guessed)[15:25, 20:35] == 9.0).all()
    with pytest.raises(ValueError, match=r"guessed depth must be \[40, 60\]"):
        seed_depth(ramp, valid, True, guessed[:10])


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


def test_a_grayscale_rigs_views_come_back_grayscale():
    """Renders with one value in all three channels are repaired as grayscale by the packaged
    base (which tints them otherwise, having learnt colour scenes too); colour stays colour."""
    from gsfix_online.fixer.inference import repair

    rng = np.random.default_rng(0)
    gray = rng.integers(40, 200, (48, 64, 1)).astype(np.uint8).repeat(3, axis=2)
    mesh = gray.copy()
    gs = gray.copy()
    gs[:, 30:] = 0  # a hole in the 3DGS render: GSFixer inpaints it
    cfg = dataclasses.replace(FixerConfig(), inference=InferenceConfig(steps=1, shifts=1))
    rep = ViewRepairer(cfg)
    rep.load_base()
    out = rep.repair(gs, mesh).image
    assert out.shape == (48, 64, 3) and out.dtype == np.uint8
    assert (out[..., 0] == out[..., 1]).all() and (out[..., 0] == out[..., 2]).all()

    def one(img):  # the first channel, as the model's grayscale input
        return torch.from_numpy(img[..., :1].copy()).permute(2, 0, 1)[None].float() / 255

    want = repair(rep.bundle, one(mesh), one(gs), cfg.inference).images[0, 0].numpy()
    np.testing.assert_array_equal(out[..., 0], np.rint(np.clip(want, 0, 1) * 255).astype(np.uint8))
    tinted = repair(rep.bundle, one(mesh).expand(-1, 3, -1, -1), one(gs).expand(-1, 3, -1, -1),
                    cfg.inference).images[0]  # fmt: skip
    assert float((tinted[0] - tinted[2]).abs().mean()) > 1 / 255  # what the gray path avoids
    colour = gs.copy()
    colour[..., 0] = np.clip(colour[..., 0].astype(int) + 40, 0, 255).astype(np.uint8)
    mixed = rep.repair(colour, mesh).image  # one colour render: repaired in colour
    assert (mixed[..., 0] != mixed[..., 2]).any()


def _ref_repairer() -> ViewRepairer:
    from tests.fixer.conftest import tiny_model_cfg

    cfg = FixerConfig(model=tiny_model_cfg("mesh+gs+ref"), inference=InferenceConfig(steps=1))
    rep = ViewRepairer(cfg)
    rep.load_base()
    return rep


def test_a_ref_model_without_a_warp_takes_the_mesh_render_in_the_reference_slot():
    """No warp (None) is a warp without pixels: the reference slot shows the mesh render. A warp
    with pixels changes the repair; colours under its holes do not."""
    rep = _ref_repairer()
    rng = np.random.default_rng(1)
    gs, mesh, ref = (rng.integers(0, 255, (16, 24, 3)).astype(np.uint8) for _ in range(3))
    none = np.zeros((16, 24), bool)
    no_warp = rep.repair(gs, mesh).image
    np.testing.assert_array_equal(rep.repair(gs, mesh, ref, none).image, no_warp)
    np.testing.assert_array_equal(rep.repair(gs, mesh, mesh, ~none).image, no_warp)
    half = none.copy()
    half[:, :12] = True
    with_warp = rep.repair(gs, mesh, ref, half).image
    assert not np.array_equal(with_warp, no_warp)
    other = ref.copy()
    other[:, 12:] = 0  # under the warp's holes
    np.testing.assert_array_equal(rep.repair(gs, mesh, other, half).image, with_warp)


def test_a_ref_models_warp_is_checked_in_one_line():
    rep = _ref_repairer()
    img = np.zeros((16, 24, 3), np.uint8)
    for args, msg in (
        ((img, None), "ref_color and ref_valid must be given together"),
        ((img[:8], np.zeros((16, 24), bool)), r"ref_color must be uint8 \[16, 24, 3\], got"),
        ((img, np.zeros((16, 24), np.uint8)), r"ref_valid must be bool \[16, 24\], got uint8"),
    ):
        with pytest.raises(ValueError, match=msg):
            rep.repair(img, img, *args)


def test_a_render_that_repaired_views_grew_is_a_hole_to_fit():
    """Where half the 3DGS render's colour or more comes from Gaussians grown from other
    repaired views, the map shows a fill, not what a frame saw: the view fits its delivered
    image there (a hole) in every mode but ``all``, so later repairs do not repaint it."""
    alpha = np.ones((20, 30), np.float32)
    alpha[5:8, 10:12] = 0.2  # a hole
    synth = np.zeros((20, 30), np.float32)
    synth[12:16, 2:6] = 0.8  # grown for another view
    synth[0:3, 20:25] = 0.3  # mostly the frames' Gaussians
    rep = np.zeros((20, 30), bool)
    want = (alpha < 0.5) | (synth >= 0.5)
    for mode, kw in (("holes", {}), ("delivered", {"replaced": rep})):
        m = distill_mask(alpha, 0.5, mode, dilate_px=0, synthesised=synth, **kw)
        np.testing.assert_array_equal(m == 255, want)
    np.testing.assert_array_equal(  # no share given: as before
        distill_mask(alpha, 0.5, "holes", 0, synthesised=None) == 255, alpha < 0.5
    )
    assert distill_mask(alpha, 0.5, "all", synthesised=synth) is None
    with pytest.raises(ValueError, match=r"synthesised must be \[20, 30\] like gs_alpha"):
        distill_mask(alpha, 0.5, "holes", synthesised=synth[:4])
