"""The floor under every repair: GSFixer's output is used only where it measured better than what
the mesh and OpenCV alone give.

Each pixel of a view falls in one *region*, by which map covers it: ``both`` (3DGS alpha >=
``alpha_min`` and the mesh hit a surface), ``gs_only``, ``mesh_only``, ``neither``. Three
*candidates* can fill it: ``fixed`` (GSFixer), ``inpaint`` (mesh fill + OpenCV Telea, see
:mod:`gsfix_online.repair.baselines`), ``mesh_inpaint`` (the mesh render alone, its holes
inpainted by Telea) and ``ref_inpaint`` (the nearest real frames warped into the view by the mesh
depth, :mod:`gsfix_online.repair.ref_warp`, its holes from the mesh render, then Telea; without
references it is ``mesh_inpaint`` exactly, so a measurement that has none never prefers it). On held-out samples, whose real image is known, :func:`accumulate` sums
each candidate's squared error per region (with holes cut into the renders, so that every region
occurs, as it does in novel views); :func:`choose` then picks per region the candidate with the
lowest error, and GSFixer only where it beats the best other one by ``margin``. A region with
too few measured pixels takes the candidate that is best over all pixels. :func:`compose` builds
a view's output from that choice. Pure functions on arrays; no IO.

With ``blend`` a region may also take a *blend* of GSFixer and one fallback,
``w * fixed + (1 - w) * fallback``, with the share ``w`` in [0, 1] that minimises the measured
squared error (exact from two more sums per region and fallback, :class:`RegionErrors`): a hard
choice is the blend with ``w`` 0 or 1, so the blend never measures worse. GSFixer and the
fallbacks err in different ways (the repair smooths, the renders carry pose error and Telea
streaks), and their average is often closer to the truth than either. On 6 procedural scenes no
model trained on (seeds 94-99, 160x128, the packaged base untuned; each scene's choice measured
on its 6 held-out trajectory frames as the repair node measures it), the 48 novel views scored
a mean +1.39 dB over mesh fill + Telea with blends, +0.63 with one candidate per region and
+1.05 with GSFixer alone (benchmarks/results/blend_maps_cpu.json). In the repair graph it was
mixed (benchmarks/results/blend_maps_cpu.md), so the repair node's ``blend`` is off by default.
The share is fitted for that per-pixel mix; :func:`compose` blends with the fallback's colours
only (:func:`blend`, :data:`BLEND_DETAIL_PX`), so that the two fills' shapes never show through
each other.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

REGIONS = ("both", "gs_only", "mesh_only", "neither")
BOTH, GS_ONLY, MESH_ONLY, NEITHER = range(len(REGIONS))
# A region index beside REGIONS: a no-map hole whose surroundings are flat, which takes the
# ``neither`` region's fallback alone (far_regions, FLAT_RING_STD)
FLAT = len(REGIONS)
# The region classes where the mesh render has a surface (what distillation's split may refine)
MESH_SAW = (BOTH, MESH_ONLY)
CANDIDATES = ("fixed", "inpaint", "mesh_inpaint", "ref_inpaint")
FALLBACKS = ("inpaint", "mesh_inpaint", "ref_inpaint")
# Seams where the choice switches blend over a Gaussian of this sigma (compose): on the tank's
# 10 repaired views (40 frames, seed 0) +0.09 dB median PSNR over hard seams, all 10 better;
# wider blends keep gaining (8 px +0.15, 16 px +0.21) by averaging the candidates, not by
# removing seams, so the default stays at seam width (benchmarks/results/feather_cpu.json).
FEATHER_PX = 4.0
# Where a region blends GSFixer into a fallback (far views' no-map parts, FAR_NEITHER_SHARE; or
# ``blend``), the two fills disagree on shapes: Telea streaks the border's colours into facets,
# GSFixer washes the hole with texture, and their per-pixel mean shows both (a double image). A
# blend therefore takes the fallback's colours only, blurred by a Gaussian of this sigma, and its
# shapes from GSFixer alone (blend()). Recomposed from the saved candidates of 3 demo runs and a
# room (benchmarks/bench_seams.py, benchmarks/results/seams_cpu.md), the medians over each run's
# views rose (demo +0.05, +0.01, +0.06 dB, SSIM +0.003 each; the room's 8 blending views +0.06
# dB, +0.001; 29 of 32 views better, the worst -0.02 dB), and the gradient the output keeps on
# Telea's facet edges fell from about 0.6 of Telea's own to 0.36-0.40 (GSFixer alone: 0.42-0.51).
# 16 px removed more facets (0.30-0.35) but blurred the no-map parts further; GSFixer's detail
# at full contrast over both blurred cost SSIM (room -0.006); picking one fill per pixel where
# they differ (GSFixer, Telea, the smoother, or Telea near the border) cost up to 0.8 dB.
BLEND_DETAIL_PX = 8.0


def regions(
    gs_alpha: npt.NDArray[np.floating],  # [H, W] 0..1
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    alpha_min: float = 0.5,
) -> npt.NDArray[np.uint8]:  # [H, W] index into REGIONS
    gs = np.asarray(gs_alpha) >= alpha_min
    mesh = np.asarray(mesh_valid, bool)
    out = np.full(gs.shape, 3, np.uint8)  # neither
    out[gs & mesh] = 0
    out[gs & ~mesh] = 1
    out[~gs & mesh] = 2
    return out


def candidate(
    candidates: dict[str, npt.NDArray[np.uint8]], name: str
) -> npt.NDArray[np.uint8]:  # [H, W, 3]
    """``candidates[name]``; ``ref_inpaint`` absent is ``mesh_inpaint`` (no reference warped)."""
    if name == "ref_inpaint" and name not in candidates:
        name = "mesh_inpaint"
    return np.asarray(candidates[name])


@dataclass
class RegionErrors:
    """Sums of squared error (8-bit levels, over channels) and pixel counts per region."""

    sse: dict[str, dict[str, float]] = field(
        default_factory=lambda: {r: dict.fromkeys(CANDIDATES, 0.0) for r in REGIONS}
    )
    pixels: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REGIONS, 0))
    samples: int = 0
    # For blends of GSFixer with each fallback b: sums of (fixed - b) * (truth - b) and of
    # (fixed - b)^2 (channel means, 8-bit levels); the best share is their ratio
    cross: dict[str, dict[str, float]] = field(
        default_factory=lambda: {r: dict.fromkeys(FALLBACKS, 0.0) for r in REGIONS}
    )
    spread: dict[str, dict[str, float]] = field(
        default_factory=lambda: {r: dict.fromkeys(FALLBACKS, 0.0) for r in REGIONS}
    )

    def combined(self, other: RegionErrors, sign: int = 1) -> RegionErrors:
        """These sums plus ``sign`` times ``other``'s: every field is a sum over samples, so
        ``sign=-1`` takes a measured sample back out (cross-fitting, :func:`held_out_choices`)."""

        def add(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
            return {k: add(v, b[k]) if isinstance(v, dict) else v + sign * b[k]
                    for k, v in a.items()}  # fmt: skip

        return RegionErrors(add(self.sse, other.sse), add(self.pixels, other.pixels),
                            self.samples + sign * other.samples, add(self.cross, other.cross),
                            add(self.spread, other.spread))  # fmt: skip


def accumulate(
    errors: RegionErrors,
    gt: npt.NDArray[np.uint8],  # [H, W, 3]
    candidates: dict[str, npt.NDArray[np.uint8]],  # name -> [H, W, 3], CANDIDATES (candidate())
    region: npt.NDArray[np.uint8],  # [H, W] from regions()
) -> None:
    g = np.asarray(gt, np.float64)
    for ri, r in enumerate(REGIONS):
        sel = region == ri
        n = int(sel.sum())
        if n == 0:
            continue
        errors.pixels[r] += n
        for c in CANDIDATES:
            d = candidate(candidates, c).astype(np.float64)[sel] - g[sel]
            errors.sse[r][c] += float(np.mean(d * d, axis=-1).sum())
        fixed = np.asarray(candidates["fixed"], np.float64)[sel]
        for b in FALLBACKS:
            base = candidate(candidates, b).astype(np.float64)[sel]
            d, e = fixed - base, g[sel] - base
            errors.cross[r][b] += float(np.mean(d * e, axis=-1).sum())
            errors.spread[r][b] += float(np.mean(d * d, axis=-1).sum())
    errors.samples += 1


def blend_share(cross: float, spread: float) -> float:
    """GSFixer's share in ``w * fixed + (1 - w) * fallback`` with the least squared error,
    clamped to [0, 1] (0 where GSFixer and the fallback agree everywhere)."""
    return float(np.clip(cross / spread, 0.0, 1.0)) if spread > 0 else 0.0


@dataclass(frozen=True)
class Choice:
    """Which candidate fills each region, and the errors it was chosen by."""

    per_region: dict[str, str]  # "fixed" or the fallback the region's output comes from
    mse: dict[str, dict[str, float]]  # region -> candidate -> mean squared error (NaN: unseen)
    pixels: dict[str, int]
    samples: int
    why: str
    # GSFixer's share where a region blends it into its fallback (absent: 0; "fixed": 1)
    share: dict[str, float] = field(default_factory=dict)
    # region (and "all", every measured pixel) -> fallback -> the least-squares share measured
    fit: dict[str, dict[str, float]] = field(default_factory=dict)
    # the choice the same measurement makes without blends (recorded to compare; {}: as chosen)
    hard: dict[str, str] = field(default_factory=dict)

    def hardened(self) -> Choice:
        """This measurement's choice without blends."""
        return dataclasses.replace(self, per_region=dict(self.hard or self.per_region), share={})

    def source(self, region: str) -> tuple[str, float]:
        """Where a region's output comes from: (candidate, GSFixer's share in it)."""
        c = self.per_region[region]
        return (c, 1.0) if c == "fixed" else (c, float(self.share.get(region, 0.0)))

    def describe(self) -> dict[str, str]:
        """Per region, its source in words: ``fixed``, a fallback, or ``0.45 fixed + inpaint``."""
        out = {}
        for r in self.per_region:
            c, w = self.source(r)
            out[r] = c if c == "fixed" or w == 0.0 else f"{w:.2f} fixed + {c}"
        return out

    @property
    def uses_fixer(self) -> bool:
        return any(self.source(r)[1] > 0.0 for r in self.per_region)

    def overall_best(self, margin: float = 0.02) -> str | None:
        """The candidate with the lowest error over all measured pixels, by :func:`choose`'s
        rule (GSFixer only with ``margin``); None when nothing was measured."""
        sse = dict.fromkeys(CANDIDATES, 0.0)
        for r in REGIONS:
            n = self.pixels.get(r, 0)
            m = self.mse.get(r, {})
            if "mesh_inpaint" in m:  # measured without references: their warp is the mesh's
                m = {"ref_inpaint": m["mesh_inpaint"], **m}
            if n and all(np.isfinite(m.get(c, np.nan)) for c in CANDIDATES):
                for c in CANDIDATES:
                    sse[c] += m[c] * n
        return _pick(sse, margin) if any(sse.values()) else None

    def without_fixer(self) -> Choice:
        """The choice for a view GSFixer did not run on (the planner skipped it): its regions
        take the fallback the same measurement found better there (mesh fill + Telea where it
        measured neither), the others keep theirs. On tank:drift seed 1 the measurement gave
        GSFixer the parts no map covers, where mesh + Telea had the lower error (3,362 against
        4,222); a skipped held-out frame's such part went from 11.2 to 12.5 dB."""

        def next_best(r: str) -> str:  # unmeasured counts as worst; a tie keeps inpaint
            m = self.mse.get(r, {})
            return min(FALLBACKS, key=lambda c: m[c] if np.isfinite(m.get(c, np.nan)) else np.inf)

        def drop(choice: dict[str, str]) -> dict[str, str]:
            return {r: (next_best(r) if c == "fixed" else c) for r, c in choice.items()}

        return Choice(drop(self.per_region), self.mse, self.pixels, self.samples, self.why, {},
                      self.fit, drop(self.hard))  # fmt: skip

    def to_json(self) -> str:
        def nums(m: dict[str, float]) -> dict[str, float | None]:
            return {k: (None if np.isnan(v) else v) for k, v in m.items()}

        return json.dumps(
            {
                "per_region": self.per_region,
                "share": self.share,
                "mse": {r: nums(m) for r, m in self.mse.items()},
                "fit": {r: nums(m) for r, m in self.fit.items()},
                "hard": self.hard,
                "pixels": self.pixels,
                "samples": self.samples,
                "why": self.why,
            }  # fmt: skip
        )

    @classmethod
    def from_json(cls, text: str) -> Choice:  # also a run's record from before blends
        d = json.loads(text)

        def nums(m: dict[str, float | None]) -> dict[str, float]:
            out = {k: (np.nan if v is None else float(v)) for k, v in m.items()}
            if "mesh_inpaint" in out:  # a record from before references: their warp is none
                out.setdefault("ref_inpaint", out["mesh_inpaint"])
            return out

        return cls(
            dict(d["per_region"]), {r: nums(m) for r, m in d["mse"].items()}, dict(d["pixels"]),
            int(d["samples"]), d["why"], {r: float(w) for r, w in d.get("share", {}).items()},
            {r: nums(m) for r, m in d.get("fit", {}).items()}, dict(d.get("hard", {})),
        )  # fmt: skip


def fixer_only(why: str = "no held-out measurement") -> Choice:
    """GSFixer everywhere (what the system did before it measured anything)."""
    nan = {r: dict.fromkeys(CANDIDATES, float("nan")) for r in REGIONS}
    return Choice(dict.fromkeys(REGIONS, "fixed"), nan, dict.fromkeys(REGIONS, 0), 0, why)


def _pick(sse: dict[str, float], margin: float) -> str:
    best_fb = min(FALLBACKS, key=lambda c: sse[c])
    return "fixed" if sse["fixed"] < (1 - margin) * sse[best_fb] else best_fb


def _pick_blend(
    sse: dict[str, float],  # candidate -> summed squared error over some pixels
    cross: dict[str, float],  # fallback -> RegionErrors.cross over the same pixels
    spread: dict[str, float],
    margin: float,
) -> tuple[str, float]:  # (candidate, GSFixer's share)
    """The best blend of GSFixer with one fallback; GSFixer takes a share only if that cuts
    the error below ``(1 - margin)`` times the best fallback's alone."""
    best_fb = min(FALLBACKS, key=lambda c: sse[c])
    err, b, w = min(
        (sse[b] - 2.0 * w * cross[b] + w * w * spread[b], b, w)
        for b in FALLBACKS
        for w in [blend_share(cross[b], spread[b])]
    )
    if w == 0.0 or err >= (1 - margin) * sse[best_fb]:
        return best_fb, 0.0
    return ("fixed", 1.0) if w == 1.0 else (b, round(w, 3))


def choose(
    errors: RegionErrors,
    min_pixels: int = 500,
    margin: float = 0.02,
    min_fraction: float = 0.0,
    backup: RegionErrors | None = None,
    blend: bool = False,
) -> Choice:
    """Per region, the candidate with the lowest error; GSFixer only if its error is below
    ``(1 - margin)`` times the best fallback's (a tie goes to the fallback: it is free). With
    ``blend``, the blend of GSFixer and one fallback with the lowest error, by the same rule.

    A region is measured when it holds at least ``min_pixels`` and ``min_fraction`` of all the
    measured pixels. One that is not takes its choice from ``backup`` (another measurement, e.g.
    with holes cut into the renders, where every region occurs) when that measured it, else the
    candidate that is best over all pixels. ``fit`` records each measured region's best share
    against each fallback (and over all pixels, ``all``) for :func:`for_view`."""
    mse = {
        r: {
            c: (errors.sse[r][c] / errors.pixels[r] if errors.pixels[r] else float("nan"))
            for c in CANDIDATES
        }
        for r in REGIONS
    }
    total = sum(errors.pixels.values())
    enough = max(min_pixels, min_fraction * total)

    def pick(e: RegionErrors, regs: tuple[str, ...], blend: bool = blend) -> tuple[str, float]:
        sse = {c: sum(e.sse[r][c] for r in regs) for c in CANDIDATES}
        if not blend:
            c = _pick(sse, margin)
            return c, 1.0 if c == "fixed" else 0.0
        cross = {b: sum(e.cross[r][b] for r in regs) for b in FALLBACKS}
        spread = {b: sum(e.spread[r][b] for r in regs) for b in FALLBACKS}
        return _pick_blend(sse, cross, spread, margin)

    def fit(e: RegionErrors, regs: tuple[str, ...]) -> dict[str, float]:
        return {b: round(blend_share(sum(e.cross[r][b] for r in regs),
                                     sum(e.spread[r][b] for r in regs)), 3)
                for b in FALLBACKS}  # fmt: skip

    overall, overall_hard = pick(errors, REGIONS), pick(errors, REGIONS, False)[0]
    picked, fits, hard, notes = {}, {"all": fit(errors, REGIONS)}, {}, []
    for r in REGIONS:
        if errors.pixels[r] >= enough:
            picked[r], fits[r] = pick(errors, (r,)), fit(errors, (r,))
            hard[r] = pick(errors, (r,), False)[0]
        elif backup is not None and backup.pixels[r] >= min_pixels:
            picked[r], fits[r] = pick(backup, (r,)), fit(backup, (r,))
            hard[r] = pick(backup, (r,), False)[0]
            notes.append(f"{r}: {errors.pixels[r]} px measured, takes the backup measurement's "
                         f"({backup.pixels[r]} px)")  # fmt: skip
        else:
            picked[r], hard[r] = overall, overall_hard
            notes.append(f"{r}: {errors.pixels[r]} px measured, takes the overall best")
    per_region = {r: c for r, (c, _) in picked.items()}
    share = {r: w for r, (c, w) in picked.items() if c != "fixed" and w > 0.0}
    best = overall[0] if overall[1] in (0.0, 1.0) else f"{overall[1]:.2f} fixed + {overall[0]}"
    why = (f"{errors.samples} held-out samples, {total} px; overall best {best}"
           + ("; " + "; ".join(notes) if notes else ""))  # fmt: skip
    return Choice(per_region, mse, dict(errors.pixels), errors.samples, why, share, fits, hard)


# Beyond the held-out frames' reach, which candidate fills each region (fallback.for_view): the
# mesh render wherever the mesh covers the view, the 3DGS render where only it does (unless
# far_regions makes that a hole, FAR_GS_ONLY_HOLES), and where neither map does, GSFixer and
# the mesh render's Telea fill half and half (FAR_NEITHER_SHARE).
MESH_FIRST = {"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "mesh_inpaint"}
# GSFixer's share where neither map covers a view beyond every measurement, blended into mesh +
# Telea. There no measurement the run has predicts which fill is nearer the truth: at threshold
# 1 on tank:drift seed 1 and room:real seed 3 (40 frames, --holdout 10; pooled over the 8 novel
# views' no-map pixels, median over 4 fine-tuning seeds, benchmarks/bench_fixer_seeds.py) mesh
# + Telea was better on the tank (14.06 against GSFixer's 13.62 dB) and GSFixer on the room
# (15.27 against 13.29); the held-out frames with the views' holes cut in chose the other one
# on both, the trainer's overall best (mesh + Telea on both) on the tank only. Half and half
# scored 14.44 and 14.98 there, and the runs' novel views gained over the rule before (the
# trainer's overall best): tank 16.80 -> 16.96 dB, SSIM 0.502 -> 0.504; room 15.17 -> 15.97
# dB, 0.557 -> 0.566 (benchmarks/results/reach_far_neither_cpu.json). The two fills err
# differently (Telea streaks the border's colours across the hole, GSFixer washes it with the
# scene's colours), so where both guess their average is nearer than either.
FAR_NEITHER_SHARE = 0.5
# Except where the hole's surroundings are flat: where the output around a no-map hole of a far
# view varies by under this standard deviation of luma (8-bit levels, over a ring FEATHER_PX
# wide outside the hole; flat_holes), the hole is most likely that flat surface going on (a
# wall, a ceiling), which Telea's smooth continuation of the border draws nearly exactly and
# GSFixer's wash does not. Such a hole (FLAT) takes mesh + Telea alone. On a room nobody had
# tuned on (scene seed 2) views 000 and 006 had such holes (mesh + Telea 33.5 and 33.0 dB
# there, the half-and-half output 24.0 and 26.2); recomposed, the mean over its 8 views rose
# 0.45 dB, and the demo, tank seed 1 and the room's seed 1 (3 fine-tuning seeds each) changed
# by -0.008 to +0.010 dB. 4 levels caught none of that room's holes, 6 to 10 the same ones
# (the luma std over the ring measured on the run's own output;
# benchmarks/results/far_regions_cpu.md).
FLAT_RING_STD = 6.0
# Which pixels of a far view that only the 3DGS map covers are holes no map covers, repaired as
# such (far_regions), and not the 3DGS render: "grown" (the default), those whose render repaired
# views' Gaussians make (provenance gs_repaired: another view's invention, e.g. a pale grid over a
# plain ceiling; the view fits its own repair there); "all" (the map's edges and floaters too:
# a dark seam along the mesh's border; the map keeps what its keyframes observed there); "none".
# Recomposed from 13 runs' saved candidates (with FLAT holes), the far views' mean PSNR changed
# with "all" by -0.07 to +0.09 dB on the demo's 3 fine-tuning seeds, -0.03 to +0.07 on tank
# seed 1's, +0.14 to +0.28 on the room's, and on inputs nobody tuned on by +0.12 (tank seed 3)
# and +0.20, +1.08, +1.42 (rooms 3, 2, 4); SSIM rose in all 13. But in the repair graph "all"
# cost tank seed 1's final map 0.03-0.26 dB (3 fine-tuning seeds, 17.62 -> 17.41 in the
# median) for +0.01 dB of output; "grown" gained on the three untuned inputs it ran on (rooms 2
# and 3, tank 3: final map +0.62, +0.43, +0.05 dB; output +0.69, +0.47, +0.06)
# (benchmarks/results/far_regions_cpu.md).
FAR_GS_ONLY_HOLES = "grown"


@dataclass(frozen=True)
class HeldOutChoices:
    """A choice measured on held-out frames, and per frame the choice measured without it."""

    all: Choice  # from every held-out frame: for the views to repair
    without: dict[int, Choice | None]  # frame id -> from the other frames (None: a lone frame)


def held_out_choices(
    each: list[RegionErrors],  # measure_each's, one per held-out frame
    ids: list[int],  # the frames' ids, in the same order
    backup_each: list[RegionErrors] | None = None,  # the same frames with holes cut in
    **kw: Any,  # choose()'s
) -> HeldOutChoices:
    """The choice measured on every held-out frame, and for each frame the choice measured on
    the *other* frames: a frame that is scored must not have chosen its own candidates
    (cross-fitting), or the choice reads its truth."""

    if len(ids) != len(each):
        raise ValueError(f"{len(ids)} ids for {len(each)} measured frames")

    def total(es: list[RegionErrors]) -> RegionErrors:
        out = RegionErrors()
        for e in es:
            out = out.combined(e)
        return out

    errors = total(each)
    backup = None if backup_each is None else total(backup_each)
    full = choose(errors, backup=backup, **kw)
    if len(each) < 2:
        return HeldOutChoices(full, dict.fromkeys(ids))
    without = {
        f: choose(errors.combined(each[i], -1),
                  backup=None if backup is None else backup.combined(backup_each[i], -1), **kw)  # type: ignore[index]
        for i, f in enumerate(ids)
    }  # fmt: skip
    return HeldOutChoices(full, without)


def for_view(
    distance_m: float | None,  # the view's keyframe distance (planner.keyframe_distance)
    near: Choice | None,  # measured at the held-out input frames; None without them
    reach_m: float | None,  # the farthest held-out frame's keyframe distance
    trainer: Choice,  # measured by the trainer on its held-out samples
    blend: bool = False,
    neither_share: float = FAR_NEITHER_SHARE,  # GSFixer's, where neither map covers a far view
) -> tuple[Choice, str]:
    """The choice a view follows, and where it comes from.

    A measurement holds for views like the ones it was made on. The held-out input frames lie
    on the trajectory; a view as near the keyframes as the farthest of them (``reach_m``) takes
    their choice per region (``"held-out frames"``). A view farther away (the planner's views
    are often metres off the trajectory), or any view when no frame was held out, is beyond
    every measurement the run has, and takes the mesh first (``"mesh first"``,
    :data:`MESH_FIRST`): a 3DGS map fitted from the trajectory's own views renders worse the
    farther a view is from them, while the TSDF mesh fuses every frame into one surface and
    colour. At such views (1.2-3.8 m off, 9 runs: two scene families, five degradations, two
    seeds) the mesh beat the 3DGS render where both cover in 8 of 9, by up to 4.5 dB (the
    room's seed 0 lost 0.33); GSFixer was best where neither covers in 8 of 9. Recomposed on
    those runs, the views gained a median 0.32 dB over the trainer's single best candidate
    (the rule before; all 9 better), and a median 0.31 dB on three demo runs
    (benchmarks/results/reach_mesh_first_cpu.json). Where neither map covers, GSFixer and mesh
    + Telea fill with ``neither_share`` and 1 - ``neither_share`` (:data:`FAR_NEITHER_SHARE`; 1:
    GSFixer alone, 0: mesh + Telea alone). Without a trainer measurement the held-out choice,
    or else the trainer's, applies as it is. With ``blend``, a far view's regions blend GSFixer
    into those fallbacks by the shares the trainer fitted for them (``Choice.fit``; over all its
    pixels for a region it did not measure), and where neither map covers it takes the
    trainer's choice for that region (measured with holes cut in)."""
    best = trainer.overall_best()
    unknown = distance_m is None or reach_m is None  # no keyframe yet: nothing says it is far
    if near is not None and (best is None or unknown or distance_m <= reach_m):  # type: ignore[operator]
        return near, "held-out frames"
    if best is None:
        return trainer, "trainer"
    far = "" if distance_m is None else f" at {distance_m:.2f} m"
    lim = "no held-out frames" if near is None else f"held-out frames reach {reach_m or 0:.2f} m"
    per: dict[str, str] = dict(MESH_FIRST)
    share: dict[str, float] = {}
    if not blend:
        per["neither"] = "fixed" if neither_share >= 1.0 else "mesh_inpaint"
        if 0.0 < neither_share < 1.0:
            share["neither"] = neither_share
        rule = f"GSFixer {neither_share:g} + mesh + Telea {1 - neither_share:g}"
    else:
        per["neither"] = best
        for r, b in MESH_FIRST.items():
            w = trainer.fit.get(r, trainer.fit.get("all", {})).get(b, float("nan"))
            if np.isfinite(w) and w >= 1.0:
                per[r] = "fixed"
            elif np.isfinite(w) and w > 0.0:
                share[r] = w
        if "neither" in trainer.fit:
            c, w = trainer.source("neither")
            per["neither"] = c
            if c != "fixed" and w > 0.0:
                share["neither"] = w
        rule = f"the trainer's {'choice' if 'neither' in trainer.fit else 'overall best'}"
    what = Choice(per, trainer.mse, trainer.pixels, trainer.samples, "", share).describe()
    why = (f"view{far}, {lim}: the mesh where it covers, else the 3DGS render where "
           f"far_regions keeps it, else {rule} "
           f"({', '.join(f'{r}={c}' for r, c in what.items())}; {trainer.why})")  # fmt: skip
    return Choice(per, trainer.mse, trainer.pixels, trainer.samples, why, share, trainer.fit,
                  {**MESH_FIRST, "neither": best}), "mesh first"  # fmt: skip


def lowpass(
    img: npt.NDArray[np.floating],  # [H, W] or [H, W, C]
    sigma_px: float,  # 0: the image as it is
) -> npt.NDArray[np.float32]:  # same shape
    """A Gaussian blur of ``sigma_px`` (edges replicated): the colours a blend takes from its
    fallback (:func:`blend`)."""
    out = np.asarray(img, np.float32)
    if sigma_px <= 0:
        return out
    import cv2

    return cv2.GaussianBlur(out, (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)


def blend(
    fixed: npt.NDArray[np.uint8],  # [H, W, 3] GSFixer's output
    fallback: npt.NDArray[np.uint8],  # [H, W, 3]
    share: float,  # GSFixer's, in [0, 1]
    detail_px: float = BLEND_DETAIL_PX,  # 0: the per-pixel mean of the two
) -> npt.NDArray[np.uint8]:  # [H, W, 3]
    """GSFixer blended into a fallback without a double image, ``share * fixed + (1 - share) *
    lowpass(fallback)``: the fallback gives its colours (below a Gaussian of ``detail_px``),
    never its edges. Where the two agree but for smooth changes of colour this is their mean;
    where they disagree on a shape (an edge or facet only one of them has) the output has
    GSFixer's shape only, in the blend's colour (BLEND_DETAIL_PX)."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"share must be in [0, 1], got {share}")
    mix = share * np.asarray(fixed, np.float32)
    mix += (1.0 - share) * lowpass(np.asarray(fallback, np.float32), detail_px)
    return np.clip(np.rint(mix), 0, 255).astype(np.uint8)


def flat_holes(
    region: npt.NDArray[np.uint8],  # [H, W] from regions()
    around: npt.NDArray[np.uint8],  # [H, W, 3] the view as composed, seams feathered
    max_std: float = FLAT_RING_STD,  # 8-bit levels; 0: no hole is flat
    ring_px: int = round(FEATHER_PX),
) -> npt.NDArray[np.bool_]:  # [H, W]
    """The pixels of the holes no map covers (``neither``, each connected part on its own)
    whose surroundings are flat: the luma of ``around`` varies by under ``max_std`` (standard
    deviation) over the covered pixels within ``ring_px`` of the hole (:data:`FLAT_RING_STD`).
    ``around`` is the output with its seams feathered: the raw mesh render's ragged border
    would make every hole look textured. A hole with no covered pixel around it is not flat
    (nothing says what goes on there)."""
    import cv2

    region = np.asarray(region)
    out = np.zeros(region.shape, bool)
    if max_std <= 0:
        return out
    holes = (region == NEITHER).astype(np.uint8)
    n, label, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=8)
    luma = np.asarray(around, np.float32) @ np.float32([0.299, 0.587, 0.114])
    kernel = np.ones((2 * ring_px + 1, 2 * ring_px + 1), np.uint8)
    covered = region != NEITHER
    H, W = region.shape
    for k in range(1, n):  # each hole within its bounding box widened by the ring
        x, y, w, h = stats[k, :4]
        box = (slice(max(y - ring_px, 0), min(y + h + ring_px, H)),
               slice(max(x - ring_px, 0), min(x + w + ring_px, W)))  # fmt: skip
        hole = label[box] == k
        ring = (cv2.dilate(hole.astype(np.uint8), kernel) > 0) & covered[box]
        if ring.sum() >= 2 and float(luma[box][ring].std()) < max_std:
            out[box] |= hole
    return out


def far_regions(
    region: npt.NDArray[np.uint8],  # [H, W] from regions()
    candidates: dict[str, npt.NDArray[np.uint8]],  # compose's
    choice: Choice,  # the far view's (for_view's "mesh first")
    feather_px: float = FEATHER_PX,
    max_std: float = FLAT_RING_STD,  # flat_holes'; 0: no hole is flat
    holes: npt.NDArray[np.bool_] | None = None,  # [H, W] 3DGS-only pixels to repair as holes
) -> npt.NDArray[np.uint8]:  # [H, W] index into REGIONS, or FLAT
    """The regions a view beyond every measurement is composed by (:func:`compose`): the
    3DGS-only pixels in ``holes``, holes no map covers (:data:`FAR_GS_ONLY_HOLES`); a hole
    whose surroundings are flat, :data:`FLAT` (:data:`FLAT_RING_STD`)."""
    out = np.array(region, np.uint8, copy=True)
    if holes is not None:
        out[(out == GS_ONLY) & np.asarray(holes, bool)] = NEITHER
    if max_std > 0 and choice.source("neither")[1] > 0.0 and (out == NEITHER).any():
        around = compose(candidates, out, choice, feather_px)
        out[flat_holes(out, around, max_std)] = FLAT
    return out


def region_sources(
    region: npt.NDArray[np.uint8],  # [H, W] index into REGIONS, or FLAT
    choice: Choice,
) -> list[tuple[str, float]]:
    """Each region's source (candidate, GSFixer's share) that compose and provenance draw
    from, by region index; with :data:`FLAT` pixels in ``region`` a fifth: the ``neither``
    region's fallback alone (mesh + Telea where that region is GSFixer's alone)."""
    chosen = [choice.source(r) for r in REGIONS]
    if not np.any(np.asarray(region) == FLAT):
        return chosen
    name = chosen[NEITHER][0]
    return [*chosen, ("mesh_inpaint" if name == "fixed" else name, 0.0)]


def compose(
    candidates: dict[str, npt.NDArray[np.uint8]],  # name -> [H, W, 3]
    region: npt.NDArray[np.uint8],  # [H, W] index into REGIONS, or FLAT (far_regions)
    choice: Choice,
    feather_px: float = 0.0,  # sigma of the blend across region borders, px; 0 = hard seams
    detail_px: float = BLEND_DETAIL_PX,  # a blend's fallback blurred by it (blend); 0: the mean
) -> npt.NDArray[np.uint8]:  # [H, W, 3]
    """The view from the source each region chose (a candidate, or GSFixer blended into a
    fallback by its share, :func:`blend`). With ``feather_px`` > 0 each source's weight is its
    indicator blurred by a Gaussian of that sigma (renormalised), so the seams where the choice
    switches blend over a few pixels instead of stepping. :data:`FLAT` holes take the
    ``neither`` region's fallback without GSFixer."""
    chosen = region_sources(region, choice)
    sources: dict[tuple[str, float], npt.NDArray[np.uint8]] = {}
    for name, w in chosen:
        if (name, w) in sources:
            continue
        if name == "fixed" or w == 0.0:
            sources[name, w] = candidate(candidates, name)
        else:
            sources[name, w] = blend(candidates["fixed"], candidate(candidates, name), w, detail_px)
    if feather_px <= 0 or len(sources) == 1:
        out = np.array(sources[chosen[0]], copy=True)
        for ri, key in enumerate(chosen[1:], 1):
            sel = region == ri
            if sel.any():
                out[sel] = sources[key][sel]
        return out
    keys = sorted(sources)
    index = np.array([keys.index(c) for c in chosen], np.uint8)
    weights = region_weights(np.asarray(region), len(keys), index, feather_px)
    acc = np.zeros(sources[keys[0]].shape, np.float32)
    for w, key in zip(weights, keys, strict=True):
        acc += w[..., None] * np.asarray(sources[key], np.float32)
    return np.clip(np.rint(acc), 0, 255).astype(np.uint8)


def region_weights(
    region: npt.NDArray[np.uint8],  # [H, W] index into REGIONS
    n_sources: int,  # the distinct sources a composition draws from
    index: npt.NDArray[np.uint8],  # [regions] each region's source, in [0, n_sources)
    feather_px: float,  # sigma of the blend across region borders, px; 0 = hard seams
) -> npt.NDArray[np.float32]:  # [n_sources, H, W], sums to 1 per pixel
    """Each source's weight per pixel in :func:`compose`: its regions' indicator, blurred by a
    Gaussian of ``feather_px`` and renormalised when ``feather_px`` > 0."""
    per_pixel = index[region]
    out = np.stack([(per_pixel == k).astype(np.float32) for k in range(n_sources)])
    if feather_px <= 0 or n_sources == 1:
        return out
    import cv2

    for k in range(n_sources):
        out[k] = cv2.GaussianBlur(out[k], (0, 0), feather_px, borderType=cv2.BORDER_REPLICATE)
    return out / np.maximum(out.sum(axis=0), 1e-6)


def replaced(
    region: npt.NDArray[np.uint8],  # [H, W] from regions() (or far_regions)
    choice: Choice,
) -> npt.NDArray[np.bool_]:  # [H, W]
    """Pixels of the regions the 3DGS map covers (``both``, ``gs_only``) whose composed output
    is not its render: the region chose GSFixer (or a share of it) or the mesh alone
    (``inpaint`` is the 3DGS render there). The 3DGS-only pixels far_regions makes holes are
    not among them: the map keeps what its keyframes observed there."""
    out = np.zeros(np.shape(region), bool)
    for ri, r in enumerate(REGIONS[:2]):
        if choice.source(r) != ("inpaint", 0.0):
            out |= np.asarray(region) == ri
    return out


def baseline_candidates(
    gs: npt.NDArray[np.uint8],  # [H, W, 3] 3DGS render
    gs_alpha: npt.NDArray[np.floating],  # [H, W]
    mesh: npt.NDArray[np.uint8],  # [H, W, 3] mesh render
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    alpha_min: float = 0.5,
    ref: npt.NDArray[np.uint8] | None = None,  # [H, W, 3] the reference warp (ref_warp.ref_warp)
    ref_valid: npt.NDArray[np.bool_] | None = None,  # [H, W] its pixels; None: no warp
) -> dict[str, npt.NDArray[np.uint8]]:
    """The fallbacks of a view: ``inpaint``, ``mesh_inpaint`` and ``ref_inpaint`` (the warp
    over the mesh render, Telea in the rest; ``mesh_inpaint`` itself without a warp)."""
    from gsfix_online.repair.baselines import inpaint_telea, mesh_fill

    alpha = np.asarray(gs_alpha, np.float32)
    valid = np.asarray(mesh_valid, bool)
    fill = mesh_fill(gs, alpha, mesh, valid, alpha_min)
    out = {
        "inpaint": inpaint_telea(fill.image, fill.missing),
        "mesh_inpaint": inpaint_telea(mesh, ~valid),
    }
    if ref is None or ref_valid is None or not np.any(ref_valid):
        out["ref_inpaint"] = out["mesh_inpaint"]
    else:
        out["ref_inpaint"] = ref_inpaint(mesh, valid, ref, ref_valid, gs, alpha, alpha_min)
    return out


def ref_inpaint(
    mesh: npt.NDArray[np.uint8],  # [H, W, 3] mesh render
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    ref: npt.NDArray[np.uint8],  # [H, W, 3] the reference warp
    ref_valid: npt.NDArray[np.bool_],  # [H, W] its pixels
    gs: npt.NDArray[np.uint8] | None = None,  # [H, W, 3] 3DGS render; None: the mesh's only
    gs_alpha: npt.NDArray[np.floating] | None = None,  # [H, W]
    alpha_min: float = 0.5,
) -> npt.NDArray[np.uint8]:  # [H, W, 3]
    """The fallback ``ref_inpaint``: the reference warp where it has pixels; in its holes on
    the mesh's surface mesh fill (the 3DGS render where it covers, else the mesh render); and
    OpenCV Telea from the warp around where the mesh has no surface.

    In the warp's holes on a surface (occlusions, frames that do not reach the border) the 3DGS
    render beat the mesh render by 0.4-1.6 dB in that region, and where the mesh has none, Telea
    from the warp beat the 3DGS render by 3.4-5.3 dB (benchmarks/results/ref_warp_cpu.md). Over
    the 12 held-out frames of two room:real runs the 3DGS render in those holes gained a mean
    0.80 and 0.67 dB over the mesh render, 8 of 12 frames better in each
    (benchmarks/results/ref_candidate_graph_cpu.md)."""
    from gsfix_online.repair.baselines import inpaint_telea

    seen = np.asarray(ref_valid, bool)
    surface = np.asarray(mesh_valid, bool)
    under = np.asarray(mesh)
    if gs is not None and gs_alpha is not None:
        covered = surface & (np.asarray(gs_alpha) >= alpha_min)
        under = np.where(covered[..., None], np.asarray(gs), under)
    under = np.where(seen[..., None], np.asarray(ref), under)
    return inpaint_telea(under, ~seen & ~surface)


@dataclass(frozen=True)
class HeldOutSample:
    """A held-out frame with both renders at its pose."""

    gt: npt.NDArray[np.uint8]  # [H, W, 3] the camera image
    gs: npt.NDArray[np.uint8]  # [H, W, 3]
    gs_alpha: npt.NDArray[np.float32]  # [H, W]
    mesh: npt.NDArray[np.uint8]  # [H, W, 3]
    mesh_valid: npt.NDArray[np.bool_]  # [H, W]
    ref: npt.NDArray[np.uint8] | None = None  # [H, W, 3] the reference warp; None: no warp
    ref_valid: npt.NDArray[np.bool_] | None = None  # [H, W]


def measure(
    samples: list[HeldOutSample],
    repair_fn: object,  # (gs [H, W, 3] uint8, mesh [H, W, 3] uint8) -> [H, W, 3] uint8
    hole_masks: object | None,  # (rng, height, width) -> bool [H, W]; None: cuts == ("none",)
    seed: int = 0,
    alpha_min: float = 0.5,
    cuts: tuple[str, ...] = ("none", "both", "gs", "mesh"),
    with_ref: bool = False,  # repair_fn takes (gs, mesh, ref, ref_valid): mode mesh+gs+ref
) -> RegionErrors:
    """Each sample as it is (``none``), then with a hole cut into both renders (``both``: a
    ``neither`` region), into the 3DGS render (``gs``: ``mesh_only``) and into the mesh render
    (``mesh``: ``gs_only``), as ``cuts`` lists; every candidate scored. With ``with_ref`` GSFixer
    gets the sample's reference warp too (None without one), cut where the mesh is. The sum of
    :func:`measure_each`."""
    total = RegionErrors()
    for e in measure_each(samples, repair_fn, hole_masks, seed, alpha_min, cuts, with_ref):
        total = total.combined(e)
    return total


def measure_each(
    samples: list[HeldOutSample],
    repair_fn: object,
    hole_masks: object | None,
    seed: int = 0,
    alpha_min: float = 0.5,
    cuts: tuple[str, ...] = ("none", "both", "gs", "mesh"),
    with_ref: bool = False,
) -> list[RegionErrors]:
    """:func:`measure` per sample, in order (one random stream over all samples, as
    :func:`measure` cuts its holes)."""
    if hole_masks is None and any(c != "none" for c in cuts):
        raise ValueError(f"cuts {cuts} need hole_masks")
    rng = np.random.default_rng(seed)
    out = []
    for s in samples:
        errors = RegionErrors()
        out.append(errors)
        h, w = s.gt.shape[:2]
        for cut in cuts:
            gs, alpha = s.gs.copy(), np.asarray(s.gs_alpha, np.float32).copy()
            mesh, valid = s.mesh.copy(), np.asarray(s.mesh_valid, bool).copy()
            ref_valid = None if s.ref_valid is None else np.asarray(s.ref_valid, bool).copy()
            if cut != "none":
                m = hole_masks(rng, h, w)  # type: ignore[operator]
                if cut in ("both", "gs"):
                    gs[m], alpha[m] = 0, 0.0
                if cut in ("both", "mesh"):
                    mesh[m], valid[m] = 0, False
                    if ref_valid is not None:  # the warp follows the mesh's depth
                        ref_valid[m] = False
            cands = baseline_candidates(gs, alpha, mesh, valid, alpha_min, s.ref, ref_valid)
            args = (gs, mesh, s.ref, ref_valid) if with_ref else (gs, mesh)
            cands["fixed"] = repair_fn(*args)  # type: ignore[operator]
            accumulate(errors, s.gt, cands, regions(alpha, valid, alpha_min))
        errors.samples = 1  # a frame, not the variants of it
    return out
