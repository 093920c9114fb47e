"""A corpus of damaged inputs, each made by the test from a small synthetic ship-tank scene: a
TUM folder out of time order, with a duplicate stamp, at the wrong depth scale, without depth,
with conflicting or non-unit poses, and an MCAP log with a damaged chunk. Each goes through
``gsfix-online info`` or ``convert``: the exit code, the one-line message and the frame counts
are asserted, and no command prints a traceback."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from gsfix_online.apps.cli import main
from gsfix_online.sources import SourceConfig, open_source
from gsfix_online.sources.mcap_log import McapLogWriter

N = 40  # frames of the scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from gsfix_online.scene import ShipTankConfig, generate_ship_tank

    out = tmp_path_factory.mktemp("scene")
    generate_ship_tank(ShipTankConfig(width=80, height=60, n_frames=N, n_novel=0, seed=3), out)
    return out / "tum"


def _lines(path: Path) -> tuple[list[str], list[str]]:
    lines = path.read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    return head, [ln for ln in lines if ln and not ln.startswith("#")]


def reverse_lists(root: Path) -> None:
    for name in ("rgb.txt", "depth.txt"):
        head, data = _lines(root / name)
        (root / name).write_text("\n".join(head + data[::-1]) + "\n")


def duplicate_frame(root: Path) -> None:
    for name in ("rgb.txt", "depth.txt"):
        head, data = _lines(root / name)
        (root / name).write_text("\n".join(head + data[:5] + [data[4]] + data[5:]) + "\n")


def _rewrite_depth(root: Path, fn: Callable[[np.ndarray], np.ndarray]) -> None:
    import cv2

    for p in sorted((root / "depth").glob("*.png")):
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(p), fn(raw).astype(np.uint16))


def _camera(root: Path, **set_: float) -> None:
    cam = json.loads((root / "camera.json").read_text())
    cam.pop("depth_scale")
    (root / "camera.json").write_text(json.dumps({**cam, **set_}))


def millimetre_pngs(root: Path) -> None:  # read at TUM's 5000 units/m: a fifth of the depth
    _rewrite_depth(root, lambda raw: np.rint(raw / 5.0))
    _camera(root)


def camera_scale_1(root: Path) -> None:
    _camera(root, depth_scale=1)


def zero_depth(root: Path) -> None:
    _rewrite_depth(root, np.zeros_like)


def _pose_line(root: Path, i: int, edit: Callable[[list[str]], list[str]]) -> None:
    head, data = _lines(root / "groundtruth.txt")
    data = data[:i] + [" ".join(edit(data[i].split()))] + data[i:]
    (root / "groundtruth.txt").write_text("\n".join(head + data) + "\n")


def conflicting_pose(root: Path) -> None:  # line 7: frame 5's stamp again, 5 m away
    _pose_line(root, 6, lambda f: [f[0], str(float(f[1]) + 5.0), *f[2:]])


def quaternion_norm(norm: float) -> Callable[[Path], None]:
    def edit(root: Path) -> None:
        head, data = _lines(root / "groundtruth.txt")
        f = data[3].split()
        data[3] = " ".join(f[:4] + [repr(float(v) * norm) for v in f[4:]])
        (root / "groundtruth.txt").write_text("\n".join(head + data) + "\n")

    return edit


# name -> (damage, extra arguments, exit code, what stdout (0) or stderr (2) says, frames)
CASES = {
    "reversed": (reverse_lists, [], 0, ["out_of_order              39"], N),
    "duplicate-stamp": (duplicate_frame, [], 0, ["duplicate_stamps          1"], N),
    "millimetre-at-5000": (millimetre_pngs, [], 0, ["the likely scale is 1000 units/m"], N),
    "camera-json-scale-1": (camera_scale_1, [], 0, ["is implausible", "likely scale is 5000"], N),
    "all-zero-depth": (zero_depth, [], 0, [f"{N} of {N} frames have no valid depth"], N),
    "user-scale-1": (
        lambda root: None, ["source.depth_scale=1"], 2,
        ["makes every frame's depth implausible", "set source.force_depth_scale=true"], 0,
    ),
    "user-scale-1-forced": (
        lambda root: None, ["source.depth_scale=1", "source.force_depth_scale=true"], 0,
        ["is implausible"], N,
    ),
    "conflicting-pose": (
        conflicting_pose, [], 2,
        ["groundtruth.txt: lines 8 and 9 give different poses", "source.pose_conflicts=first"], 0,
    ),
    "conflicting-pose-first": (conflicting_pose, ["source.pose_conflicts=first"], 0, [], N),
    "quaternion-norm-3": (
        quaternion_norm(3.0), [], 2, ["groundtruth.txt:5: quaternion norm must be 1 within 0.001, got 3"], 0,
    ),
    "quaternion-norm-1e-5": (
        quaternion_norm(1e-5), [], 2, ["groundtruth.txt:5: quaternion norm must be 1 within 0.001, got 1e-05"], 0,
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_info_on_a_damaged_tum_folder(case: str, scene: Path, tmp_path: Path, capsys) -> None:
    damage, extra, code, says, frames = CASES[case]
    root = tmp_path / "tum"
    shutil.copytree(scene, root)
    damage(root)
    assert main(["info", str(root), *extra, "--no-progress"]) == code
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    if code:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("gsfix-online info: error: "), err
        assert all(s in lines[0] for s in says), lines[0]
        return
    rows = [line.split(None, 1) for line in out.splitlines()]
    assert int(dict(rows)["frames"].split()[0]) == frames
    assert "median" in dict(rows)["depth"] or case == "all-zero-depth"
    warnings = [v for k, v in rows if k == "warning"]
    assert all(any(s in w for w in warnings) or s in out for s in says), out
    if not says:
        assert not warnings, warnings


def test_the_clean_scene_reads_without_warnings_and_prints_its_depth_range(scene, capsys):
    assert main(["info", str(scene), "--no-progress"]) == 0
    rows = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    assert "warning" not in rows
    median, p1, p99 = (float(rows["depth"].split()[i]) for i in (1, 4, 7))
    assert 0.1 < p1 < median < p99 < 30 and rows["depth"].endswith("% invalid")


def test_a_reversed_folder_is_read_in_time_order(scene: Path, tmp_path: Path) -> None:
    root = tmp_path / "tum"
    shutil.copytree(scene, root)
    reverse_lists(root)
    reader = open_source(SourceConfig(), root)
    stamps = [f.stamp_ns for f in reader]
    clean = [f.stamp_ns for f in open_source(SourceConfig(), scene)]
    assert stamps == clean == sorted(clean) and reader.stats.out_of_order == N - 1


# --------------------------------------------------------------------------------------------
# MCAP logs with a damaged chunk
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def log(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The scene as a log of many small chunks (the demo's log has 25 of 4 MB)."""
    path = tmp_path_factory.mktemp("log") / "log.mcap"
    with McapLogWriter(path, chunk_size=100_000) as w:
        for frame in open_source(SourceConfig(), scene):
            w.write(frame)
    return path


def _chunks(path: Path) -> list[tuple[int, int, set[int]]]:
    """(offset, length, stamps of its messages) of each chunk, in file order, read record by
    record without the summary index."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    out = []
    with path.open("rb") as fh:
        stream = StreamReader(fh, emit_chunks=True)
        for rec in stream.records:
            if isinstance(rec, Chunk):
                end = stream._stream.count  # noqa: SLF001 - bytes read so far: the chunk's end
                stamps = {m.log_time for m in breakup_chunk(rec) if isinstance(m, Message)}
                out.append((end - len(rec.data), len(rec.data), stamps))
    return out


# which chunk, where in it, and what the flip breaks: its CRC, or zstd's frame before the CRC
FLIPS = [(0, 0.5, "CRCValidationError"), (3, 0.9, "ZstdError"), (7, 0.5, "CRCValidationError"),
         (-1, 0.3, "CRCValidationError")]  # fmt: skip


@pytest.mark.parametrize("k,where,kind", FLIPS)
def test_convert_skips_a_damaged_chunk_and_reports_its_frames(
    log, tmp_path, capsys, caplog, k, where, kind
):
    chunks = _chunks(log)
    assert len(chunks) >= 10
    offset, length, lost = chunks[k]
    data = bytearray(log.read_bytes())
    data[offset + int(where * length)] ^= 0xFF  # one byte inside the chunk's compressed data
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    out_path = tmp_path / "out.mcap"
    assert main(["convert", str(bad), str(out_path), "--no-progress"]) == 0
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    every = sorted(set().union(*(c[2] for c in chunks)))
    kept = [f.stamp_ns for f in open_source(SourceConfig(), out_path)]
    assert kept == [t for t in every if t not in lost]  # every frame outside the chunk
    assert f"{len(kept)} frames ({len(lost)} frames lost)" in out
    i0, i1 = every.index(min(lost)), every.index(max(lost))
    said = f"chunk {k % len(chunks) + 1} of {len(chunks)} is damaged ({kind}: "
    lost_range = f"{len(lost)} frames lost: frames {i0} to {i1} of {N}"
    logged = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(logged) == 1 and said in logged[0] and lost_range in logged[0], logged
    assert main(["info", str(bad), "--no-progress"]) == 0
    rows = [line.split(None, 1) for line in capsys.readouterr().out.splitlines()]
    assert dict(rows)["frames_lost"] == str(len(lost))
    assert [v for k, v in rows if k == "warning"] == [logged[0].split(": ", 2)[2]]


def test_random_flips_in_a_log_read_or_fail_in_one_line(log, tmp_path, capsys) -> None:
    data = log.read_bytes()
    rng = np.random.default_rng(0)
    codes = []
    for i in range(12):
        d = bytearray(data)
        d[int(rng.integers(0, len(d)))] ^= 0xFF
        bad = tmp_path / f"bad{i}.mcap"
        bad.write_bytes(bytes(d))
        codes.append(main(["convert", str(bad), str(tmp_path / f"out{i}.mcap"), "--no-progress"]))
        err = capsys.readouterr().err
        assert "Traceback" not in err and "()" not in err, err
        if codes[-1]:
            assert len(err.strip().splitlines()) == 1, err
    assert set(codes) <= {0, 2}


def test_a_log_without_a_readable_header_names_the_reason(log, tmp_path, capsys) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x00" * 8 + log.read_bytes()[8:])
    assert main(["info", str(bad), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"gsfix-online info: error: mcap: {bad} is not a readable MCAP file (")
    assert "()" not in err and "\n" not in err
