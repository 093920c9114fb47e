"""Where each output pixel came from: the weights per source, and the run folder's files."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from gsfix_online.repair.fallback import (
    FLAT,
    MESH_FIRST,
    REGIONS,
    Choice,
    compose,
    fixer_only,
    regions,
)
from gsfix_online.repair.outputs import RepairOutputs
from gsfix_online.repair.provenance import (
    FILL,
    FIXER,
    GS,
    GS_REPAIRED,
    MESH,
    SOURCES,
    candidate_sources,
    image,
    provenance,
)

H, W = 48, 64
CUT = (slice(16, 36), slice(20, 48))  # a region cut out of both maps: neither covers it


def maps() -> tuple[np.ndarray, np.ndarray]:  # gs alpha [H, W], mesh valid [H, W]
    alpha = np.ones((H, W), np.float32)
    alpha[6:, :10] = 0.0  # a mesh_only strip on the left, a gs_only one on top: no neither
    valid = np.ones((H, W), bool)
    valid[:6, 10:] = False
    alpha[CUT], valid[CUT] = 0.0, False
    return alpha, valid


COLOURS_BY_SOURCE = np.array(
    [[200, 0, 0], [0, 200, 0], [0, 0, 200], [200, 200, 0], [0, 0, 0], [0, 200, 200],
     [100, 0, 100]]
)  # one flat colour per source of SOURCES  # fmt: skip
REF_SEEN = np.zeros((H, W), bool)
REF_SEEN[20:40, 4:30] = True  # what the reference frames see: across the cut and the strip
# the share of the 3DGS render that Gaussians grown from repaired views make: all of it in a
# block of the gs_only strip and of the region both maps cover, a fifth in another block
GROWN = np.zeros((H, W), np.float32)
GROWN[0:5, 40:60] = 1.0
GROWN[38:46, 40:60] = 1.0
GROWN[38:46, 12:18] = 0.2


def run_with_renders(tmp_path, seed: int) -> tuple:
    """A run folder's writer, random 3DGS and mesh renders, a camera and a view's score."""
    rng = np.random.default_rng(seed)
    cam = {"K": [50.0, 0, 31.5, 0, 50.0, 23.5, 0, 0, 1], "T_world_cam": np.eye(4).ravel().tolist(),
           "width": W, "height": H}  # fmt: skip
    score = {"surface_fraction": 1.0, "hole_fraction": 0.2, "disagree_fraction": 0.0,
             "underobserved_fraction": math.nan}  # fmt: skip
    gs, mesh = (rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for _ in range(2))
    return RepairOutputs(tmp_path / "run"), gs, mesh, cam, score


def choice(per_region: dict[str, str], share: dict[str, float] | None = None) -> Choice:
    return Choice(per_region, {}, {}, 0, "", share or {})


def painted(sources: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each candidate painted by its pixels' sources, one flat colour per source."""
    return {c: COLOURS_BY_SOURCE[s].astype(np.uint8) for c, s in sources.items() if c != "gs"}


@pytest.mark.parametrize("feather_px", [0.0, 4.0])
@pytest.mark.parametrize(
    "per_region,share",
    [
        ({"both": "inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
          "neither": "fixed"}, {}),
        ({"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint",
          "neither": "mesh_inpaint"}, {"neither": 0.5}),
        (dict.fromkeys(REGIONS, "fixed"), {}),
        ({"both": "ref_inpaint", "gs_only": "inpaint", "mesh_only": "ref_inpaint",
          "neither": "ref_inpaint"}, {"neither": 0.4}),
    ],
)  # fmt: skip
def test_weights_reproduce_the_composed_image(per_region, share, feather_px):
    # The slow reference: compose candidates painted by source; the provenance's weights
    # times the source colours give the same image (to rounding)
    alpha, valid = maps()
    src = candidate_sources(alpha, valid, ref_valid=REF_SEEN, gs_synthesised=GROWN)
    assert (src["inpaint"] == GS_REPAIRED).any()
    ch = choice(per_region, share)
    region = regions(alpha, valid)
    prov = provenance(src, region, ch, feather_px)
    np.testing.assert_allclose(prov.weights.sum(axis=0), 1.0, atol=1e-5)
    want = compose(painted(src), region, ch, feather_px).astype(np.float32)
    got = np.einsum("shw,sc->hwc", prov.weights, COLOURS_BY_SOURCE.astype(np.float32))
    assert np.abs(got - want).max() <= 1.0


def test_a_blend_has_its_share_as_confidence_and_is_synthesised():
    alpha, valid = maps()
    ch = choice(dict.fromkeys(REGIONS, "inpaint"), {"neither": 0.3})
    prov = provenance(candidate_sources(alpha, valid), regions(alpha, valid), ch, detail_px=0.0)
    # where neither map covers: 0.3 GSFixer + 0.7 of inpaint, which is Telea's fill there
    assert prov.weights[FIXER][CUT] == pytest.approx(0.3)
    assert prov.weights[FILL][CUT] == pytest.approx(0.7)
    assert prov.source[CUT].tolist() == np.full((20, 28), FILL).tolist()
    assert prov.confidence[CUT] == pytest.approx(0.7)
    assert prov.synthesised[CUT] == pytest.approx(1.0)
    # where the 3DGS map covers: its render, observed, pure
    assert (prov.source[10:, 12:18] == GS).all() and (prov.confidence[10:, 12:18] == 1).all()
    assert (prov.source[10:, :10] == MESH).all()  # the mesh alone covers the left strip
    assert (prov.source[:6, 12:] == GS).all()  # the 3DGS map alone covers the top strip
    assert (prov.synthesised[10:, 12:18] == 0).all()


def test_a_blend_takes_its_fills_colours_from_where_they_came():
    """GSFixer by its share over the fill's colours blurred by detail_px: GSFixer weighs its
    share everywhere; near the hole's border part of the fill's share is the map whose colours
    Telea carried in; deep inside it is the fill's."""
    alpha, valid = maps()
    ch = choice(dict.fromkeys(REGIONS, "inpaint"), {"neither": 0.3})
    prov = provenance(candidate_sources(alpha, valid), regions(alpha, valid), ch, detail_px=3.0)
    np.testing.assert_allclose(prov.weights.sum(axis=0), 1.0, atol=1e-5)
    assert prov.weights[FIXER][CUT] == pytest.approx(0.3, abs=1e-6)
    fill = prov.weights[FILL][CUT]
    assert fill[10, 14] == pytest.approx(0.7, abs=0.01)  # the centre, 10 px from the border
    assert 0.3 < fill[0, 14] < 0.5  # on the border: about half the fill's share is the map's
    assert prov.weights[GS][CUT][0, 14] == pytest.approx(0.7 - fill[0, 14], abs=0.01)
    assert prov.synthesised[CUT][10, 14] == pytest.approx(1.0, abs=0.01)


def test_the_image_has_a_colour_per_source_and_a_legend():
    alpha, valid = maps()
    prov = provenance(candidate_sources(alpha, valid), regions(alpha, valid),
                      choice(dict.fromkeys(REGIONS, "inpaint"), {"neither": 0.5}),
                      detail_px=0.0)  # fmt: skip
    img = image(prov)
    assert img.dtype == np.uint8 and img.shape[0] > H and img.shape[1] >= W
    legend_rows = (img.shape[0] - H - 4) // 14
    assert legend_rows == 5  # gs, mesh, fixer, fill are present, "none" is not; and blends
    np.testing.assert_array_equal(image(prov, legend=False)[20, 30], [240, 95, 110])  # half/half
    pure = provenance(candidate_sources(alpha, valid), regions(alpha, valid),
                      choice(dict.fromkeys(REGIONS, "inpaint")))  # fmt: skip
    assert (image(pure).shape[0] - H - 4) // 14 == 3  # gs, mesh, fill; no blend


def test_candidate_sources_reject_mismatched_maps():
    with pytest.raises(ValueError, match=r"same \[H, W\], got \[4, 5\] and \[4, 4\]"):
        candidate_sources(np.ones((4, 5), np.float32), np.ones((4, 4), bool))


def test_a_runs_provenance_marks_the_cut_out_region_synthesised_and_the_rest_observed(tmp_path):
    alpha, valid = maps()
    out, gs, mesh, cam, score = run_with_renders(tmp_path, seed=0)
    # view 0: repaired with GSFixer where neither map covers, feathered seams, as a run does
    out.on_decision(0, True, "holes 20%", score, cam)
    out.on_renders(0, gs=gs, alpha=alpha, mesh=mesh, valid=valid)
    # (mesh_inpaint in the left strip would feather Telea's fill of the top strip into it)
    per_region = {"both": "inpaint", "gs_only": "inpaint", "mesh_only": "inpaint",
                  "neither": "fixed"}  # fmt: skip
    model = {"version": 1, "step": 5, "choice": per_region, "choice_share": {}, "feather_px": 2.0}
    out.on_fixed(0, gs, {}, model)
    # view 1: skipped without a measured choice: mesh fill + Telea in its holes
    out.on_decision(1, False, "few holes", score, cam)
    out.on_renders(1, gs=gs, alpha=alpha, mesh=mesh, valid=valid)
    for i in range(2):
        out.on_final(i, gs)
    m = out.write()
    cut = np.zeros((H, W), bool)
    cut[CUT] = True
    inside = cv2.erode(cut.astype(np.uint8), np.ones((13, 13), np.uint8)) > 0
    outside = cv2.dilate(cut.astype(np.uint8), np.ones((13, 13), np.uint8)) == 0
    for i, synth_source in ((0, FIXER), (1, FILL)):
        d = tmp_path / "run" / "views" / f"{i:03d}"
        with np.load(d / "provenance.npz") as z:
            assert z["sources"].tolist() == list(SOURCES)
            src, synth = z["source"], z["synthesised"].astype(np.float32)
            conf = z["confidence"].astype(np.float32)
        assert (src[inside] == synth_source).all() and (synth[inside] == 1.0).all()
        # away from the cut, observed (a Gaussian seam blend's tail: under 1 %)
        assert (synth[outside] < 0.01).all() and np.isin(src[outside], (GS, MESH)).all()
        assert (conf[outside] > 0.99).all()
        assert cv2.imread(str(d / "provenance.png")).shape[1] >= W
        shares = m["views"][i]["provenance"]
        # the cut, and the part of its seam blend that reaches out of it
        assert cut.mean() <= shares["synthesised"] <= 1.0 - outside.mean()
        assert m["views"][i]["files"]["provenance"] == f"views/{i:03d}/provenance.png"
    # a feathered seam: the border of the repaired view's cut is a blend of sources
    with np.load(tmp_path / "run" / "views" / "000" / "provenance.npz") as z:
        border = z["confidence"].astype(np.float32)[cut & ~inside]
    assert border.min() < 0.9
    assert "views/000/provenance.png" in (tmp_path / "run" / "report.html").read_text()
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["views"][1]["provenance"]


def test_a_view_repaired_before_choices_were_recorded_is_gsfixer_everywhere(tmp_path):
    out = RepairOutputs(tmp_path / "run")
    alpha, valid = maps()
    rec = out.view(0)
    rec.repair, rec.images = True, {"gs": np.zeros((H, W, 3), np.uint8), "alpha": alpha,
                                    "valid": valid, "output": np.zeros((H, W, 3), np.uint8)}  # fmt: skip
    assert out._output_recipe(rec)[0].per_region == fixer_only().per_region
    assert (out.view_provenance(rec).source == FIXER).all()


def test_the_recipe_blends_as_the_run_recorded(tmp_path):
    """A run records how its blends blurred the fallback (``detail_px``); a run recorded before
    blended by per-pixel means (0), and its provenance follows that."""
    out = RepairOutputs(tmp_path / "run")
    alpha, valid = maps()
    rec = out.view(0)
    rec.repair, rec.images = True, {"gs": np.zeros((H, W, 3), np.uint8), "alpha": alpha,
                                    "valid": valid, "output": np.zeros((H, W, 3), np.uint8)}  # fmt: skip
    rec.model = {"choice": dict.fromkeys(REGIONS, "inpaint"), "choice_share": {"neither": 0.3},
                 "feather_px": 0.0}  # fmt: skip
    assert out._output_recipe(rec)[1:] == (0.0, 0.0)
    assert out.view_provenance(rec).weights[FILL][CUT] == pytest.approx(0.7)
    rec.model["detail_px"] = 3.0
    assert out._output_recipe(rec)[1:] == (0.0, 3.0)
    fill = out.view_provenance(rec).weights[FILL][CUT]
    assert fill[10, 14] == pytest.approx(0.7, abs=0.01) and fill[0, 14] < 0.5


def test_reference_pixels_are_observed_and_the_rest_of_ref_inpaint_is_the_mesh_or_a_fill():
    from gsfix_online.repair.provenance import GS, MESH, REF

    alpha, valid = maps()
    src = candidate_sources(alpha, valid, ref_valid=REF_SEEN)["ref_inpaint"]
    assert (src[REF_SEEN] == REF).all()
    gs = alpha >= 0.5
    assert (src[~REF_SEEN & valid & gs] == GS).all() and (
        src[~REF_SEEN & valid & ~gs] == MESH
    ).all()
    assert (src[~REF_SEEN & ~valid] == FILL).all()
    prov = provenance(candidate_sources(alpha, valid, ref_valid=REF_SEEN), regions(alpha, valid),
                      choice(dict.fromkeys(REGIONS, "ref_inpaint")))  # fmt: skip
    assert prov.synthesised[REF_SEEN].max() == 0.0  # the robot filmed it
    assert prov.synthesised[~REF_SEEN & ~valid].min() == 1.0


def test_a_3dgs_render_that_repaired_views_grew_is_synthesised_not_observed():
    """Where Gaussians that distillation grew for other views make half the 3DGS render's
    colour or more, the map shows a fill, not what a frame saw: its pixels are gs_repaired,
    synthesised, in every candidate that takes the 3DGS render; under half, observed."""
    alpha, valid = maps()
    grown = GROWN >= 0.5
    src = candidate_sources(alpha, valid, gs_synthesised=GROWN)
    for name in ("inpaint", "gs"):
        assert (src[name][grown] == GS_REPAIRED).all()
        assert (src[name][38:46, 12:18] == GS).all()  # a fifth: the frames' Gaussians dominate
    assert np.isin(src["mesh_inpaint"][grown], (MESH, FILL)).all()  # no 3DGS render in it
    ch = choice(dict.fromkeys(REGIONS, "inpaint"))
    prov = provenance(src, regions(alpha, valid), ch)
    assert (prov.synthesised[grown] == 1.0).all()
    assert (prov.synthesised[38:46, 12:18] == 0.0).all()
    assert prov.shares()["gs_repaired"] == pytest.approx(grown.mean())
    # without the share (a run or a server that does not give it) the render is the map's own
    assert not (candidate_sources(alpha, valid)["inpaint"] == GS_REPAIRED).any()
    with pytest.raises(ValueError, match=r"gs_synthesised must be \[48, 64\] like gs_alpha"):
        candidate_sources(alpha, valid, gs_synthesised=GROWN[:, :10])
    legend = image(prov)
    assert (legend.shape[0] - H - 4) // 14 == 4  # gs, mesh, fill, 3DGS of repaired views


def test_a_run_marks_the_3dgs_render_other_repairs_grew_as_synthesised(tmp_path):
    alpha, valid = maps()
    out, gs, mesh, cam, score = run_with_renders(tmp_path, seed=1)
    per_region = dict.fromkeys(REGIONS, "inpaint")
    model = {"version": 1, "step": 5, "choice": per_region, "choice_share": {}, "feather_px": 0.0}
    for vid in (0, 1):
        out.on_decision(vid, True, "holes 20%", score, cam)
        out.on_renders(vid, gs=gs, alpha=alpha, mesh=mesh, valid=valid, synthesised=GROWN)
        out.on_fixed(vid, gs, {}, model)
        out.on_final(vid, gs)
    out.on_renders(1, gs=gs, alpha=alpha)  # a later render without the share replaces it
    m = out.write()
    grown = GROWN >= 0.5
    with np.load(tmp_path / "run" / "views" / "000" / "provenance.npz") as z:
        src, synth = z["source"], z["synthesised"].astype(np.float32)
    assert (src[grown] == GS_REPAIRED).all() and (synth[grown] == 1.0).all()
    assert (src[38:46, 12:18] == GS).all() and (synth[38:46, 12:18] == 0.0).all()
    assert m["views"][0]["provenance"]["gs_repaired"] == pytest.approx(grown.mean(), abs=1e-4)
    with np.load(tmp_path / "run" / "views" / "001" / "provenance.npz") as z:
        assert not (z["source"] == GS_REPAIRED).any()


def test_a_far_views_flat_no_map_hole_is_marked_a_classical_fill_not_gsfixer(tmp_path):
    """The repair node sends the regions it composed the output by (fallback.far_regions); the
    writer's provenance gives its flat holes to the fill, not to GSFixer's blend."""
    alpha, valid = maps()
    out, gs, mesh, cam, score = run_with_renders(tmp_path, seed=2)
    model = {"version": 1, "step": 5, "choice": dict(MESH_FIRST, neither="mesh_inpaint"),
             "choice_share": {"neither": 0.5}, "feather_px": 0.0, "detail_px": 0.0}  # fmt: skip
    region = regions(alpha, valid)
    flat = region.copy()
    flat[CUT] = FLAT
    for vid, r in ((0, None), (1, flat)):
        out.on_decision(vid, True, "holes 20%", score, cam)
        out.on_renders(vid, gs=gs, alpha=alpha, mesh=mesh, valid=valid)
        out.on_fixed(vid, gs, {}, model, r)
        out.on_final(vid, gs)
    with pytest.raises(
        ValueError, match=r"region must be \[H, W\] of the output with indices 0..4"
    ):
        out.on_fixed(2, gs, {}, model, np.full((H, W), 5, np.uint8))
    m = out.write()
    shares = [m["views"][v]["provenance"] for v in (0, 1)]
    cut = (flat == FLAT).mean()
    assert shares[0]["fixer"] == pytest.approx(0.5 * cut, abs=1e-4)  # the blend: half GSFixer
    assert shares[1].get("fixer", 0.0) == 0.0
    assert shares[1]["fill"] == pytest.approx(cut, abs=1e-4)
    with np.load(tmp_path / "run" / "views" / "001" / "provenance.npz") as z:
        assert (z["source"][CUT] == FILL).all() and (z["synthesised"][CUT] == 1.0).all()
        # the regions the output was composed by travel with it: the node's, flat hole and all
        np.testing.assert_array_equal(z["region"], flat)
        assert z["regions"].tolist() == [*REGIONS, "flat"]
    with np.load(tmp_path / "run" / "views" / "000" / "provenance.npz") as z:
        np.testing.assert_array_equal(z["region"], region)  # none sent: its renders' regions
