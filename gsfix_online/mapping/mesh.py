"""A coloured triangle mesh (what the TSDF extracts and the mesh renderer draws) and its export.

PLY keeps vertex colours as uchar red/green/blue; GLB (glTF binary) is what viser, rerun and
Foxglove load. Both are written atomically: to a temporary file beside the target, then
``os.replace``, so a viewer polling the path sees the old mesh or the whole new one.
"""

from __future__ import annotations

import errno
import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.core.io import atomic_path
from gsfix_online.core.ply_header import PlyHeader, PlyHeaderError, check_ply_size, read_ply_header

MeshFormat = Literal["ply", "glb"]


@dataclass(frozen=True, eq=False)
class TriMesh:
    """Triangle mesh in the world frame with per-vertex colours."""

    vertices: npt.NDArray[np.float32]  # [N, 3] metres, world frame
    triangles: npt.NDArray[np.int32]  # [M, 3] vertex indices
    colors: npt.NDArray[np.uint8]  # [N, 3] RGB (equal channels when gray)
    gray: bool = False  # built from grayscale frames: renders give [H, W] images

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    @property
    def is_empty(self) -> bool:
        return self.n_triangles == 0

    @classmethod
    def empty(cls, gray: bool = False) -> TriMesh:
        return cls(
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3), np.int32),
            np.zeros((0, 3), np.uint8),
            gray,
        )

    def to_legacy(self):  # noqa: ANN201 -> open3d.geometry.TriangleMesh
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices.astype(np.float64)),
            o3d.utility.Vector3iVector(self.triangles.astype(np.int32)),
        )
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.colors.astype(np.float64) / 255.0)
        return mesh


class MeshFormatError(ValueError):
    """A mesh file is damaged (cut short, non-finite vertices, indices out of range) or, where
    a mesh is required, holds no triangle."""


def read_mesh(path: str | os.PathLike[str], allow_empty: bool = False) -> TriMesh:
    """Read a PLY or OBJ mesh with Open3D, or a GLB with trimesh (Open3D's assimp reader rejects
    the GLB files Open3D writes; trimesh, viser and rerun read them); colours default to gray.

    The one check of a mesh file (the exports, the map server, the viewer and the repair writer
    read through it): a PLY or GLB must have the size its header declares, every vertex must be
    finite, every index a vertex, and there must be a triangle unless ``allow_empty`` (a live
    TSDF node's first snapshots). MeshFormatError names the file and what is wrong in one line.
    """
    import shutil
    import tempfile

    p = Path(path)
    if not p.is_file():
        raise MeshFormatError(f"{p}: no such file")
    # One version of the file: a writer that replaces it (the TSDF node's atomic snapshots)
    # between the size check and the read paired one version's header with the next one's
    # vertices, so both read a private copy taken through one open file
    with tempfile.TemporaryDirectory(prefix="gsfix-mesh-") as tmp:
        copy = Path(tmp) / p.name
        with open(p, "rb") as src, open(copy, "wb") as dst:
            shutil.copyfileobj(src, dst)
        try:
            header = _check_whole(copy)
            mesh = _read_glb(copy) if p.suffix.lower() == ".glb" else _read_open3d(copy)
        except MeshFormatError as exc:  # name the user's file, not the copy
            raise MeshFormatError(str(exc).replace(str(copy), str(p))) from None
    vertex = header.element("vertex") if header is not None else None
    if vertex is not None and vertex.count != mesh.n_vertices:
        raise MeshFormatError(
            f"{p}: its header declares {vertex.count} vertices, {mesh.n_vertices} could be read"
        )
    return _check_mesh(mesh, p, allow_empty)


def _check_whole(path: Path) -> PlyHeader | None:
    """MeshFormatError when the file is shorter than its header says (a PLY whose faces are
    triangles at least; a GLB); the PLY's header, None for other formats."""
    suffix = path.suffix.lower()
    if suffix == ".glb":
        with open(path, "rb") as fh:
            head = fh.read(12)
        got = path.stat().st_size
        if len(head) < 12 or head[:4] != b"glTF":
            raise MeshFormatError(f"{path}: not a GLB file (starts with {head[:4]!r})")
        want = struct.unpack("<I", head[8:12])[0]
        if want != got:
            raise MeshFormatError(
                f"{path}: its GLB header declares {want} bytes, the file holds {got}"
            )
        return None
    if suffix != ".ply":
        return None
    try:
        header = read_ply_header(path)
        check_ply_size(path, header, list_len=3, exact=False)  # faces: triangles or more
    except PlyHeaderError as exc:
        raise MeshFormatError(str(exc)) from None
    return header


def _check_mesh(mesh: TriMesh, path: Path, allow_empty: bool) -> TriMesh:
    if mesh.is_empty and not allow_empty:
        raise MeshFormatError(f"{path}: the mesh has no triangles ({mesh.n_vertices} vertices)")
    bad = ~np.isfinite(mesh.vertices).all(axis=1)
    if bad.any():
        raise MeshFormatError(
            f"{path}: {int(bad.sum())} of {mesh.n_vertices} vertices are not finite "
            f"(first: vertex {int(np.argmax(bad))})"
        )
    if mesh.n_triangles and not (
        mesh.triangles.min() >= 0 and mesh.triangles.max() < mesh.n_vertices
    ):
        raise MeshFormatError(
            f"{path}: triangle indices must lie in [0, {mesh.n_vertices}), got "
            f"[{mesh.triangles.min()}, {mesh.triangles.max()}]"
        )
    return mesh


def _read_open3d(path: Path) -> TriMesh:
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(path))
    with np.errstate(over="ignore"):  # a huge double is caught as non-finite, not warned about
        v = np.asarray(m.vertices, dtype=np.float32)
    if m.has_vertex_colors():
        c = np.clip(np.rint(np.asarray(m.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
    else:
        c = np.full((len(v), 3), 128, np.uint8)
    return TriMesh(v, np.asarray(m.triangles, dtype=np.int32), c)


def _read_glb(path: str | os.PathLike[str]) -> TriMesh:
    try:
        import trimesh
    except ImportError:
        raise ImportError("reading .glb needs trimesh: pip install trimesh") from None
    m = trimesh.load(str(path), force="mesh", process=False)
    colors = np.asarray(m.visual.vertex_colors)[:, :3] if m.visual.kind == "vertex" else None
    v = np.asarray(m.vertices, dtype=np.float32)
    if colors is None:
        colors = np.full((len(v), 3), 128, np.uint8)
    return TriMesh(v, np.asarray(m.faces, dtype=np.int32).reshape(-1, 3), colors.astype(np.uint8))


_EMPTY_PLY = (
    b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
    b"property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
    b"property uchar blue\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
)


def _empty_glb() -> bytes:
    """A valid glTF 2.0 binary holding one empty scene."""
    body = json.dumps({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": []}]})
    chunk = body.encode().ljust((len(body) + 3) // 4 * 4, b" ")
    header = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(chunk))
    return header + struct.pack("<I4s", len(chunk), b"JSON") + chunk


def write_mesh(mesh: TriMesh, path: str | os.PathLike[str]) -> Path:
    """Write ``mesh`` to ``path`` (format from the suffix: .ply or .glb), atomically."""
    import open3d as o3d

    p = Path(path)
    if p.suffix.lower() not in (".ply", ".glb"):
        raise ValueError(f"mesh path must end in .ply or .glb, got {p.name!r}")
    # Open3D picks the format from the suffix, which the temporary file keeps.
    with atomic_path(p) as tmp:
        if mesh.is_empty:  # Open3D refuses to write an empty mesh; viewers still need a file
            tmp.write_bytes(_EMPTY_PLY if p.suffix.lower() == ".ply" else _empty_glb())
        elif not o3d.io.write_triangle_mesh(str(tmp), mesh.to_legacy(), write_ascii=False):
            raise OSError(f"Open3D could not write {p}")
        elif not _complete(tmp, mesh):
            # Open3D reports success when the disk fills up mid-file (its writes are not
            # checked): the file is checked before it replaces the old one
            raise OSError(errno.EIO, f"{p} was written incomplete (is the disk full?)")
    return p


def _complete(path: Path, mesh: TriMesh) -> bool:
    """Whether a written mesh file is whole: the size its header declares (see
    :func:`_check_whole`); a PLY also reads back with every vertex and triangle."""
    import open3d as o3d

    try:
        _check_whole(path)
    except MeshFormatError:
        return False
    if path.suffix.lower() == ".glb":
        return True
    back = o3d.io.read_triangle_mesh(str(path))
    return len(back.vertices) == mesh.n_vertices and len(back.triangles) == mesh.n_triangles
