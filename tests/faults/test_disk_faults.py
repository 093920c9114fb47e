"""A disk that fills up and an output folder that cannot be written: one line naming the path,
and never a corrupt or half-written file (temporary file, fsync, rename; the old file stays).

As root where ``mount`` works the test mounts a 1 MiB tmpfs (the real ENOSPC of a real file
system) and a read-only tmpfs; elsewhere it injects the same errors at ``os.fsync`` / ``open``.
"""

from __future__ import annotations

import builtins
import errno
import logging
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.core.io import atomic_write_bytes


def _mount(target: Path, options: str) -> bool:
    if os.geteuid() != 0:
        return False
    target.mkdir(parents=True, exist_ok=True)
    cmd = ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(target)]
    return subprocess.run(cmd, capture_output=True).returncode == 0


def _umount(target: Path) -> None:
    subprocess.run(["umount", "-l", str(target)], capture_output=True)


@pytest.fixture
def full_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A folder on a 1 MiB file system: a real tmpfs, or ENOSPC injected for files in it."""
    d = tmp_path / "disk"
    if _mount(d, "size=1m"):
        yield d
        _umount(d)
        return
    d.mkdir()
    real = os.fsync

    def fsync(fd: int) -> None:
        if (
            os.path.realpath(f"/proc/self/fd/{fd}").startswith(str(d))
            and os.fstat(fd).st_size > 2**20
        ):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    yield d


@pytest.fixture
def read_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A read-only folder holding ``old.bin``: a read-only tmpfs, or EROFS injected."""
    d = tmp_path / "ro"
    if _mount(d, "size=1m"):
        (d / "old.bin").write_bytes(b"old")
        subprocess.run(["mount", "-o", "remount,ro", str(d)], check=True)
        yield d
        _umount(d)
        return
    d.mkdir()
    (d / "old.bin").write_bytes(b"old")
    real_open = os.open

    def os_open(path, flags, *args, **kwargs):  # noqa: ANN001, ANN202
        if str(path).startswith(str(d)) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(builtins, "open", builtins.open)
    yield d


def _fill(folder: Path) -> None:
    """Take every free byte of the file system holding ``folder`` (a file named filler)."""
    with open(folder / "filler", "wb", buffering=0) as fh:
        for chunk in (2**16, 2**10, 1):
            try:
                while True:
                    fh.write(bytes(chunk))
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc


def _one_line_naming(exc: BaseException, path: Path) -> None:
    msg = str(exc)
    assert "\n" not in msg and str(path) in msg, msg


def test_a_full_disk_keeps_the_old_file_whole_and_names_the_path(full_disk: Path) -> None:
    path = full_disk / "mesh.ply"
    atomic_write_bytes(path, b"old mesh")
    with pytest.raises(OSError) as exc:
        atomic_write_bytes(path, bytes(2 * 2**20))  # twice the disk
    assert exc.value.errno == errno.ENOSPC
    _one_line_naming(exc.value, path)
    assert "No space left" in str(exc.value)
    assert path.read_bytes() == b"old mesh"  # the whole old file
    assert sorted(p.name for p in full_disk.iterdir()) == ["mesh.ply"]  # no temporary file left
    atomic_write_bytes(path, b"new mesh")  # room again: the next write succeeds
    assert path.read_bytes() == b"new mesh"


def test_a_full_disk_during_a_snapshot_leaves_the_previous_one_loadable(full_disk: Path) -> None:
    import torch

    from gsfix_online.runtime import frame_to_message
    from gsfix_online.services.splat import Params, SplatService, load_snapshot, save_snapshot
    from tests.conftest import make_frames

    svc = SplatService("splat", Params(perturbed_renders=0))
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for f in make_frames(n=2, width=24, height=18):
            svc.on_rgbd(frame_to_message(f, "rgbd/cam0"))
    finally:
        torch.set_num_threads(n)
    assert svc.mapper is not None
    path = full_disk / "map.pt"
    save_snapshot(svc.mapper, path)
    before = {p.name: p.read_bytes() for p in full_disk.iterdir()}
    if not os.path.ismount(full_disk):
        pytest.skip("needs a real small file system to fill")
    _fill(full_disk)  # the rest of the disk goes to another writer
    with pytest.raises(OSError) as exc:
        save_snapshot(svc.mapper, path)
    _one_line_naming(exc.value, path)
    (full_disk / "filler").unlink()
    after = {p.name: p.read_bytes() for p in full_disk.iterdir()}
    assert after == before  # nothing replaced, nothing half-written, no temporary file
    assert load_snapshot(Params().mapper, path).n_frames == 2


def test_an_unwritable_output_folder_is_one_line_naming_the_path(read_only: Path) -> None:
    from gsfix_online.mapping.mesh import TriMesh, write_mesh

    for path in (read_only / "old.bin", read_only / "sub" / "new.bin"):
        with pytest.raises(OSError) as exc:
            atomic_write_bytes(path, b"new")
        _one_line_naming(exc.value, path)
    mesh = TriMesh(
        np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], np.int32), np.zeros((3, 3), np.uint8)
    )
    with pytest.raises(OSError) as exc:
        write_mesh(mesh, read_only / "mesh.ply")
    _one_line_naming(exc.value, read_only / "mesh.ply")
    assert sorted(p.name for p in read_only.iterdir()) == ["old.bin"]
    assert (read_only / "old.bin").read_bytes() == b"old"


def test_the_tsdf_node_reports_a_full_disk_in_one_line_and_keeps_its_mesh(
    full_disk: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from gsfix_online.nodes import tsdf

    from gsfix_online.mapping.tsdf import TsdfConfig
    from gsfix_online.runtime import InMemoryTransport, Message, NodeRuntimeConfig, frame_to_message
    from tests.mapping.splat.test_mapper import plane_frame

    cfg = TsdfConfig(voxel_size=0.05, depth_max=6.0, mesh_weight_threshold=1.0)
    params = tsdf.Params(tsdf=cfg, mesh_dir=str(full_disk), formats=["ply"], write_periodic=False)
    t = InMemoryTransport()
    node, svc = tsdf.build_node("tsdf", params, t, NodeRuntimeConfig(log_period_s=0.0))
    for x in (0.0, 0.05, 0.1):  # a wall 2 m in front of the camera
        t.feed(frame_to_message(plane_frame(x), "rgbd/cam0"))
    t.feed(Message("tsdf/snapshot", "command", meta={"kind": "snapshot", "path": ""}))
    node.run_until_idle()
    mesh = full_disk / "mesh.ply"
    good = mesh.read_bytes()
    assert len(good) > 2000 and not node.handler_errors
    if not os.path.ismount(full_disk):
        pytest.skip("needs a real small file system to fill")
    _fill(full_disk)
    t.feed(Message("tsdf/snapshot", "command", meta={"kind": "snapshot", "path": ""}))
    with caplog.at_level(logging.WARNING, logger="gsfix_online.runtime.node"):
        node.run_until_idle()
    assert node.handler_errors == {"OSError": 1}
    (line,) = [r.getMessage() for r in caplog.records if "handler for" in r.getMessage()]
    assert "\n" not in line and str(mesh) in line, line
    assert mesh.read_bytes() == good  # the whole old mesh
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler", "mesh.ply"]
