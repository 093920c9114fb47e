"""Pareto fronts of run time against error, and their plots.

A run *dominates* another when it is no slower and no worse, and strictly better in one of the
two. The front is the set of runs no other run dominates. :func:`front_gap` says how far a run
(the defaults) sits behind the front: the most error any front run at most as slow does better.
Pure functions on lists; :func:`plot_fronts` draws them with matplotlib (Agg, no display).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

# The panels of the plot: (column, label, higher is better)
PANELS = (
    ("psnr_final", "final map PSNR dB (novel views)", True),
    ("psnr_output", "delivered repair PSNR dB", True),
    ("depth_mae_cm", "final map depth error cm", False),
    ("mesh_completeness_cm", "mesh completeness cm", False),
)


def _ok(x: Any) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


def pareto_front(
    time_s: Sequence[float | None], error: Sequence[float | None]
) -> list[int]:  # indices into the inputs, by increasing time
    """Indices of the points no other point dominates (both lower is better); points with a
    missing or non-finite value take no part. Of equal points, the first is on the front."""
    if len(time_s) != len(error):
        raise ValueError(f"time_s and error differ in length: {len(time_s)} != {len(error)}")
    pts = sorted((t, e, i) for i, (t, e) in enumerate(zip(time_s, error, strict=True))
                 if _ok(t) and _ok(e))  # fmt: skip
    front: list[int] = []
    best = math.inf
    for _, e, i in pts:  # by time, then error: a point is on the front if it beats all before
        if e < best:
            front.append(i)
            best = e
    return front


def front_gap(time_s: Sequence[float | None], error: Sequence[float | None], i: int) -> float:
    """How much lower the error of the best run at most as slow as run ``i`` is (0: ``i`` is on
    the front or nothing that fast beats it; nan: run ``i`` has no values)."""
    if not (_ok(time_s[i]) and _ok(error[i])):
        return math.nan
    better = [e for t, e in zip(time_s, error, strict=True)
              if _ok(t) and _ok(e) and t <= time_s[i]]  # fmt: skip
    return max(0.0, error[i] - min(better))  # type: ignore[operator]


def plot_fronts(
    rows: list[dict[str, Any]],
    path: Path,
    title: str,
    time_key: str = "total_s",
    panels: Sequence[tuple[str, str, bool]] = PANELS,
) -> list[str]:
    """One panel per error column that the rows hold: every run (coloured by the knob it
    changes, labelled with its value), the defaults as a black star, the front as a line.
    Writes ``path`` (PNG, atomically); returns the columns drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gsfix_online.core.io import atomic_write_bytes
    from gsfix_online.core.pages import figure_png

    drawn = [p for p in panels if sum(_ok(r.get(p[0])) for r in rows) >= 2]
    if not drawn:
        raise ValueError(f"no error column has two runs with values to plot ({path})")
    knobs = list(dict.fromkeys(r.get("knob") or "default" for r in rows))
    colours = {k: plt.get_cmap("tab10")(n % 10) for n, k in enumerate(knobs)}
    fig, axes = plt.subplots(1, len(drawn), figsize=(4.6 * len(drawn), 4.0), squeeze=False)
    t = [r.get(time_key) for r in rows]
    for ax, (col, label, higher) in zip(axes[0], drawn, strict=True):
        err = [(-r[col] if higher else r[col]) if _ok(r.get(col)) else None for r in rows]
        front = pareto_front(t, err)
        ax.step([t[i] for i in front], [rows[i][col] for i in front], where="post",
                color="0.6", lw=1.2, zorder=1, label="Pareto front")  # fmt: skip
        for r in rows:
            if not (_ok(r.get(time_key)) and _ok(r.get(col))):
                continue
            knob = r.get("knob") or "default"
            if knob == "default":
                ax.scatter(r[time_key], r[col], marker="*", s=160, c="k", zorder=3)
                continue
            ax.scatter(r[time_key], r[col], s=28, color=colours[knob], zorder=2)
            ax.annotate(f"{knob}={r.get('value')}", (r[time_key], r[col]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")  # fmt: skip
        ax.set_xlabel("CPU s of all nodes" if time_key == "cpu_s" else "wall time s")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], marker="*", ls="", c="k", ms=10, label="defaults")]
    handles += [plt.Line2D([], [], marker="o", ls="", color=colours[k], label=k)
                for k in knobs if k != "default"]  # fmt: skip
    handles.append(plt.Line2D([], [], color="0.6", label="Pareto front"))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=8,
               frameon=False)  # fmt: skip
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    atomic_write_bytes(path, figure_png(fig))
    plt.close(fig)
    return [c for c, _, _ in drawn]


__all__ = ["PANELS", "front_gap", "pareto_front", "plot_fronts"]
