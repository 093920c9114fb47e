"""The viewer's geometry (rays, picks, distances, labels, splat conversion) and its handlers on a
real viser server over a tiny run folder made here. The browser drives the same handlers in
test_browser.py."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from gsfix_online.apps.measure import (
    Label,
    LabelsError,
    Picker,
    distance_m,
    labels_from_json,
    labels_to_json,
    load_labels,
    pixel_ray,
    ray_camera,
    save_labels,
)
from gsfix_online.apps.viewer import (
    FRUSTUM_SHARE,
    OVERVIEW_MARGIN,
    SYNTHESISED_TINT,
    TINT_SHARE,
    RunFolderSource,
    ViewerError,
    fov_intrinsics,
    map_bounds,
    overview_pose,
    pose_to_wxyz_position,
    splat_arrays,
    start_viewer,
    wxyz_position_to_pose,
)
from gsfix_online.core.se3 import look_at
from gsfix_online.core.types import Intrinsics
from gsfix_online.mapping.mesh import TriMesh, write_mesh
from gsfix_online.mapping.splat.gaussians import ORIGIN_REPAIRED, GaussianMap, rgb_to_sh0
from gsfix_online.mapping.splat.ply import CameraEntry, camera_name, save_model
from gsfix_online.repair.outputs import RepairOutputs

# The test scene: a teal square wall at z = PLANE_Z (2 m x 2 m), a red patch of splats 0.2 m in
# front of it, cameras at z = 0 looking along +z. Points on the wall are picked on the mesh.
PLANE_Z = 2.0
SPLAT_Z = 1.8
WALL_RGB = (0, 160, 160)  # teal: no GUI element or frustum has its hue
SPLAT_RGB = (230, 20, 20)
REPAIRED_X_M = 0.05  # the patch's Gaussians right of this grew from a repaired view
POINT_A = np.array([-0.5, 0.4, PLANE_Z])
POINT_B = np.array([0.5, -0.3, PLANE_Z])
KNOWN_DISTANCE_M = math.sqrt(1.0**2 + 0.7**2)
W, H = 64, 48
K_VIEW = Intrinsics(60.0, 60.0, (W - 1) / 2, (H - 1) / 2, W, H)
TOL_M = 1e-6  # float32 ray casting on a plane 2 m away (measured worst 2.4e-7 m)


def wall_mesh(n: int = 8) -> TriMesh:
    """A flat n x n grid over x, y in [-1, 1] at z = PLANE_Z, facing -z (towards the cameras)."""
    xs = np.linspace(-1.0, 1.0, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, PLANE_Z)], 1).astype(np.float32)
    tris = []
    for r in range(n):
        for c in range(n):
            i = r * (n + 1) + c
            tris += [[i, i + n + 1, i + 1], [i + 1, i + n + 1, i + n + 2]]
    colors = np.tile(np.array(WALL_RGB, np.uint8), (len(v), 1))
    return TriMesh(v, np.asarray(tris, np.int32), colors)


def splat_patch(n: int = 7, half: float = 0.3, sigma: float = 0.04) -> GaussianMap:
    """n x n opaque red Gaussians on a square patch at z = SPLAT_Z; those right of
    x = REPAIRED_X_M grew from a repaired view."""
    xs = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(xs, xs)
    means = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, SPLAT_Z)], 1)
    m = len(means)
    rgb = torch.tensor(np.array(SPLAT_RGB) / 255.0, dtype=torch.float32).expand(m, 3)
    gmap = GaussianMap.from_tensors(
        torch.tensor(means, dtype=torch.float32),
        torch.full((m, 3), math.log(sigma)),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(m, 4),
        torch.full((m,), 6.0),  # opacity 0.9975
        rgb_to_sh0(rgb)[:, None, :],
    )
    gmap.origin[torch.from_numpy(means[:, 0] > REPAIRED_X_M)] = ORIGIN_REPAIRED
    return gmap


def make_run_folder(root: Path, with_mesh: bool = True) -> Path:
    """A finished run folder: map/ (splats + 2 keyframes, and view 0 as the repaired camera
    distillation adds), mesh.ply, two views (one repaired, one skipped) with their images,
    metrics.json and report.html."""
    cams = [
        CameraEntry.from_pose(
            i, f"{i:06d}.png", K_VIEW, look_at([x, 0.0, 0.0], [x, 0.0, 2.0], (0, -1, 0))
        )
        for i, x in enumerate((-0.2, 0.2))
    ]
    view0 = look_at([0.0, 0.1, 0.0], [0.0, 0.0, 2.0], (0, -1, 0))
    cams.append(CameraEntry.from_pose(2, camera_name(2, True), K_VIEW, view0))
    save_model(root / "map", splat_patch(), 100, cams)
    if with_mesh:
        write_mesh(wall_mesh(), root / "mesh.ply")
    out = RepairOutputs(root)
    rng = np.random.default_rng(0)
    for vid, repair in ((0, True), (1, False)):
        T = look_at([0.1 * vid, 0.1, 0.0], [0.0, 0.0, 2.0], (0, -1, 0))
        camera = {"K": K_VIEW.K.ravel().tolist(), "T_world_cam": T.ravel().tolist(),
                  "width": W, "height": H}  # fmt: skip
        out.on_decision(vid, repair, "holes 30%" if repair else "complete", {}, camera)
        gs = np.zeros((H, W, 3), np.uint8)
        gs[:, : W // 2] = SPLAT_RGB
        out.on_renders(vid, gs=gs, mesh=np.full((H, W, 3), WALL_RGB, np.uint8))
        if repair:
            out.on_fixed(vid, rng.integers(0, 256, (H, W, 3), dtype=np.uint8), {}, {})
        out.on_final(vid, gs)
    m = out.write(extra={"files": {"map": "map", "mesh": "mesh.ply"}})
    assert m["views"][0]["files"]["output"] == "views/000/output.png"
    return root


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run_folder(tmp_path_factory.mktemp("run"))


@pytest.fixture
def viewer(run_dir, tmp_path):
    v = start_viewer(RunFolderSource(run_dir), port=0, labels_path=tmp_path / "labels.json")
    yield v
    v.server.stop()


# -- rays and picks -------------------------------------------------------------------------------


def test_pixel_ray_through_principal_point_is_the_optical_axis():
    T = look_at([1.0, 2.0, 3.0], [1.0, 2.0, 5.0], (0, -1, 0))
    o, d = pixel_ray(T, K_VIEW.K, K_VIEW.cx, K_VIEW.cy)
    np.testing.assert_allclose(o, [1, 2, 3])
    np.testing.assert_allclose(d, [0, 0, 1], atol=1e-12)
    _, d2 = pixel_ray(T, K_VIEW.K, K_VIEW.cx + K_VIEW.fx, K_VIEW.cy)  # 45 degrees to the right
    np.testing.assert_allclose(d2, T[:3, 0] / math.sqrt(2) + T[:3, 2] / math.sqrt(2), atol=1e-12)


def test_ray_camera_looks_along_the_ray():
    d = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    T = ray_camera(np.array([1.0, 2.0, 3.0]), d)
    np.testing.assert_allclose(T[:3, 2], d, atol=1e-12)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) > 0


@pytest.mark.parametrize("target", [POINT_A, POINT_B, np.array([0.9, 0.9, PLANE_Z])])
def test_mesh_pick_hits_the_wall_at_the_known_point(target):
    eye = np.array([0.1, -0.2, 0.0])
    pick = Picker(wall_mesh()).pick(eye, target - eye)
    assert pick is not None and pick.source == "mesh"
    np.testing.assert_allclose(pick.point, target, atol=TOL_M)
    assert pick.range_m == pytest.approx(np.linalg.norm(target - eye), abs=TOL_M)


def test_mesh_pick_misses_outside_the_wall_and_rejects_bad_rays():
    picker = Picker(wall_mesh())
    assert picker.pick([0, 0, 0], [0, 0, -1]) is None  # away from the wall
    assert picker.pick([0, 0, 0], [2.0, 0, 1]) is None  # past its edge
    with pytest.raises(ValueError, match="ray direction must be non-zero"):
        picker.pick([0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="ray must be finite"):
        picker.pick([0, np.nan, 0], [0, 0, 1])


def test_splat_pick_without_a_mesh_reads_the_splats_depth():
    picker = Picker(None, splat_patch())
    pick = picker.pick([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    assert pick is not None and pick.source == "splats"
    # Opaque splats at z = 1.8: the expected depth is theirs to within their own spread.
    np.testing.assert_allclose(pick.point, [0.0, 0.0, SPLAT_Z], atol=2e-3)
    assert picker.pick([0.0, 0.0, 0.0], [1.0, 0.0, 0.5]) is None  # empty space


def test_distance_between_known_points():
    assert distance_m(POINT_A, POINT_B) == pytest.approx(KNOWN_DISTANCE_M, abs=1e-12)
    assert distance_m([0, 0, 0], [0, 3, 4]) == 5.0


# -- labels ---------------------------------------------------------------------------------------


def test_labels_round_trip_through_the_file(tmp_path):
    labels = [
        Label.make("wall width", POINT_A, POINT_B),
        Label.make(" frame 12 ", [0, 0, 0], [0, 0, 1], [False, True]),
    ]
    path = save_labels(tmp_path / "labels.json", labels)
    back = load_labels(path)
    assert back == [labels[0], Label("frame 12", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (False, True))]
    doc = json.loads(path.read_text())
    assert doc["version"] == 1 and doc["labels"][0]["distance_m"] == round(KNOWN_DISTANCE_M, 6)
    assert doc["labels"][1]["synthesised"] == [False, True]
    # a file from before: no synthesised points
    del doc["labels"][1]["synthesised"]
    assert labels_from_json(json.dumps(doc))[1].synthesised == (False, False)
    assert not list(tmp_path.glob("*.tmp*"))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{", "not valid JSON"),
        ('{"labels": []}', "version must be 1"),
        ('{"version": 1, "labels": [{"name": "x", "a": [0, 0, 0]}]}', "label 0 must have name, a and b"),
        ('{"version": 1, "labels": [{"name": "", "a": [0,0,0], "b": [1,0,0]}]}', "non-empty"),
        ('{"version": 1, "labels": [{"name": "x", "a": [0,0], "b": [1,0,0]}]}', "a must be 3 finite"),
        ('{"version": 1, "labels": [{"name": "x", "a": [0,0,0], "b": ["q",0,0]}]}', "b must be 3 finite"),
        ('{"version": 1, "labels": [{"name": "x", "a": [0,0,0], "b": [1,0,0], "distance_m": 2}]}',
         "disagrees with its points"),
        ('{"version": 1, "labels": [{"name": "x", "a": [0,0,0], "b": [1,0,0], "synthesised": [1]}]}',
         "synthesised must be two true/false values, got \\[1\\]"),
    ],
)  # fmt: skip
def test_bad_labels_files_name_the_problem(text, message):
    with pytest.raises(LabelsError, match=message) as exc:
        labels_from_json(text, "x/labels.json")
    assert str(exc.value).startswith("x/labels.json") and "\n" not in str(exc.value)


def test_labels_json_is_what_load_reads():
    labels = [Label.make("a", [0, 0, 0], [1, 2, 2])]
    assert labels_from_json(labels_to_json(labels)) == labels


# -- conversions ----------------------------------------------------------------------------------


def test_splat_arrays_give_rotated_covariances_colours_and_opacities():
    q = np.array([math.cos(math.pi / 8), 0.0, 0.0, math.sin(math.pi / 8)])  # 45 deg about z
    sigma = np.array([0.2, 0.05, 0.1])
    g = GaussianMap.from_tensors(
        torch.tensor([[1.0, 2.0, 3.0]]),
        torch.tensor(np.log(sigma)[None], dtype=torch.float32),
        torch.tensor(2.0 * q[None], dtype=torch.float32),  # any norm
        torch.tensor([0.0]),
        rgb_to_sh0(torch.tensor([[[0.25, 0.5, 1.5]]])),
    )
    a = splat_arrays(g)
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(a.covariances[0], R @ np.diag(sigma**2) @ R.T, atol=1e-7)
    np.testing.assert_allclose(a.centers, [[1, 2, 3]])
    np.testing.assert_allclose(a.rgbs, [[0.25, 0.5, 1.0]], atol=1e-6)  # clamped to [0, 1]
    np.testing.assert_allclose(a.opacities, [[0.5]])
    assert a.covariances.dtype == np.float32 and a.opacities.shape == (1, 1)


def test_gray_splats_are_shown_grey():
    g = GaussianMap.from_tensors(
        torch.zeros((2, 3)), torch.zeros((2, 3)), torch.tensor([[1.0, 0, 0, 0]] * 2),
        torch.zeros(2), rgb_to_sh0(torch.tensor([[[0.3]], [[0.7]]])),
    )  # fmt: skip
    np.testing.assert_allclose(splat_arrays(g).rgbs, [[0.3] * 3, [0.7] * 3], atol=1e-6)


def test_tinted_splats_mark_only_the_synthesised_gaussians():
    g = splat_patch()
    plain, tinted = splat_arrays(g).rgbs, splat_arrays(g, tint_synthesised=True).rgbs
    synth = g.repaired().numpy()
    assert 0 < synth.sum() < len(g)
    np.testing.assert_array_equal(tinted[~synth], plain[~synth])
    want = TINT_SHARE * np.asarray(SYNTHESISED_TINT) / 255.0 + (1 - TINT_SHARE) * plain[synth]
    np.testing.assert_allclose(tinted[synth], want, atol=1e-6)


@pytest.mark.parametrize("aspect", [4 / 3, 0.75])
def test_overview_looks_at_the_centre_from_outside_with_the_box_filling_the_view(aspect):
    lo, hi = np.array([-2.0, -1.0, 0.0]), np.array([4.0, 1.0, 3.0])
    cams = [look_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0], (0, 0, 1))]  # looking along +x, z up
    fov = math.radians(60.0)
    T = overview_pose(lo, hi, cams, fov, aspect)
    centre = 0.5 * (lo + hi)
    eye, z = T[:3, 3], T[:3, 2]
    assert not ((eye >= lo) & (eye <= hi)).all()  # outside the box
    assert eye[0] < centre[0] and eye[2] > centre[2]  # behind the cameras' view, raised
    assert T[:3, 1] @ np.array([0.0, 0.0, 1.0]) < 0  # image up is world up
    # the optical axis passes through the box near its centre (moved sideways to centre the
    # picture of a box seen from above)
    nearest = eye + ((centre - eye) @ z) * z
    assert ((nearest >= lo) & (nearest <= hi)).all()
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                        for c in (lo[2], hi[2])])  # fmt: skip
    cam = (np.linalg.inv(T) @ np.c_[corners, np.ones(8)].T)[:3].T  # [8, 3]
    assert (cam[:, 2] > 0).all()
    u = cam[:, 0] / cam[:, 2] / (math.tan(fov / 2) * aspect)  # +-1 = the view's edges
    v = cam[:, 1] / cam[:, 2] / math.tan(fov / 2)
    edge = max(np.abs(u).max(), np.abs(v).max())
    assert edge == pytest.approx(1 / OVERVIEW_MARGIN, abs=0.01)  # fills it, all inside
    assert abs(u.max() + u.min()) < 0.02 and abs(v.max() + v.min()) < 0.02  # centred


def test_pose_and_viser_camera_round_trip():
    T = look_at([0.5, -1.0, 2.0], [0.0, 0.3, 4.0], (0, -1, 0))
    wxyz, pos = pose_to_wxyz_position(T)
    np.testing.assert_allclose(wxyz_position_to_pose(wxyz, pos), T, atol=1e-12)


def test_fov_intrinsics():
    K = fov_intrinsics(math.pi / 2, 640, 480)
    assert K[1, 1] == pytest.approx(240.0) and K[0, 0] == K[1, 1]
    assert (K[0, 2], K[1, 2]) == (319.5, 239.5)
    with pytest.raises(ViewerError, match="0 < fov_y < pi"):
        fov_intrinsics(0.0, 640, 480)


# -- the viewer's handlers on a real server -------------------------------------------------------


def test_viewer_loads_the_run_folder(viewer):
    c = viewer.content
    assert len(c.gmap) == 49 and c.mesh.n_triangles == 128
    # the map's repaired camera (2) is view 0: not shown again as a keyframe
    assert [(x.kind, x.id) for x in c.cameras] == [
        ("keyframe", 0), ("keyframe", 1), ("view", 0), ("view", 1)
    ]  # fmt: skip
    assert viewer.server.get_port() > 0 and viewer.picker.has_mesh


def test_viewer_opens_on_the_overview_with_cameras_hidden_and_frusta_sized_to_the_map(viewer):
    lo, hi = map_bounds(viewer.content)
    np.testing.assert_allclose(lo, [-1.0, -1.0, SPLAT_Z], atol=1e-6)  # the wall and the patch
    np.testing.assert_allclose(hi, [1.0, 1.0, PLANE_Z], atol=1e-6)
    init = viewer.server.initial_camera
    np.testing.assert_allclose(init.position, viewer.overview[:3, 3], atol=1e-6)
    eye, z = viewer.overview[:3, 3], viewer.overview[:3, 2]
    np.testing.assert_allclose(init.look_at, eye + z * ((0.5 * (lo + hi) - eye) @ z), atol=1e-6)
    assert init.position[2] < SPLAT_Z  # on the cameras' side of the wall
    assert not viewer.show_cameras.value and not viewer._groups["/cameras"].visible
    assert viewer._frustum_scale == pytest.approx(FRUSTUM_SHARE * np.linalg.norm(hi - lo))


def test_distance_tool_measures_known_points_by_pixel_rays(viewer):
    """Two clicks: the rays through the pixels where A and B project in a view camera."""
    T = look_at([0.0, 0.0, 0.0], [0.0, 0.0, PLANE_Z], (0, -1, 0))
    for p in (POINT_A, POINT_B):
        uv = K_VIEW.K @ (np.linalg.inv(T) @ np.append(p, 1.0))[:3]
        pick = viewer.on_ray(*pixel_ray(T, K_VIEW.K, uv[0] / uv[2], uv[1] / uv[2]))
        np.testing.assert_allclose(pick.point, p, atol=TOL_M)
    assert viewer.distance_m == pytest.approx(KNOWN_DISTANCE_M, abs=1e-3)
    assert "1.2207 m" in viewer.measure_text.content
    # a third click starts a new measurement
    viewer.on_ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    assert len(viewer.points) == 1 and viewer.distance_m is None
    assert viewer.on_ray([0.0, 0.0, 0.0], [0.0, 0.0, -1.0]) is None  # nothing there
    assert len(viewer.points) == 1


def test_viewer_saves_and_loads_labels(viewer):
    with pytest.raises(LabelsError, match="measure two points"):
        viewer.save_label("too early")
    viewer.on_ray([0, 0, 0], POINT_A)
    viewer.on_ray([0, 0, 0], POINT_B)
    label = viewer.save_label("wall span")
    assert label.distance_m == pytest.approx(KNOWN_DISTANCE_M, abs=1e-6)
    assert load_labels(viewer.labels_path) == [label]
    viewer.labels = []
    assert viewer.load_labels() == [label] and viewer.labels == [label]
    assert "wall span: 1.2207 m" in viewer.labels_text.content


def test_clicked_views_show_before_and_after(viewer, run_dir):
    view0 = next(c for c in viewer.content.cameras if c.kind == "view" and c.id == 0)
    images = viewer.view_images(view0)
    assert list(images) == ["before (gs)", "after (output)"]
    np.testing.assert_array_equal(images["before (gs)"][0, 0], SPLAT_RGB)
    viewer.select_view(view0)
    assert viewer.before_image.visible and viewer.after_image.visible
    assert "repaired: holes 30%" in viewer.view_text.content
    view1 = next(c for c in viewer.content.cameras if c.kind == "view" and c.id == 1)
    assert list(viewer.view_images(view1)) == ["before (gs)", "after (final)"]  # skipped


def test_clicked_keyframe_shows_a_render_of_the_map(viewer):
    kf = viewer.content.cameras[0]
    img = viewer.view_images(kf)["3DGS render"]
    assert img.shape == (H, W, 3)
    centre = img[H // 2, W // 2].astype(int)
    assert centre[0] > 150 and centre[1] < 60 and centre[2] < 60  # the red splats


def test_repair_without_a_map_server_says_how_to_get_one(viewer):
    assert viewer.repair_button.disabled
    with pytest.raises(ViewerError, match="repairs need a map server"):
        viewer.repair_view(np.eye(4), K_VIEW.K, W, H)


def test_without_a_mesh_clicks_pick_on_the_splats(tmp_path):
    run = make_run_folder(tmp_path / "run", with_mesh=False)
    v = start_viewer(RunFolderSource(run), port=0)
    try:
        assert not v.picker.has_mesh and v.labels_path == run / "labels.json"
        pick = v.on_ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
        assert pick.source == "splats" and pick.point[2] == pytest.approx(SPLAT_Z, abs=2e-3)
    finally:
        v.server.stop()


def test_distance_tool_warns_when_a_point_lies_on_a_synthesised_surface(tmp_path):
    """Without a mesh, clicks pick on the splats: the patch's left part was observed, its right
    part grew from a repaired view; a measurement that ends there says so."""
    run = make_run_folder(tmp_path / "run", with_mesh=False)
    v = start_viewer(RunFolderSource(run), port=0)
    try:
        observed = v.on_ray([0.0, 0.0, 0.0], [-0.2, 0.0, SPLAT_Z])
        assert observed.synthesised == pytest.approx(0.0, abs=1e-6)
        assert not observed.on_synthesised and v.synthesis_warning == ""
        assert "Warning" not in v.measure_text.content
        repaired = v.on_ray([0.0, 0.0, 0.0], [0.2, 0.1, SPLAT_Z])
        assert repaired.synthesised > 0.9 and repaired.on_synthesised
        assert v.synthesised_points == [False, True]
        assert v.synthesis_warning.startswith("point 2 lies on a synthesised surface")
        assert "**Warning:** point 2 lies on a synthesised surface" in v.measure_text.content
        # a new measurement starts clean; both points synthesised are both named
        v.on_ray([0.0, 0.0, 0.0], [0.3, 0.0, SPLAT_Z])
        assert v.synthesised_points == [True] and "point 1 lies" in v.measure_text.content
        v.on_ray([0.0, 0.0, 0.0], [0.1, -0.2, SPLAT_Z])
        assert v.synthesis_warning.startswith("point 1 and point 2 lie on a synthesised")
        # a saved label keeps it, and the labels list says it
        label = v.save_label("patch span")
        assert label.synthesised == (True, True)
        assert load_labels(run / "labels.json")[0].synthesised == (True, True)
        assert "— point 1 and point 2 on a synthesised surface" in v.labels_text.content
    finally:
        v.server.stop()


def test_a_mesh_point_away_from_any_gaussian_is_not_called_synthesised(viewer):
    pick = viewer.on_ray([0.0, 0.0, 0.0], POINT_B)  # on the wall, 0.2 m behind no Gaussian
    assert pick.source == "mesh" and pick.synthesised is None and not pick.on_synthesised


def test_start_viewer_rejects_bad_ports(run_dir):
    with pytest.raises(ViewerError, match="port must be an int in 0..65535"):
        start_viewer(RunFolderSource(run_dir), port=70000)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["view"], "give a run folder or --live ADDRESS"),
        (["view", "RUN", "--live", "tcp://127.0.0.1:5590"], "give a run folder or --live"),
        (["view", "RUN", "--map", "m"], "--map names a map of --live ADDRESS"),
        (["view", "--live", "tcp://127.0.0.1:5590", "--server", "tcp://x:1"], "--server is for"),
        (["view", "--live", "localhost:5590"], "--live takes a map server's address"),
        (["view", "NO_SUCH_RUN_DIR"], "NO_SUCH_RUN_DIR: no such folder"),
    ],
)
def test_view_command_names_what_is_wrong(argv, message, capsys):
    from gsfix_online.apps.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("gsfix-online view: error: ") and message in err and "\n" not in err


def test_live_takes_an_address_or_the_map_server_of_a_graph(tmp_path):
    from gsfix_online.apps.viewer import live_address

    assert live_address("tcp://10.0.0.2:5591") == "tcp://10.0.0.2:5591"
    graph = tmp_path / "g.yaml"
    graph.write_text(
        "name: g\nhosts: {local: 127.0.0.1, robot: 10.0.0.7}\nnodes:\n  maps:\n"
        "    kind: map_server\n    machine: robot\n    params: {host: 0.0.0.0, port: 5599}\n"
    )
    assert live_address(str(graph)) == "tcp://10.0.0.7:5599"  # all interfaces: the machine's
    graph.write_text("name: g\nnodes: {}\n")
    with pytest.raises(ViewerError, match="needs one map_server node to attach to, has 0"):
        live_address(str(graph))
    with pytest.raises(ViewerError, match="--live takes a map server's address"):
        live_address("localhost:5590")


def test_run_viewer_serves_until_stopped(run_dir, tmp_path):
    import threading
    import urllib.request

    from gsfix_online.apps.viewer import free_port, run_viewer

    port, stop, errors = free_port(), threading.Event(), []

    def serve():
        try:
            run_viewer(RunFolderSource(run_dir), port=port, poll_s=0.05, stop=stop)
        except Exception as exc:  # reported below
            errors.append(exc)

    t = threading.Thread(target=serve)
    t.start()
    try:
        deadline = time.monotonic() + 10.0
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=1.0) as r:
                    assert r.status == 200 and b"<html" in r.read().lower()
                break
            except OSError:
                assert time.monotonic() < deadline and not errors, errors
                time.sleep(0.05)
    finally:
        stop.set()
        t.join(10.0)
    assert not t.is_alive() and not errors


# -- attached to a real map server ----------------------------------------------------------------


@pytest.fixture
def map_server(tmp_path):
    """The map server's request loop over a run folder (with a tiny GSFixer checkpoint), on a
    free loopback port, answering on a thread."""
    import threading

    from gsfix_online.nodes.map_server import Params, RequestLoop, build_service

    from gsfix_online.apps.viewer import free_port
    from tests.apps.served_run import tiny_checkpoint

    run = make_run_folder(tmp_path / "run")
    tiny_checkpoint(run / "work" / "checkpoints")
    params = Params(runs=[str(run)], port=free_port())
    loop = RequestLoop(build_service(params), params)
    stop = threading.Event()
    thread = threading.Thread(target=lambda: [loop.step() for _ in iter(stop.is_set, True)])
    thread.start()
    yield loop.address, run
    stop.set()
    thread.join()
    loop.close()


def test_live_viewer_shows_the_servers_map_and_repairs_the_current_view(map_server, tmp_path):
    from gsfix_online.apps.viewer import LiveSource, ThreadClients

    address, run = map_server
    source = LiveSource(ThreadClients(address), labels_path=tmp_path / "labels.json")
    v = start_viewer(source, port=0)
    try:
        c = v.content
        assert len(c.gmap) == 49 and c.mesh.n_triangles == 128 and c.version == 0
        assert [(x.kind, x.id) for x in c.cameras][1:3] == [("keyframe", 1), ("view", 0)]
        view0 = c.cameras[2]
        images = v.view_images(view0)
        from gsfix_online.repair.outputs import read_png_rgb

        np.testing.assert_array_equal(
            images["after (output)"], read_png_rgb(run / "views/000/output.png")
        )
        assert not v.refresh()  # same version: nothing reloaded
        # The repair button's handler, at the view's own camera
        assert not v.repair_button.disabled
        image = v.repair_view(view0.T_world_cam, view0.K, W, H)
        assert image.shape == (H, W, 3) and image.dtype == np.uint8
        assert v.repair_image.visible and "Repaired" in v.repair_text.content
        assert v.refresh() and v.content.version == 1  # the repair was distilled: a new version
    finally:
        v.server.stop()
