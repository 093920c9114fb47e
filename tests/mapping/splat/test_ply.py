"""Standard 3DGS PLY and model folder: exact layout, bit-exact round trips, grayscale storage."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from gsfix_online.core.se3 import look_at
from gsfix_online.core.types import Intrinsics
from gsfix_online.mapping.splat.gaussians import ORIGIN_REPAIRED, PARAM_KEYS, GaussianMap
from gsfix_online.mapping.splat.ply import (
    CameraEntry,
    PlyFormatError,
    check_ply,
    iterations,
    load_model,
    parse_cfg_args,
    ply_property_names,
    read_ply,
    save_model,
    write_ply,
)

# The Inria construct_list_of_attributes() order at degree 3: 62 properties.
STANDARD_DEG3 = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def random_map(n: int, sh_degree: int, channels: int, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    # values with full 23-bit mantissas, extremes included, to catch any rounding
    return GaussianMap.from_tensors(
        torch.randn(n, 3, generator=g) * 1e3,
        torch.randn(n, 3, generator=g) * 5,
        torch.randn(n, 4, generator=g),
        torch.randn(n, generator=g) * 20,
        torch.randn(n, 1, channels, generator=g),
        torch.randn(n, k - 1, channels, generator=g) * 1e-3,
        sh_degree=sh_degree,
    )


def assert_same_bits(a: GaussianMap, b: GaussianMap) -> None:
    assert (a.sh_degree, a.channels, len(a)) == (b.sh_degree, b.channels, len(b))
    for k in PARAM_KEYS:
        x, y = a.params[k].detach(), b.params[k].detach()
        assert x.shape == y.shape and x.dtype == y.dtype == torch.float32, k
        assert torch.equal(x.view(torch.int32), y.view(torch.int32)), k


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
@pytest.mark.parametrize("channels", [1, 3])
def test_round_trip_bit_exact(tmp_path: Path, sh_degree: int, channels: int) -> None:
    gmap = random_map(50, sh_degree, channels)
    write_ply(tmp_path / "g.ply", gmap)
    assert_same_bits(read_ply(tmp_path / "g.ply"), gmap)


def test_standard_property_names_and_values(tmp_path: Path) -> None:
    gmap = random_map(5, 3, 3)
    write_ply(tmp_path / "g.ply", gmap)
    ply = PlyData.read(str(tmp_path / "g.ply"))
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"].data
    assert list(v.dtype.names) == [*STANDARD_DEG3, "origin", "observations"]
    assert ply_property_names(3) == STANDARD_DEG3
    assert all(v.dtype[n] == np.dtype("<f4") for n in STANDARD_DEG3)
    assert (v.dtype["origin"], v.dtype["observations"]) == (np.dtype("u1"), np.dtype("<u2"))
    assert ply.byte_order == "<" and not ply.text
    p = {k: t.detach().numpy() for k, t in gmap.params.items()}
    np.testing.assert_array_equal(v["x"], p["means"][:, 0])
    np.testing.assert_array_equal(v["nx"], 0.0)
    np.testing.assert_array_equal(v["opacity"], p["opacities"])  # logit
    np.testing.assert_array_equal(v["scale_2"], p["scales"][:, 2])  # log
    np.testing.assert_array_equal(v["rot_0"], p["quats"][:, 0])  # w first
    np.testing.assert_array_equal(v["f_dc_1"], p["sh0"][:, 0, 1])
    # channel-major f_rest: index c * 15 + j holds band coefficient j of channel c
    np.testing.assert_array_equal(v["f_rest_0"], p["shN"][:, 0, 0])
    np.testing.assert_array_equal(v["f_rest_1"], p["shN"][:, 1, 0])
    np.testing.assert_array_equal(v["f_rest_15"], p["shN"][:, 0, 1])
    np.testing.assert_array_equal(v["f_rest_44"], p["shN"][:, 14, 2])


def test_degree_zero_has_no_f_rest(tmp_path: Path) -> None:
    write_ply(tmp_path / "g.ply", random_map(3, 0, 3))
    names = PlyData.read(str(tmp_path / "g.ply"))["vertex"].data.dtype.names
    assert list(names) == [
        *(n for n in STANDARD_DEG3 if not n.startswith("f_rest")),
        "origin",
        "observations",
    ]


def test_grayscale_replicates_three_channels(tmp_path: Path) -> None:
    gmap = random_map(4, 1, 1)
    write_ply(tmp_path / "g.ply", gmap)
    ply = PlyData.read(str(tmp_path / "g.ply"))
    v = ply["vertex"].data
    assert "gsfix-online channels=1" in ply.comments
    assert len(v.dtype.names) == len(ply_property_names(1)) + 2  # origin, observations
    for c in range(3):
        np.testing.assert_array_equal(v[f"f_dc_{c}"], gmap.params["sh0"][:, 0, 0].detach().numpy())
        np.testing.assert_array_equal(
            v[f"f_rest_{3 * c + 2}"], gmap.params["shN"][:, 2, 0].detach().numpy()
        )


def test_foreign_file_without_comment_reads_as_colour(tmp_path: Path) -> None:
    gmap = random_map(4, 1, 3)
    write_ply(tmp_path / "g.ply", gmap)
    ply = PlyData.read(str(tmp_path / "g.ply"))
    ply.comments = []
    ply.write(str(tmp_path / "foreign.ply"))
    assert_same_bits(read_ply(tmp_path / "foreign.ply"), gmap)


def test_round_trip_keeps_each_gaussians_origin_and_observations(tmp_path: Path) -> None:
    gmap = random_map(6, 1, 3)
    gmap.origin[[1, 4]] = ORIGIN_REPAIRED
    gmap.observations[:] = torch.tensor([0, 1, 7, 300, 65535, 70000], dtype=torch.int32)
    write_ply(tmp_path / "g.ply", gmap)
    back = read_ply(tmp_path / "g.ply")
    assert_same_bits(back, gmap)
    assert back.origin.tolist() == [0, 1, 0, 0, 1, 0]
    assert back.observations.tolist() == [0, 1, 7, 300, 65535, 65535]  # ushort: clamped
    # a standard viewer's file without them: observed, never counted
    ply = PlyData.read(str(tmp_path / "g.ply"))
    v = ply["vertex"].data
    names = [n for n in v.dtype.names if n not in ("origin", "observations")]
    bare = np.empty(len(v), dtype=[(n, "<f4") for n in names])
    for n in names:
        bare[n] = v[n]
    PlyData([PlyElement.describe(bare, "vertex")], comments=ply.comments).write(
        str(tmp_path / "bare.ply")
    )
    plain = read_ply(tmp_path / "bare.ply")
    assert_same_bits(plain, gmap)
    assert plain.origin.tolist() == [0] * 6 and plain.observations.tolist() == [0] * 6
    # an origin of another type
    floats = np.empty(len(v), dtype=[(n, "<f4") for n in v.dtype.names])
    for n in v.dtype.names:
        floats[n] = v[n]
    PlyData([PlyElement.describe(floats, "vertex")]).write(str(tmp_path / "float.ply"))
    with pytest.raises(PlyFormatError, match="origin must be an integer property, got float"):
        read_ply(tmp_path / "float.ply")
    # an origin nobody defined
    odd = v.copy()
    odd["origin"][2] = 5
    PlyData([PlyElement.describe(odd, "vertex")]).write(str(tmp_path / "odd.ply"))
    with pytest.raises(
        PlyFormatError, match=r"origin must be 0 \(observed\) or 1 \(repaired\), got \[5\]"
    ):
        read_ply(tmp_path / "odd.ply")


def test_empty_map(tmp_path: Path) -> None:
    write_ply(tmp_path / "g.ply", GaussianMap(sh_degree=2, channels=1))
    back = read_ply(tmp_path / "g.ply")
    assert (len(back), back.sh_degree, back.channels) == (0, 2, 1)


def test_model_folder_round_trip(tmp_path: Path) -> None:
    gmap = random_map(20, 3, 1)
    K = Intrinsics(300.123456789, 301.5, 159.5, 119.5, 320, 240)
    cams = [
        CameraEntry.from_pose(i, f"{i:06d}", K, look_at([0.1 * i, 1.0 / 3.0, 0.7], [2.0, 1.0, 1.0]))
        for i in range(3)
    ]
    model = tmp_path / "model"
    save_model(model, gmap, 7000, cams, source_path="/data/tank")
    save_model(model, random_map(3, 3, 1, seed=1), 30, cams, source_path="/data/tank")
    assert (model / "point_cloud" / "iteration_7000" / "point_cloud.ply").is_file()
    assert iterations(model) == [30, 7000]
    out = load_model(model)  # the latest
    assert out.iteration == 7000
    assert_same_bits(out.gmap, gmap)
    for a, b in zip(out.cameras, cams, strict=True):
        assert (a.id, a.img_name, a.width, a.height, a.fx, a.fy) == (
            b.id,
            b.img_name,
            320,
            240,
            b.fx,
            b.fy,
        )
        assert np.array_equal(a.T_world_cam, b.T_world_cam)  # JSON floats round-trip exactly
    # the original's cameras.json keys and cfg_args text
    entry = json.loads((model / "cameras.json").read_text())[1]
    assert list(entry) == ["id", "img_name", "width", "height", "position", "rotation", "fy", "fx"]
    np.testing.assert_array_equal(entry["position"], cams[1].T_world_cam[:3, 3])
    text = (model / "cfg_args").read_text()
    assert text.startswith("Namespace(sh_degree=3, source_path='/data/tank', model_path=")
    assert out.cfg_args["white_background"] is False and out.cfg_args["sh_degree"] == 3
    assert load_model(model, iteration=30).iteration == 30
    # nothing left behind by the atomic writes
    assert not [p for p in model.rglob(".*")]


def test_atomic_write_keeps_old_file_on_failure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "g.ply"
    gmap = random_map(3, 0, 3)
    write_ply(path, gmap)

    def boom(*args: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_ply(path, random_map(9, 0, 3))
    monkeypatch.undo()
    assert_same_bits(read_ply(path), gmap)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.ply"]


def test_parse_cfg_args_is_literal_only() -> None:
    assert parse_cfg_args("Namespace(sh_degree=3, source_path='x', eval=False)") == {
        "sh_degree": 3,
        "source_path": "x",
        "eval": False,
    }
    with pytest.raises(PlyFormatError, match="value of a is not a literal"):
        parse_cfg_args("Namespace(a=__import__('os'))")
    with pytest.raises(PlyFormatError, match="not a Namespace"):
        parse_cfg_args("print(1)")


def test_malformed_files(tmp_path: Path) -> None:
    gmap = random_map(2, 1, 3)
    write_ply(tmp_path / "g.ply", gmap)
    ply = PlyData.read(str(tmp_path / "g.ply"))
    data = ply["vertex"].data
    # a renamed property
    renamed = data.copy()
    renamed.dtype.names = ["rot_w" if n == "rot_0" else n for n in data.dtype.names]
    PlyData([type(ply["vertex"]).describe(renamed, "vertex")]).write(str(tmp_path / "bad.ply"))
    with pytest.raises(PlyFormatError, match="property 22 is 'rot_w', expected 'rot_0'"):
        read_ply(tmp_path / "bad.ply")
    # a grayscale mark on differing channels
    ply.comments = ["gsfix-online channels=1"]
    ply.write(str(tmp_path / "gray.ply"))
    with pytest.raises(
        PlyFormatError, match="marked channels=1 but its three colour channels differ"
    ):
        read_ply(tmp_path / "gray.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply")
    with pytest.raises(PlyFormatError, match="not a PLY file"):
        read_ply(tmp_path / "junk.ply")
    with pytest.raises(PlyFormatError, match="no such file"):
        read_ply(tmp_path / "missing.ply")
    with pytest.raises(PlyFormatError, match="no point_cloud/iteration_N"):
        load_model(tmp_path)
    with pytest.raises(ValueError, match="iteration must be a non-negative int"):
        save_model(tmp_path / "m", gmap, -1)


def _truncated(data: bytes) -> bytes:
    return data[: len(data) * 2 // 3]


def _longer(data: bytes) -> bytes:
    return data + b"\0" * 8


def _nan_scale(data: bytes) -> bytes:  # Gaussian 3's scale_0 := NaN
    header = data.index(b"end_header\n") + len(b"end_header\n")
    row = 4 * len(ply_property_names(3)) + 3  # 62 floats at SH 3, origin (1 byte), observations (2)
    at = header + 3 * row + 4 * ply_property_names(3).index("scale_0")
    return data[:at] + np.float32(np.nan).tobytes() + data[at + 4 :]


DAMAGED_PLY = {
    "truncated": (
        _truncated,
        r"truncated: its header declares element vertex 5 \(\d+ bytes\), the file",
    ),
    "longer": (_longer, "longer than its header says"),
    "non-finite": (_nan_scale, r"1 of 5 Gaussians hold non-finite values \(first: Gaussian 3, "),
}


@pytest.mark.parametrize("damage", sorted(DAMAGED_PLY))
def test_damaged_ply_is_refused_in_one_line(tmp_path: Path, damage: str) -> None:
    path = write_ply(tmp_path / "g.ply", random_map(5, 3, 3))
    assert check_ply(path).n == 5 and check_ply(path).sh_degree == 3
    change, message = DAMAGED_PLY[damage]
    path.write_bytes(change(path.read_bytes()))
    for read in (check_ply, read_ply):
        with pytest.raises(PlyFormatError, match=message) as exc:
            read(path)
        assert str(exc.value).startswith(str(path)) and "\n" not in str(exc.value)
