"""The veil guard (``MapperConfig.distill_veil_guard``): a repaired view's seed depth judges the
seeds of other repaired views, so that none stands in front of what that view delivered.

Two repaired views and no input keyframe near them: A looks along +z at a textured plane
2 m away (its seeds lie on it); B, beside A and turned 45 degrees towards A's axis, guesses its
surface 0.8 m away, so its seeds stand 0.2-0.9 m in front of A's camera, across A's view.
"""

from __future__ import annotations

import dataclasses
import io
import math

import numpy as np
import pytest
import torch

from gsfix_online.core.se3 import make_T
from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.mapping.splat.growth import GrowthConfig
from gsfix_online.mapping.splat.mapper import Mapper, MapperConfig
from gsfix_online.mapping.splat.prune import CarveConfig, carve_mask

W, H, F, Z = 48, 36, 40.0, 2.0
K = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
CFG = MapperConfig(backend="cpu", kf_iters=0, train_downscale=1,
                   growth=GrowthConfig(max_cell_px=8, min_cell_px=2, init_opacity=0.95))  # fmt: skip
GUARD = dataclasses.replace(CFG, distill_veil_guard=True)
T_A = make_T(np.eye(3), [0.0, 0.0, 0.0])
_a = -math.pi / 4  # B's axis (-0.71, 0, 0.71): towards A's axis
T_B = make_T(np.array([[math.cos(_a), 0, math.sin(_a)], [0, 1, 0],
                       [-math.sin(_a), 0, math.cos(_a)]]), [0.8, 0.0, 0.0])  # fmt: skip
B_DEPTH = 0.8  # m: B's guessed surface


@pytest.fixture(autouse=True, scope="module")
def one_thread():  # tiny images: more threads only add barrier waits
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _image_a() -> np.ndarray:  # [H, W, 3] the textured plane z = 2 seen from A
    v, u = np.mgrid[0:H, 0:W]
    x, y = (u - K.cx) / F * Z, (v - K.cy) / F * Z
    rgb = np.stack([0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.3 * np.cos(4 * y), 0.5 + 0.2 * x], -1)
    return np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def _image_b() -> np.ndarray:  # [H, W, 3] flat red: a veil of it shows in A's render
    return np.broadcast_to(np.uint8([220, 30, 30]), (H, W, 3)).copy()


def _mapper(cfg: MapperConfig) -> Mapper:
    """A map with one input keyframe far from both views (its depth judges nothing there)."""
    m = Mapper(cfg)
    far = make_T(np.eye(3), [50.0, 0.0, 0.0])
    m.process(make_frame(_image_a(), np.full((H, W), Z, np.float32), K, far, 0))
    return m


def _distil(m: Mapper, view: str) -> int:  # Gaussians the view added (after carving)
    n0 = len(m.gmap)
    if view == "A":
        m.distill(_image_a(), T_A, K.K, iters=0, depth=np.full((H, W), Z, np.float32))
    else:
        m.distill(_image_b(), T_B, K.K, iters=0, depth=np.full((H, W), B_DEPTH, np.float32))
    return len(m.gmap) - n0


def _veils_over_a(m: Mapper) -> int:
    """Seeded Gaussians in front of A's surface where A sees them (its footprint included)."""
    g, seeded = m.gmap, m.seeded()
    return int(carve_mask(g.means.detach()[seeded], g.params["scales"].detach()[seeded],
                          torch.full((H, W), Z), torch.as_tensor(K.K, dtype=torch.float32),
                          torch.as_tensor(T_A, dtype=torch.float32), CarveConfig(),
                          footprint=True).sum())  # fmt: skip


def _render_a(m: Mapper) -> np.ndarray:  # [H, W, 3] in [0, 1]
    return m.render_numpy(T_A, K.K, W, H)[0]


def test_later_seeds_in_front_of_a_repaired_view_move_away_and_leave_its_render() -> None:
    """A first, then B. Unguarded, B's seeds veil A (its render turns red); guarded, each of
    B's seeds either moved along its own ray to where A does not see it or, where no move
    hides it, is removed: none stands in front of A's surface, A renders as before B came,
    and B keeps the seeds that moved."""
    got = {}
    for name, cfg in (("off", CFG), ("guard", GUARD)):
        m = _mapper(cfg)
        _distil(m, "A")
        before = _render_a(m)
        n_b = _distil(m, "B")
        change = float(np.abs(_render_a(m) - before).mean())
        got[name] = (n_b, _veils_over_a(m), change, m.n_pushed)
    (n_off, veils_off, change_off, pushed_off), (n_g, veils_g, change_g, pushed_g) = got.values()
    assert veils_off > 20 and change_off > 0.05 and pushed_off == 0, got
    assert veils_g == 0 and change_g < 0.01, got  # 2/255: what bleeds through A's seeds
    assert 0 < n_g < n_off and pushed_g >= n_g, got  # B kept the seeds it could move


def test_a_veil_grown_before_the_view_it_covers_is_pruned() -> None:
    """B first, then A: when A arrives, B's seeds already stand in front of A's surface.
    Guarded, A's seed depth judges them: they are removed, and A's render matches its image
    far better than with the veil kept."""
    got = {}
    for name, cfg in (("off", CFG), ("guard", GUARD)):
        m = _mapper(cfg)
        n_b = _distil(m, "B")
        carved0 = m.n_carved
        _distil(m, "A")
        err = float(np.abs(_render_a(m) - _image_a() / 255.0).mean())
        got[name] = (n_b, _veils_over_a(m), err, m.n_carved - carved0)
    (_, veils_off, err_off, carved_off), (n_b, veils_g, err_g, carved_g) = got.values()
    assert veils_off > 20 and carved_off == 0, got
    assert veils_g == 0 and carved_g >= veils_off and n_b > 20, got
    assert err_g < 0.5 * err_off, got


def test_the_seed_depths_that_judge_survive_a_snapshot() -> None:
    """A guarded map saved after A and restored judges B's seeds as the original does."""
    m = _mapper(GUARD)
    _distil(m, "A")
    buf = io.BytesIO()
    torch.save(m.state_dict(), buf)
    buf.seek(0)
    restored = Mapper(GUARD)
    restored.load_state_dict(torch.load(buf, weights_only=True))
    added = [_distil(x, "B") for x in (m, restored)]
    assert added[0] == added[1] and _veils_over_a(restored) == 0
    np.testing.assert_allclose(_render_a(restored), _render_a(m), atol=1e-6)
