"""The training-sample builder (sample_builder.py) on a tiny synthetic scene: a textured plane
at z = 2 m mapped by the Gaussian mapper, and a uniform quad mesh at the same depth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsfix_online.fixer.sample_builder import (
    Perturbation,
    keyframe_sample,
    map_arrays,
    mesh_image,
    render_pair,
    rgb8,
    training_sample,
)
from gsfix_online.mapping.mesh import TriMesh
from gsfix_online.mapping.mesh_render import MeshRenderer
from gsfix_online.mapping.splat.mapper import Mapper
from tests.mapping.splat.test_mapper import (
    CFG,
    H,
    W,
    Z,
    one_thread,  # noqa: F401 -- autouse: one torch thread
    plane_frame,
)

GREY = 90  # the quad's colour
PERTURB = Perturbation(renders=2, max_deg=25.0, max_m=0.3, downscale=2)


@pytest.fixture(scope="module")
def scene() -> tuple[Mapper, MeshRenderer]:
    torch.manual_seed(0)
    mapper = Mapper(CFG)
    for i in range(2):
        mapper.process(plane_frame(0.1 * i, i))
    half = 5.0
    v = np.array([[-half, -half, Z], [half, -half, Z], [half, half, Z], [-half, half, Z]],
                 np.float32)  # fmt: skip
    quad = TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), np.full((4, 3), GREY, np.uint8))
    return mapper, MeshRenderer(quad)


def test_rgb8_scales_clamps_and_replicates_gray() -> None:
    x = np.array([[[-0.1], [0.5], [1.2]]], np.float32)  # [1, 3, 1]
    out = rgb8(x)
    assert out.dtype == np.uint8 and out.shape == (1, 3, 3)
    np.testing.assert_array_equal(out[0, :, 0], [0, 128, 255])
    u = np.zeros((2, 2), np.uint8)
    assert rgb8(u).shape == (2, 2, 3)


def test_map_arrays_carry_the_frame_and_the_maps_renders(scene) -> None:
    mapper, _ = scene
    f = plane_frame(0.05)
    color, _, alpha = mapper.render_numpy(f.T_world_cam, f.intrinsics.K, W, H)
    a = map_arrays(mapper, f, color, alpha, np.random.default_rng(0), PERTURB)
    assert set(a) == {"color", "depth", "K", "T_world_cam", "gs_render", "gs_alpha",
                      "perturbed_alpha"}  # fmt: skip
    assert a["gs_render"].dtype == np.uint8 and a["gs_render"].shape == (H, W, 3)
    assert a["gs_alpha"].dtype == np.float32 and a["gs_alpha"].shape == (H, W)
    p = a["perturbed_alpha"]
    assert p.shape == (2, H, W) and p.dtype == np.float32 and 0 <= p.min() <= p.max() <= 1
    np.testing.assert_allclose(a["depth"], Z)  # the plane's depth, as measured
    # the same generator gives the same perturbed renders (the run is reproducible)
    b = map_arrays(mapper, f, color, alpha, np.random.default_rng(0), PERTURB)
    np.testing.assert_array_equal(a["perturbed_alpha"], b["perturbed_alpha"])
    none = map_arrays(mapper, f, color, alpha, np.random.default_rng(0),
                      Perturbation(0, 25.0, 0.3, 2))  # fmt: skip
    assert "perturbed_alpha" not in none


def test_render_pair_of_a_plane_at_known_depth(scene) -> None:
    mapper, renderer = scene
    f = plane_frame(0.05)
    pair = render_pair(mapper, renderer, f.T_world_cam, f.intrinsics)
    assert pair.mesh_valid.all() and (pair.mesh == GREY).all()
    assert pair.gs.shape == (H, W, 3) and pair.gs_alpha.shape == (H, W)
    assert float(np.median(pair.gs_alpha)) > 0.9  # the mapped plane covers the view
    _, depth, _ = mapper.render_numpy(f.T_world_cam, f.intrinsics.K, W, H)
    centre = depth[H // 4 : -H // 4, W // 4 : -W // 4]
    assert float(np.median(centre)) == pytest.approx(Z, abs=0.05)  # the map renders z = 2 m


def test_a_keyframe_sample_is_the_triplet_of_its_renders(scene) -> None:
    mapper, renderer = scene
    f = plane_frame(0.05)
    color, _, alpha = mapper.render_numpy(f.T_world_cam, f.intrinsics.K, W, H)
    arrays, s = keyframe_sample(mapper, f, color, alpha, renderer, np.random.default_rng(0),
                                PERTURB, 0.5)  # fmt: skip
    t = s.triplet
    assert t.image_mesh.shape == t.image_gs.shape == t.image_gt.shape == (3, H, W)
    torch.testing.assert_close(t.image_mesh, torch.full((3, H, W), GREY / 255))
    torch.testing.assert_close(t.image_gt, torch.from_numpy(f.color).permute(2, 0, 1) / 255.0)
    torch.testing.assert_close(t.image_gs, torch.from_numpy(arrays["gs_render"]).permute(2, 0, 1)
                               / 255.0)  # fmt: skip
    # the map explains the frame it was fitted near: far closer to it than the mesh
    gs_err = float((t.image_gs - t.image_gt).abs().mean())
    assert gs_err < 0.5 * float((t.image_mesh - t.image_gt).abs().mean()), gs_err
    assert s.disocclusions == []  # no neighbours
    np.testing.assert_array_equal(mesh_image(renderer, arrays), np.full((H, W, 3), GREY))


def test_disocclusions_are_what_the_neighbours_depth_does_not_cover(scene) -> None:
    mapper, _ = scene
    f = plane_frame(0.05)
    color, _, alpha = mapper.render_numpy(f.T_world_cam, f.intrinsics.K, W, H)
    a = map_arrays(mapper, f, color, alpha, np.random.default_rng(0), Perturbation(0, 0, 0, 1))
    same = dict(a)
    half = dict(a, depth=np.where(np.arange(W) < W // 2, 0.0, Z).astype(np.float32)[None]
                .repeat(H, 0))  # fmt: skip
    s = training_sample(a, None, 0.5, [same, half])
    # the same view covers everything (no candidate); the half-measured one leaves its left half
    assert len(s.disocclusions) == 1
    m = s.disocclusions[0]
    assert m.shape == (H, W) and 0.4 < m.mean() < 0.6 and m[:, : W // 2 - 2].all()
    assert not s.triplet.image_mesh.any()  # no mesh: mode gs


def test_perturbed_alpha_of_the_wrong_size_is_refused(scene) -> None:
    mapper, _ = scene
    f = plane_frame()
    a = map_arrays(mapper, f, np.zeros((H, W, 3)), np.ones((H, W)), np.random.default_rng(0),
                   Perturbation(0, 0, 0, 1))  # fmt: skip
    a["perturbed_alpha"] = np.zeros((1, H, W + 1), np.float32)
    with pytest.raises(ValueError, match="perturbed_alpha must be"):
        training_sample(a, None, 0.5)
