"""Exports of a finished repair run that other tools open.

``gsfix-online export KIND RUN_DIR [--out PATH]``:

===========  =====================  ===================================================
KIND         default file           opens in
===========  =====================  ===================================================
``ply``      ``point_cloud.ply``    3DGS viewers (SuperSplat, the original SIBR viewer,
                                    nerfstudio, gsplat, rerun): the run's standard 3DGS
                                    PLY, byte for byte
``mesh-ply`` ``mesh.ply``           MeshLab, CloudCompare, Blender, Open3D: the TSDF mesh
                                    with vertex colours, byte for byte
``glb``      ``mesh.glb``           Blender, three.js, trimesh, viser, Foxglove, any glTF
                                    viewer: the same mesh as glTF binary
``rrd``      ``run.rrd``            the rerun viewer (``rerun run.rrd``): the run on one
                                    timeline (see :func:`export_rrd`)
``mcap``     ``run.mcap``           Foxglove, Lichtblick: mesh, splat centres, view poses
                                    and images (see :func:`export_mcap`)
===========  =====================  ===================================================

Every file is written atomically. The run folder is read through
:class:`~gsfix_online.services.run_folder.RunFolder`, which validates it once.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from gsfix_online.core.io import atomic_path
from gsfix_online.services.run_folder import RunFolder, RunFolderError

logger = logging.getLogger(__name__)

ExportKind = Literal["ply", "mesh-ply", "glb", "rrd", "mcap"]
DEFAULT_NAMES: dict[str, str] = {
    "ply": "point_cloud.ply",
    "mesh-ply": "mesh.ply",
    "glb": "mesh.glb",
    "rrd": "run.rrd",
    "mcap": "run.mcap",
}
SUFFIXES = {"ply": ".ply", "mesh-ply": ".ply", "glb": ".glb", "rrd": ".rrd", "mcap": ".mcap"}
VIEW_IMAGES = {"before": "gs", "after": "output", "final": "final"}  # entity name -> run image
RERUN_INSTALL = "pip install 'gsfix-online[viewer]'"


class ExportError(ValueError):
    """An export cannot be made (what is missing or wrong, in one line)."""


@dataclass
class ExportResult:
    path: Path
    counts: dict[str, int] = field(default_factory=dict)  # what went in, e.g. {"views": 8}

    def summary(self) -> str:
        size_mb = self.path.stat().st_size / 1e6
        what = ", ".join(f"{v} {k}" for k, v in self.counts.items())
        return f"{self.path} ({size_mb:.2f} MB{'; ' + what if what else ''})"


# ----------------------------------------------------------------------------------------------
# Files as they are: the 3DGS PLY and the mesh
# ----------------------------------------------------------------------------------------------


def _copy(src: Path, out: Path) -> None:
    with atomic_path(out) as tmp:
        shutil.copyfile(src, tmp)


def export_ply(run: RunFolder, out: Path) -> ExportResult:
    """The run's standard 3DGS PLY (its latest iteration), byte for byte, once it is checked."""
    from gsfix_online.mapping.splat.ply import check_ply

    src = run.splat_ply()
    _copy(src, out)
    return ExportResult(out, {"Gaussians": check_ply(src).n})


def _mesh(run: RunFolder) -> Any:
    mesh = run.mesh()
    if mesh is None:
        raise ExportError(f"{run.path}: no mesh ({run.mesh_path.name} is missing)")
    return mesh


def export_mesh(run: RunFolder, out: Path, fmt: Literal["ply", "glb"]) -> ExportResult:
    """The TSDF mesh: the PLY byte for byte, or converted to GLB (vertex colours kept)."""
    from gsfix_online.mapping.mesh import write_mesh

    mesh = _mesh(run)
    if fmt == "ply":
        _copy(run.mesh_path, out)
    else:
        write_mesh(mesh, out)
    return ExportResult(out, {"vertices": mesh.n_vertices, "triangles": mesh.n_triangles})


# ----------------------------------------------------------------------------------------------
# What both recordings hold
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Splats:
    centers: npt.NDArray[np.float32]  # [N, 3] m
    scales: npt.NDArray[np.float32]  # [N, 3] m, standard deviations
    quats_xyzw: npt.NDArray[np.float32]  # [N, 4]
    rgba: npt.NDArray[np.uint8]  # [N, 4] base colour and opacity


def _gaussians(run: RunFolder) -> Any:
    """The run's GaussianMap, or None when it has no 3DGS map folder."""
    return run.splat_model().gmap if run.map_dir.is_dir() else None


def _splats(g: Any) -> _Splats:
    """A GaussianMap in natural units."""
    import torch

    from gsfix_online.mapping.splat.gaussians import normalize_quats, sh0_to_rgb

    with torch.no_grad():
        rgb = sh0_to_rgb(g.params["sh0"][:, 0]).clamp(0, 1).expand(-1, 3)  # [N, 3]
        rgba = torch.cat([rgb, g.opacities[:, None]], 1)
        wxyz = normalize_quats(g.params["quats"])
        return _Splats(
            g.means.cpu().numpy().astype(np.float32),
            g.scales.cpu().numpy().astype(np.float32),
            wxyz[:, [1, 2, 3, 0]].cpu().numpy().astype(np.float32),
            np.rint(rgba.cpu().numpy() * 255).astype(np.uint8),
        )


def _read_bytes(run: RunFolder, rel: str) -> bytes:
    return run.resolve(rel).read_bytes()


def _view_images(run: RunFolder, images: dict[str, str]) -> Iterator[tuple[str, bytes]]:
    """(entity name, PNG bytes) of a view's before / after / final images that exist."""
    for name, key in VIEW_IMAGES.items():
        if key in images and run.resolve(images[key]).is_file():
            yield name, _read_bytes(run, images[key])


def _input_frames(src: str | Path, every: int) -> Iterator[Any]:
    from gsfix_online.sources import SourceConfig, open_source

    reader = open_source(SourceConfig(path=str(src)))
    for i, frame in enumerate(reader):
        if i % every == 0:
            yield frame


# ----------------------------------------------------------------------------------------------
# rerun
# ----------------------------------------------------------------------------------------------


def _import_rerun() -> Any:
    try:
        import rerun as rr
    except ImportError:
        raise ImportError(f"the rrd export needs the rerun SDK: {RERUN_INSTALL}") from None
    return rr


def _log_camera(rec: Any, rr: Any, path: str, T: np.ndarray, K: np.ndarray, w: int, h: int) -> None:
    rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    rec.log(
        path, rr.Pinhole(image_from_camera=K, width=w, height=h, camera_xyz=rr.ViewCoordinates.RDF)
    )


# The provenance layer's colours per origin (gaussians.ORIGINS): observed grey, repaired magenta
ORIGIN_COLOURS = ((150, 150, 150), (230, 40, 200))


def _log_provenance(rec: Any, rr: Any, gmap: Any, centers: np.ndarray) -> None:
    """``world/provenance``: every Gaussian's centre, its class its origin (observed, or grown
    from a repaired view), with how many input frames saw it (``observations``)."""
    from gsfix_online.mapping.splat.gaussians import ORIGINS

    labels = [rr.AnnotationInfo(id=i, label=name, color=ORIGIN_COLOURS[i])
              for i, name in enumerate(ORIGINS)]  # fmt: skip
    rec.log("world/provenance", rr.AnnotationContext(labels), static=True)
    rec.log("world/provenance", rr.Points3D(centers, class_ids=gmap.origin.cpu().numpy()),
            rr.AnyValues(observations=gmap.observations.cpu().numpy()), static=True)  # fmt: skip


def _render_keyframe(gmap: Any, kf: Any) -> tuple[np.ndarray, np.ndarray]:
    """The 3DGS map's colour [H, W, 3] uint8 and depth [H, W] m at a keyframe."""
    import torch

    from gsfix_online.mapping.splat.render import render

    with torch.no_grad():
        out = render(
            gmap.means, gmap.params["quats"], gmap.scales, gmap.opacities, gmap.sh, None,
            torch.tensor(kf.K, dtype=torch.float32), kf.width, kf.height,
            T_world_cam=torch.tensor(kf.T_world_cam, dtype=torch.float32),
            sh_degree=gmap.sh_degree,
        )  # fmt: skip
        color = out.color.clamp(0, 1).expand(-1, -1, 3).cpu().numpy()
    return np.rint(color * 255).astype(np.uint8), out.depth.cpu().numpy().astype(np.float32)


def export_rrd(
    run: RunFolder,
    out: Path,
    input_path: str | Path | None = None,
    input_every: int = 1,
    keyframe_images: bool = True,
) -> ExportResult:
    """A rerun recording of the run on one sequence timeline, ``step``.

    Entities (camera entities hold a ``Transform3D`` camera-to-world and a ``Pinhole``, OpenCV
    axes)::

        world/mesh                    Mesh3D: the TSDF mesh (static)
        world/splats                  GaussianSplats3D: the 3DGS map (static)
        world/provenance              Points3D: each Gaussian's centre, its class its origin
                                      (observed / repaired), with ``observations`` (static)
        world/keyframes/<id>          the map's keyframes (static), with image and depth
                                      rendered from the map unless keyframe_images is False
        world/input                   with an input: its frames at steps 0..F-1 (image, depth)
        world/input_path              LineStrips3D: the input trajectory (static)
        world/views/<NNN>             each repaired view at step F + i: before (the 3DGS
                                      render), after (the repair), final (the distilled map)
    """
    rr = _import_rerun()
    if input_every < 1:
        raise ExportError(f"input_every must be >= 1, got {input_every}")
    counts: dict[str, int] = {}
    with atomic_path(out) as tmp:
        rec = rr.RecordingStream("gsfix-online", recording_id=f"run-{run.path.resolve().name}")
        rec.save(str(tmp))
        # 1. The maps, static
        m = run.mesh()
        if m is not None:
            rec.log("world/mesh", rr.Mesh3D(vertex_positions=m.vertices,
                    triangle_indices=m.triangles, vertex_colors=m.colors), static=True)  # fmt: skip
            counts["mesh triangles"] = m.n_triangles
        gmap = _gaussians(run)
        if gmap is not None:
            splats = _splats(gmap)
            rec.log("world/splats", rr.GaussianSplats3D(centers=splats.centers,
                    scales=splats.scales, quaternions=splats.quats_xyzw, colors=splats.rgba),
                    static=True)  # fmt: skip
            counts["splats"] = len(splats.centers)
            _log_provenance(rec, rr, gmap, splats.centers)
        # 2. The keyframes, static
        for kf in run.keyframes:
            path = f"world/keyframes/{kf.id}"
            rec.log(path, rr.Transform3D(translation=kf.T_world_cam[:3, 3],
                    mat3x3=kf.T_world_cam[:3, :3]), static=True)  # fmt: skip
            rec.log(path, rr.Pinhole(image_from_camera=kf.K, width=kf.width, height=kf.height,
                    camera_xyz=rr.ViewCoordinates.RDF), static=True)  # fmt: skip
            if gmap is not None and keyframe_images:
                color, depth = _render_keyframe(gmap, kf)
                rec.log(f"{path}/image", rr.Image(color), static=True)
                rec.log(f"{path}/depth", rr.DepthImage(depth, meter=1.0), static=True)
        counts["keyframes"] = len(run.keyframes)
        # 3. The input frames, steps 0..F-1
        step = 0
        if input_path is not None:
            positions = []
            for frame in _input_frames(input_path, input_every):
                rec.set_time("step", sequence=step)
                k = frame.intrinsics
                _log_camera(rec, rr, "world/input", frame.T_world_cam, k.K, k.width, k.height)
                rec.log("world/input/image", rr.Image(frame.color))
                rec.log("world/input/depth", rr.DepthImage(frame.depth, meter=1.0))
                positions.append(frame.T_world_cam[:3, 3])
                step += 1
            if positions:
                rec.log("world/input_path", rr.LineStrips3D([np.asarray(positions)]), static=True)
            counts["input frames"] = step
        # 4. The views, after the input
        for v in run.views:
            rec.set_time("step", sequence=step)
            path = f"world/views/{v.name}"
            _log_camera(rec, rr, path, v.T_world_cam, v.K, v.width, v.height)
            for name, png in _view_images(run, v.images):
                rec.log(f"{path}/{name}", rr.EncodedImage(contents=png, media_type="image/png"))
            step += 1
        counts["views"] = len(run.views)
        rec.flush()
        rec.disconnect()
    return ExportResult(out, counts)


# ----------------------------------------------------------------------------------------------
# MCAP for Foxglove
# ----------------------------------------------------------------------------------------------

MCAP_WORLD = "world"
MCAP_TOPICS = {
    "mesh": "/run/mesh",  # foxglove.SceneUpdate: one glTF model
    "splats": "/run/splats",  # foxglove.PointCloud: centres, RGBA
    "tf": "/tf",  # foxglove.FrameTransform: world -> keyframe_<id>, view_<NNN>
    "calibration": "/run/views/calibration",  # foxglove.CameraCalibration per view
}  # and /run/views/<before|after|final>: foxglove.CompressedImage (PNG)


def _glb_bytes(run: RunFolder) -> bytes | None:
    import tempfile

    from gsfix_online.mapping.mesh import write_mesh

    mesh = run.mesh()
    if mesh is None:
        return None
    with tempfile.TemporaryDirectory(prefix="gsfix-export-") as tmp:
        return write_mesh(mesh, Path(tmp) / "mesh.glb").read_bytes()


def _point_cloud_bytes(s: _Splats) -> bytes:  # [N] x y z float32, r g b a uint8
    rec = np.zeros(len(s.centers), dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])
    rec["xyz"], rec["rgba"] = s.centers, s.rgba
    return rec.tobytes()


class _McapOut:
    """An MCAP writer with the Foxglove protobuf schemas registered on demand."""

    def __init__(self, fh: Any) -> None:
        from mcap.writer import Writer

        self._w = Writer(fh)
        self._w.start(profile="", library="gsfix-online export")
        self._channels: dict[str, int] = {}
        self.messages = 0

    def add(self, topic: str, msg: Any, t_ns: int) -> None:
        from mcap.well_known import MessageEncoding
        from mcap_protobuf.schema import register_schema

        if topic not in self._channels:
            schema = register_schema(self._w, type(msg))
            self._channels[topic] = self._w.register_channel(
                topic, MessageEncoding.Protobuf, schema
            )
        self._w.add_message(self._channels[topic], log_time=t_ns, data=msg.SerializeToString(),
                            publish_time=t_ns)  # fmt: skip
        self.messages += 1

    def finish(self) -> None:
        self._w.finish()


def _stamp(t_ns: int) -> Any:
    from google.protobuf.timestamp_pb2 import Timestamp

    return Timestamp(seconds=t_ns // 1_000_000_000, nanos=t_ns % 1_000_000_000)


def _transform(child: str, T: np.ndarray, t_ns: int) -> Any:
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

    from gsfix_online.core.se3 import R_to_quat_xyzw

    tf = FrameTransform(timestamp=_stamp(t_ns), parent_frame_id=MCAP_WORLD, child_frame_id=child)
    tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in T[:3, 3])
    q = R_to_quat_xyzw(T[:3, :3])
    tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = (float(v) for v in q)
    return tf


def export_mcap(run: RunFolder, out: Path, step_s: float = 1.0) -> ExportResult:
    """An MCAP file with Foxglove schemas: at time 0 the mesh (a glTF model in a SceneUpdate),
    the splat centres (PointCloud) and the keyframe poses (``/tf``); then one view every
    ``step_s`` seconds: its pose, calibration and before / after / final images (PNG).

    The input log itself is MCAP already (``gsfix-online convert SRC log.mcap``)."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.ModelPrimitive_pb2 import ModelPrimitive
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    counts: dict[str, int] = {}
    glb = _glb_bytes(run)
    gmap = _gaussians(run)
    splats = _splats(gmap) if gmap is not None else None
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        w = _McapOut(fh)
        t0 = 0
        # 1. The maps and the keyframes at time 0
        if glb is not None:
            model = ModelPrimitive(media_type="model/gltf-binary", data=glb)
            model.scale.x = model.scale.y = model.scale.z = 1.0
            model.pose.orientation.w = 1.0
            entity = SceneEntity(
                timestamp=_stamp(t0), frame_id=MCAP_WORLD, id="mesh", models=[model]
            )
            w.add(MCAP_TOPICS["mesh"], SceneUpdate(entities=[entity]), t0)
            counts["mesh"] = 1
        if splats is not None:
            F = PackedElementField
            fields = [F(name=n, offset=4 * i, type=F.FLOAT32) for i, n in enumerate("xyz")]
            fields += [F(name=n, offset=12 + i, type=F.UINT8)
                       for i, n in enumerate(("red", "green", "blue", "alpha"))]  # fmt: skip
            cloud = PointCloud(timestamp=_stamp(t0), frame_id=MCAP_WORLD, point_stride=16,
                               fields=fields, data=_point_cloud_bytes(splats))  # fmt: skip
            cloud.pose.orientation.w = 1.0
            w.add(MCAP_TOPICS["splats"], cloud, t0)
            counts["splats"] = len(splats.centers)
        for kf in run.keyframes:
            w.add(MCAP_TOPICS["tf"], _transform(f"keyframe_{kf.id}", kf.T_world_cam, t0), t0)
        counts["keyframes"] = len(run.keyframes)
        # 2. One view per step
        for i, v in enumerate(run.views):
            t = int(round((i + 1) * step_s * 1e9))
            frame = f"view_{v.name}"
            w.add(MCAP_TOPICS["tf"], _transform(frame, v.T_world_cam, t), t)
            P = np.hstack([v.K, np.zeros((3, 1))])
            calib = CameraCalibration(timestamp=_stamp(t), frame_id=frame, width=v.width,
                                      height=v.height, distortion_model="", D=[],
                                      K=v.K.ravel().tolist(), R=np.eye(3).ravel().tolist(),
                                      P=P.ravel().tolist())  # fmt: skip
            w.add(MCAP_TOPICS["calibration"], calib, t)
            for name, png in _view_images(run, v.images):
                img = CompressedImage(timestamp=_stamp(t), frame_id=frame, data=png, format="png")
                w.add(f"/run/views/{name}", img, t)
        counts["views"] = len(run.views)
        w.finish()
        fh.flush()
        os.fsync(fh.fileno())
    return ExportResult(out, counts)


# ----------------------------------------------------------------------------------------------
# One entry point
# ----------------------------------------------------------------------------------------------


def export(
    kind: ExportKind,
    run_dir: str | os.PathLike[str],
    out: str | os.PathLike[str] | None = None,
    input_path: str | Path | None = None,
    input_every: int = 1,
    keyframe_images: bool = True,
) -> ExportResult:
    """Write the export ``kind`` of the run in ``run_dir`` to ``out`` (default: the run folder,
    ``DEFAULT_NAMES[kind]``, under ``exports/``)."""
    # 1. Check the request
    if kind not in DEFAULT_NAMES:
        raise ExportError(f"export kind must be one of {', '.join(DEFAULT_NAMES)}, got {kind!r}")
    run = RunFolder(run_dir)
    path = Path(out) if out is not None else run.path / "exports" / DEFAULT_NAMES[kind]
    if path.suffix.lower() != SUFFIXES[kind]:
        raise ExportError(
            f"--out for a {kind} export must end in {SUFFIXES[kind]}, got {path.name!r}"
        )
    if input_path is not None and kind != "rrd":
        raise ExportError(f"--input goes into the rrd export only, not {kind}")
    if input_path is not None and not Path(input_path).exists():
        raise ExportError(f"--input {input_path}: no such file or folder")
    # 2. Write it
    try:
        if kind == "ply":
            return export_ply(run, path)
        if kind in ("mesh-ply", "glb"):
            return export_mesh(run, path, "ply" if kind == "mesh-ply" else "glb")
        if kind == "rrd":
            return export_rrd(run, path, input_path, input_every, keyframe_images)
        return export_mcap(run, path)
    except RunFolderError as exc:
        raise ExportError(str(exc)) from None
