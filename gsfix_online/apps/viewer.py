"""The web viewer of a map: ``gsfix-online view RUN_DIR`` or ``gsfix-online view --live ADDRESS``.

Built on viser. One metric world frame holds:

- the Gaussian map (viser's splat renderer; it draws the degree-0 colour of each Gaussian, so
  view-dependent colour is not shown) and the TSDF mesh, each with a toggle; a toggle tints the
  synthesised part of the map (Gaussians grown from repaired views, which no input frame saw);
- the camera frusta of the map's keyframes (blue) and of the run's views (orange: repaired,
  grey: skipped), hidden until the Cameras toggle shows them, sized to a few per cent of the
  map. Clicking one shows its images: before (3DGS render) and after (the delivered repair) for
  a view, a render of the Gaussian map from its pose for a keyframe;
- a two-click distance tool in metres (:mod:`gsfix_online.apps.measure`): the pick point
  of a click is the first hit of its ray on the mesh, or on the splats without a mesh; it warns
  when a point lies on a synthesised surface; named measurements are labels, saved to
  ``labels.json`` next to the map and loaded again;
- a button that asks the map server to repair the current view and shows the result.

Where the map comes from is a :class:`MapSource`: :class:`RunFolderSource` reads a finished run
folder (repairs go to a map server when one is named), :class:`LiveSource` asks a running map
server for everything through :class:`gsfix_online.apps.client.MapClient`.
The viewer opens on an overview (:func:`overview_pose`): outside the map, looking at it, the
whole map filling the view. It binds 127.0.0.1 unless the user names another host.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import tempfile
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import numpy.typing as npt

from gsfix_online.apps.measure import (
    LABELS_FILE,
    Label,
    LabelsError,
    Pick,
    Picker,
    load_labels,
    render_splats,
    save_labels,
)
from gsfix_online.core.config import rng
from gsfix_online.core.se3 import R_to_quat_xyzw, make_T, quat_xyzw_to_R
from gsfix_online.core.types import FrameError, Intrinsics, check_pose
from gsfix_online.mapping.mesh import TriMesh

logger = logging.getLogger(__name__)

VIEWER_EXTRA = "pip install 'gsfix-online[viewer]'"
KEYFRAME_COLOR = (40, 90, 230)
REPAIRED_COLOR = (240, 140, 20)
SKIPPED_COLOR = (140, 140, 140)
RESULT_COLOR = (20, 170, 60)
MEASURE_COLOR = (230, 30, 200)
SYNTHESISED_TINT = (150, 60, 255)  # the toggle tints Gaussians grown from repaired views so
TINT_SHARE = 0.8  # a tinted Gaussian's colour: this much tint, the rest its own colour
FRUSTUM_SHARE = 0.03  # a camera frustum's depth, as a share of the map's bounding-box diagonal
OVERVIEW_FOV_Y = math.radians(60.0)  # the opening view's vertical field of view
# The canvas aspect the opening view is framed for: square, so the map fits any canvas at least
# as wide as it is tall (a wider one shows more around it). Framing each browser for its own
# canvas raced the panel docking beside it (the first aspect a browser reports is the full
# window's)
OVERVIEW_ASPECT = 1.0
OVERVIEW_ELEVATION = math.radians(20.0)  # above the cameras' mean horizon
OVERVIEW_MARGIN = 1.02  # the map's picture fills 1 / this of the view
OVERVIEW_CENTRING_STEPS = 50  # at most this many sideways moves centre the map's picture
KEYFRAME_RENDER_WIDTH = 240  # px: the render shown for a clicked keyframe (CPU time ~ pixels)
Progress = Callable[[float, str], None]


@dataclass(frozen=True)
class ViewConfig:
    """``gsfix-online view``'s settings (``-c``; ``--host`` and ``--port`` set the same keys)."""

    host: str = "127.0.0.1"  # loopback unless you name another address
    port: int = field(default=8080, metadata=rng(1, 65535, "HTTP port"))


class ViewerError(ValueError):
    """The viewer cannot show a map: bad input, or a source that cannot do what was asked."""


def _require_viser() -> Any:
    try:
        import viser
    except ImportError:
        raise ImportError(f"the web viewer needs viser: {VIEWER_EXTRA}") from None
    return viser


# ----------------------------------------------------------------------------------------------
# Pure conversions
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SplatArrays:
    """A Gaussian map as viser's ``add_gaussian_splats`` takes it."""

    centers: npt.NDArray[np.float32]  # [N, 3] world, metres
    covariances: npt.NDArray[np.float32]  # [N, 3, 3] metres^2
    rgbs: npt.NDArray[np.float32]  # [N, 3] in [0, 1] (degree-0 colour)
    opacities: npt.NDArray[np.float32]  # [N, 1] in [0, 1]


def splat_arrays(gmap: Any, tint_synthesised: bool = False) -> SplatArrays:
    """Convert a GaussianMap (log-scales, w x y z quaternions, SH DC colour, logit opacity) to
    centres, covariances R diag(s^2) R^T, clamped DC colours (grey replicated) and opacities.
    With ``tint_synthesised``, the Gaussians grown from repaired views take SYNTHESISED_TINT
    (TINT_SHARE of their colour)."""
    import torch

    from gsfix_online.mapping.splat.gaussians import sh0_to_rgb

    with torch.no_grad():
        means = gmap.means.detach().cpu().numpy().astype(np.float32)
        q_wxyz = gmap.quats.cpu().numpy().astype(np.float64)  # [N, 4] unit
        s = gmap.scales.cpu().numpy().astype(np.float64)  # [N, 3] metres
        rgb = sh0_to_rgb(gmap.params["sh0"][:, 0, :]).clamp(0, 1).cpu().numpy()  # [N, C]
        alpha = gmap.opacities.cpu().numpy()
    n = len(means)
    R = quat_xyzw_to_R(q_wxyz[:, [1, 2, 3, 0]]) if n else np.zeros((0, 3, 3))  # [N, 3, 3]
    cov = np.einsum("nij,nj,nkj->nik", R, s * s, R)
    if rgb.shape[1] == 1:
        rgb = np.repeat(rgb, 3, axis=1)
    if tint_synthesised:
        synth = gmap.repaired().cpu().numpy()
        tint = np.asarray(SYNTHESISED_TINT, np.float32) / 255.0
        rgb[synth] = TINT_SHARE * tint + (1.0 - TINT_SHARE) * rgb[synth]
    return SplatArrays(
        means,
        cov.astype(np.float32),
        rgb.astype(np.float32),
        alpha.astype(np.float32).reshape(n, 1),
    )


def pose_to_wxyz_position(
    T_world_cam: npt.ArrayLike,  # [4, 4]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:  # wxyz [4], position [3]
    T = np.asarray(T_world_cam, dtype=np.float64)
    q = R_to_quat_xyzw(T[:3, :3])
    return q[[3, 0, 1, 2]], T[:3, 3].copy()


def wxyz_position_to_pose(wxyz: npt.ArrayLike, position: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """viser's camera (R_world_camera as w x y z, OpenCV axes) -> T_world_cam [4, 4]."""
    q = np.asarray(wxyz, dtype=np.float64)
    return make_T(quat_xyzw_to_R(q[[1, 2, 3, 0]]), position)


def fov_intrinsics(fov_y: float, width: int, height: int) -> npt.NDArray[np.float64]:  # [3, 3]
    """Pinhole K of a camera with vertical field of view ``fov_y`` (radians), square pixels and
    the principal point at the image centre (pixel-centre convention)."""
    if not (0.0 < fov_y < math.pi) or width <= 0 or height <= 0:
        raise ViewerError(f"need 0 < fov_y < pi and a positive size, got {fov_y}, {width}x{height}")
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# Where a map comes from
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ViewCamera:
    """A camera drawn as a frustum: a keyframe of the map or a view of the run."""

    kind: Literal["keyframe", "view"]
    id: int
    K: npt.NDArray[np.float64]  # [3, 3] pixels
    T_world_cam: npt.NDArray[np.float64]  # [4, 4] camera-to-world, OpenCV axes
    width: int
    height: int
    images: dict[str, str] = field(default_factory=dict)  # name -> path relative to the run
    repair: bool | None = None  # views: the planner's decision
    reason: str = ""

    @property
    def name(self) -> str:
        return f"{self.kind} {self.id:03d}"

    @property
    def fov_y(self) -> float:
        return 2.0 * math.atan(0.5 * self.height / float(self.K[1, 1]))

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ViewCamera:
        """A camera as the map server's ``views`` lists it; one-line ViewerError if malformed."""
        try:
            kind = d["kind"]
            if kind not in ("keyframe", "view"):
                raise ViewerError(f"camera kind must be 'keyframe' or 'view', got {kind!r}")
            w, h = int(d["width"]), int(d["height"])
            K = np.asarray(d["K"], dtype=np.float64).reshape(3, 3)
            Intrinsics.from_K(K, w, h)
            T = check_pose(np.asarray(d["T_world_cam"], dtype=np.float64).reshape(4, 4))
            images = {str(k): str(v) for k, v in (d.get("images") or {}).items()}
            return cls(kind, int(d["id"]), K, T, w, h, images, d.get("repair"), d.get("reason", ""))
        except (KeyError, TypeError, ValueError, FrameError) as exc:
            if isinstance(exc, ViewerError):
                raise
            raise ViewerError(f"map server camera {d.get('id', '?')}: {exc!s}") from None


@dataclass(eq=False)
class MapContent:
    gmap: Any | None  # GaussianMap
    mesh: TriMesh | None
    cameras: list[ViewCamera]
    version: int


class MapSource(Protocol):
    """What the viewer needs from a map (a run folder, or a map server)."""

    name: str
    labels_path: Path | None  # where labels are saved by default

    @property
    def can_repair(self) -> bool: ...

    def version(self) -> int: ...

    def load(self) -> MapContent: ...

    def image(self, rel: str) -> npt.NDArray[np.uint8]: ...  # [H, W, 3]

    def repair(
        self,
        T_world_cam: npt.NDArray[np.float64],  # [4, 4]
        K: npt.NDArray[np.float64],  # [3, 3]
        width: int,
        height: int,
        progress: Progress | None,
    ) -> tuple[npt.NDArray[np.uint8], str]: ...  # image [H, W, 3], reason


def decode_png(data: bytes) -> npt.NDArray[np.uint8]:  # [H, W, 3] RGB
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ViewerError(f"not a PNG image ({len(data)} bytes)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class ThreadClients:
    """One MapClient per thread (a MapClient is not thread-safe; the viewer's GUI callbacks run
    on viser's thread pool while the main thread polls the live map)."""

    def __init__(self, address: str, timeout_s: float = 10.0) -> None:
        from gsfix_online.apps.client import MapClient

        self.address = address
        self.timeout_s = timeout_s
        self._local = threading.local()
        self._local.client = MapClient(address, timeout_s)  # checks the address now

    def get(self) -> Any:  # MapClient
        from gsfix_online.apps.client import MapClient

        if getattr(self._local, "client", None) is None:
            self._local.client = MapClient(self.address, self.timeout_s)
        return self._local.client

    def repair(
        self, map_name: str | None, T: Any, K: Any, w: int, h: int, progress: Progress | None
    ) -> tuple[npt.NDArray[np.uint8], str]:
        r = self.get().repair(
            T.reshape(-1).tolist(), K.reshape(-1).tolist(), w, h, map=map_name, progress=progress
        )
        return np.asarray(r.image, np.uint8), str(r.reason)


class RunFolderSource:
    """A finished run folder; repairs need a map server (``server``: its MapClient)."""

    def __init__(
        self, run_dir: str | os.PathLike[str], server: ThreadClients | None = None
    ) -> None:
        from gsfix_online.services.run_folder import RunFolder

        self.run = RunFolder(run_dir)
        self.name = self.run.path.name
        self.labels_path: Path | None = self.run.path / LABELS_FILE
        self.server = server

    @property
    def can_repair(self) -> bool:
        return self.server is not None

    def version(self) -> int:
        return 0  # a finished run does not change

    def load(self) -> MapContent:
        gmap = self.run.splat_model().gmap if self.run.map_dir.is_dir() else None
        mesh = self.run.mesh()  # checked: a damaged mesh is refused in one line
        cams = [  # the repaired views among the map's cameras come as views, below
            ViewCamera("keyframe", k.id, k.K, k.T_world_cam, k.width, k.height)
            for k in self.run.keyframes
            if not k.repaired
        ]
        cams += [
            ViewCamera(
                "view",
                v.view_id,
                v.K,
                v.T_world_cam,
                v.width,
                v.height,
                v.images,
                v.repair,
                v.reason,
            )  # fmt: skip
            for v in self.run.views
        ]
        return MapContent(gmap, mesh, cams, 0)

    def image(self, rel: str) -> npt.NDArray[np.uint8]:
        from gsfix_online.repair.outputs import read_png_rgb

        return read_png_rgb(self.run.resolve(rel))

    def repair(self, T_world_cam, K, width, height, progress=None):  # noqa: ANN001, ANN201
        if self.server is None:
            raise ViewerError(
                "repairs need a map server: start 'gsfix-online serve RUN_DIR' and pass --server"
            )
        return self.server.repair(None, T_world_cam, K, width, height, progress)


class LiveSource:
    """A map held by a running map server (``gsfix-online serve`` or a graph's map server)."""

    def __init__(
        self, clients: ThreadClients, map_name: str | None = None, labels_path: Path | None = None
    ) -> None:
        self.clients = clients
        self.map_name = map_name
        self.name = map_name or "live"
        self.labels_path = labels_path

    @property
    def can_repair(self) -> bool:
        return True

    def _info(self) -> Any:
        maps = self.clients.get().maps()
        if not maps:
            raise ViewerError("the map server holds no map yet")
        if self.map_name is None:
            return maps[0]
        for m in maps:
            if m.name == self.map_name:
                return m
        raise ViewerError(f"the map server has no map {self.map_name!r} ({[m.name for m in maps]})")

    def version(self) -> int:
        return int(self._info().version)

    def load(self) -> MapContent:
        from gsfix_online.mapping.mesh import read_mesh
        from gsfix_online.mapping.splat.ply import read_ply

        info = self._info()
        client = self.clients.get()
        with tempfile.TemporaryDirectory(prefix="gsfix-view-") as tmp:
            splats = Path(tmp) / "splats.ply"
            splats.write_bytes(client.splats(map=self.map_name))
            gmap = read_ply(splats)
            mesh = None
            if info.has_mesh:
                mesh_path = Path(tmp) / "mesh.ply"
                mesh_path.write_bytes(client.mesh(map=self.map_name, fmt="ply"))
                mesh = read_mesh(mesh_path, allow_empty=True)  # a live one may be empty yet
        cams = [ViewCamera.from_json(d) for d in client.views(map=self.map_name)]
        return MapContent(gmap, mesh, cams, int(info.version))

    def image(self, rel: str) -> npt.NDArray[np.uint8]:
        return decode_png(self.clients.get().image(rel, map=self.map_name))

    def repair(self, T_world_cam, K, width, height, progress=None):  # noqa: ANN001, ANN201
        return self.clients.repair(self.map_name, T_world_cam, K, width, height, progress)


# ----------------------------------------------------------------------------------------------
# The viewer
# ----------------------------------------------------------------------------------------------


def map_bounds(content: MapContent) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(lower [3], upper [3]) corners of the map's bounding box, metres: the mesh and the
    Gaussians' centres (1st to 99th percentile: a few stray Gaussians do not stretch it); the
    cameras' positions when the map holds nothing."""
    pts = []
    if content.mesh is not None and not content.mesh.is_empty:
        pts.append(content.mesh.vertices.astype(np.float64))
    if content.gmap is not None and len(content.gmap):
        means = content.gmap.means.detach().cpu().numpy().astype(np.float64)
        pts.append(np.percentile(means, [1, 99], axis=0) if len(means) > 100 else means)
    if not pts:
        pts = [c.T_world_cam[None, :3, 3] for c in content.cameras] or [np.zeros((1, 3))]
    allp = np.concatenate(pts)
    return allp.min(0), allp.max(0)


def map_points(content: MapContent, max_points: int = 20000) -> npt.NDArray[np.float64]:
    """[M, 3] the points the opening view frames: mesh vertices and Gaussian centres inside
    the map's bounding box (map_bounds), at most ``max_points`` of them (evenly strided)."""
    lo, hi = map_bounds(content)
    pts = []
    if content.mesh is not None and not content.mesh.is_empty:
        pts.append(content.mesh.vertices.astype(np.float64))
    if content.gmap is not None and len(content.gmap):
        pts.append(content.gmap.means.detach().cpu().numpy().astype(np.float64))
    if not pts:
        return np.array([lo, hi])
    allp = np.concatenate(pts)
    allp = allp[((allp >= lo) & (allp <= hi)).all(1)]
    return allp[:: max(1, len(allp) // max_points)]


def overview_pose(
    lo: npt.ArrayLike,  # [3] the map's bounding box, metres
    hi: npt.ArrayLike,  # [3]
    cameras: Sequence[npt.NDArray[np.float64]] = (),  # [4, 4] each: camera-to-world, OpenCV axes
    fov_y: float = OVERVIEW_FOV_Y,
    aspect: float = OVERVIEW_ASPECT,
    points: npt.ArrayLike | None = None,  # [M, 3] the map's points to fit; None: the box's corners
) -> npt.NDArray[np.float64]:  # [4, 4] camera-to-world, OpenCV axes
    """A pose outside the map, looking at it, the whole map filling the view.

    Up is the cameras' mean up (-y), else world z. The camera stands on the side the cameras
    look from (against their mean viewing direction, levelled), raised OVERVIEW_ELEVATION, as
    far as the farthest of ``points`` (or of the box's corners) needs to fit in the field of
    view (the canvas assumed ``aspect`` wide), with OVERVIEW_MARGIN to spare; moved sideways
    until their picture is centred (a box seen from above projects its near side larger:
    looking at its centre would leave a band of the view empty)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = 0.5 * (lo + hi)
    up = np.array([0.0, 0.0, 1.0])
    back = np.array([1.0, -1.0, 0.0])  # the side to stand on without cameras
    if len(cameras):
        R = np.stack([np.asarray(T)[:3, :3] for T in cameras])
        mean_up = -R[:, :, 1].mean(0)
        if np.linalg.norm(mean_up) > 1e-6:
            up = mean_up / np.linalg.norm(mean_up)
        back = -R[:, :, 2].mean(0)
    back = back - up * float(back @ up)  # levelled
    if np.linalg.norm(back) < 1e-6:  # cameras looking straight up or down: any side
        back = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    back /= np.linalg.norm(back)
    out = math.cos(OVERVIEW_ELEVATION) * back + math.sin(OVERVIEW_ELEVATION) * up  # unit
    z = -out  # the optical axis, towards the centre
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # down in the image
    pts = (np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                     for c in (lo[2], hi[2])]) if points is None
           else np.asarray(points, np.float64)) - centre  # fmt: skip
    tan_y = math.tan(0.5 * fov_y) / OVERVIEW_MARGIN
    tan_x = tan_y * aspect
    shift = np.zeros(3)  # of the optical axis off the centre, sideways: centres the picture
    for _ in range(OVERVIEW_CENTRING_STEPS):
        rel = pts - shift
        # a point at lateral offsets (px, py) and depth dist - (point . out) fits when
        # |px| <= depth tan_x and |py| <= depth tan_y
        dist = max(float((np.maximum(np.abs(rel @ x) / tan_x, np.abs(rel @ y) / tan_y)
                          + rel @ out).max()), 1e-3)  # fmt: skip
        depth = np.maximum(dist - rel @ out, 1e-9)
        u, v = (rel @ x) / depth, (rel @ y) / depth
        mid_u, mid_v = 0.5 * (u.max() + u.min()), 0.5 * (v.max() + v.min())
        if max(abs(mid_u), abs(mid_v)) < 1e-3:
            break
        shift += 0.5 * dist * (mid_u * x + mid_v * y)  # half a step: a full one oscillates
    rel = pts - shift
    dist = max(float((np.maximum(np.abs(rel @ x) / tan_x, np.abs(rel @ y) / tan_y)
                      + rel @ out).max()), 1e-3)  # fmt: skip
    centre = centre + shift
    return make_T(np.stack([x, y, z], axis=1), centre + dist * out)


class MapViewer:
    """The viewer's scene and GUI on a viser server; the handlers the GUI calls are public, so a
    program (or a test) can drive the same code a click drives."""

    def __init__(
        self,
        server: Any,  # viser.ViserServer
        source: MapSource,
        labels_path: str | os.PathLike[str] | None = None,
        repair_width: int = 320,
    ) -> None:
        self.server = server
        self.source = source
        path = labels_path if labels_path is not None else source.labels_path
        self.labels_path = Path(path) if path is not None else Path(LABELS_FILE)
        self.repair_width = repair_width
        self._lock = threading.RLock()
        self.content: MapContent | None = None
        self.picker = Picker()
        self.points: list[npt.NDArray[np.float64]] = []  # the current measurement's picks
        self.labels: list[Label] = []
        self.selected: ViewCamera | None = None
        self.last_repair: npt.NDArray[np.uint8] | None = None
        self._frustum_scale = 0.1
        self.overview: npt.NDArray[np.float64] | None = None  # [4, 4] the opening view
        # the current measurement's picks: each on a synthesised surface or not
        self.synthesised_points: list[bool] = []
        self._groups: dict[str, Any] = {}  # toggled node name -> its scene handle
        # No shadows: they add render passes (slow in software WebGL) and darken the colours a
        # user compares with the images.
        server.scene.configure_default_lights(True, cast_shadow=False)
        # The panel docked beside the canvas, not over it: the opening view frames the map in
        # the canvas a user sees
        server.gui.main_panel.dock_right()
        self._build_gui()
        self.reload()

    # -- building ----------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.server.gui
        placeholder = np.full((48, 64, 3), 235, np.uint8)
        with gui.add_folder("Layers"):
            self.show_splats = gui.add_checkbox("Gaussian map", True)
            self.show_mesh = gui.add_checkbox("Mesh", True)
            self.show_cameras = gui.add_checkbox("Cameras", False)
            self.show_labels = gui.add_checkbox("Labels", True)
            self.tint_box = gui.add_checkbox("Tint synthesised", False)
            self.tint_box.on_update(lambda _e: self._gui_call(self._draw_splats))
        for box, node in (
            (self.show_splats, "/map/splats"),
            (self.show_mesh, "/map/mesh"),
            (self.show_cameras, "/cameras"),
            (self.show_labels, "/labels"),
        ):
            box.on_update(lambda _e, b=box, n=node: self._set_visible(n, b.value))
        with gui.add_folder("View"):
            self.view_text = gui.add_markdown("Click a camera frustum to see its images.")
            self.before_image = gui.add_image(placeholder, label="before", visible=False)
            self.after_image = gui.add_image(placeholder, label="after", visible=False)
            self.goto_button = gui.add_button("Look through this camera", visible=False)
            self.goto_button.on_click(lambda e: self._goto_selected(e.client))
        with gui.add_folder("Measure"):
            self.measure_box = gui.add_checkbox("Distance tool (click two points)", False)
            self.measure_box.on_update(lambda _e: self._set_measuring(self.measure_box.value))
            self.measure_text = gui.add_markdown("Distance: –")
            self.label_name = gui.add_text("Label name", "")
            self.save_button = gui.add_button("Save label")
            self.save_button.on_click(lambda _e: self._gui_call(self.save_label))
            self.load_button = gui.add_button("Load labels")
            self.load_button.on_click(lambda _e: self._gui_call(self.load_labels))
            self.labels_text = gui.add_markdown(f"Labels file: `{self.labels_path}`")
        with gui.add_folder("Repair"):
            self.repair_button = gui.add_button(
                "Repair current view", disabled=not self.source.can_repair
            )
            self.repair_button.on_click(lambda e: self._gui_call(self.repair_client_view, e.client))
            self.repair_progress = gui.add_progress_bar(0.0, visible=False)
            hint = "" if self.source.can_repair else "Repairs need a map server (`--server`)."
            self.repair_text = gui.add_markdown(hint)
            self.repair_image = gui.add_image(placeholder, label="repaired", visible=False)

    def _set_visible(self, group: str, visible: bool) -> None:
        handle = self._groups.get(group)
        if handle is not None:
            handle.visible = visible

    def _group(self, name: str) -> Any:
        """A frame that parents a toggled group of nodes (hiding it hides them all)."""
        h = self.server.scene.add_frame(name, show_axes=False)
        self._groups[name] = h
        return h

    def _gui_call(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run a GUI action; its one-line error goes to the panel instead of the log only."""
        try:
            fn(*args)
        except (LabelsError, ViewerError, FrameError, OSError, RuntimeError, ValueError) as exc:
            logger.warning("%s", exc)
            self.server.gui.add_notification("Error", str(exc), color="red", auto_close_seconds=8)

    def reload(self) -> None:
        """Read the map from the source and (re)draw it."""
        content = self.source.load()
        with self._lock:
            self.content = content
            self.picker = Picker(content.mesh, content.gmap)
            self._draw_map(content)
        logger.info(
            "map %s v%d: %d Gaussians, mesh %s, %d cameras",
            self.source.name, content.version,
            0 if content.gmap is None else len(content.gmap),
            "none" if content.mesh is None else f"{content.mesh.n_triangles} triangles",
            len(content.cameras),
        )  # fmt: skip

    def refresh(self) -> bool:
        """Reload when the source's version changed (a live map); True if it did."""
        if self.content is not None and self.source.version() == self.content.version:
            return False
        self.reload()
        return True

    def _draw_splats(self) -> None:
        """(Re)draw the Gaussian map, tinting its synthesised part when the toggle says so."""
        gmap = self.content.gmap if self.content is not None else None
        if gmap is None or not len(gmap):
            return
        a = splat_arrays(gmap, tint_synthesised=self.tint_box.value)
        self._groups["/map/splats"] = self.server.scene.add_gaussian_splats(
            "/map/splats", a.centers, a.covariances, a.rgbs, a.opacities,
            visible=self.show_splats.value,
        )  # fmt: skip

    def _draw_map(self, content: MapContent) -> None:
        scene = self.server.scene
        lo, hi = map_bounds(content)
        self._frustum_scale = max(FRUSTUM_SHARE * float(np.linalg.norm(hi - lo)), 1e-3)
        self._draw_splats()
        if content.mesh is not None and not content.mesh.is_empty:
            import trimesh

            m = content.mesh
            tm = trimesh.Trimesh(
                m.vertices, m.triangles, vertex_colors=m.colors, process=False, validate=False
            )
            self._groups["/map/mesh"] = scene.add_mesh_trimesh(
                "/map/mesh", tm, visible=self.show_mesh.value
            )
        self._group("/cameras").visible = self.show_cameras.value
        for cam in content.cameras:
            self._add_frustum(cam)
        T = overview_pose(lo, hi, [c.T_world_cam for c in content.cameras],
                          points=map_points(content))  # fmt: skip
        self.overview = T
        # the scene's up is the overview's (orbiting keeps the floor down; the lights follow)
        scene.set_up_direction(tuple(-T[:3, 1]))
        init = self.server.initial_camera
        init.fov = OVERVIEW_FOV_Y
        init.up = tuple(-T[:3, 1])
        init.position = tuple(T[:3, 3])
        # the orbit centre: the point of the optical axis nearest the map's centre
        eye, z = T[:3, 3], T[:3, 2]
        init.look_at = tuple(eye + z * float((0.5 * (lo + hi) - eye) @ z))

    def _add_frustum(self, cam: ViewCamera) -> None:
        color = (
            KEYFRAME_COLOR
            if cam.kind == "keyframe"
            else REPAIRED_COLOR
            if cam.repair
            else SKIPPED_COLOR
        )
        wxyz, pos = pose_to_wxyz_position(cam.T_world_cam)
        h = self.server.scene.add_camera_frustum(
            f"/cameras/{cam.kind}_{cam.id:03d}",
            fov=cam.fov_y, aspect=cam.width / cam.height, scale=self._frustum_scale,
            thickness=0.05 * self._frustum_scale, color=color, wxyz=wxyz, position=pos,
        )  # fmt: skip
        h.on_click(lambda e, c=cam, handle=h: self._gui_call(self.select_view, c, handle))

    # -- views -------------------------------------------------------------------------------

    def view_images(self, cam: ViewCamera) -> dict[str, npt.NDArray[np.uint8]]:
        """The images shown for a camera: before/after of a view, or the Gaussian map rendered
        at a keyframe's pose (the run folder keeps no keyframe images)."""
        out: dict[str, npt.NDArray[np.uint8]] = {}
        if cam.kind == "view":
            for label, keys in (("before", ("gs",)), ("after", ("output", "fixed", "final"))):
                key = next((k for k in keys if k in cam.images), None)
                if key is not None:
                    out[f"{label} ({key})"] = self.source.image(cam.images[key])
            return out
        gmap = self.content.gmap if self.content is not None else None
        if gmap is not None and len(gmap):
            w = min(KEYFRAME_RENDER_WIDTH, cam.width)
            h = max(1, round(cam.height * w / cam.width))
            K = Intrinsics.from_K(cam.K, cam.width, cam.height).scaled(w, h).K
            out["3DGS render"] = render_splats(gmap, cam.T_world_cam, K, w, h)[0]
        return out

    def select_view(self, cam: ViewCamera, handle: Any | None = None) -> None:
        """Show a camera's images in the panel (and the last one on its frustum)."""
        images = self.view_images(cam)
        self.selected = cam
        note = f" — {'repaired' if cam.repair else 'skipped'}: {cam.reason}" if cam.reason else ""
        self.view_text.content = f"**{cam.name}**{note}"
        slots = [self.before_image, self.after_image]
        for slot, (label, img) in zip(slots, images.items(), strict=False):
            slot.image, slot.label, slot.visible = img, label, True
        for slot in slots[len(images) :]:
            slot.visible = False
        self.goto_button.visible = True
        if handle is not None and images:
            handle.image = list(images.values())[-1]

    def _goto_selected(self, client: Any) -> None:
        if self.selected is not None and client is not None:
            set_client_pose(client, self.selected.T_world_cam, self.selected.fov_y)

    # -- measuring ---------------------------------------------------------------------------

    def _set_measuring(self, on: bool) -> None:
        scene = self.server.scene
        if on:
            scene.on_click()(self._on_scene_click)
        else:
            scene.remove_click_callback(self._on_scene_click)

    def _on_scene_click(self, event: Any) -> None:
        self.on_ray(event.ray_origin, event.ray_direction)

    def on_ray(self, origin: Sequence[float], direction: Sequence[float]) -> Pick | None:
        """A click of the distance tool: pick the point under the ray; the second pick of a
        measurement shows the distance, a third starts a new one."""
        pick = self.picker.pick(origin, direction)
        scene = self.server.scene
        with self._lock:
            if pick is None:
                self.measure_text.content = "Nothing under the click (no mesh or splats there)."
                return None
            if len(self.points) == 2:
                self.points, self.synthesised_points = [], []
                scene.remove_by_name("/measure")
            self.points.append(pick.point)
            self.synthesised_points.append(pick.on_synthesised)
            r = 0.15 * self._frustum_scale
            scene.add_icosphere(
                f"/measure/p{len(self.points)}", radius=r, color=MEASURE_COLOR,
                position=tuple(pick.point),
            )  # fmt: skip
            d = self.distance_m
            if d is None:
                p = pick.point
                self.measure_text.content = (
                    f"First point ({pick.source}): {p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f} m"
                )
            else:
                self._draw_measurement("/measure", self.points[0], self.points[1], f"{d:.3f} m")
                self.measure_text.content = f"Distance: **{d:.4f} m**"
            if self.synthesis_warning:
                self.measure_text.content += f"\n\n**Warning:** {self.synthesis_warning}"
        return pick

    @property
    def synthesis_warning(self) -> str:
        """What the measurement's reader must know: which of its points lie on a synthesised
        surface (grown from repaired views, seen by no input frame); "" when none does."""
        which = [i for i, s in enumerate(self.synthesised_points, start=1) if s]
        if not which:
            return ""
        points = " and ".join(f"point {i}" for i in which)
        verb = "lie" if len(which) > 1 else "lies"
        return (f"{points} {verb} on a synthesised surface (repaired, not observed): the "
                "distance is not a measurement of what the robot saw")  # fmt: skip

    @property
    def distance_m(self) -> float | None:
        """The current measurement in metres, once two points are picked."""
        if len(self.points) != 2:
            return None
        return float(np.linalg.norm(self.points[1] - self.points[0]))

    def _draw_measurement(self, name: str, a: Any, b: Any, text: str) -> None:
        scene = self.server.scene
        seg = np.array([[a, b]], np.float32)
        scene.add_line_segments(
            f"{name}/line", seg, MEASURE_COLOR, thickness=3.0, thickness_units="screen"
        )
        scene.add_label(f"{name}/text", text, position=tuple(0.5 * (np.asarray(a) + b)))

    def save_label(self, name: str | None = None) -> Label:
        """Name the current measurement and save every label to the labels file."""
        with self._lock:
            if len(self.points) != 2:
                raise LabelsError("measure two points before saving a label")
            label = Label.make(self.label_name.value if name is None else name, *self.points,
                               self.synthesised_points)  # fmt: skip
            self.labels.append(label)
            save_labels(self.labels_path, self.labels)
            self._draw_labels()
        return label

    def load_labels(self) -> list[Label]:
        """Replace the labels by those in the labels file and draw them."""
        labels = load_labels(self.labels_path)
        with self._lock:
            self.labels = labels
            self._draw_labels()
        return labels

    def _draw_labels(self) -> None:
        self.server.scene.remove_by_name("/labels")
        self._group("/labels").visible = self.show_labels.value
        for i, lab in enumerate(self.labels):
            text = f"{lab.name}: {lab.distance_m:.3f} m{' (synthesised)' * any(lab.synthesised)}"
            self._draw_measurement(f"/labels/{i:03d}", lab.a, lab.b, text)
        lines = [f"- {lab.name}: {lab.distance_m:.4f} m" + _synthesised_note(lab)
                 for lab in self.labels]  # fmt: skip
        self.labels_text.content = "\n".join([f"Labels file: `{self.labels_path}`", *lines])

    # -- repair ------------------------------------------------------------------------------

    def client_camera(
        self, client: Any
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], int, int]:
        """(T_world_cam [4, 4], K [3, 3], width, height) of a browser's current view, at
        ``repair_width`` pixels wide with the canvas's aspect."""
        cam = client.camera
        aspect = cam.aspect if cam.aspect > 0 else 4 / 3
        w = self.repair_width
        h = max(8, round(w / aspect))
        return wxyz_position_to_pose(cam.wxyz, cam.position), fov_intrinsics(cam.fov, w, h), w, h

    def repair_client_view(self, client: Any) -> npt.NDArray[np.uint8]:
        return self.repair_view(*self.client_camera(client))

    def repair_view(
        self,
        T_world_cam: npt.ArrayLike,  # [4, 4]
        K: npt.ArrayLike,  # [3, 3]
        width: int,
        height: int,
    ) -> npt.NDArray[np.uint8]:  # [H, W, 3]
        """Ask the source's map server to repair a view; show progress, then the result."""
        T = check_pose(T_world_cam)
        Kf = Intrinsics.from_K(K, width, height).K

        def progress(fraction: float, text: str) -> None:
            self.repair_progress.value = float(np.clip(100.0 * fraction, 0.0, 100.0))
            self.repair_text.content = text

        self.repair_progress.visible, self.repair_progress.value = True, 0.0
        self.repair_text.content = "Asking the map server to repair the view…"
        try:
            image, reason = self.source.repair(T, Kf, width, height, progress)
        except Exception as exc:
            self.repair_text.content = f"Repair failed: {exc}"
            raise
        finally:
            self.repair_progress.visible = False
        self.last_repair = image
        self.repair_image.image, self.repair_image.visible = image, True
        self.repair_text.content = f"Repaired ({reason})" if reason else "Repaired"
        wxyz, pos = pose_to_wxyz_position(T)
        self.server.scene.add_camera_frustum(
            "/cameras/repaired", fov=2 * math.atan(0.5 * height / Kf[1, 1]),
            aspect=width / height, scale=self._frustum_scale, color=RESULT_COLOR, image=image,
            wxyz=wxyz, position=pos,
        )  # fmt: skip
        return image


def _synthesised_note(label: Label) -> str:
    """`` — point 2 on a synthesised surface`` for a label that has such points, else ""."""
    which = [f"point {i}" for i, s in enumerate(label.synthesised, start=1) if s]
    return f" — {' and '.join(which)} on a synthesised surface" if which else ""


def set_client_pose(client: Any, T_world_cam: npt.ArrayLike, fov_y: float | None = None) -> None:
    """Move a browser's camera to a pose (OpenCV axes), looking along its z axis."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    if fov_y is not None:
        client.camera.fov = fov_y
    client.camera.up_direction = tuple(-T[:3, 1])
    client.camera.position = tuple(T[:3, 3])
    client.camera.look_at = tuple(T[:3, 3] + T[:3, 2])


# ----------------------------------------------------------------------------------------------
# Process
# ----------------------------------------------------------------------------------------------


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (another process may still take it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def start_viewer(
    source: MapSource,
    host: str = "127.0.0.1",
    port: int = 8080,  # 0: a free port
    labels_path: str | os.PathLike[str] | None = None,
    repair_width: int = 320,
) -> MapViewer:
    """Start a viser server on ``host:port`` showing ``source``; returns at once."""
    viser = _require_viser()
    if not isinstance(port, int) or not 0 <= port <= 65535:
        raise ViewerError(f"port must be an int in 0..65535, got {port!r}")
    if not 16 <= repair_width <= 4096:
        raise ViewerError(f"repair width must be 16..4096 px, got {repair_width}")
    server = viser.ViserServer(host=host, port=port or free_port(host), verbose=False)
    try:
        viewer = MapViewer(server, source, labels_path, repair_width)
    except BaseException:
        server.stop()
        raise
    logger.info("viewer of %s at http://%s:%d", source.name, host, server.get_port())
    return viewer


def run_viewer(
    source: MapSource,
    host: str = "127.0.0.1",
    port: int = 8080,
    labels_path: str | os.PathLike[str] | None = None,
    poll_s: float = 2.0,  # a live map is checked for a new version this often
    stop: threading.Event | None = None,
) -> None:
    """Serve the viewer until ``stop`` is set or the process is interrupted."""
    import signal

    viewer = start_viewer(source, host, port, labels_path)
    stop = stop or threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():  # SIGTERM stops as Ctrl+C does
        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print(f"viewer: http://{host}:{viewer.server.get_port()}  (Ctrl+C to stop)", flush=True)
    try:
        while not stop.wait(poll_s):
            if isinstance(source, LiveSource):
                try:
                    viewer.refresh()
                except (ViewerError, OSError, RuntimeError, ValueError) as exc:
                    logger.warning("live map: %s", exc)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        viewer.server.stop()


def live_address(value: str) -> str:
    """The map server's address from ``--live``: an address as given, or the address of the
    ``map_server`` node of a graph YAML (its params' host and port)."""
    if "://" in value:
        return value
    path = Path(value)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise ViewerError(
            f"--live takes a map server's address (tcp://HOST:PORT) or a graph YAML, got {value!r}"
        )
    from gsfix_online.runtime.graph import load_graph, node_params

    graph = load_graph(path)
    servers = [(n, e) for n, e in graph.nodes.items() if e.kind == "map_server"]
    if len(servers) != 1:
        raise ViewerError(f"{path}: needs one map_server node to attach to, has {len(servers)}")
    name, entry = servers[0]
    params = node_params(entry, where=f"{path}: nodes.{name}.params")
    host = graph.hosts[entry.machine] if params.host in ("0.0.0.0", "*") else params.host
    return f"tcp://{host}:{params.port}"


def cli_main(args: Any) -> int:
    """``gsfix-online view``: parse-level checks, the source, then serve until Ctrl+C."""
    import sys

    from gsfix_online.apps.client import MapClientError
    from gsfix_online.core.config import ConfigError
    from gsfix_online.services.run_folder import RunFolderError

    try:
        if (args.run is None) == (args.live is None):
            raise ViewerError("give a run folder or --live ADDRESS (one of them)")
        source: MapSource
        if args.live is not None:
            if args.server is not None:
                raise ViewerError("--server is for a run folder; --live repairs through ADDRESS")
            labels = args.labels if args.labels is not None else Path(LABELS_FILE)
            source = LiveSource(ThreadClients(live_address(args.live)), args.map, labels)
        else:
            if args.map is not None:
                raise ViewerError("--map names a map of --live ADDRESS")
            server = ThreadClients(args.server) if args.server is not None else None
            source = RunFolderSource(args.run, server)
        run_viewer(source, args.host, args.port, args.labels)
    except (ViewerError, RunFolderError, LabelsError, MapClientError, ConfigError, OSError) as exc:
        print(f"gsfix-online view: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0
