"""Damaged maps of a finished run are refused before they leave: every export kind, the map
server, the viewer and the repair writer check a run's 3DGS PLY and mesh through the same two
validators (``mapping.splat.ply.check_ply``, ``mapping.mesh.read_mesh``) and say in one line which
file is damaged; nothing is written. Before, a truncated point_cloud.ply exported with exit 0, a
truncated mesh became a GLB of 0 triangles and the map server reported has_mesh=True and
rendered the mesh black."""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.apps.cli import main
from gsfix_online.apps.viewer import free_port
from gsfix_online.mapping.mesh import TriMesh, write_mesh
from gsfix_online.mapping.splat.ply import ply_path
from gsfix_online.services.run_folder import RunFolderError
from tests.apps.run_data import make_run


def _cut(path: Path) -> None:  # a copy cut short, a full disk
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])


def _nan_ply(path: Path) -> None:  # Gaussian 0's x := NaN
    data = path.read_bytes()
    at = data.index(b"end_header\n") + len(b"end_header\n")
    path.write_bytes(data[:at] + np.float32(np.nan).tobytes() + data[at + 4 :])


def _nan_mesh(path: Path) -> None:  # vertex 0's x := NaN (Open3D writes doubles)
    data = path.read_bytes()
    at = data.index(b"end_header\n") + len(b"end_header\n")
    path.write_bytes(data[:at] + np.float64(np.nan).tobytes() + data[at + 8 :])


def _empty_mesh(path: Path) -> None:
    write_mesh(TriMesh.empty(), path)


# damage -> (which file, how, what the one line says)
DAMAGE = {
    "truncated ply": ("ply", _cut, "truncated: its header declares element vertex 40"),
    "nan ply": ("ply", _nan_ply, "1 of 40 Gaussians hold non-finite values"),
    "truncated mesh": ("mesh", _cut, "truncated: its header declares element vertex 8"),
    "nan mesh": ("mesh", _nan_mesh, "1 of 8 vertices are not finite"),
    "empty mesh": ("mesh", _empty_mesh, "the mesh has no triangles"),
}


@pytest.fixture(scope="module")
def good_run(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("good"), gt=False)


def damaged(good_run: Path, root: Path, damage: str) -> tuple[Path, Path, str]:
    """A copy of the run with one map damaged: (run, the damaged file, the expected text)."""
    run = shutil.copytree(good_run, root / "run")
    which, change, text = DAMAGE[damage]
    path = ply_path(run / "map", 7) if which == "ply" else run / "mesh.ply"
    change(path)
    return run, path, text


def _one_line(err: str, path: Path, text: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert str(path) in lines[0] and text in lines[0], lines[0]


# what each export reads: the 3DGS map (ply, mcap), the mesh (mesh-ply, glb, mcap)
EXPORT_CASES = [
    (kind, damage)
    for kind in ("ply", "mesh-ply", "glb", "mcap")
    for damage in DAMAGE
    if (DAMAGE[damage][0] == "ply") == (kind in ("ply", "mcap")) or kind == "mcap"
]


@pytest.mark.parametrize(("kind", "damage"), EXPORT_CASES)
def test_export_refuses_a_damaged_map(good_run, tmp_path, capsys, kind, damage) -> None:
    run, path, text = damaged(good_run, tmp_path, damage)
    out = tmp_path / f"out.{'glb' if kind == 'glb' else 'mcap' if kind == 'mcap' else 'ply'}"
    assert main(["export", kind, str(run), "--out", str(out)]) == 2
    _one_line(capsys.readouterr().err, path, text)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # nothing written


def test_export_of_the_intact_run_still_works(good_run, tmp_path, capsys) -> None:
    for kind, name in (("ply", "a.ply"), ("mesh-ply", "b.ply"), ("glb", "c.glb")):
        assert main(["export", kind, str(good_run), "--out", str(tmp_path / name)]) == 0
    out = capsys.readouterr().out
    assert "(0.00 MB; 40 Gaussians)" in out and out.count("8 vertices, 12 triangles") == 2


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_map_server_and_viewer_refuse_a_damaged_map(good_run, tmp_path, damage) -> None:
    from gsfix_online.apps.viewer import RunFolderSource
    from gsfix_online.services.map_server import MapServer, ServerConfig

    run, path, text = damaged(good_run, tmp_path, damage)
    with pytest.raises(RunFolderError, match=text) as exc:
        MapServer(ServerConfig(), started=0.0).add_run(run)
    assert str(exc.value).startswith(str(path)) and "\n" not in str(exc.value)
    with pytest.raises(RunFolderError, match=text):
        RunFolderSource(run).load()


def test_serve_command_refuses_a_truncated_mesh(good_run, tmp_path) -> None:
    """The command as a user runs it: before, it reported has_mesh=True and served on."""
    run, path, text = damaged(good_run, tmp_path, "truncated mesh")
    r = subprocess.run(
        [sys.executable, "-m", "gsfix_online.apps.cli", "serve", str(run), "--port",
         str(free_port())],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2 and "serving map" not in r.stdout, (r.stdout, r.stderr)
    _one_line(r.stderr.replace("\x1b", ""), path, text)


@pytest.mark.parametrize("damage", ["truncated ply", "nan ply", "truncated mesh", "nan mesh"])
def test_repair_writer_refuses_a_damaged_map_and_asks_again(tmp_path, caplog, damage) -> None:
    from gsfix_online.runtime import Message
    from gsfix_online.services.writer import Params, WriterService

    run = make_run(tmp_path, n_views=1, gt=False)
    which, change, text = DAMAGE[damage]
    writer = WriterService("writer", Params(out_dir=str(run)), 0.0)
    path = ply_path(run / "map", 7) if which == "ply" else writer.mesh_path
    change(path)
    events = {
        "mesh": Message("mesh/tsdf", "map_event", meta={
            "kind": "mesh_written", "path": str(writer.mesh_path)}),
        "ply": Message("export/splat", "map_event", meta={
            "kind": "exported", "path": str(writer.map_dir / "point_cloud")}),
    }  # fmt: skip
    with caplog.at_level(logging.ERROR):
        for msg in events.values():
            writer.on_map_event(msg)
    name = {"mesh": "mesh", "ply": "map"}[which]
    assert name not in writer.files and len(writer.files) == 1  # the other one is taken
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and str(path) in errors[0] and text in errors[0], errors
