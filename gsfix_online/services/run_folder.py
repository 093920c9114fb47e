"""Read the output folder of a finished ``gsfix-online repair`` run.

The map server, the viewer and the exports read a run through :class:`RunFolder`; the layout
is the one :mod:`gsfix_online.repair.outputs` and ``nodes/repair_writer.py`` write::

    DIR/metrics.json        summary, per view: camera (K, T_world_cam, width, height), files, ...
    DIR/views/NNN/*.png     the images of view NNN
    DIR/map/                the standard 3DGS model folder (cameras.json: the keyframes)
    DIR/mesh.ply            the TSDF mesh
    DIR/work/checkpoints/   GSFixer fine-tuning checkpoints (``latest`` names the newest)
    DIR/work/keyframes/     the input keyframes the trainer kept (kf_NNNNNNNN.npz: colour,
                            depth, K, T_world_cam): the reference frames warped into views

Reading is validated once, here: a folder that is not a run folder, a metrics.json whose
cameras are not finite rigid poses, or a damaged map (a 3DGS PLY or a mesh cut short or holding
non-finite values, a mesh without triangles) raises :class:`RunFolderError` with one line naming
the file and what is wrong. Nothing is fixed up silently.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from gsfix_online.core.types import FrameError, Intrinsics, check_pose

if TYPE_CHECKING:
    from gsfix_online.mapping.mesh import TriMesh
    from gsfix_online.mapping.splat.ply import SplatModel
    from gsfix_online.repair.references import ReferenceStore

logger = logging.getLogger(__name__)

METRICS = "metrics.json"
MAP_DIR = "map"
MESH = "mesh.ply"
CHECKPOINTS = "work/checkpoints"
KEYFRAMES = "work/keyframes"


class RunFolderError(ValueError):
    """A folder is not a (readable) run folder of ``gsfix-online repair``."""


@dataclass(frozen=True, eq=False)
class RunView:
    """One view of the run as metrics.json records it."""

    view_id: int
    name: str  # "000": its folder under views/
    K: npt.NDArray[np.float64]  # [3, 3] pixels
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] camera-to-world, OpenCV axes
    width: int
    height: int
    images: dict[str, str]  # image name ("gs", "output", ...) -> path relative to the run folder
    repair: bool | None  # None: no decision recorded
    reason: str
    metrics: dict[str, Any] = field(default_factory=dict)  # stage -> {psnr_db, ssim}


@dataclass(frozen=True, eq=False)
class Keyframe:
    """One keyframe of the 3DGS map (``map/cameras.json``; its principal point is the centre)."""

    id: int
    img_name: str
    K: npt.NDArray[np.float64]  # [3, 3] pixels, cx = (width - 1) / 2, cy = (height - 1) / 2
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] camera-to-world, OpenCV axes
    width: int
    height: int

    @property
    def repaired(self) -> bool:
        """A repaired view distilled into the map, not an input frame (``ply.camera_name``)."""
        from gsfix_online.mapping.splat.ply import is_repaired_name

        return is_repaired_name(self.img_name)


def _camera(cam: Any, where: str) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """K [3, 3] and T_world_cam [4, 4] of a metrics.json camera, or a one-line error."""
    if not isinstance(cam, dict):
        raise RunFolderError(f"{where}: camera must be an object, got {type(cam).__name__}")
    missing = [k for k in ("K", "T_world_cam", "width", "height") if k not in cam]
    if missing:
        raise RunFolderError(f"{where}: camera lacks {', '.join(missing)}")
    try:
        K = np.asarray(cam["K"], dtype=np.float64)
        T = np.asarray(cam["T_world_cam"], dtype=np.float64)
    except (TypeError, ValueError):
        raise RunFolderError(f"{where}: camera K and T_world_cam must be numbers") from None
    if K.shape != (9,) or T.shape != (16,):
        raise RunFolderError(
            f"{where}: camera K must hold 9 numbers and T_world_cam 16, got {K.size} and {T.size}"
        )
    try:
        T = check_pose(T.reshape(4, 4))
        Intrinsics.from_K(K.reshape(3, 3), cam["width"], cam["height"])
    except (FrameError, TypeError) as exc:
        raise RunFolderError(f"{where}: {exc}") from None
    return K.reshape(3, 3), T


def read_keyframes(model_dir: Path) -> list[Keyframe]:
    """The cameras of a 3DGS model folder (``cameras.json``); [] when it has none."""
    from gsfix_online.mapping.splat.ply import CameraEntry, PlyFormatError

    path = model_dir / "cameras.json"
    if not path.is_file():
        return []
    try:
        entries = json.loads(path.read_text())
        if not isinstance(entries, list):
            raise RunFolderError(f"{path}: must hold a list of cameras")
        cams = [CameraEntry.from_json(e, str(path)) for e in entries]
    except (json.JSONDecodeError, PlyFormatError) as exc:
        raise RunFolderError(f"{path}: {exc}") from None
    out = []
    for c in cams:
        K = np.array([[c.fx, 0.0, (c.width - 1) / 2], [0.0, c.fy, (c.height - 1) / 2], [0, 0, 1.0]])
        out.append(Keyframe(c.id, c.img_name, K, c.T_world_cam, c.width, c.height))
    return out


def _keyframe_arrays(path: Path, keys: tuple[str, ...], what: str) -> dict[str, Any]:
    """``keys`` of a keyframe file of ``work/keyframes``, T_world_cam checked as a pose; a file
    that is damaged or lacks one raises RunFolderError ``"{path}: {what}: ..."``."""
    import zipfile

    try:
        with np.load(path) as z:
            missing = [k for k in keys if k not in z]
            if missing:
                raise ValueError(f"lacks arrays {missing}, has {sorted(z.files)}")
            arrays = {k: z[k] for k in keys}
        if "T_world_cam" in arrays:
            arrays["T_world_cam"] = check_pose(arrays["T_world_cam"])
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, FrameError) as exc:
        raise RunFolderError(f"{path}: {what}: {exc}") from None
    return arrays


class RunFolder:
    """A finished run's folder: metrics, views, keyframes, the maps and the checkpoints."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        root = Path(path)
        if not root.is_dir():
            raise RunFolderError(f"{root}: no such folder")
        metrics = root / METRICS
        if not metrics.is_file():
            raise RunFolderError(
                f"{root}: not a run folder of 'gsfix-online repair' (no {METRICS})"
            )
        try:
            data = json.loads(metrics.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise RunFolderError(f"{metrics}: not valid JSON ({exc})") from None
        if not isinstance(data, dict) or not isinstance(data.get("views", []), list):
            raise RunFolderError(f"{metrics}: must be an object with a 'views' list")
        self.path = root
        self.metrics: dict[str, Any] = data
        self.views: list[RunView] = [
            self._view(v, i, metrics) for i, v in enumerate(data.get("views", []))
        ]
        ids = [v.view_id for v in self.views]
        if len(set(ids)) != len(ids):
            raise RunFolderError(f"{metrics}: view ids repeat: {ids}")

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r}, views={len(self.views)})"

    def _view(self, v: Any, index: int, metrics: Path) -> RunView:
        where = f"{metrics}: views[{index}]"
        if not isinstance(v, dict):
            raise RunFolderError(f"{where}: must be an object")
        vid = v.get("view_id", v.get("view"))
        try:
            view_id = int(vid)  # "view" is the folder name ("000"), "view_id" the number
        except (TypeError, ValueError):
            raise RunFolderError(f"{where}: no integer view id (got {vid!r})") from None
        K, T = _camera(v.get("camera"), where)
        files = v.get("files", {})
        if not isinstance(files, dict) or not all(isinstance(p, str) for p in files.values()):
            raise RunFolderError(f"{where}: files must map image names to relative paths")
        bad = [p for p in files.values() if not self._inside(p)]
        if bad:
            raise RunFolderError(f"{where}: file path {bad[0]!r} leaves the run folder")
        repair = v.get("repair")
        return RunView(
            view_id,
            f"{view_id:03d}",
            K,
            T,
            int(v["camera"]["width"]),
            int(v["camera"]["height"]),
            dict(files),
            None if repair is None else bool(repair),
            str(v.get("reason", "")),
            dict(v.get("metrics") or {}),
        )

    # -- paths -------------------------------------------------------------------------------

    def _inside(self, rel: str) -> bool:
        p = Path(rel)
        return not p.is_absolute() and ".." not in p.parts and rel.strip() != ""

    def resolve(self, rel: str) -> Path:
        """The path of a file of the run given relative to its folder; a path that would leave
        the folder (absolute, ``..``, or a link pointing out) is an error."""
        if not isinstance(rel, str) or not self._inside(rel):
            raise RunFolderError(f"path {rel!r} must be relative and inside the run folder")
        root = self.path.resolve()
        p = (root / rel).resolve()
        if root not in p.parents:
            raise RunFolderError(f"path {rel!r} leaves the run folder")
        return p

    def _named(self, key: str, default: str) -> str:
        files = self.metrics.get("files")
        name = files.get(key) if isinstance(files, dict) else None
        name = name or self.metrics.get(key) or default
        if not isinstance(name, str) or not self._inside(name):
            raise RunFolderError(f"{self.path / METRICS}: {key} path {name!r} is not relative")
        return name

    @property
    def map_dir(self) -> Path:
        return self.path / self._named("map", MAP_DIR)

    @property
    def mesh_path(self) -> Path:
        return self.path / self._named("mesh", MESH)

    @property
    def checkpoint_dir(self) -> Path | None:
        """The run's checkpoint root when it holds a ``latest`` checkpoint, else None."""
        root = self.path / CHECKPOINTS
        return root if (root / "latest").is_file() else None

    @property
    def fallback(self) -> dict[str, Any] | None:
        """The fallback choice the repairs followed (``repair.fallback.Choice`` as JSON)."""
        summary = self.metrics.get("summary")
        choice = summary.get("fallback") if isinstance(summary, dict) else None
        return choice if isinstance(choice, dict) else None

    @property
    def records_choices(self) -> bool:
        """The run records what :meth:`choices` needs (runs before it recorded the fallback
        choice alone, and named repaired views like keyframes in ``cameras.json``)."""
        summary = self.metrics.get("summary")
        return isinstance(summary, dict) and "holdout_reach_m" in summary

    def choices(self) -> tuple[dict[str, Any] | None, float | None, dict[str, Any] | None]:
        """What the run's repairs chose by (``repair.fallback.for_view``): the held-out frames'
        choice and how far it holds (None, None: not measured on held-out frames), and the
        trainer's choice, which views beyond held (None: not recorded). A run written before
        the reach was recorded gives its fallback choice for every distance: (fallback, None,
        None)."""
        summary = self.metrics.get("summary")
        summary = summary if isinstance(summary, dict) else {}
        fallback = self.fallback
        if not self.records_choices:
            return fallback, None, None
        reach = summary["holdout_reach_m"]
        trainer = summary.get("trainer_choice")
        trainer = trainer if isinstance(trainer, dict) else None
        if not isinstance(reach, (int, float)) or isinstance(reach, bool):
            return None, None, trainer or fallback  # the fallback was the trainer's
        return fallback, float(reach), trainer

    def view(self, view_id: int) -> RunView:
        for v in self.views:
            if v.view_id == view_id:
                return v
        raise RunFolderError(
            f"{self.path}: no view {view_id} (has {[v.view_id for v in self.views]})"
        )

    def reference_frames(self) -> list[Path]:
        """The run's input keyframes with their images and depths (``work/keyframes``), oldest
        first; [] for a run without them."""
        return sorted((self.path / KEYFRAMES).glob("kf_*.npz"))

    def keyframe_poses(self) -> list[npt.NDArray[np.float64]]:
        """The poses ([4, 4] camera-to-world) of every input keyframe of :meth:`reference_frames`,
        checked; a file without one raises RunFolderError naming it."""
        return [_keyframe_arrays(p, ("T_world_cam",), "no keyframe pose")["T_world_cam"]
                for p in self.reference_frames()]  # fmt: skip

    def references(self, capacity: int) -> ReferenceStore:
        """The reference frames (:meth:`reference_frames`) in a store of at most ``capacity``,
        as the planner keeps them (the most redundant evicted); one that is damaged or lacks
        an array raises RunFolderError naming the file."""
        from gsfix_online.repair.references import ReferenceStore, reference_from_arrays

        store = ReferenceStore(capacity)
        for path in self.reference_frames():
            arrays = _keyframe_arrays(path, ("color", "depth", "K", "T_world_cam"),
                                      "not a reference frame")  # fmt: skip
            store.add(int(path.stem[3:]), reference_from_arrays(arrays))
        return store

    # -- the maps ----------------------------------------------------------------------------

    @cached_property
    def keyframes(self) -> list[Keyframe]:
        """The 3DGS map's training cameras (``map/cameras.json``); [] when there are none."""
        return read_keyframes(self.map_dir)

    def splat_ply(self) -> Path:
        """The run's standard 3DGS PLY (its latest iteration), checked whole (layout, size,
        finite values: :func:`~gsfix_online.mapping.splat.ply.check_ply`)."""
        from gsfix_online.mapping.splat.ply import PlyFormatError, check_ply, iterations, ply_path

        its = iterations(self.map_dir)
        if not its:
            raise RunFolderError(
                f"{self.path}: no 3DGS map (no {self.map_dir.name}/point_cloud/iteration_N)"
            )
        try:
            return check_ply(ply_path(self.map_dir, its[-1])).path
        except PlyFormatError as exc:
            raise RunFolderError(str(exc)) from None

    def mesh(self) -> TriMesh | None:
        """The run's TSDF mesh, checked (whole, finite, with triangles: a run's mesh is never
        empty); None when the run has no mesh file."""
        from gsfix_online.mapping.mesh import MeshFormatError, read_mesh

        if not self.mesh_path.is_file():
            return None
        try:
            return read_mesh(self.mesh_path)
        except MeshFormatError as exc:
            raise RunFolderError(str(exc)) from None

    def splat_model(self, device: str = "cpu") -> SplatModel:
        """The run's Gaussian map (its latest iteration), cameras and cfg_args."""
        from gsfix_online.mapping.splat.ply import PlyFormatError, load_model

        if not self.map_dir.is_dir():
            raise RunFolderError(f"{self.path}: has no 3DGS map folder {self.map_dir.name}/")
        try:
            return load_model(self.map_dir, device=device)
        except PlyFormatError as exc:
            raise RunFolderError(str(exc)) from None
