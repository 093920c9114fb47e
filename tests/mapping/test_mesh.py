"""The mesh file check (``read_mesh``): a damaged or empty mesh is refused in one line naming
the file, before an export, the map server or the viewer uses it."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.mapping.mesh import MeshFormatError, TriMesh, read_mesh, write_mesh


def box() -> TriMesh:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(1.0, 0.8, 0.2)
    v = np.asarray(m.vertices, np.float32)
    return TriMesh(v, np.asarray(m.triangles, np.int32), np.full((len(v), 3), 90, np.uint8))


def _cut(data: bytes) -> bytes:  # what a copy cut short leaves
    return data[: len(data) // 2]


def _nan_vertex(data: bytes) -> bytes:  # vertex 0's x := NaN (PLY: 3 doubles + 3 uchar a row)
    at = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:at] + np.float64(np.nan).tobytes() + data[at + 8 :]


def _index_out_of_range(data: bytes) -> bytes:  # the last face's last index := 99
    return data[:-4] + struct.pack("<I", 99)


DAMAGED = {
    ("ply", "truncated"): (
        _cut,
        r"truncated: its header declares element vertex 8, element face 12 \(\d+ bytes",
    ),
    ("glb", "truncated"): (_cut, r"its GLB header declares \d+ bytes, the file holds \d+"),
    ("ply", "non-finite"): (_nan_vertex, r"1 of 8 vertices are not finite \(first: vertex 0\)"),
    ("ply", "index"): (
        _index_out_of_range,
        r"triangle indices must lie in \[0, 8\), got \[0, 99\]",
    ),
}


@pytest.mark.parametrize(("fmt", "damage"), sorted(DAMAGED))
def test_damaged_mesh_is_refused_in_one_line(tmp_path: Path, fmt: str, damage: str) -> None:
    if fmt == "glb":
        pytest.importorskip("trimesh")
    path = write_mesh(box(), tmp_path / f"mesh.{fmt}")
    assert read_mesh(path).n_triangles == 12
    change, message = DAMAGED[(fmt, damage)]
    path.write_bytes(change(path.read_bytes()))
    with pytest.raises(MeshFormatError, match=message) as exc:
        read_mesh(path, allow_empty=True)  # damage is refused even where empty is fine
    assert str(exc.value).startswith(f"{path}: ") and "\n" not in str(exc.value)


def test_missing_and_foreign_files(tmp_path: Path) -> None:
    with pytest.raises(MeshFormatError, match="no such file"):
        read_mesh(tmp_path / "none.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a mesh")
    with pytest.raises(MeshFormatError, match=r"junk.ply: not a PLY file"):
        read_mesh(tmp_path / "junk.ply")
    (tmp_path / "junk.glb").write_bytes(b"not a mesh either")
    with pytest.raises(MeshFormatError, match=r"junk.glb: not a GLB file"):
        read_mesh(tmp_path / "junk.glb")


def test_a_mesh_replaced_while_it_is_read_is_read_as_one_version(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import open3d as o3d

    from gsfix_online.mapping import mesh as mesh_mod

    path = write_mesh(box(), tmp_path / "mesh.ply")
    s = o3d.geometry.TriangleMesh.create_sphere(0.5)
    v = np.asarray(s.vertices, np.float32)
    bigger = TriMesh(v, np.asarray(s.triangles, np.int32), np.full((len(v), 3), 90, np.uint8))
    nxt = write_mesh(bigger, tmp_path / "next.ply")
    check = mesh_mod._check_whole

    def check_then_replace(p: Path):  # a TSDF snapshot replaces the file after the size check
        header = check(p)
        if nxt.exists():
            nxt.replace(path)
        return header

    monkeypatch.setattr(mesh_mod, "_check_whole", check_then_replace)
    got = read_mesh(path)
    assert got.n_vertices == 8 and got.n_triangles == 12  # the version that was checked
    assert read_mesh(path).n_vertices == len(v)  # the next read: the new version, whole
