"""The floor under every repair: regions, per-region errors, the choice and the composed output."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gsfix_online.repair.fallback import (
    FLAT,
    REGIONS,
    Choice,
    HeldOutSample,
    RegionErrors,
    accumulate,
    baseline_candidates,
    blend,
    choose,
    compose,
    far_regions,
    fixer_only,
    flat_holes,
    for_view,
    held_out_choices,
    measure,
    measure_each,
    regions,
    replaced,
)

H, W = 20, 24


def test_regions_follow_which_map_covers_the_pixel() -> None:
    alpha = np.array([[1.0, 1.0, 0.2, 0.2]], np.float32)
    valid = np.array([[True, False, True, False]])
    assert regions(alpha, valid).tolist() == [[0, 1, 2, 3]]
    assert [REGIONS[i] for i in regions(alpha, valid)[0]] == ["both", "gs_only", "mesh_only",
                                                              "neither"]  # fmt: skip


def _errors(fixed: int, inpaint: int, mesh_inpaint: int, region: np.ndarray) -> RegionErrors:
    gt = np.full((H, W, 3), 100, np.uint8)
    cands = {k: np.full((H, W, 3), 100 + d, np.uint8)
             for k, d in (("fixed", fixed), ("inpaint", inpaint), ("mesh_inpaint", mesh_inpaint))}  # fmt: skip
    e = RegionErrors()
    accumulate(e, gt, cands, region)
    return e


def test_the_choice_takes_the_lowest_error_and_gsfixer_only_with_a_margin() -> None:
    region = np.zeros((H, W), np.uint8)
    region[:, W // 2 :] = 3  # half both, half neither
    e = _errors(fixed=4, inpaint=10, mesh_inpaint=6, region=region)
    c = choose(e, min_pixels=10)
    # without a reference warp, ref_inpaint is mesh_inpaint: the same error
    assert c.mse["both"] == {
        "fixed": 16.0,
        "inpaint": 100.0,
        "mesh_inpaint": 36.0,
        "ref_inpaint": 36.0,
    }
    assert c.per_region["both"] == "fixed" and c.per_region["neither"] == "fixed"
    # regions nobody measured take the best candidate over all pixels
    assert c.per_region["gs_only"] == c.per_region["mesh_only"] == "fixed"
    # a tie (within the margin) goes to the free fallback
    tie = choose(_errors(fixed=6, inpaint=10, mesh_inpaint=6, region=region), min_pixels=10)
    assert set(tie.per_region.values()) == {"mesh_inpaint"}


def test_a_region_with_too_few_pixels_takes_the_backup_measurement() -> None:
    """A sliver of 'neither' (2 % of the pixels) is not measured by itself: with min_fraction
    above its share it takes what a backup measurement (holes cut in) chose there, and without
    a backup the candidate best over all pixels."""
    region = np.zeros((H, W), np.uint8)
    region[:, : W // 2] = 0
    region[:, W // 2 :] = 1  # both | gs_only
    region[0, :10] = 3  # 10 px of neither: 2 % of 480
    e = _errors(fixed=10, inpaint=4, mesh_inpaint=6, region=region)
    e.sse["neither"]["fixed"] = 0.0  # a lucky sliver: GSFixer exact there (hard choices: the
    # blends' sums are left as the constant images made them)
    assert choose(e, min_pixels=5, blend=False).per_region["neither"] == "fixed"
    thin = choose(e, min_pixels=5, min_fraction=0.05, blend=False)
    assert thin.per_region["neither"] == "inpaint" and "overall best" in thin.why
    cut = np.full((H, W), 3, np.uint8)  # the backup: all neither, where GSFixer is best
    backup = _errors(fixed=2, inpaint=9, mesh_inpaint=9, region=cut)
    c = choose(e, min_pixels=5, min_fraction=0.05, backup=backup, blend=False)
    assert c.per_region == {"both": "inpaint", "gs_only": "inpaint", "mesh_only": "inpaint",
                            "neither": "fixed"}  # fmt: skip
    assert "backup measurement" in c.why and c.pixels["neither"] == 10


def test_a_choice_round_trips_through_json() -> None:
    region = np.zeros((H, W), np.uint8)
    c = choose(_errors(1, 2, 3, region), min_pixels=10)
    back = Choice.from_json(c.to_json())
    assert back.per_region == c.per_region and back.pixels == c.pixels
    assert back.mse["both"] == c.mse["both"] and np.isnan(back.mse["neither"]["fixed"])
    assert fixer_only().per_region == dict.fromkeys(REGIONS, "fixed")


def test_without_the_fixer_its_regions_take_mesh_fill_and_telea() -> None:
    c = Choice({"both": "fixed", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
                "neither": "fixed"}, {}, {"both": 7}, 3, "measured")  # fmt: skip
    got = c.without_fixer()
    assert got.per_region == {"both": "inpaint", "gs_only": "inpaint",
                              "mesh_only": "mesh_inpaint", "neither": "inpaint"}  # fmt: skip
    assert (got.pixels, got.samples, got.why) == ({"both": 7}, 3, "measured")
    assert c.per_region["both"] == "fixed"  # the original is unchanged


def test_without_the_fixer_its_regions_take_the_fallback_measured_better_there() -> None:
    nan = float("nan")
    mse = {"both": {"fixed": 1.0, "inpaint": 5.0, "mesh_inpaint": 3.0},
           "gs_only": {"fixed": 1.0, "inpaint": 2.0, "mesh_inpaint": 4.0},
           "mesh_only": {"fixed": 1.0, "inpaint": nan, "mesh_inpaint": 2.0},
           "neither": {"fixed": 1.0, "inpaint": 4.0, "mesh_inpaint": nan}}  # fmt: skip
    c = Choice(dict.fromkeys(REGIONS, "fixed"), mse, {}, 4, "measured", {}, {},
               dict.fromkeys(REGIONS, "fixed"))  # fmt: skip
    want = {"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
            "neither": "inpaint"}  # fmt: skip
    got = c.without_fixer()
    assert got.per_region == want and got.hard == want
    assert Choice.from_json(c.to_json()).without_fixer().per_region == want


def test_the_overall_best_weighs_each_region_by_its_pixels() -> None:
    region = np.zeros((H, W), np.uint8)
    region[:, W // 4 :] = 3  # a quarter both, three quarters neither
    e = _errors(fixed=4, inpaint=10, mesh_inpaint=6, region=region)
    e.sse["both"]["inpaint"] = 0.0  # the 3DGS render exact where it covers (hard choices)
    c = choose(e, min_pixels=10, blend=False)
    assert c.per_region["both"] == "inpaint" and c.per_region["neither"] == "fixed"
    # over all pixels: fixed 16, inpaint 0.75 * 100 = 75, mesh_inpaint 36
    assert c.overall_best() == "fixed" and "overall best fixed" in c.why
    e.sse["neither"]["inpaint"] = 0.0
    assert choose(e, min_pixels=10, blend=False).overall_best() == "inpaint"
    assert fixer_only().overall_best() is None  # nothing measured


def test_a_view_beyond_the_held_out_frames_reach_takes_the_mesh_first() -> None:
    region = np.zeros((H, W), np.uint8)
    region[:, W // 4 :] = 3
    trainer = choose(_errors(fixed=4, inpaint=10, mesh_inpaint=6, region=region), min_pixels=10)
    near = Choice(dict.fromkeys(REGIONS, "inpaint"), trainer.mse, trainer.pixels, 2, "held out")
    # as near the keyframes as the farthest held-out frame, or nearer: the held-out choice
    assert for_view(0.3, near, 0.3, trainer) == (near, "held-out frames")
    assert for_view(None, near, 0.3, trainer) == (near, "held-out frames")  # no keyframe yet
    # farther (without blends): the mesh where it covers, the 3DGS render where only it does,
    # and GSFixer and mesh + Telea half and half where neither does, whatever the trainer
    # measured best there (its measurement does not reach such views)
    c, source = for_view(1.2, near, 0.3, trainer, blend=False)
    assert source == "mesh first"
    assert [c.source(r) for r in REGIONS] == [("mesh_inpaint", 0.0), ("inpaint", 0.0),
                                              ("mesh_inpaint", 0.0), ("mesh_inpaint", 0.5)]  # fmt: skip
    assert "1.20 m" in c.why and "held-out frames reach 0.30 m" in c.why
    assert "GSFixer 0.5 + mesh + Telea 0.5" in c.why
    # the rule before, one candidate per region, is recorded: the trainer's overall best there
    assert c.hard == {"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
                      "neither": "fixed"}  # fmt: skip
    # no held-out frames: every view
    c, source = for_view(0.01, None, None, trainer, blend=False)
    assert source == "mesh first" and c.source("neither") == ("mesh_inpaint", 0.5)
    assert c.per_region["both"] == "mesh_inpaint" and "no held-out frames" in c.why
    # the share is the user's: 1 is GSFixer alone, 0 mesh + Telea alone, as is a trainer's
    # fallback best overall
    e = _errors(fixed=9, inpaint=10, mesh_inpaint=6, region=region)
    for share, want in ((1.0, ("fixed", 1.0)), (0.0, ("mesh_inpaint", 0.0)),
                        (0.25, ("mesh_inpaint", 0.25))):  # fmt: skip
        for t in (trainer, choose(e, min_pixels=10)):
            c, _ = for_view(1.2, near, 0.3, t, blend=False, neither_share=share)
            assert c.source("neither") == want and c.per_region["gs_only"] == "inpaint"
    # no trainer measurement: the held-out choice everywhere, else GSFixer as before
    assert for_view(1.2, near, 0.3, fixer_only()) == (near, "held-out frames")
    assert for_view(1.2, None, None, fixer_only())[1] == "trainer"


def test_compose_takes_each_region_from_its_candidate() -> None:
    region = np.zeros((H, W), np.uint8)
    region[:5], region[5:10], region[10:15] = 1, 2, 3
    cands = {k: np.full((H, W, 3), v, np.uint8)
             for k, v in (("fixed", 10), ("inpaint", 20), ("mesh_inpaint", 30))}  # fmt: skip
    c = Choice({"both": "fixed", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
                "neither": "inpaint"}, {}, {}, 0, "")  # fmt: skip
    out = compose(cands, region, c)
    assert out[:5].max() == out[:5].min() == 20 and out[5:10].min() == 30
    assert out[10:15].min() == 20 and out[15:].max() == 10


def test_replaced_marks_covered_pixels_whose_output_is_not_the_3dgs_render() -> None:
    region = np.zeros((H, W), np.uint8)
    region[:5], region[5:10], region[10:15] = 1, 2, 3
    cands = {k: np.full((H, W, 3), v, np.uint8)
             for k, v in (("fixed", 10), ("inpaint", 20), ("mesh_inpaint", 30))}  # fmt: skip
    for both, gs_only in (("fixed", "inpaint"), ("inpaint", "mesh_inpaint"), ("inpaint",) * 2):
        c = Choice({"both": both, "gs_only": gs_only, "mesh_only": "fixed",
                    "neither": "fixed"}, {}, {}, 0, "")  # fmt: skip
        r = replaced(region, c)
        assert r.dtype == bool and r.shape == (H, W)
        # where the 3DGS map covers the view: exactly the pixels compose did not take from it
        covered = region <= 1
        np.testing.assert_array_equal(r[covered], (compose(cands, region, c) != 20)[covered, 0])
        assert not r[~covered].any()  # holes are the holes mask's, not this one's


def test_feathered_compose_blends_only_across_seams() -> None:
    """A seam between two regions blends over a few pixels (a Gaussian of sigma feather_px);
    far from it each region keeps its candidate exactly, and one candidate everywhere is exact."""
    h, w = 16, 40
    region = np.zeros((h, w), np.uint8)
    region[:, 20:] = 3  # both | neither
    cands = {"fixed": np.full((h, w, 3), 200, np.uint8),
             "inpaint": np.full((h, w, 3), 100, np.uint8),
             "mesh_inpaint": np.full((h, w, 3), 0, np.uint8)}  # fmt: skip
    c = Choice({"both": "inpaint", "gs_only": "inpaint", "mesh_only": "inpaint",
                "neither": "fixed"}, {}, {}, 0, "")  # fmt: skip
    hard = compose(cands, region, c)
    soft = compose(cands, region, c, feather_px=2.0)
    np.testing.assert_array_equal(hard[:, :20], 100)
    np.testing.assert_array_equal(hard[:, 20:], 200)
    row = soft[8, :, 0].astype(int)
    assert (row[:12] == 100).all() and (row[-12:] == 200).all()  # 4 sigma away: exact
    assert (np.diff(row) >= 0).all()  # a monotone ramp across the seam
    assert row[19] == pytest.approx(150 - 100 * 0.0995, abs=2)  # Gaussian CDF at -0.25 sigma
    assert row[20] == pytest.approx(150 + 100 * 0.0995, abs=2)
    same = Choice(dict.fromkeys(REGIONS, "fixed"), {}, {}, 0, "")
    np.testing.assert_array_equal(compose(cands, region, same, feather_px=3.0), cands["fixed"])


def _stripes(h: int, w: int, lo: int, hi: int) -> np.ndarray:  # [h, w, 3] 2-px vertical bars
    bars = np.where((np.arange(w) // 2) % 2 == 0, lo, hi).astype(np.uint8)
    return np.broadcast_to(bars[None, :, None], (h, w, 3)).copy()


def test_a_blend_of_fills_that_disagree_on_a_shape_takes_one_shape_not_their_mean() -> None:
    """Telea's facets (here stripes) against GSFixer's flat wash: the per-pixel mean shows the
    stripes through the wash (a double image); the blend keeps GSFixer's shape (flat) in the
    mixed colour. GSFixer's own stripes over a flat fill stay, at GSFixer's share."""
    h, w = 48, 64
    fixed = np.full((h, w, 3), 100, np.uint8)
    telea = _stripes(h, w, 60, 200)  # mean colour 130
    mean = blend(fixed, telea, 0.5, detail_px=0.0)
    assert set(np.unique(mean[20, 20:44, 0])) == {80, 150}  # both at half: the double image
    out = blend(fixed, telea, 0.5)
    inner = out[16:32, 16:48].astype(int)
    assert inner.max() - inner.min() <= 2  # no stripe left: GSFixer's flat shape
    assert inner.mean() == pytest.approx(115, abs=1.5)  # in the colour of the 0.5/0.5 mix
    out = blend(_stripes(h, w, 60, 200), fixed, 0.5)[16:32, 16:48].astype(int)
    assert out.max() - out.min() == pytest.approx(70, abs=2)  # GSFixer's, at its share
    assert out.mean() == pytest.approx(115, abs=1.5)


def test_a_blend_of_fills_that_agree_is_their_mean() -> None:
    """Two fills that differ only by smooth changes of colour (a ramp, an offset): the blend is
    their mean by the share, to rounding; detail_px 0 is the per-pixel mean exactly."""
    h, w = 32, 96
    ramp = np.rint(np.linspace(40, 200, w))[None, :, None] * np.ones((h, 1, 3))
    fallback = ramp.astype(np.uint8)
    fixed = (ramp + 30).astype(np.uint8)
    inner = (slice(None), slice(24, 72))  # 3 sigma in: the replicated border bends the ends
    for share in (0.0, 0.3, 0.5, 1.0):
        want = np.rint(share * fixed.astype(float) + (1 - share) * fallback).astype(int)
        got = blend(fixed, fallback, share).astype(int)
        assert np.abs(got - want)[inner].max() <= 1
        np.testing.assert_array_equal(blend(fixed, fallback, share, detail_px=0.0), want)


def test_a_blend_rejects_a_share_outside_0_1() -> None:
    img = np.zeros((4, 4, 3), np.uint8)
    with pytest.raises(ValueError, match=r"share must be in \[0, 1\], got 1.5"):
        blend(img, img, 1.5)


def test_compose_blends_far_no_map_parts_without_a_double_image_and_feathers_the_seam() -> None:
    """A far view: the mesh on the left, GSFixer and Telea half and half where no map covers
    (right). The no-map part has GSFixer's shape; across the seam the output changes by a few
    levels a pixel (a feathered ramp), not in a step."""
    h, w = 40, 80
    region = np.full((h, w), 2, np.uint8)  # mesh_only
    region[:, 40:] = 3  # neither
    cands = {"fixed": np.full((h, w, 3), 100, np.uint8), "inpaint": np.zeros((h, w, 3), np.uint8),
             "mesh_inpaint": _stripes(h, w, 60, 200)}  # fmt: skip
    cands["mesh_inpaint"][:, :52] = 220  # the mesh where it covers, and Telea carrying it on
    c = Choice({"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
                "neither": "mesh_inpaint"}, {}, {}, 0, "", {"neither": 0.5})  # fmt: skip
    out = compose(cands, region, c, feather_px=4.0).astype(int)
    before = compose(cands, region, c, feather_px=4.0, detail_px=0.0).astype(int)
    far = (slice(8, 32), slice(60, 76))  # 20 px and more from the seam
    assert np.abs(np.diff(before[far], axis=1)).max() >= 60  # the mean: stripes in the wash
    assert np.abs(np.diff(out[far], axis=1)).max() <= 2  # one shape (the colours' slow drift)
    row = out[20, :, 0]
    assert (row[:24] == 220).all()  # the mesh, exactly, 4 sigma from the seam
    assert np.abs(np.diff(row[24:56])).max() <= 12  # 220 -> ~130 over the seam: a ramp
    hard = compose(cands, region, c, feather_px=0.0).astype(int)[20, :, 0]
    assert abs(hard[40] - hard[39]) >= 60  # without feathering: a step


def _two_holes(h: int = 40, w: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """A far view's regions (mesh everywhere but two no-map holes) and its mesh + Telea: the
    left hole in a flat grey wall, the right one in a wall of 8 px stripes."""
    region = np.full((h, w), 2, np.uint8)
    region[14:26, 10:26] = 3
    region[14:26, 50:66] = 3
    telea = np.full((h, w, 3), 120, np.uint8)
    telea[:, 40:] = _stripes(h, w - 40, 60, 200)
    return region, telea


def test_flat_holes_are_the_no_map_holes_whose_surroundings_are_flat() -> None:
    region, around = _two_holes()
    rng = np.random.default_rng(0)
    noisy = np.clip(around + rng.normal(0, 3, (*around.shape[:2], 1)), 0, 255).astype(np.uint8)
    flat = flat_holes(region, noisy)
    assert flat.dtype == bool and flat.shape == region.shape
    np.testing.assert_array_equal(flat[:, :40], region[:, :40] == 3)  # sensor-like noise: flat
    assert not flat[:, 40:].any()  # stripes around it: GSFixer's part stays
    assert not flat_holes(region, noisy, max_std=0).any()  # 0: never
    assert not flat_holes(region, noisy, max_std=2.0)[:, :40].any()  # noise of 3 levels > 2
    assert not flat_holes(np.full((8, 8), 3, np.uint8), noisy[:8, :8]).any()  # nothing around


def test_a_far_view_is_a_hole_where_only_the_3dgs_map_covers_it_and_flat_holes_take_telea() -> None:
    """A far view trusts the mesh alone: what only the 3DGS map covers is a hole (but not one
    to distil: the map keeps what it observed there). Where it blends GSFixer into mesh + Telea, a hole in a flat wall
    takes mesh + Telea alone; the other hole keeps the blend, and so does its provenance."""
    from gsfix_online.repair.provenance import FILL, FIXER, candidate_sources, provenance

    region, telea = _two_holes(h=60)
    region[48:56, 60:70] = 1  # gs_only, in the striped part
    covered = region == 1
    cands = {"fixed": np.full(telea.shape, 30, np.uint8), "inpaint": telea, "mesh_inpaint": telea}
    c = Choice({"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
                "neither": "mesh_inpaint"}, {}, {}, 0, "", {"neither": 0.5})  # fmt: skip
    far = far_regions(region, cands, c, holes=covered)
    assert (far[14:26, 10:26] == FLAT).all() and (far[14:26, 50:66] == 3).all()
    assert (far[48:56, 60:70] == 3).all()  # 3DGS only: a hole, textured around
    changed = (region == 3) & (far == FLAT) | covered
    np.testing.assert_array_equal(far != region, changed)
    assert (far_regions(region, cands, c)[48:56, 60:70] == 1).all()  # no holes given
    np.testing.assert_array_equal(far_regions(region, cands, c, 4.0, 0), region)
    half = np.zeros_like(covered)
    half[48:56, 60:65] = True  # holes only where given, only where the 3DGS map alone covers
    half[0:4, 0:4] = True
    np.testing.assert_array_equal(far_regions(region, cands, c, 4.0, 0, half) != region,
                                  half & covered)  # fmt: skip
    # the 3DGS render it no longer shows is not distilled: the map keeps its observation there
    assert not replaced(far, c).any() and not replaced(region, c).any()
    out = compose(cands, far, c, feather_px=4.0).astype(int)
    before = compose(cands, region, c, feather_px=4.0).astype(int)
    assert (out[18:22, 14:22] == 120).all()  # the flat hole: Telea's wall, not 75 (the blend)
    assert (before[18:22, 14:22] < 100).all()
    np.testing.assert_array_equal(out[14:26, 50:66], before[14:26, 50:66])  # the blend, as before
    src = candidate_sources(covered.astype(np.float32), np.isin(region, (0, 2)))
    prov = provenance(src, far, c, 4.0)
    assert (prov.source[18:22, 14:22] == FILL).all()
    assert (prov.weights[FIXER][18:22, 14:22] == 0).all()
    was = provenance(src, region, c, 4.0)
    np.testing.assert_allclose(prov.weights[:, 14:26, 50:66], was.weights[:, 14:26, 50:66],
                               atol=1e-3)  # fmt: skip
    assert (was.weights[FIXER][18:22, 14:22] > 0.3).all()  # the blend's share there before
    assert (was.weights[FIXER][50:54, 62:68] == 0).all()  # the 3DGS render before
    assert (prov.weights[FIXER][50:54, 62:68] > 0.2).all()  # repaired as a hole (a small one)
    # GSFixer alone in the no-map parts: the flat hole takes mesh + Telea
    alone = Choice({**c.per_region, "neither": "fixed"}, {}, {}, 0, "")
    assert (compose(cands, far, alone)[18:22, 14:22] == 120).all()
    # a choice with no GSFixer in the no-map parts: no hole is told apart
    none = Choice(dict(c.per_region), {}, {}, 0, "")
    assert not (far_regions(region, cands, none) == FLAT).any()


def test_measure_falls_back_where_the_repair_is_worse() -> None:
    """A 'GSFixer' that outputs grey loses to the renders and Telea on a smooth ramp (which
    Telea continues well): no region takes it; one that returns the truth wins
    where no map covers the view."""
    ramp = np.linspace(0, 255, W)[None, :, None] * np.ones((H, 1, 3))
    gt = np.rint(ramp).astype(np.uint8)
    sample = HeldOutSample(gt, gt.copy(), np.ones((H, W), np.float32), gt.copy(),
                           np.ones((H, W), bool))  # fmt: skip

    def holes(r: np.random.Generator, h: int, w: int) -> np.ndarray:
        m = np.zeros((h, w), bool)
        m[4:12, 6:16] = True
        return m

    grey = measure([sample], lambda gs, mesh: np.full_like(gs, 128), holes)
    c = choose(grey, min_pixels=10, blend=False)
    assert c.samples == 1 and not c.uses_fixer
    assert c.per_region["both"] in ("inpaint", "mesh_inpaint")
    oracle = measure([sample], lambda gs, mesh: gt.copy(), holes)
    c = choose(oracle, min_pixels=10)
    assert c.per_region["neither"] == "fixed"  # only the oracle knows what no map holds
    # where a render is exact too, the tie goes to the free fallback
    assert c.per_region["both"] in ("inpaint", "mesh_inpaint")
    assert oracle.pixels["neither"] == 80 and oracle.sse["neither"]["fixed"] == pytest.approx(0)


def test_measure_without_hole_masks_takes_the_samples_as_they_are() -> None:
    gt = np.full((H, W, 3), 100, np.uint8)
    s = HeldOutSample(gt, gt, np.ones((H, W), np.float32), gt, np.ones((H, W), bool))
    errors = measure([s], lambda gs, mesh: gs, None, cuts=("none",))
    assert errors.pixels["both"] == H * W and errors.pixels["neither"] == 0
    with pytest.raises(ValueError, match="need hole_masks"):
        measure([s], lambda gs, mesh: gs, None)


def test_per_sample_errors_sum_to_the_measurement_and_one_can_be_taken_back_out() -> None:
    rng = np.random.default_rng(3)
    samples = []
    for _ in range(3):
        gt = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        gs = np.clip(gt.astype(int) + rng.integers(-30, 31, gt.shape), 0, 255).astype(np.uint8)
        samples.append(HeldOutSample(gt, gs, np.ones((H, W), np.float32), gt // 2,
                                     np.ones((H, W), bool)))  # fmt: skip

    def holes(r: np.random.Generator, h: int, w: int) -> np.ndarray:
        m = np.zeros((h, w), bool)
        m[int(r.integers(0, h // 2)) :, : W // 3] = True
        return m

    total = measure(samples, lambda gs, mesh: gs, holes)
    each = measure_each(samples, lambda gs, mesh: gs, holes)
    assert total.samples == 3 and [e.samples for e in each] == [1, 1, 1]
    summed = each[0].combined(each[1]).combined(each[2])
    assert summed.pixels == total.pixels
    assert summed.sse["neither"]["inpaint"] == pytest.approx(total.sse["neither"]["inpaint"])
    rest = total.combined(each[1], -1)
    assert rest.samples == 2 and rest.pixels == each[0].combined(each[2]).pixels
    assert rest.sse["both"]["mesh_inpaint"] == pytest.approx(
        each[0].sse["both"]["mesh_inpaint"] + each[2].sse["both"]["mesh_inpaint"])  # fmt: skip
    h = held_out_choices(each, [4, 5, 6], min_pixels=10)
    assert h.all.samples == 3 and {f: c.samples for f, c in h.without.items() if c} == {
        4: 2, 5: 2, 6: 2}  # fmt: skip
    assert held_out_choices(each[:1], [4], min_pixels=10).without == {4: None}
    with pytest.raises(ValueError, match="2 ids for 3 measured frames"):
        held_out_choices(each, [4, 5])


def test_a_blend_takes_the_share_of_gsfixer_with_the_least_error() -> None:
    """GSFixer 10 levels too bright, mesh fill + Telea 10 too dark: half of each is exact, which
    neither alone is; a hard choice can only tie them (and gives the free fallback)."""
    region = np.zeros((H, W), np.uint8)
    e = _errors(fixed=10, inpaint=-10, mesh_inpaint=20, region=region)
    c = choose(e, min_pixels=10, blend=True)
    assert c.source("both") == ("inpaint", 0.5) and c.uses_fixer
    assert (
        c.fit["both"] == {"inpaint": 0.5, "mesh_inpaint": 1.0, "ref_inpaint": 1.0}
        and c.fit["all"]["inpaint"] == 0.5
    )
    assert c.describe()["both"] == "0.50 fixed + inpaint" and "0.50 fixed + inpaint" in c.why
    hard = choose(e, min_pixels=10, blend=False)
    assert hard.source("both") == ("inpaint", 0.0) and not hard.uses_fixer
    assert c.hardened().per_region == hard.per_region == c.hard and c.hardened().share == {}
    gt = np.full((H, W, 3), 100, np.uint8)
    cands = {k: np.full((H, W, 3), 100 + d, np.uint8)
             for k, d in (("fixed", 10), ("inpaint", -10), ("mesh_inpaint", 20))}  # fmt: skip
    np.testing.assert_array_equal(compose(cands, region, c), gt)
    np.testing.assert_array_equal(compose(cands, region, c, feather_px=3.0), gt)
    assert replaced(region, c).all() and not replaced(region, hard).any()
    back = Choice.from_json(c.to_json())
    assert back.share == dict.fromkeys(REGIONS, 0.5) and back.fit == c.fit  # unmeasured: overall
    assert back.hard == c.hard
    assert back.without_fixer().source("both") == ("inpaint", 0.0)
    old = json.loads(c.to_json())  # a run recorded before blends
    del old["share"], old["fit"]
    assert Choice.from_json(json.dumps(old)).source("both") == ("inpaint", 0.0)


def test_the_blend_share_is_the_least_squares_optimum() -> None:
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)

    def noisy(sigma: float, bias: float) -> np.ndarray:
        return np.clip(gt + rng.normal(bias, sigma, gt.shape), 0, 255).round().astype(np.uint8)

    cands = {"fixed": noisy(20, 5), "inpaint": noisy(30, -5), "mesh_inpaint": noisy(40, 0)}
    region = np.zeros((H, W), np.uint8)
    e = RegionErrors()
    accumulate(e, gt, cands, region)
    c = choose(e, min_pixels=10, margin=0.0, blend=True)
    name, w = c.source("both")
    grid = np.linspace(0, 1, 201)
    errs = {b: [np.mean((g * cands["fixed"].astype(float) + (1 - g) * cands[b] - gt) ** 2)
                for g in grid] for b in ("inpaint", "mesh_inpaint")}  # fmt: skip
    best_b = min(errs, key=lambda b: min(errs[b]))
    assert name == best_b and 0.0 < w < 1.0
    assert w == pytest.approx(grid[int(np.argmin(errs[best_b]))], abs=0.006)
    for b in errs:
        assert c.fit["both"][b] == pytest.approx(grid[int(np.argmin(errs[b]))], abs=0.006)


def test_a_far_view_blends_gsfixer_into_the_mesh_by_the_trainers_shares() -> None:
    region = np.zeros((H, W), np.uint8)
    region[:, W // 2 :] = 3  # half both, half neither
    trainer = choose(
        _errors(fixed=10, inpaint=-10, mesh_inpaint=-10, region=region), 10, blend=True
    )
    near = choose(_errors(fixed=1, inpaint=5, mesh_inpaint=6, region=region), min_pixels=10)
    c, source = for_view(1.2, near, 0.3, trainer, blend=True)
    assert source == "mesh first"
    assert c.source("both") == ("mesh_inpaint", 0.5)  # the mesh first, blended by the fit
    assert c.source("neither") == trainer.source("neither") and c.source("neither")[1] == 0.5
    assert c.source("gs_only") == ("inpaint", 0.5)  # fitted over all pixels, as measured
    assert c.hard == {"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
                      "neither": trainer.overall_best()}  # fmt: skip
    hard, _ = for_view(1.2, near, 0.3, trainer, blend=False, neither_share=0.0)
    assert {**hard.per_region, "neither": trainer.overall_best()} == c.hard
    assert [hard.source(r) for r in REGIONS] == [("mesh_inpaint", 0.0), ("inpaint", 0.0),
                                                 ("mesh_inpaint", 0.0), ("mesh_inpaint", 0.0)]  # fmt: skip


def test_the_reference_warp_is_a_fallback_that_wins_where_it_is_nearer_the_truth() -> None:
    """``ref_inpaint``: the warp where it has pixels, the mesh render under it, Telea in the
    rest; without a warp it is ``mesh_inpaint`` exactly. Where the warp is the truth and the
    renders are off, the measured choice takes it; a cut into the mesh cuts the warp too."""
    ramp = np.linspace(0, 255, W)[None, :, None] * np.ones((H, 1, 3))
    gt = np.rint(ramp).astype(np.uint8)
    off = np.clip(gt.astype(int) + 30, 0, 255).astype(np.uint8)  # the renders' colour error
    ones, every = np.ones((H, W), np.float32), np.ones((H, W), bool)
    bare = baseline_candidates(off, ones, off, every)
    np.testing.assert_array_equal(bare["ref_inpaint"], bare["mesh_inpaint"])
    part = every.copy()
    part[:, : W // 2] = False  # the references see the right half only
    mesh_valid = every.copy()
    mesh_valid[:4] = False  # and the mesh misses the top rows
    c = baseline_candidates(off, ones, off, mesh_valid, ref=gt, ref_valid=part)["ref_inpaint"]
    np.testing.assert_array_equal(c[:, W // 2 :], gt[:, W // 2 :])
    np.testing.assert_array_equal(c[4:, : W // 2], off[4:, : W // 2])
    assert c[:4, : W // 2].min() > 0  # Telea filled what neither has

    sample = HeldOutSample(gt, off, ones, off, every, ref=gt, ref_valid=every)
    errors = measure([sample], lambda gs, mesh: off, None, cuts=("none",))
    assert errors.sse["both"]["ref_inpaint"] == 0.0 < errors.sse["both"]["mesh_inpaint"]
    assert choose(errors, min_pixels=10).per_region["both"] == "ref_inpaint"
    mesh_cut = measure([sample], lambda gs, mesh: off, lambda r, h, w: ~part, cuts=("mesh",))
    # the cut half lost the mesh and the warp: the 3DGS render fills it (gs_only), no warp
    assert mesh_cut.pixels["gs_only"] == H * W // 2
    assert mesh_cut.sse["gs_only"]["ref_inpaint"] > 0.0
    assert mesh_cut.sse["both"]["ref_inpaint"] == 0.0


def test_the_reference_warps_holes_take_mesh_fill_on_the_surface_and_telea_off_it() -> None:
    from gsfix_online.repair.fallback import ref_inpaint

    gs, mesh, ref = (np.full((H, W, 3), v, np.uint8) for v in (60, 120, 200))
    ref_valid = np.zeros((H, W), bool)
    ref_valid[:, W // 2 :] = True  # the warp: the right half
    mesh_valid = np.ones((H, W), bool)
    mesh_valid[: H // 2, : W // 4] = False  # no surface top left
    alpha = np.ones((H, W), np.float32)
    alpha[H // 2 :, : W // 4] = 0.0  # the 3DGS map misses the bottom left
    out = ref_inpaint(mesh, mesh_valid, ref, ref_valid, gs, alpha)
    assert (out[:, W // 2 :] == 200).all()  # the warp
    assert (out[H // 2 :, W // 4 : W // 2] == 60).all()  # on the surface, 3DGS covers: 3DGS
    assert (out[H // 2 :, : W // 4] == 120).all()  # on the surface, no 3DGS: the mesh
    # no surface: Telea from around (the warp and mesh fill), not the 3DGS render there
    top_left = out[: H // 2 - 2, : W // 4 - 2]
    assert top_left.min() >= 60 and top_left.max() > 60  # Telea mixes 3DGS and mesh, not 3DGS alone
    np.testing.assert_array_equal(
        ref_inpaint(mesh, mesh_valid, ref, ref_valid)[H // 2 :, W // 4 : W // 2],
        mesh[H // 2 :, W // 4 : W // 2],
    )
