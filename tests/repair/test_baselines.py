"""Mesh fill and Telea inpainting baselines."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.repair.baselines import inpaint_telea, mesh_fill


def test_mesh_fill_takes_gs_where_opaque_mesh_elsewhere_and_reports_missing():
    gs = np.full((4, 6, 3), 200, np.uint8)
    mesh = np.full((4, 6, 3), 50, np.uint8)
    alpha = np.ones((4, 6), np.float32)
    alpha[:, 3:] = 0.1
    valid = np.ones((4, 6), bool)
    valid[:, 5] = False
    r = mesh_fill(gs, alpha, mesh, valid)
    assert (r.image[:, :3] == 200).all() and (r.image[:, 3:5] == 50).all()
    assert (r.image[:, 5] == 200).all()  # neither covers: the 3DGS value stays, marked missing
    assert r.missing.sum() == 4 and r.missing[:, 5].all()


def test_telea_fills_missing_from_surroundings_only():
    img = np.full((20, 20), 120, np.uint8)
    missing = np.zeros((20, 20), bool)
    missing[8:12, 8:12] = True
    img[missing] = 0
    out = inpaint_telea(img, missing)
    assert np.abs(out[missing].astype(int) - 120).max() <= 2
    assert np.array_equal(out[~missing], img[~missing])
    assert np.array_equal(inpaint_telea(img, np.zeros_like(missing)), img)


def test_mesh_fill_rejects_mismatched_shapes():
    gs = np.zeros((4, 6, 3), np.uint8)
    with pytest.raises(ValueError, match="mesh_color must match"):
        mesh_fill(
            gs, np.ones((4, 6), np.float32), np.zeros((4, 6), np.uint8), np.ones((4, 6), bool)
        )
    with pytest.raises(ValueError, match="gs_alpha must be float"):
        mesh_fill(gs, np.ones((4, 6), np.uint8), gs, np.ones((4, 6), bool))
