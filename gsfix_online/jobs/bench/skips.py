"""The work the system skips, each measured against the same run without the skip.

Each :class:`Skip` names the override(s) that turn it off; ``gsfix-online bench --skips`` runs
the repair graph once with the defaults (every skip on) and once per skip with that skip off,
and :func:`skip_table` says for each what it saved and what it cost. Skips the library does not
have yet carry ``off = None`` and the reason, so the table lists them too.

The judgement (:func:`verdict`): a skip is worth its error when it costs at most 1 dB of final
map PSNR per 100 % of wall time it saves (0.1 dB per 10 %); a change within ``noise_db`` counts
as no change. A skip that costs more is to be off by default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

DB_PER_TIME = 1.0  # dB of final PSNR a skip may cost per 100 % of wall time it saves
NOISE_DB = 0.05  # PSNR changes this small are no change (seed-to-seed spread of a tiny scene)


@dataclass(frozen=True)
class Skip:
    name: str
    what: str  # what is skipped, in the issue's words
    off: tuple[str, ...] | None  # overrides that turn it off; None: not in the library
    note: str = ""  # how the library does it, or why it is missing


SKIPS = (
    Skip("planner", "the planner skips views that need no repair",
         ("planner.skip.enabled=false",), "off: every view is repaired and distilled"),
    Skip("static_frames", "frames with little new content skip 3DGS work",
         ("splat.mapper.non_kf_every=1",),
         "only every non_kf_every-th (4th) non-keyframe is optimised; off: every one"),
    Skip("non_kf_steps", "non-keyframes get fewer steps",
         ("splat.mapper.non_kf_iters=2",),
         "non-keyframes 1 step, keyframes kf_iters (2); off: 2 steps for both"),
    Skip("fallback_regions", "a poor map's part of a view does not go through GSFixer",
         ("trainer.fallback_samples=0",),
         "the library chooses per region (both maps, 3DGS only, mesh only, neither) between "
         "GSFixer and the mesh/OpenCV fallbacks; off: GSFixer everywhere. A per-view switch to "
         "mode gs or mesh is not in the library"),
    Skip("trainer_early_stop", "the trainer stops early when nothing new is learnt",
         ("trainer.policy.patience=100000",),
         "patience 10 evaluations; off: the whole step budget (with a budget below 10 "
         "evaluations, as in the quick base, both runs are the same: the row shows the noise). "
         "Offline the trainer starts one run when the input ends, so not starting a run "
         "without new keyframes is not measured"),
    Skip("ddim_easy_views", "easy views use fewer DDIM steps", None,
         "not in the library: every view gets repair.fixer.inference.steps, whose default (1) "
         "is already the fewest"),
    Skip("distill_plateau", "distillation stops when the view's loss stops falling", None,
         "not in the library: every repaired view gets distill_iters steps"),
)  # fmt: skip


def verdict(saved_frac: float, change_db: float) -> str:
    """``keep`` or ``off`` for a skip that saves ``saved_frac`` of the wall time (0.2 = 20 %) and
    changes final PSNR by ``change_db`` (negative: the skip costs)."""
    if not (math.isfinite(saved_frac) and math.isfinite(change_db)):
        return "not measured"
    if change_db >= -NOISE_DB:
        return "keep: no error cost" if saved_frac > 0 else "keep: no error cost, no time saved"
    if saved_frac > 0 and -change_db <= DB_PER_TIME * saved_frac:
        return "keep: saves more time than it costs"
    return "off: costs more error than it saves time"


def _get(row: dict[str, Any] | None, key: str) -> float:
    v = (row or {}).get(key)
    return float(v) if isinstance(v, int | float) and math.isfinite(v) else math.nan


def skip_table(
    with_skips: dict[str, Any], without: dict[str, dict[str, Any]], time_key: str = "cpu_s"
) -> list[dict[str, Any]]:
    """One entry per :data:`SKIPS`: the default run's time (``time_key``: CPU seconds of the
    nodes, which other jobs' load barely moves, or wall ``total_s``) against the run with that
    skip off, time saved (s, share), final and delivered PSNR change, the verdict."""
    out = []
    t_on = _get(with_skips, time_key)
    for s in SKIPS:
        row = without.get(s.name)
        t_off = _get(row, time_key)
        saved = t_off - t_on
        frac = saved / t_off if t_off > 0 else math.nan
        d_final = _get(with_skips, "psnr_final") - _get(row, "psnr_final")
        d_output = _get(with_skips, "psnr_output") - _get(row, "psnr_output")
        out.append({
            "skip": s.name, "what": s.what, "off": list(s.off or []), "note": s.note,
            "time": time_key, "time_with_s": t_on, "time_without_s": t_off, "saved_s": saved,
            "saved_frac": frac, "wall_with_s": _get(with_skips, "total_s"),
            "wall_without_s": _get(row, "total_s"),
            "psnr_final_change_db": d_final, "psnr_output_change_db": d_output,
            "verdict": verdict(frac, d_final) if s.off else "not in the library",
        })  # fmt: skip
    return out


def _fmt(v: float, spec: str) -> str:
    return format(v, spec) if math.isfinite(v) else "–"


def to_markdown(table: list[dict[str, Any]]) -> str:
    unit = "CPU s" if table and table[0]["time"] == "cpu_s" else "s"
    lines = [
        f"| skip | turned off by | {unit} with / without | saved | wall s with / without "
        "| final PSNR Δ dB | repair PSNR Δ dB | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in table:
        off = ", ".join(f"`{o}`" for o in e["off"]) or "–"
        saved = (f"{_fmt(e['saved_s'], '.0f')} s ({_fmt(100 * e['saved_frac'], '.0f')} %)"
                 if e["off"] else "–")  # fmt: skip
        lines.append(
            f"| {e['what']} | {off} | {_fmt(e['time_with_s'], '.0f')} / "
            f"{_fmt(e['time_without_s'], '.0f')} | {saved} | {_fmt(e['wall_with_s'], '.0f')} / "
            f"{_fmt(e['wall_without_s'], '.0f')} | "
            f"{_fmt(e['psnr_final_change_db'], '+.2f')} | "
            f"{_fmt(e['psnr_output_change_db'], '+.2f')} | {e['verdict']} |"
        )
    return "\n".join(lines)


__all__ = ["DB_PER_TIME", "NOISE_DB", "SKIPS", "Skip", "skip_table", "to_markdown", "verdict"]
