"""Stress property of TSDF integration (gsfix_online/mapping/tsdf.py), and the inputs that broke it."""

from __future__ import annotations

import numpy as np

from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.jobs.stress import properties
from gsfix_online.jobs.stress.runner import assert_property
from gsfix_online.mapping.tsdf import TsdfConfig, TsdfVolume

K = Intrinsics(30.0, 30.0, 20.0, 15.0, 40, 30)
CFG = TsdfConfig(device="CPU:0", block_count=64, mesh_weight_threshold=1.0)


def _frame(depth):
    return make_frame(np.full((30, 40, 3), 90, np.uint8), depth, K, np.eye(4), 1)


def test_plane_property_holds():
    (prop,) = properties("tsdf")
    assert_property(prop)


def test_frame_without_valid_depth_is_counted_not_raised():
    # found by tsdf.plane: Open3D raised "No block is touched" (the TSDF node crashed)
    vol = TsdfVolume(CFG)
    res = vol.integrate(_frame(np.zeros((30, 40), np.float32)))
    assert (res.valid_pixels, res.blocks_touched, res.invalid.zero) == (0, 0, 1200)
    far = np.full((30, 40), 50.0, np.float32)  # all beyond depth_max (5 m)
    res = vol.integrate(_frame(far))
    assert (res.valid_pixels, res.invalid.far, vol.frames, vol.n_blocks) == (0, 1200, 2, 0)


def test_sparse_depth_off_open3ds_4_pixel_grid_is_fused():
    # found by tsdf.plane: valid pixels that all miss every 4th pixel of every 4th row (a
    # projected lidar scan, a tiny image) touched no block in Open3D and raised
    vol = TsdfVolume(CFG)
    depth = np.zeros((30, 40), np.float32)
    depth[1::4, 1::4] = 1.0  # a plane at 1 m, seen by 80 pixels
    res = vol.integrate(_frame(depth))
    assert res.valid_pixels == 80 and res.blocks_touched > 0
    mesh = vol.extract_mesh()
    assert len(mesh.vertices) > 0
    z = mesh.vertices[:, 2]
    assert np.abs(z - 1.0).max() <= CFG.voxel_size  # the plane, within a voxel
