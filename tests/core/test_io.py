"""Atomic writes: whole files or none, the umask's mode, and the folder synced after the rename."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from gsfix_online.core import io
from gsfix_online.core.io import atomic_path, atomic_write_bytes, atomic_write_text


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_files_get_the_mode_the_umask_gives(tmp_path: Path, umask: int, mode: int) -> None:
    old = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
        with atomic_path(tmp_path / "b.bin") as tmp:
            tmp.write_bytes(b"y")
    finally:
        os.umask(old)
    for name in ("a.txt", "b.bin"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == mode
    assert os.umask(old) == old  # the umask is left as it was
    os.umask(old)


def test_the_folder_is_synced_after_the_rename(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    events: list[str] = []
    real_replace, real_fsync = os.replace, os.fsync

    def replace(src: str, dst: str | Path) -> None:
        events.append(f"replace {Path(dst).name}")
        real_replace(src, dst)

    def fsync(fd: int) -> None:
        kind = "folder" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file"
        events.append(f"fsync {kind}")
        real_fsync(fd)

    monkeypatch.setattr(io.os, "replace", replace)
    monkeypatch.setattr(io.os, "fsync", fsync)
    atomic_write_bytes(tmp_path / "c.bin", b"z")
    assert events.index("replace c.bin") < len(events) - 1
    assert events[events.index("replace c.bin") + 1 :] == ["fsync folder"]
    assert "fsync file" in events[: events.index("replace c.bin")]
    assert (tmp_path / "c.bin").read_bytes() == b"z"


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "d.txt"
    atomic_write_text(target, "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer failed")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.txt"]


def test_an_os_error_is_one_line_naming_the_target(tmp_path: Path) -> None:
    (tmp_path / "plain").write_text("a file, not a folder")  # fails for root too
    target = tmp_path / "plain" / "e.txt"
    with pytest.raises(OSError, match=rf"^\[Errno \d+\] cannot write {target}: "):
        atomic_write_text(target, "x")
