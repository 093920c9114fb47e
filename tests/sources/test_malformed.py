"""Every malformed input gets a one-line error or a counted warning, never a silent fix."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from gsfix_online.core.types import FrameError
from gsfix_online.sources import SourceConfig, SourceError, detect_format, open_source
from gsfix_online.sources.base import associate, ns_to_seconds, seconds_to_ns
from gsfix_online.sources.okvis import write_okvis
from gsfix_online.sources.redwood import write_redwood
from gsfix_online.sources.replica import write_replica
from gsfix_online.sources.scannetpp import write_scannetpp
from gsfix_online.sources.tum import write_tum


def one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def edit_lines(path: Path, fn) -> None:  # noqa: ANN001
    lines = path.read_text().splitlines()
    path.write_text("\n".join(fn(lines)) + "\n")


# ---------------------------------------------------------------- TUM


@pytest.fixture
def tum(tmp_path, frames) -> Path:
    write_tum(tmp_path / "seq", frames)
    return tmp_path / "seq"


@pytest.mark.parametrize(
    ("mutate", "msg"),
    [
        (
            lambda ls: ls[:2] + ["1700000000.1 1 2 3 0 0 0"] + ls[3:],
            "expected 'timestamp tx ty tz qx qy qz qw', got 7 fields",
        ),
        (lambda ls: ls[:2] + ["1700000000.1 1 2 nan 0 0 0 1"] + ls[3:], "NaN or inf"),
        (
            lambda ls: ls[:2] + ["1700000000.1 1 2 3 0 0 0 0"] + ls[3:],
            "quaternion norm must be 1 within 0.001, got 0",
        ),
        (lambda ls: ls[:2] + ["1700000000.1 a 2 3 0 0 0 1"] + ls[3:], "must be numbers"),
    ],
)
def test_tum_bad_pose_lines(tum, mutate, msg):
    edit_lines(tum / "groundtruth.txt", mutate)
    with pytest.raises(SourceError) as err:
        open_source(SourceConfig(), tum)
    assert msg in one_line(err) and "groundtruth.txt:3" in str(err.value)


def test_tum_missing_index_file(tum):
    (tum / "depth.txt").unlink()
    with pytest.raises(SourceError, match="depth.txt does not exist"):
        open_source(SourceConfig(format="tum"), tum)


def test_tum_bad_timestamp(tum):
    edit_lines(tum / "rgb.txt", lambda ls: ls[:1] + ["17x00 rgb/a.png"] + ls[1:])
    with pytest.raises(SourceError, match="bad timestamp '17x00'"):
        open_source(SourceConfig(), tum)


def test_tum_unpaired_and_poseless_frames_are_counted(tum, frames):
    # shift every depth stamp by 0.03 s (> 0.02 s): nothing pairs
    edit_lines(
        tum / "depth.txt",
        lambda ls: (
            ls[:1]
            + [
                f"{ns_to_seconds(seconds_to_ns(line.split()[0]) + 30_000_000)} {line.split()[1]}"
                for line in ls[1:]
            ]
        ),
    )
    r = open_source(SourceConfig(), tum)
    assert list(r) == [] and r.stats.unpaired == 2 * len(frames)
    # with a larger association window they pair again
    assert len(list(open_source(SourceConfig(max_assoc_s=0.04), tum))) == len(frames)


def test_tum_frames_outside_trajectory_are_counted(tum, frames):
    edit_lines(tum / "groundtruth.txt", lambda ls: ls[:1] + ls[4:])  # drop the first three poses
    r = open_source(SourceConfig(), tum)
    got = list(r)
    assert len(got) == len(frames) - 3 and r.stats.without_pose == 3


def test_tum_pose_gap_too_large(tum, frames):
    edit_lines(
        tum / "groundtruth.txt", lambda ls: ls[:4] + ls[6:]
    )  # 0.3 s hole around frames 3 and 4
    r = open_source(SourceConfig(max_pose_gap_s=0.2), tum)
    assert len(list(r)) == len(frames) - 2 and r.stats.without_pose == 2


def test_tum_missing_image_and_wrong_depth_type(tum):
    first = sorted((tum / "depth").iterdir())[0]
    cv2.imwrite(str(first), np.zeros((30, 40), np.uint8))  # 8-bit depth
    with pytest.raises(SourceError, match="must be 16-bit single channel, got uint8"):
        list(open_source(SourceConfig(), tum))
    first.unlink()
    with pytest.raises(SourceError, match="cannot read depth image"):
        list(open_source(SourceConfig(), tum))


def test_tum_size_mismatch(tum):
    first = sorted((tum / "rgb").iterdir())[0]
    cv2.imwrite(str(first), np.zeros((20, 40, 3), np.uint8))
    with pytest.raises(SourceError, match=r"colour \[20, 40\] and depth \[30, 40\] sizes differ"):
        list(open_source(SourceConfig(), tum))


def test_tum_intrinsics_from_config_and_freiburg_names(tum, tmp_path):
    (tum / "camera.json").unlink()
    with pytest.raises(SourceError, match="has no camera file; set source.camera"):
        next(iter(open_source(SourceConfig(), tum)))
    from gsfix_online.core.config import build

    cfg = build(SourceConfig, base={"camera": {"fx": 30.0, "fy": 31.0, "cx": 19.5, "cy": 14.5}})
    assert next(iter(open_source(cfg, tum))).intrinsics.fy == 31.0
    fr3 = tmp_path / "rgbd_dataset_freiburg3_long_office_household"
    shutil.copytree(tum, fr3)
    k = next(iter(open_source(SourceConfig(), fr3))).intrinsics  # 40x30 images: scaled from 640x480
    assert k.fx == pytest.approx(535.4 * 40 / 640)


# ---------------------------------------------------------------- other folder formats


def test_replica_bad_traj(tmp_path, frames):
    write_replica(tmp_path, frames, color_ext=".png")
    edit_lines(tmp_path / "traj.txt", lambda ls: [ls[0].rsplit(" ", 1)[0]] + ls[1:])
    with pytest.raises(SourceError, match=r"traj.txt:1: expected 16 numbers"):
        open_source(SourceConfig(), tmp_path)
    edit_lines(tmp_path / "traj.txt", lambda ls: ls[1:3])
    with pytest.raises(SourceError, match="traj.txt has 2 poses but frames go up to 7"):
        open_source(SourceConfig(), tmp_path)


def test_replica_non_orthonormal_pose(tmp_path, frames):
    write_replica(tmp_path, frames, color_ext=".png")
    edit_lines(tmp_path / "traj.txt", lambda ls: ["2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"] + ls[1:])
    with pytest.raises(FrameError, match="traj.txt line 1 rotation is not orthonormal"):
        open_source(SourceConfig(), tmp_path)


def test_redwood_bad_log(tmp_path, frames):
    write_redwood(tmp_path, frames)
    edit_lines(tmp_path / "trajectory.log", lambda ls: ls[:-1])
    with pytest.raises(SourceError, match="groups of 5 lines"):
        open_source(SourceConfig(), tmp_path)
    edit_lines(tmp_path / "trajectory.log", lambda ls: ["0 x 1"] + ls[1:] + ["0 0 0 1"])
    with pytest.raises(SourceError, match="expected 'id id n'"):
        open_source(SourceConfig(), tmp_path)


def test_scannetpp_missing_pose(tmp_path, frames):
    import json

    write_scannetpp(tmp_path, frames)
    meta_path = tmp_path / "iphone" / "pose_intrinsic_imu.json"
    meta = json.loads(meta_path.read_text())
    del meta["frame_000002"]["aligned_pose"]
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(SourceError, match="frame_000002: needs aligned_pose and intrinsic"):
        open_source(SourceConfig(), tmp_path)


def test_scannetpp_resizes_colour_to_depth(tmp_path, frames):
    write_scannetpp(tmp_path, frames)
    for p in (tmp_path / "iphone" / "rgb").iterdir():  # colour at twice the depth resolution
        img = cv2.imread(str(p))
        cv2.imwrite(str(p), cv2.resize(img, (80, 60), interpolation=cv2.INTER_NEAREST))
    import json

    meta_path = tmp_path / "iphone" / "pose_intrinsic_imu.json"
    meta = json.loads(meta_path.read_text())
    for v in meta.values():
        K = np.asarray(v["intrinsic"])
        K[:2] *= 2.0
        K[:2, 2] += 0.5  # pixel-centre convention
        v["intrinsic"] = K.tolist()
    meta_path.write_text(json.dumps(meta))
    got = next(iter(open_source(SourceConfig(), tmp_path)))
    assert got.color.shape == (30, 40, 3)
    assert pytest.approx(frames[0].intrinsics.K, abs=1e-9) == got.intrinsics.K


def test_okvis_needs_T_SC_and_columns(tmp_path, frames):
    write_okvis(tmp_path, frames, np.eye(4))
    with pytest.raises(SourceError, match="source.T_SC must be set"):
        open_source(SourceConfig(format="okvis"), tmp_path)
    eye = np.eye(4).ravel().tolist()
    edit_lines(tmp_path / "trajectory.csv", lambda ls: [ls[0].replace("q_WS_w", "qw")] + ls[1:])
    with pytest.raises(SourceError, match=r"header lacks columns \['q_WS_w'\]"):
        open_source(SourceConfig(T_SC=eye), tmp_path)


def test_config_rejects_bad_T_SC():
    from gsfix_online.core.config import ConfigError, build

    with pytest.raises(ConfigError, match="T_SC must have 16 numbers"):
        build(SourceConfig, base={"T_SC": [1.0, 0.0]})


# ---------------------------------------------------------------- MCAP


def test_mcap_garbage_and_truncated(tmp_path, frames):
    bad = tmp_path / "garbage.mcap"
    bad.write_bytes(b"not an mcap file at all" * 10)
    with pytest.raises(SourceError, match="not a readable MCAP file"):
        open_source(SourceConfig(), bad)
    good = tmp_path / "log.mcap"
    from gsfix_online.sources.mcap_log import McapLogWriter

    with McapLogWriter(good, chunk_size=16_000) as w:  # small chunks: a crash loses only the last
        for i, f in enumerate(frames * 4):
            w.write(f.__class__(**{**f.__dict__, "stamp_ns": f.stamp_ns + i * 10**9, "seq": i}))
    data = good.read_bytes()
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(
        data[: len(data) // 2]
    )  # a writer that died half-way: no summary, partial chunk
    r = open_source(SourceConfig(format="mcap"), cut)
    got = list(r)
    assert 4 <= len(got) < 32  # everything in the complete chunks
    assert [g.seq for g in got] == list(range(len(got)))


def test_detect_format_errors(tmp_path):
    with pytest.raises(SourceError, match="does not exist"):
        detect_format(tmp_path / "nope")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(SourceError, match="cannot tell the format of file"):
        detect_format(tmp_path / "x.txt")
    with pytest.raises(SourceError, match="cannot tell the dataset layout"):
        detect_format(tmp_path)


# ---------------------------------------------------------------- stamps and association


def test_timestamps_are_exact():
    assert seconds_to_ns("1305031102.175304") == 1305031102_175304000
    assert seconds_to_ns("1305031102.1753041239") == 1305031102_175304123  # beyond ns: truncated
    assert seconds_to_ns("-1.5") == -1_500_000_000 and seconds_to_ns("1e-3") == 1_000_000
    for ns in (0, 1, 1_700_000_000_123_456_789, -5):
        assert seconds_to_ns(ns_to_seconds(ns)) == ns
    with pytest.raises(SourceError):
        seconds_to_ns("nan")


def test_associate_one_to_one_closest_first():
    a = [0, 100, 200]
    b = [5, 95, 110, 400]
    assert associate(a, b, 20) == [(0, 0), (1, 1)]  # 110 loses to 95 for a=100; 200 has nobody
    assert associate(a, b, 0) == [] and associate([], b, 10) == []
