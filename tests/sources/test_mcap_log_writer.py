"""The MCAP log writer leaves a whole log or nothing: a failure while writing (a bad frame, a
reader error in the caller's ``with`` block, a full disk at the summary) removes its temporary
file. Before, ``convert`` wrote ``OUT.mcap.partial`` itself and left it behind on failure."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.mcap_log import McapLogWriter
from tests.conftest import make_frames


class ReaderFailed(RuntimeError):
    pass


def test_a_whole_log_replaces_the_path_on_close(tmp_path: Path) -> None:
    frames = make_frames(n=3)
    with McapLogWriter(tmp_path / "log.mcap") as w:
        for f in frames:
            w.write(f)
        assert list(tmp_path.iterdir()) != [tmp_path / "log.mcap"]  # not there before close
    assert [p.name for p in tmp_path.iterdir()] == ["log.mcap"]
    assert [f.seq for f in open_source(SourceConfig(), tmp_path / "log.mcap")] == [0, 1, 2]


@pytest.mark.parametrize("existing", [False, True])
def test_a_failure_in_the_block_leaves_no_file_and_keeps_the_old_log(tmp_path, existing) -> None:
    path = tmp_path / "log.mcap"
    if existing:
        path.write_bytes(b"the old log")
    with pytest.raises(ReaderFailed), McapLogWriter(path) as w:
        for f in make_frames(n=3):
            w.write(f)
        raise ReaderFailed("frame 3 is damaged")
    assert sorted(p.name for p in tmp_path.iterdir()) == (["log.mcap"] if existing else [])
    if existing:
        assert path.read_bytes() == b"the old log"


def test_a_bad_frame_leaves_no_file(tmp_path: Path) -> None:
    f = make_frames(n=1)[0]
    bad = f.__class__(**{**f.__dict__, "stamp_ns": -1})
    with pytest.raises(ValueError, match="stamp_ns in"), McapLogWriter(tmp_path / "l.mcap") as w:
        w.write(bad)
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_at_the_summary_is_one_line_and_leaves_no_file(tmp_path, monkeypatch) -> None:
    w = McapLogWriter(tmp_path / "log.mcap")
    w.write(make_frames(n=1)[0])

    def full(*_: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")  # what a write raises

    monkeypatch.setattr(w._w, "finish", full)
    with pytest.raises(OSError, match=f"cannot write {tmp_path / 'log.mcap'}: No space left"):
        w.close()
    assert list(tmp_path.iterdir()) == []


def test_the_recorder_mode_writes_in_place_and_keeps_what_it_wrote(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    w = McapLogWriter(path, chunk_size=4_000, atomic=False)
    for f in make_frames(n=4):
        w.write(f)
    assert path.stat().st_size > 0  # there while it records: a crash keeps the chunks
    w.close()
    assert len(list(open_source(SourceConfig(), path))) == 4
