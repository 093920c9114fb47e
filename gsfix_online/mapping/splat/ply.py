"""The standard 3DGS PLY and model folder (the layout of the original 3DGS code, GSFusion, GSFix3D).

PLY: one binary little-endian ``vertex`` element of float32 properties, in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

then two provenance properties of our own (:mod:`.gaussians`), which standard viewers ignore::

    origin (uchar: 0 observed, 1 grown from a repaired view) observations (ushort, clamped)

A PLY without them (another tool's, or ours from before) reads as observed, never counted.

- normals are zero; ``opacity`` is the logit; ``scale_*`` are log sigmas; ``rot_*`` is w, x, y, z.
- ``f_rest`` is channel-major: all K-1 coefficients of channel 0, then channel 1, then channel 2
  (our ``shN`` [N, K-1, C] transposed to [N, C, K-1] and flattened).
- Grayscale maps (C = 1) store their channel three times, so every viewer shows them in grey,
  and the header carries ``comment gsfix-online channels=1``; :func:`read_ply` reads the comment
  and returns a one-channel map with the same bits. Files without the comment are colour.

Model folder (``save_model`` / ``load_model``)::

    MODEL/cfg_args                                  Namespace(sh_degree=.., source_path=.., ...)
    MODEL/cameras.json                              [{id, img_name, width, height, position,
                                                      rotation (3x3 camera-to-world), fx, fy}]
    MODEL/point_cloud/iteration_N/point_cloud.ply

Every file is written atomically (temporary file, fsync, rename): a reader sees the old file or
the whole new one.
"""

from __future__ import annotations

import argparse
import ast
import io
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from plyfile import PlyData, PlyElement

from gsfix_online.core.io import atomic_write_bytes, atomic_write_text
from gsfix_online.core.ply_header import PlyHeaderError, check_ply_size, read_ply_header
from gsfix_online.core.types import Intrinsics, RGBDFrame, check_pose
from gsfix_online.mapping.splat.gaussians import GaussianMap, num_sh_bases

CHANNELS_COMMENT = "gsfix-online channels="
PLY_NAME = "point_cloud.ply"
ITERATION_DIR = re.compile(r"^iteration_(\d+)$")
# the provenance properties after the standard ones: name -> PLY type (numpy's)
PROVENANCE_PROPERTIES = {"origin": "u1", "observations": "<u2"}
INTEGER_TYPES = {"uchar", "uint8", "ushort", "uint16", "uint", "uint32", "char", "int8", "short",
                 "int16", "int", "int32"}  # fmt: skip


class PlyFormatError(ValueError):
    """A PLY file, cameras.json or cfg_args does not follow the 3DGS layout."""


def ply_property_names(sh_degree: int) -> list[str]:
    """The standard property names, in order, for SH degree ``sh_degree`` (always 3 channels)."""
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return [
        *("x", "y", "z", "nx", "ny", "nz"),
        *(f"f_dc_{i}" for i in range(3)),
        *(f"f_rest_{i}" for i in range(n_rest)),
        "opacity",
        *(f"scale_{i}" for i in range(3)),
        *(f"rot_{i}" for i in range(4)),
    ]


# ----------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------


def gaussians_to_ply(gmap: GaussianMap) -> PlyData:
    """The map as a PlyData in the standard layout (see the module docstring)."""
    n = len(gmap)
    p = {k: v.detach().cpu().to(torch.float32).numpy() for k, v in gmap.params.items()}
    rep = 3 // gmap.channels  # 3 for grayscale (replicate), 1 for colour
    f_dc = np.repeat(p["sh0"][:, 0, :], rep, axis=1)  # [N, 3]
    shN_cm = np.repeat(p["shN"].transpose(0, 2, 1), rep, axis=1)  # [N, 3, K-1] channel-major
    f_rest = shN_cm.reshape(n, 3 * (gmap.num_bases - 1))
    columns = np.concatenate(
        [
            p["means"],
            np.zeros((n, 3), np.float32),
            f_dc,
            f_rest,
            p["opacities"][:, None],
            p["scales"],
            p["quats"],
        ],
        axis=1,
    )
    names = ply_property_names(gmap.sh_degree)
    assert columns.shape == (n, len(names))
    extra = list(PROVENANCE_PROPERTIES.items())
    vertex = np.empty(n, dtype=[(name, "<f4") for name in names] + extra)
    for i, name in enumerate(names):
        vertex[name] = columns[:, i]
    vertex["origin"] = gmap.origin.cpu().numpy()
    vertex["observations"] = np.minimum(gmap.observations.cpu().numpy(), 2**16 - 1)
    return PlyData(
        [PlyElement.describe(vertex, "vertex")],
        byte_order="<",
        comments=[f"{CHANNELS_COMMENT}{gmap.channels}"],
    )


def write_ply(path: str | os.PathLike[str], gmap: GaussianMap) -> Path:
    """Write ``gmap`` as a standard 3DGS PLY, atomically; returns the path."""
    if not isinstance(gmap, GaussianMap):
        raise TypeError(f"gmap must be a GaussianMap, got {type(gmap).__name__}")
    buf = io.BytesIO()
    gaussians_to_ply(gmap).write(buf)
    out = Path(path)
    atomic_write_bytes(out, buf.getvalue())
    return out


@dataclass(frozen=True)
class PlyInfo:
    """What :func:`check_ply` found in a valid 3DGS PLY."""

    path: Path
    n: int  # Gaussians
    sh_degree: int
    channels: int  # 1 (grayscale, marked by the comment) or 3
    provenance: tuple[str, ...] = ()  # the provenance properties it has (PROVENANCE_PROPERTIES)


def check_ply(path: str | os.PathLike[str]) -> PlyInfo:
    """Validate a 3DGS PLY without building the map: the property layout, the file size against
    the vertex count, finite values. The one check every reader of a map file goes through
    (:func:`read_ply`, the exports, the map server, the viewer, the repair writer); PlyFormatError
    names the file and what is wrong in one line."""
    return _read_checked(Path(path))[0]


def _read_checked(
    p: Path,
) -> tuple[PlyInfo, npt.NDArray[np.float32], dict[str, npt.NDArray[np.int64]]]:
    """(what the file holds, its columns [N, P] in the order of ply_property_names, the
    provenance properties it has: name -> [N])."""
    # 1. The header: the layout and the size the body must have
    if not p.is_file():
        raise PlyFormatError(f"{p}: no such file")
    try:
        header = read_ply_header(p)
        check_ply_size(p, header)
    except PlyHeaderError as exc:
        raise PlyFormatError(str(exc)) from None
    vertex_header = header.element("vertex")
    if vertex_header is None:
        raise PlyFormatError(f"{p}: has no 'vertex' element")
    props = [prop for prop in vertex_header.properties if prop.name not in PROVENANCE_PROPERTIES]
    extra = [prop for prop in vertex_header.properties if prop.name in PROVENANCE_PROPERTIES]
    names = [prop.name for prop in props]
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    k = n_rest // 3 + 1
    degree = round(math.sqrt(k)) - 1
    if n_rest % 3 or (degree + 1) ** 2 != k:
        raise PlyFormatError(f"{p}: {n_rest} f_rest properties match no SH degree")
    expected = ply_property_names(degree)
    if names != expected:
        diff = next(
            (i for i, (a, b) in enumerate(zip(names, expected, strict=False)) if a != b),
            min(len(names), len(expected)),
        )
        got = names[diff] if diff < len(names) else "nothing"
        want = expected[diff] if diff < len(expected) else "nothing"
        raise PlyFormatError(f"{p}: property {diff} is {got!r}, expected {want!r}")
    bad_types = sorted({prop.count_type or prop.type for prop in props} - {"float", "float32"})
    if bad_types or any(prop.count_type for prop in props):
        got = ", ".join(bad_types) or "a list"
        raise PlyFormatError(f"{p}: properties must be float32, got {got}")
    for prop in extra:
        if prop.count_type or prop.type not in INTEGER_TYPES:
            raise PlyFormatError(f"{p}: {prop.name} must be an integer property, got "
                                 f"{prop.count_type or prop.type}")  # fmt: skip
    channels = _channels_from_comments(p, header.comments)
    # 2. The body
    try:
        with p.open("rb") as fh:
            ply = PlyData.read(fh)
    except Exception as exc:  # plyfile raises several types for malformed headers and bodies
        raise PlyFormatError(f"{p}: not a readable PLY ({exc})") from None
    vertex = ply["vertex"].data
    n = len(vertex)
    cols = np.stack([np.asarray(vertex[name], dtype=np.float32) for name in names], axis=1)
    cols = cols.reshape(n, len(names))
    # 3. Finite values: a NaN or an infinity renders as nothing, or as everything
    bad = ~np.isfinite(cols)
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise PlyFormatError(
            f"{p}: {int(bad.any(axis=1).sum())} of {n} Gaussians hold non-finite values "
            f"(first: Gaussian {row}, {names[col]} = {cols[row, col]})"
        )
    meta = {prop.name: np.asarray(vertex[prop.name], np.int64) for prop in extra}
    origin = meta.get("origin", np.zeros(0, np.int64))
    if not np.isin(origin, (0, 1)).all():
        odd = sorted(set(np.unique(origin).tolist()) - {0, 1})[:3]
        raise PlyFormatError(f"{p}: origin must be 0 (observed) or 1 (repaired), got {odd}")
    return PlyInfo(p, n, degree, channels, tuple(meta)), cols, meta


def read_ply(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> GaussianMap:
    """Read a standard 3DGS PLY (ours or another tool's) into a GaussianMap, bit-exact; the file
    is checked first (:func:`check_ply`)."""
    p = Path(path)
    info, cols, meta = _read_checked(p)
    n, k = info.n, num_sh_bases(info.sh_degree)
    n_rest = 3 * (k - 1)
    i = iter(range(cols.shape[1]))

    def take(m: int) -> npt.NDArray[np.float32]:
        idx = [next(i) for _ in range(m)]
        return np.ascontiguousarray(cols[:, idx])

    means, _normals, f_dc, f_rest = take(3), take(3), take(3), take(n_rest)
    opacity, scales, quats = take(1)[:, 0], take(3), take(4)
    shN = f_rest.reshape(n, 3, k - 1)  # channel-major
    if info.channels == 1:
        if not (
            np.array_equal(f_dc[:, :1].repeat(3, 1), f_dc)
            and np.array_equal(shN[:, :1].repeat(3, 1), shN)
        ):
            raise PlyFormatError(f"{p}: marked channels=1 but its three colour channels differ")
        f_dc, shN = f_dc[:, :1], shN[:, :1]
    try:
        gmap = GaussianMap.from_tensors(
            means,
            scales,
            quats,
            opacity,
            f_dc[:, None, :],
            shN.transpose(0, 2, 1),
            sh_degree=info.sh_degree,
            device=device,
        )
        # without them (another tool's file, or ours from before): observed, never counted
        gmap.set_meta({"origin": torch.from_numpy(meta.get("origin", np.zeros(n, np.int64))),
                       "observations": torch.from_numpy(meta.get("observations",
                                                                 np.zeros(n, np.int64)))})  # fmt: skip
    except ValueError as exc:
        raise PlyFormatError(f"{p}: {exc}") from None
    return gmap


def _channels_from_comments(path: Path, comments: Sequence[str]) -> int:
    for c in comments:
        if c.startswith(CHANNELS_COMMENT):
            value = c[len(CHANNELS_COMMENT) :].strip()
            if value not in ("1", "3"):
                raise PlyFormatError(f"{path}: comment '{c}' must say channels=1 or channels=3")
            return int(value)
    return 3


# ----------------------------------------------------------------------------------------------
# Model folder: cameras.json and cfg_args
# ----------------------------------------------------------------------------------------------


def camera_name(kf_id: int, repaired: bool) -> str:
    """A keyframe's ``img_name`` in ``cameras.json``: ``kf_NNNNNN`` for an input frame,
    ``repaired_NNNNNN`` for a repaired view distilled into the map (:func:`is_repaired_name`)."""
    return f"{'repaired' if repaired else 'kf'}_{int(kf_id):06d}"


def is_repaired_name(img_name: str) -> bool:
    """Whether a ``cameras.json`` camera is a repaired view (:func:`camera_name`), not an input
    frame the map observed."""
    return img_name.startswith("repaired_")


@dataclass(frozen=True, eq=False)
class CameraEntry:
    """One training camera as the 3DGS ``cameras.json`` stores it (no principal point there)."""

    id: int
    img_name: str
    width: int
    height: int
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] camera-to-world, OpenCV axes
    fx: float
    fy: float

    @classmethod
    def from_frame(cls, id: int, img_name: str, frame: RGBDFrame) -> CameraEntry:
        return cls.from_pose(id, img_name, frame.intrinsics, frame.T_world_cam)

    @classmethod
    def from_pose(
        cls, id: int, img_name: str, intrinsics: Intrinsics, T_world_cam: npt.ArrayLike
    ) -> CameraEntry:
        K = intrinsics
        return cls(int(id), str(img_name), K.width, K.height, check_pose(T_world_cam), K.fx, K.fy)

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "img_name": self.img_name,
            "width": self.width,
            "height": self.height,
            "position": self.T_world_cam[:3, 3].tolist(),
            "rotation": self.T_world_cam[:3, :3].tolist(),
            "fy": float(self.fy),
            "fx": float(self.fx),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any], where: str = "cameras.json") -> CameraEntry:
        keys = ("id", "img_name", "width", "height", "position", "rotation", "fx", "fy")
        missing = [k for k in keys if k not in d]
        if missing:
            raise PlyFormatError(f"{where}: camera entry lacks {', '.join(missing)}")
        T = np.eye(4)
        try:
            T[:3, :3] = np.asarray(d["rotation"], dtype=np.float64)
            T[:3, 3] = np.asarray(d["position"], dtype=np.float64)
            T = check_pose(T, "camera rotation/position")
        except ValueError as exc:
            raise PlyFormatError(f"{where}: camera {d['id']}: {exc}") from None
        return cls(
            int(d["id"]),
            str(d["img_name"]),
            int(d["width"]),
            int(d["height"]),
            T,
            float(d["fx"]),
            float(d["fy"]),
        )


def format_cfg_args(args: Mapping[str, Any]) -> str:
    """``Namespace(key=value, ...)`` text, as the original 3DGS writes ``cfg_args``."""
    return str(argparse.Namespace(**args))


def parse_cfg_args(text: str, where: str = "cfg_args") -> dict[str, Any]:
    """Parse ``Namespace(...)`` text safely (literals only, never ``eval``)."""
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except SyntaxError:
        raise PlyFormatError(f"{where}: not a Namespace(...) expression") from None
    if not (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == "Namespace"
        and not node.args
    ):
        raise PlyFormatError(f"{where}: not a Namespace(...) expression")
    out: dict[str, Any] = {}
    for kw in node.keywords:
        try:
            out[str(kw.arg)] = ast.literal_eval(kw.value)
        except ValueError:
            raise PlyFormatError(f"{where}: value of {kw.arg} is not a literal") from None
    return out


def default_cfg_args(
    sh_degree: int, model_path: str, source_path: str = "", white_background: bool = False
) -> dict[str, Any]:
    """The fields of the original 3DGS ``ModelParams``, in its order."""
    return {
        "sh_degree": sh_degree,
        "source_path": source_path,
        "model_path": model_path,
        "images": "images",
        "depths": "",
        "resolution": -1,
        "white_background": white_background,
        "train_test_exp": False,
        "data_device": "cuda",
        "eval": False,
    }


@dataclass(frozen=True, eq=False)
class SplatModel:
    """What :func:`load_model` reads from a model folder."""

    gmap: GaussianMap
    cameras: list[CameraEntry]
    cfg_args: dict[str, Any]
    iteration: int
    ply_path: Path


def ply_path(model_dir: str | os.PathLike[str], iteration: int) -> Path:
    return Path(model_dir) / "point_cloud" / f"iteration_{iteration}" / PLY_NAME


def iterations(model_dir: str | os.PathLike[str]) -> list[int]:
    """The iterations saved under ``model_dir/point_cloud``, ascending."""
    root = Path(model_dir) / "point_cloud"
    found = []
    if root.is_dir():
        for d in root.iterdir():
            m = ITERATION_DIR.match(d.name)
            if m and (d / PLY_NAME).is_file():
                found.append(int(m.group(1)))
    return sorted(found)


def save_model(
    model_dir: str | os.PathLike[str],
    gmap: GaussianMap,
    iteration: int,
    cameras: Sequence[CameraEntry] = (),
    source_path: str = "",
    white_background: bool = False,
    extra_args: Mapping[str, Any] | None = None,  # appended to cfg_args
) -> Path:
    """Write ``point_cloud/iteration_N/point_cloud.ply``, ``cameras.json`` and ``cfg_args``."""
    if isinstance(iteration, bool) or not isinstance(iteration, int) or iteration < 0:
        raise ValueError(f"iteration must be a non-negative int, got {iteration!r}")
    if not all(isinstance(c, CameraEntry) for c in cameras):
        raise TypeError("cameras must be CameraEntry items (see CameraEntry.from_frame)")
    model_dir = Path(model_dir)
    # 1. The point cloud of this iteration
    out = write_ply(ply_path(model_dir, iteration), gmap)
    # 2. Cameras (the original writes a JSON list, one dict per camera)
    atomic_write_text(model_dir / "cameras.json", json.dumps([c.to_json() for c in cameras]))
    # 3. cfg_args: what the original's renderers and GSFix3D read
    args = default_cfg_args(gmap.sh_degree, str(model_dir.resolve()), source_path, white_background)
    args.update(extra_args or {})
    atomic_write_text(model_dir / "cfg_args", format_cfg_args(args))
    return out


def load_model(
    model_dir: str | os.PathLike[str],
    iteration: int | None = None,  # None = the latest saved
    device: str | torch.device = "cpu",
) -> SplatModel:
    """Read a model folder written by :func:`save_model` or by the original 3DGS tools."""
    model_dir = Path(model_dir)
    if iteration is None:
        its = iterations(model_dir)
        if not its:
            raise PlyFormatError(f"{model_dir}: no point_cloud/iteration_N/{PLY_NAME}")
        iteration = its[-1]
    path = ply_path(model_dir, iteration)
    gmap = read_ply(path, device)
    cameras: list[CameraEntry] = []
    cam_file = model_dir / "cameras.json"
    if cam_file.is_file():
        try:
            entries = json.loads(cam_file.read_text())
        except json.JSONDecodeError as exc:
            raise PlyFormatError(f"{cam_file}: not valid JSON ({exc.msg})") from None
        if not isinstance(entries, list):
            raise PlyFormatError(f"{cam_file}: must hold a list of cameras")
        cameras = [CameraEntry.from_json(e, str(cam_file)) for e in entries]
    cfg_file = model_dir / "cfg_args"
    cfg_args = parse_cfg_args(cfg_file.read_text(), str(cfg_file)) if cfg_file.is_file() else {}
    return SplatModel(gmap, cameras, cfg_args, iteration, path)
