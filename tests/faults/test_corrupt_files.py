"""Corrupt or truncated snapshots, checkpoints and MCAP logs: detected (SHA-256 record, size,
the container's own checks), reported in one line, and the previous good one used."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch

from gsfix_online.runtime import frame_to_message
from gsfix_online.services.splat import (
    Params,
    SnapshotError,
    SplatService,
    load_snapshot,
    save_snapshot,
)
from tests.conftest import make_frames


def _flip(path: Path, at: float = 0.6) -> None:
    data = bytearray(path.read_bytes())
    data[int(len(data) * at)] ^= 0xFF
    path.write_bytes(bytes(data))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


DAMAGE = {"flipped byte": _flip, "truncated": _truncate}


@pytest.fixture(scope="module")
def two_snapshots(tmp_path_factory) -> tuple[Path, int, int]:  # noqa: ANN001
    """A snapshot after 2 frames (kept as .prev) and one after 3."""
    d = tmp_path_factory.mktemp("snap")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        svc = SplatService("splat", Params(perturbed_renders=0))
        for f in make_frames(n=3, width=24, height=18):
            svc.on_rgbd(frame_to_message(f, "rgbd/cam0"))
            if svc.frames >= 2:
                assert svc.mapper is not None
                save_snapshot(svc.mapper, d / "map.pt")
    finally:
        torch.set_num_threads(n)
    return d, 2, 3


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_damaged_snapshot_falls_back_to_the_previous(two_snapshots, tmp_path, caplog, damage):  # noqa: ANN001
    src, prev_frames, last_frames = two_snapshots
    for f in src.iterdir():
        (tmp_path / f.name).write_bytes(f.read_bytes())
    path = tmp_path / "map.pt"
    assert load_snapshot(Params().mapper, path).n_frames == last_frames
    DAMAGE[damage](path)
    with caplog.at_level(logging.ERROR):
        mapper = load_snapshot(Params().mapper, path)
    assert mapper.n_frames == prev_frames
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and str(path) in errors[0] and "\n" not in errors[0], errors
    # a node started on it resumes from the previous good snapshot
    svc = SplatService("splat", Params(snapshot=str(path)))
    assert svc.frames == prev_frames
    # both damaged: one line naming the path, no silent fresh start
    DAMAGE[damage](tmp_path / "map.pt.prev")
    with pytest.raises(SnapshotError, match="no usable snapshot") as exc:
        load_snapshot(Params().mapper, path)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_damaged_checkpoint_falls_back_to_the_previous(tmp_path, caplog, damage):  # noqa: ANN001
    from gsfix_online.fixer import checkpoint as ck
    from gsfix_online.fixer.sources import build_default
    from tests.fixer.conftest import tiny_model_cfg

    cfg = tiny_model_cfg()
    bundle = build_default(cfg)
    for step in (1, 2):
        ck.save_checkpoint(tmp_path, bundle, step, cfg, trainer_state={"step": step})
    DAMAGE[damage](tmp_path / "step_000002" / "unet.safetensors")
    with caplog.at_level(logging.ERROR):
        loaded = ck.load_checkpoint(tmp_path)
    assert loaded.step == 1 and loaded.trainer_state == {"step": 1}
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "step_000002" in errors[0] and "\n" not in errors[0], errors
    # named directly, the damaged one is refused in one line
    with pytest.raises(ck.CheckpointError) as exc:
        ck.load_checkpoint(tmp_path / "step_000002")
    assert "\n" not in str(exc.value) and "unet.safetensors" in str(exc.value)


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_damaged_mcap_log_reads_its_good_part_or_fails_in_one_line(tmp_path, damage):  # noqa: ANN001
    from gsfix_online.sources import SourceConfig, SourceError, open_source
    from gsfix_online.sources.mcap_log import McapLogWriter

    frames = make_frames(n=4, width=24, height=18)
    path = tmp_path / "log.mcap"
    with McapLogWriter(path, chunk_size=4_000) as w:  # small chunks: damage costs one of them
        for i in range(12):
            f = frames[i % 4]
            w.write(f.__class__(**{**f.__dict__, "stamp_ns": f.stamp_ns + i * 10**9, "seq": i}))
    DAMAGE[damage](path)
    try:
        got = list(open_source(SourceConfig(format="mcap"), path))
    except SourceError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    seqs = [g.seq for g in got]
    assert 1 <= len(got) < 12 and seqs == sorted(seqs), seqs  # the good part, in order
