"""Pose lists read from files (TUM ``groundtruth.txt``, OKVIS CSV, bag pose topics), checked.

A pose list is trusted by everything downstream, so two faults that used to pass silently are
refused here, naming the file and line: a quaternion whose norm is not 1 (within
``QUAT_NORM_TOL``; normalising a norm of 3 or 1e-5 hides a broken writer), and two different
poses at one stamp (keeping either puts frames metres off). ``source.pose_conflicts=first``
keeps the first pose listed at a stamp instead, and says how many were dropped.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from gsfix_online.core.se3 import pose_from_tq
from gsfix_online.core.trajectory import Trajectory
from gsfix_online.sources.base import SourceError, ns_to_seconds
from gsfix_online.sources.config import PoseConflicts

logger = logging.getLogger(__name__)

QUAT_NORM_TOL = 1e-3  # |norm - 1| allowed: 4-decimal lists (TUM's groundtruth) stay within 3e-4
SAME_POSE_TOL = 1e-6  # metres, and quaternion components: a repeated line is not a conflict


def checked_trajectory(
    where: str,
    stamps_ns: Sequence[int],
    tq: npt.ArrayLike,  # [N, 7] tx, ty, tz, qx, qy, qz, qw
    lines: Sequence[int | str],  # where each pose came from, for messages (line numbers)
    conflicts: PoseConflicts = "error",
) -> Trajectory:
    """The trajectory of the listed poses after the checks above; ``where`` names the file."""
    tq = np.asarray(tq, dtype=np.float64).reshape(-1, 7)
    if not np.all(np.isfinite(tq)):
        i = int(np.flatnonzero(~np.all(np.isfinite(tq), axis=1))[0])
        raise SourceError(f"{where}:{lines[i]}: pose contains NaN or inf")
    norm = np.linalg.norm(tq[:, 3:], axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_NORM_TOL)
    if len(bad):
        i = int(bad[0])
        more = f" ({len(bad) - 1} more lines like it)" if len(bad) > 1 else ""
        raise SourceError(
            f"{where}:{lines[i]}: quaternion norm must be 1 within {QUAT_NORM_TOL:g}, got "
            f"{norm[i]:.6g}{more}"
        )
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    stamps, tq, lines = stamps[order], tq[order], [lines[i] for i in order]
    q = tq[:, 3:] * np.where(tq[:, 6:7] < 0, -1.0, 1.0)  # q and -q are one rotation
    dup = np.flatnonzero(np.diff(stamps) == 0) + 1  # a later entry at the stamp before it
    differs = [
        int(i)
        for i in dup
        if np.abs(tq[i, :3] - tq[i - 1, :3]).max() > SAME_POSE_TOL
        or np.abs(q[i] - q[i - 1]).max() > SAME_POSE_TOL
    ]
    if differs and conflicts == "error":
        i = differs[0]
        more = f" ({len(differs) - 1} more stamps like it)" if len(differs) > 1 else ""
        raise SourceError(
            f"{where}: lines {lines[i - 1]} and {lines[i]} give different poses at stamp "
            f"{ns_to_seconds(int(stamps[i]))}{more}; fix the list or set "
            "source.pose_conflicts=first to keep the first pose listed"
        )
    if differs:
        logger.warning("%s: %d stamps with conflicting poses: kept the first pose listed at each "
                       "(source.pose_conflicts=first)", where, len(differs))  # fmt: skip
    keep = np.ones(len(stamps), dtype=bool)
    keep[dup] = False
    return Trajectory(stamps[keep], pose_from_tq(tq[keep, :3], tq[keep, 3:]))
