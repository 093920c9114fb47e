from __future__ import annotations

import subprocess
import sys

import numpy as np
import yaml

from gsfix_online.apps.cli import main
from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.tum import write_tum


def test_help_lists_subcommands():
    out = subprocess.run(
        [sys.executable, "-m", "gsfix_online.apps.cli", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for cmd in ("scene", "convert", "info", "replay", "config", "demo"):
        assert cmd in out


def test_convert_then_info(tmp_path, frames, capsys):
    write_tum(tmp_path / "seq", frames)
    assert (
        main(["convert", str(tmp_path / "seq"), str(tmp_path / "out.mcap"), "--no-progress"]) == 0
    )
    got = list(open_source(SourceConfig(), tmp_path / "out.mcap"))
    assert len(got) == len(frames) and all(
        np.array_equal(a.color, b.color) for a, b in zip(got, frames, strict=True)
    )
    resolved = yaml.safe_load((tmp_path / "out.config.yaml").read_text())
    assert resolved["source"]["path"] == str(
        tmp_path / "seq"
    )  # the resolved config sits next to the output
    assert not (tmp_path / "out.mcap.partial").exists()
    capsys.readouterr()
    assert main(["info", str(tmp_path / "out.mcap"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    rows = dict(line.split(None, 1) for line in out.splitlines())
    assert rows["format"] == "mcap" and rows["frames"].startswith(f"{len(frames)} (")
    assert "40x30 RGB" in rows["camera"] and rows["depth_pixels_invalidated"] == "0"
    assert sum(line.split()[0] == "frames" for line in out.splitlines()) == 1


def test_info_shows_the_processing_resolution(tmp_path, frames, capsys):
    write_tum(tmp_path / "seq", frames)
    assert main(["info", str(tmp_path / "seq"), "source.max_width=32", "--no-progress"]) == 0
    rows = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    assert rows["camera"].startswith("40x30 RGB, fx=32.00 fy=32.00 cx=19.50 cy=14.50")
    # half-pixel rule: cx' = (19.5 + 0.5) * 0.8 - 0.5
    assert rows["processing"] == "32x24, fx=25.60 fy=25.60 cx=15.50 cy=11.50 (source.max_width=32)"
    assert main(["info", str(tmp_path / "seq"), "--no-progress"]) == 0
    rows = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    assert rows["processing"] == "40x30, the camera's (source.max_width not set)"


def test_replay_realtime_runs(tmp_path, frames, capsys):
    write_tum(tmp_path / "seq", frames[:3])
    assert (
        main(
            [
                "replay",
                str(tmp_path / "seq"),
                "--mode",
                "realtime",
                "--speed",
                "100",
                "--no-progress",
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.splitlines()[2].split()[:2] == ["frames", "3"]


def test_errors_are_one_line_with_exit_code_2(tmp_path, frames, capsys):
    write_tum(tmp_path / "seq", frames)
    assert main(["info", str(tmp_path / "seq"), "source.max_assoc_s=-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err
        == "gsfix-online info: error: command line 'source.max_assoc_s=-1': source.max_assoc_s: value -1.0 is out of range [0, 10]"
    )
    assert main(["info", str(tmp_path / "nothing")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_a_node_process_ends_with_its_code_its_exit_handlers_run_and_its_output_flushed(
    tmp_path,
):
    """``gsfix-online node`` ends its process without the interpreter's module teardown; what
    the node relies on at exit still happens: its exit handlers (a timeline's last spans), its
    log lines and its buffered output."""
    mark = tmp_path / "atexit.txt"
    script = (
        "import atexit, logging, sys\n"
        "from gsfix_online.apps.cli import exit_without_teardown\n"
        f"atexit.register(lambda: open({str(mark)!r}, 'w').write('ran'))\n"
        "logging.basicConfig(stream=sys.stderr)\n"
        "logging.getLogger('n').warning('last line')\n"
        "sys.stdout.write('buffered, no newline')\n"
        "exit_without_teardown(3)\n"
        "print('never')\n"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60)  # fmt: skip
    assert res.returncode == 3
    assert res.stdout == "buffered, no newline" and "last line" in res.stderr
    assert mark.read_text() == "ran"
