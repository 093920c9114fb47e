"""Exports of a run that other tools open: read back with those tools' own readers.

The 3DGS PLY with plyfile (the original property layout, the same bytes), the GLB with trimesh,
the rerun recording with the rerun SDK's RRD reader, the MCAP with the mcap reader and the
Foxglove protobuf schemas.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.apps.cli import main
from gsfix_online.apps.export import ExportError, export
from gsfix_online.core.types import Intrinsics, make_frame
from gsfix_online.mapping.splat.ply import ply_path, ply_property_names
from gsfix_online.services.run_folder import RunFolder
from gsfix_online.sources.mcap_log import write_mcap
from tests.apps.run_data import N_GAUSSIANS, SH_DEGREE, H, W, box_mesh, make_run, pose

N_FRAMES = 4


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("export"), gt=False)


@pytest.fixture(scope="module")
def input_log(tmp_path_factory) -> Path:
    """A 4-frame MCAP log, the input the run came from."""
    path = tmp_path_factory.mktemp("input") / "log.mcap"
    intr = Intrinsics(30.0, 30.0, 15.5, 11.5, W, H)
    rng = np.random.default_rng(0)
    frames = [
        make_frame(
            rng.integers(0, 255, (H, W, 3), dtype=np.uint8),
            np.full((H, W), 2.0 + 0.1 * i, np.float32),
            intr,
            pose(0.05 * i),
            1_000_000_000 + i * 33_000_000,
            seq=i,
        )  # fmt: skip
        for i in range(N_FRAMES)
    ]
    assert write_mcap(path, frames) == N_FRAMES
    return path


def test_ply_is_the_map_file_byte_for_byte_in_the_original_layout(run_dir, tmp_path):
    from plyfile import PlyData

    res = export("ply", run_dir, tmp_path / "splats.ply")
    assert res.path.read_bytes() == ply_path(run_dir / "map", 7).read_bytes()
    ply = PlyData.read(str(res.path))
    names = [p.name for p in ply["vertex"].properties]
    # x y z nx ny nz f_dc_0.. f_rest_0.. opacity.., then each Gaussian's provenance
    assert names == [*ply_property_names(SH_DEGREE), "origin", "observations"]
    assert [p.val_dtype for p in ply["vertex"].properties][-2:] == ["u1", "u2"]
    assert all(p.val_dtype == "f4" for p in ply["vertex"].properties[:-2])
    assert ply["vertex"]["origin"].tolist() == [0] * (N_GAUSSIANS - 10) + [1] * 10
    assert ply["vertex"].count == N_GAUSSIANS and res.counts == {"Gaussians": N_GAUSSIANS}


def test_mesh_ply_is_the_run_mesh_and_glb_opens_in_trimesh_with_its_colours(run_dir, tmp_path):
    import trimesh

    ply = export("mesh-ply", run_dir, tmp_path / "m.ply")
    assert ply.path.read_bytes() == (run_dir / "mesh.ply").read_bytes()
    glb = export("glb", run_dir)  # default: RUN/exports/mesh.glb
    assert glb.path == run_dir / "exports" / "mesh.glb"
    m = trimesh.load(str(glb.path), force="mesh", process=False)
    box = box_mesh()
    assert len(m.faces) == box.n_triangles == 12 and glb.counts["triangles"] == 12
    # Open3D's glTF writer may split vertices per face; every vertex keeps its position's colour
    for v, c in zip(np.asarray(m.vertices), np.asarray(m.visual.vertex_colors)[:, :3], strict=True):
        i = int(np.argmin(np.linalg.norm(box.vertices - v, axis=1)))
        np.testing.assert_allclose(v, box.vertices[i], atol=1e-6)
        np.testing.assert_array_equal(c, box.colors[i])


def _rrd_entities(path: Path) -> dict[str, dict[str, list]]:
    """entity path -> column name -> rows, from the recording read back with the rerun SDK."""
    from rerun.chunk import RrdReader

    out: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for chunk in RrdReader(path).stream().collect().stream():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name in ("log_time", "rerun.controls.RowId"):  # wall-clock time, row ids
                continue
            out[chunk.entity_path][name] += batch.column(name).to_pylist()
    return out


def test_rrd_loads_back_with_the_rerun_sdk_and_holds_the_run(run_dir, input_log, tmp_path):
    res = export("rrd", run_dir, tmp_path / "run.rrd", input_path=input_log)
    e = _rrd_entities(res.path)
    run = RunFolder(run_dir)
    views = [f"/world/views/{v.name}" for v in run.views]
    expected = {
        "/world/mesh", "/world/splats", "/world/keyframes/0", "/world/keyframes/0/image",
        "/world/keyframes/0/depth", "/world/keyframes/1", "/world/input", "/world/input/image",
        "/world/input/depth", "/world/input_path", *views,
        *(f"{v}/{n}" for v in views for n in ("before", "final")),
        "/world/views/000/after", "/world/views/002/after",
    }  # fmt: skip
    assert expected <= set(e)
    assert "/world/views/001/after" not in e  # the planner skipped view 1: nothing repaired
    # the maps: every Gaussian and triangle
    (centers,) = e["/world/splats"]["GaussianSplats3D:centers"]
    assert len(centers) == N_GAUSSIANS
    np.testing.assert_allclose(centers, run.splat_model().gmap.means.detach().numpy(), atol=1e-6)
    # the provenance layer: each Gaussian's origin and observation count
    gmap = run.splat_model().gmap
    (ids,) = e["/world/provenance"]["Points3D:class_ids"]
    assert ids == gmap.origin.tolist() and 0 < sum(ids) < N_GAUSSIANS
    (seen,) = e["/world/provenance"]["observations"]
    assert seen == gmap.observations.tolist()
    (tris,) = e["/world/mesh"]["Mesh3D:triangle_indices"]
    assert len(tris) == 12
    # keyframes: pose and a rendered image of the keyframe size
    (t,) = e["/world/keyframes/1"]["Transform3D:translation"]
    np.testing.assert_allclose(t, [[-0.1, 0, 0]], atol=1e-6)  # one row per instance
    assert e["/world/keyframes/0/image"]["Image:format"][0][0]["width"] == W
    # one timeline: the input frames at steps 0..3, then the views at 4, 5, 6
    assert e["/world/input/image"]["step"] == list(range(N_FRAMES))
    assert e["/world/input/depth"]["step"] == list(range(N_FRAMES))
    assert [e[v]["step"][0] for v in views] == [N_FRAMES, N_FRAMES + 1, N_FRAMES + 2]
    # the images are the run's PNG files
    (blob,) = e["/world/views/002/after"]["EncodedImage:blob"]
    assert bytes(blob[0]) == (run_dir / "views" / "002" / "output.png").read_bytes()
    assert res.counts == {"mesh triangles": 12, "splats": N_GAUSSIANS, "keyframes": 2,
                          "input frames": N_FRAMES, "views": 3}  # fmt: skip


def test_mcap_holds_mesh_splats_poses_and_view_images_in_foxglove_schemas(run_dir, tmp_path):
    import trimesh
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    res = export("mcap", run_dir, tmp_path / "run.mcap")
    msgs = defaultdict(list)
    with res.path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, proto in reader.iter_decoded_messages():
            msgs[channel.topic].append((schema.name, message.log_time, proto))
    assert {t: {s for s, _, _ in m} for t, m in msgs.items()} == {
        "/run/mesh": {"foxglove.SceneUpdate"},
        "/run/splats": {"foxglove.PointCloud"},
        "/tf": {"foxglove.FrameTransform"},
        "/run/views/calibration": {"foxglove.CameraCalibration"},
        "/run/views/before": {"foxglove.CompressedImage"},
        "/run/views/after": {"foxglove.CompressedImage"},
        "/run/views/final": {"foxglove.CompressedImage"},
    }
    (model,) = msgs["/run/mesh"][0][2].entities[0].models
    glb = trimesh.load(trimesh.util.wrap_as_stream(model.data), file_type="glb", force="mesh")
    assert len(glb.faces) == 12 and model.media_type == "model/gltf-binary"
    cloud = msgs["/run/splats"][0][2]
    assert cloud.point_stride == 16 and len(cloud.data) == 16 * N_GAUSSIANS
    xyz = np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])["xyz"]
    np.testing.assert_allclose(xyz, RunFolder(run_dir).splat_model().gmap.means.detach().numpy())
    frames = [p.child_frame_id for _, _, p in msgs["/tf"]]
    assert frames == ["keyframe_0", "keyframe_1", "view_000", "view_001", "view_002"]
    assert [t for _, t, _ in msgs["/run/views/before"]] == [1_000_000_000, 2_000_000_000,
                                                            3_000_000_000]  # fmt: skip
    assert len(msgs["/run/views/after"]) == 2  # view 1 was skipped
    assert msgs["/run/views/after"][0][2].data == (run_dir / "views/000/output.png").read_bytes()


def test_bad_requests_fail_with_one_line(run_dir, tmp_path, input_log):
    with pytest.raises(
        ExportError, match=r"--out for a glb export must end in \.glb, got 'm\.ply'"
    ):
        export("glb", run_dir, tmp_path / "m.ply")
    with pytest.raises(ExportError, match="--input goes into the rrd export only, not mcap"):
        export("mcap", run_dir, input_path=input_log)
    with pytest.raises(ExportError, match="no such file or folder"):
        export("rrd", run_dir, input_path=tmp_path / "missing.mcap")
    with pytest.raises(ValueError, match="not a run folder of 'gsfix-online repair'"):
        export("ply", tmp_path)


def test_export_command_writes_the_file_and_names_it(run_dir, tmp_path, capsys):
    out = tmp_path / "cli.glb"
    assert main(["export", "glb", str(run_dir), "--out", str(out)]) == 0
    assert out.is_file() and str(out) in capsys.readouterr().out
    assert main(["export", "rrd", str(tmp_path / "nothing")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_a_run_without_maps_names_what_is_missing(tmp_path):
    bare = make_run(tmp_path, n_views=1, maps=False, gt=False)
    with pytest.raises(ExportError, match=r"no 3DGS map \(no map/point_cloud/iteration_N\)"):
        export("ply", bare)
    with pytest.raises(ExportError, match=r"no mesh \(mesh.ply is missing\)"):
        export("glb", bare)
    res = export("rrd", bare)  # the views alone still make a recording
    assert res.counts == {"keyframes": 0, "views": 1}
    assert not list((bare / "exports").glob(".*"))  # no temporary files left behind
