"""The side-by-side figure of a run's views, drawn from a run folder its own writers made."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.jobs.figure import (
    BEST,
    CLASSICAL_TITLES,
    COLUMNS,
    GAP_PX,
    LABEL_PX,
    MISSING,
    best_classical,
    provenance_legend,
    repaired_views,
    views_figure,
    write_views_figure,
)
from gsfix_online.repair.outputs import read_png_rgb
from tests.apps.run_data import H, W, make_run


def test_figure_puts_every_stage_beside_the_ground_truth(tmp_path):
    run = make_run(tmp_path, n_views=3, maps=False)
    gt_dir = tmp_path / "gt"
    assert repaired_views(run, gt_dir, 4) == [0, 2]  # view 1 was skipped
    assert repaired_views(run, tmp_path / "elsewhere", 4) == []  # no ground truth: none
    img = views_figure(run, gt_dir, [0, 2])
    tile_h, tile_w = LABEL_PX + H + GAP_PX, W + GAP_PX
    legend = provenance_legend(run, [0, 2], W)  # of both views, below their rows
    assert img.shape == (2 * tile_h + legend.shape[0], len(COLUMNS) * tile_w, 3)
    assert (img[2 * tile_h :] < 128).any()  # the legend's text

    def tile(row: int, col: int) -> np.ndarray:
        y, x = row * tile_h + LABEL_PX, col * tile_w
        return img[y : y + H, x : x + W]

    cols = [k for k, _ in COLUMNS]
    best = best_classical(run)
    assert best in CLASSICAL_TITLES  # the run's own best, from its metrics
    for row, vid in enumerate((0, 2)):
        gt = read_png_rgb(gt_dir / f"{vid:03d}.png")
        assert np.array_equal(tile(row, cols.index("gt")), gt)
        view = run / "views" / f"{vid:03d}"
        for key, col in (("fixed", "fixed"), (best, BEST), ("provenance", "provenance")):
            if (view / f"{key}.png").is_file():  # provenance: its colours, not the legend
                want = read_png_rgb(view / f"{key}.png")[:H, :W]
                assert np.array_equal(tile(row, cols.index(col)), want)
        assert (img[row * tile_h : row * tile_h + LABEL_PX] < 128).any()  # the labels' text


def test_a_stage_the_run_lacks_is_a_grey_tile_and_missing_ground_truth_is_an_error(tmp_path):
    run = make_run(tmp_path, n_views=1, maps=False)
    (run / "views" / "000" / "final.png").unlink()
    img = views_figure(run, tmp_path / "gt", [0])
    x = [k for k, _ in COLUMNS].index("final") * (W + GAP_PX)
    assert (img[LABEL_PX : LABEL_PX + H, x : x + W] == MISSING).all()
    with pytest.raises(FileNotFoundError, match="no ground truth for view 005"):
        views_figure(run, tmp_path / "gt", [5])


def test_written_figure_is_resized_and_defaults_to_the_repaired_views(tmp_path):
    run = make_run(tmp_path, n_views=3, maps=False)
    w, h = write_views_figure(run, tmp_path / "fig.png", tmp_path / "gt", scale=0.5)
    full = views_figure(run, tmp_path / "gt", [0, 2])
    assert (w, h) == (round(full.shape[1] * 0.5), round(full.shape[0] * 0.5))
    assert read_png_rgb(tmp_path / "fig.png").shape == (h, w, 3)


def test_the_legend_names_a_source_that_only_a_later_view_has(tmp_path):
    """The figure's one legend covers every view: a source view 000 lacks (here the 3DGS render
    of other views' repairs, in view 002) is named too, with its colour."""
    from gsfix_online.repair.provenance import COLOURS, GS_REPAIRED, SOURCES

    run = make_run(tmp_path, n_views=3, maps=False)
    first = provenance_legend(run, [0], W)
    path = run / "views" / "002" / "provenance.npz"
    with np.load(path) as z:
        arrays = dict(z)
    assert not (arrays["source"] == GS_REPAIRED).any()
    arrays["source"][:4, :4] = GS_REPAIRED
    arrays["sources"] = np.array(SOURCES)
    np.savez_compressed(path, **arrays)
    both = provenance_legend(run, [0, 2], W)
    assert both.shape[0] >= first.shape[0] + 14  # one row more (or two, with view 2's own)
    swatch = COLOURS[GS_REPAIRED].astype(np.uint8)
    assert (both == swatch).all(axis=2).any() and not (first == swatch).all(axis=2).any()
    img = views_figure(run, tmp_path / "gt", [0, 2])
    assert (img[-both.shape[0] :] == swatch).all(axis=2).any()  # drawn under the rows
