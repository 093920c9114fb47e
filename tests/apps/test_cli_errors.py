"""Every user error of the command line is one line naming the path, exit code 2, never a
traceback (``--debug`` keeps it), and a failed command leaves no temporary file behind.

Before, ``main()`` let OSError through (a 30-line traceback for an unreadable input folder, an
``--out`` that is a folder, a read-only output folder), a failed ``convert`` left
``OUT.mcap.partial`` behind and OpenCV printed ``[ WARN ]`` lines before the real error. The
tests run as root, where chmod stops nothing: an unreadable folder and a read-only one are
simulated by the call that fails on them raising what the OS raises (EACCES)."""

from __future__ import annotations

import errno
import shutil
import tempfile
from pathlib import Path

import pytest

from gsfix_online.apps.cli import main
from gsfix_online.sources.tum import write_tum
from tests.apps.run_data import make_run
from tests.conftest import make_frames


@pytest.fixture(scope="module")
def tum(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tum") / "seq"
    write_tum(root, make_frames(n=6))
    return root


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("run"), gt=False)


def one_line(capfd: pytest.CaptureFixture[str], command: str, *texts: str) -> str:
    """The error line of ``command`` (the whole of stderr, C libraries' output included)."""
    err = capfd.readouterr().err
    assert "Traceback" not in err and "[ WARN" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"gsfix-online {command}: error: "), err
    assert all(t in lines[0] for t in texts), lines[0]
    return lines[0]


def _deny(monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
    """Reading an entry of ``folder`` fails as in a folder without read/search permission."""
    real = Path.stat

    def stat(self: Path, *a, **kw):  # noqa: ANN002, ANN003, ANN202
        if self.parent == folder:
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real(self, *a, **kw)

    monkeypatch.setattr(Path, "stat", stat)


def _read_only(monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
    """Creating a file in ``folder`` fails as in a read-only folder."""
    real = tempfile.mkstemp

    def mkstemp(*a, dir=None, **kw):  # noqa: ANN002, ANN003, ANN202, A002
        if dir is not None and Path(dir) == folder:
            raise PermissionError(errno.EACCES, "Permission denied", str(Path(dir) / "x"))
        return real(*a, dir=dir, **kw)

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)


@pytest.mark.parametrize("command", ["info", "convert"])
def test_unreadable_input_folder(tum, tmp_path, monkeypatch, capfd, command) -> None:
    _deny(monkeypatch, tum)
    out = [str(tmp_path / "out.mcap")] if command == "convert" else []
    assert main([command, str(tum), *out, "--no-progress"]) == 2
    one_line(capfd, command, str(tum), "Permission denied")
    assert list(tmp_path.iterdir()) == []


def test_export_out_is_an_existing_folder(run_dir, tmp_path, capfd) -> None:
    (tmp_path / "splats.ply").mkdir()
    assert main(["export", "ply", str(run_dir), "--out", str(tmp_path / "splats.ply")]) == 2
    one_line(capfd, "export", f"cannot write {tmp_path / 'splats.ply'}: Is a directory")
    assert [p.name for p in tmp_path.iterdir()] == ["splats.ply"]  # no temporary left


@pytest.mark.parametrize("command", ["export", "convert"])
def test_read_only_output_folder(tum, run_dir, tmp_path, monkeypatch, capfd, command) -> None:
    out_dir = tmp_path / "ro"
    out_dir.mkdir()
    _read_only(monkeypatch, out_dir)
    if command == "export":
        args = ["export", "glb", str(run_dir), "--out", str(out_dir / "m.glb")]
        target = out_dir / "m.glb"
    else:
        args = ["convert", str(tum), str(out_dir / "o.mcap"), "--no-progress"]
        target = out_dir / "o.mcap"
    assert main(args) == 2
    one_line(capfd, command, f"cannot write {target}: Permission denied")
    assert list(out_dir.iterdir()) == []


def _missing(path: Path) -> None:
    path.unlink()


def _cut(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:100])


@pytest.mark.parametrize(("damage", "reason"), [
    (_missing, "No such file or directory"), (_cut, "not a whole image file"),
])  # fmt: skip
def test_failed_convert_leaves_no_partial_log(tum, tmp_path, capfd, damage, reason) -> None:
    seq = shutil.copytree(tum, tmp_path / "seq")
    image = sorted((seq / "rgb").iterdir())[3]  # frames 0-2 are written before it fails
    damage(image)
    assert main(["convert", str(seq), str(tmp_path / "out.mcap"), "--no-progress"]) == 2
    one_line(capfd, "convert", f"cannot read image {image}: {reason}")
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]  # no out.mcap, .partial or temporary


def test_debug_keeps_the_traceback(run_dir, tmp_path) -> None:
    (tmp_path / "splats.ply").mkdir()
    with pytest.raises(IsADirectoryError, match="cannot write"):
        main(["export", "ply", str(run_dir), "--out", str(tmp_path / "splats.ply"), "--debug"])
    with pytest.raises(IsADirectoryError):  # before the command too
        main(["--debug", "export", "ply", str(run_dir), "--out", str(tmp_path / "splats.ply")])


@pytest.mark.parametrize("command", ["serve", "view"])
def test_help_says_how_to_open_to_a_network_and_that_there_is_no_authentication(
    capsys, command
) -> None:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--host 0.0.0.0 opens it to every network" in text
    assert "There is no authentication" in text and "binds 127.0.0.1" in text
