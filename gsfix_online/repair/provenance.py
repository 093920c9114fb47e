"""Where each pixel of a delivered view came from: observed by a map, or synthesised.

An output view is composed per region class (:func:`.fallback.compose`) from candidates that
are themselves mixtures: ``inpaint`` is the 3DGS render where the Gaussian map covers the pixel,
the mesh render where only the mesh does, and OpenCV Telea elsewhere; ``mesh_inpaint`` is the
mesh render where it hit a surface, Telea elsewhere; ``ref_inpaint`` is the nearest real frames
warped into the view where they see it (observed: the robot filmed that surface), else mesh
fill on the mesh's surface and Telea elsewhere; ``fixed`` is GSFixer everywhere. This module
splits an output into the weights of its atomic :data:`SOURCES` per pixel, with the same seam
feathering as the composition, so that an inspector can tell a rust patch the robot filmed
(a map's render where that map covered the pixel: *observed*) from a wall colour GSFixer or a
classical fill invented (*synthesised*). Pure functions on arrays; the run folder writes the
result (:mod:`.outputs`: ``views/NNN/provenance.png`` and ``provenance.npz``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from gsfix_online.repair.fallback import (
    BLEND_DETAIL_PX,
    Choice,
    lowpass,
    region_sources,
    region_weights,
)

# Atomic sources, in the order of the index written per pixel (``ref`` came last, so that the
# indices of runs written before it still read the same)
SOURCES = ("gs", "mesh", "fixer", "fill", "none", "ref", "gs_repaired")
GS, MESH, FIXER, FILL, NONE, REF, GS_REPAIRED = range(len(SOURCES))
# GSFixer's output, classical fills of holes, and the 3DGS render where Gaussians that
# distillation grew from other repaired views make it (the map's fill of a hole, not observed)
SYNTHESISED = (FIXER, FILL, GS_REPAIRED)
# a 3DGS render's pixel is theirs when they make this much of its colour or more
GS_REPAIRED_SHARE = 0.5
LABELS = {
    "gs": "3DGS render (observed)",
    "mesh": "mesh render (observed)",
    "fixer": "GSFixer (synthesised)",
    "fill": "classical fill (synthesised)",
    "none": "nothing (no map, no fill)",
    "ref": "real frames warped (observed)",
    "gs_repaired": "3DGS of repaired views (synthesised)",
}
BLEND_BELOW = 0.99  # a pixel whose main source weighs less than this is a blend (legend)
COLOURS = np.array(
    [
        [40, 110, 230],
        [40, 180, 70],
        [230, 40, 200],
        [250, 150, 20],
        [0, 0, 0],
        [20, 200, 200],
        [150, 60, 20],
    ],
    np.float32,
)  # [S, 3] RGB per source; a blend's pixel mixes its sources' colours by their weights


@dataclass(frozen=True)
class Provenance:
    """Per pixel: the weight of every source in the output's value."""

    weights: npt.NDArray[np.float32]  # [S, H, W], sums to 1 per pixel

    @property
    def source(self) -> npt.NDArray[np.uint8]:  # [H, W] index into SOURCES: the largest weight
        return np.argmax(self.weights, axis=0).astype(np.uint8)

    @property
    def confidence(self) -> npt.NDArray[np.float32]:  # [H, W] that source's weight (1: pure)
        return self.weights.max(axis=0)

    @property
    def synthesised(self) -> npt.NDArray[np.float32]:  # [H, W] share of synthesised sources
        return self.weights[list(SYNTHESISED)].sum(axis=0)

    def shares(self) -> dict[str, float]:
        """Each source's share of the view's pixels, and ``synthesised`` (their sum)."""
        out = {s: float(self.weights[i].mean()) for i, s in enumerate(SOURCES)}
        out["synthesised"] = float(self.synthesised.mean())
        return out


def candidate_sources(
    gs_alpha: npt.NDArray[np.floating],  # [H, W] 0..1
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    alpha_min: float = 0.5,
    ref_valid: npt.NDArray[np.bool_] | None = None,  # [H, W] the reference warp's pixels
    # [H, W] the share of the 3DGS render's colour Gaussians grown from repaired views make
    gs_synthesised: npt.NDArray[np.floating] | None = None,
) -> dict[str, npt.NDArray[np.uint8]]:  # candidate -> [H, W] index into SOURCES
    """The atomic source of every pixel of each candidate (and of the bare 3DGS render, ``gs``),
    as :func:`.fallback.baseline_candidates` and :func:`.baselines.mesh_fill` build them. The
    3DGS render's pixels are ``gs`` (observed), or ``gs_repaired`` (synthesised) where
    ``gs_synthesised`` reaches :data:`GS_REPAIRED_SHARE`: there the map shows what other views'
    repairs grew, not what a frame saw."""
    from_gs = np.asarray(gs_alpha) >= alpha_min
    mesh = np.asarray(mesh_valid, bool)
    if from_gs.shape != mesh.shape:
        raise ValueError(
            f"gs_alpha and mesh_valid must be the same [H, W], got {list(from_gs.shape)} "
            f"and {list(mesh.shape)}"
        )
    gs = np.full(from_gs.shape, GS, np.uint8)
    if gs_synthesised is not None:
        if np.shape(gs_synthesised) != from_gs.shape:
            raise ValueError(f"gs_synthesised must be {list(from_gs.shape)} like gs_alpha, got "
                             f"{list(np.shape(gs_synthesised))}")  # fmt: skip
        gs[np.asarray(gs_synthesised) >= GS_REPAIRED_SHARE] = GS_REPAIRED
    mesh_or_fill = np.where(mesh, MESH, FILL).astype(np.uint8)
    ref = np.zeros(from_gs.shape, bool) if ref_valid is None else np.asarray(ref_valid, bool)
    return {
        "fixed": np.full(from_gs.shape, FIXER, np.uint8),
        "inpaint": np.where(from_gs, gs, mesh_or_fill),
        "mesh_inpaint": mesh_or_fill,
        "ref_inpaint": np.where(ref, np.uint8(REF), np.where(from_gs & mesh, gs, mesh_or_fill)),
        "gs": np.where(from_gs, gs, np.uint8(NONE)),
    }


def provenance(
    sources: dict[str, npt.NDArray[np.uint8]],  # from candidate_sources
    region: npt.NDArray[np.uint8],  # [H, W] from fallback.regions (or far_regions)
    choice: Choice,
    feather_px: float = 0.0,
    detail_px: float = BLEND_DETAIL_PX,
) -> Provenance:
    """The provenance of ``compose(candidates, region, choice, feather_px, detail_px)``. A
    blend of GSFixer into a fallback (:func:`.fallback.blend`) is linear in its inputs: GSFixer
    weighs ``share`` and the fallback's sources ``1 - share``, each blurred by ``detail_px``
    as the fallback's colours are (so near a hole's border part of a fill's share is the map
    whose colours it carries)."""
    chosen = region_sources(region, choice)
    keys = sorted(set(chosen))
    index = np.array([keys.index(c) for c in chosen], np.uint8)
    w_key = region_weights(np.asarray(region), len(keys), index, feather_px)
    weights = np.zeros((len(SOURCES), *np.shape(region)), np.float32)
    rows, cols = np.indices(np.shape(region))
    for (name, share), w in zip(keys, w_key, strict=True):
        if name == "fixed":
            weights[FIXER] += w
            continue
        if share == 0.0:
            np.add.at(weights, (sources[name], rows, cols), w)
            continue
        # share * fixed + (1 - share) * lowpass(fallback); GSFixer is one source throughout
        weights[FIXER] += share * w
        for i in np.unique(sources[name]):
            part = lowpass((sources[name] == i).astype(np.float32), detail_px)
            weights[i] += (1.0 - share) * part * w
    return Provenance(weights)


def single(sources: dict[str, npt.NDArray[np.uint8]], name: str) -> Provenance:
    """The provenance of one candidate (or ``gs``) taken whole."""
    src = sources[name]
    return Provenance(np.stack([(src == i).astype(np.float32) for i in range(len(SOURCES))]))


def image(prov: Provenance, legend: bool = True) -> npt.NDArray[np.uint8]:  # [H(+L), W, 3]
    """The provenance as colours (:data:`COLOURS`, a blend's pixel mixes its sources' colours),
    with a legend of the sources present below it."""
    rgb = np.einsum("shw,sc->hwc", prov.weights, COLOURS)
    img = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    if not legend:
        return img
    present = [i for i in range(len(SOURCES)) if prov.weights[i].max() > 0]
    strip = legend_strip(present, bool((prov.confidence < BLEND_BELOW).any()), img.shape[1])
    if strip.shape[1] > img.shape[1]:
        pad = np.full((img.shape[0], strip.shape[1] - img.shape[1], 3), 255, np.uint8)
        img = np.concatenate([img, pad], axis=1)
    return np.concatenate([img, strip], axis=0)


def legend_strip(
    present: list[int],  # indices into SOURCES, in order
    blends: bool,  # add the entry for mixed colours
    width: int,  # px; at least 220
) -> npt.NDArray[np.uint8]:  # [14 x entries + 4, max(width, 220), 3]
    """The legend of the provenance colours: one row per source present (and blends)."""
    import cv2

    w = max(width, 220)
    row = 14
    strip = np.full((row * (len(present) + blends) + 4, w, 3), 255, np.uint8)
    entries = [(COLOURS[i], LABELS[SOURCES[i]]) for i in present]
    if blends:  # the colours of the blended sources, mixed
        entries.append((None, "mixed colour: a blend of sources"))
    for j, (colour, text) in enumerate(entries):
        y = 2 + j * row
        if colour is None:
            strip[y + 2 : y + row - 2, 4:9] = COLOURS[present[0]].astype(np.uint8)
            strip[y + 2 : y + row - 2, 9:14] = COLOURS[present[-1]].astype(np.uint8)
        else:
            strip[y + 2 : y + row - 2, 4:14] = colour.astype(np.uint8)
        cv2.putText(strip, text, (18, y + row - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1,
                    cv2.LINE_AA)  # fmt: skip
    return strip


def to_npz(prov: Provenance) -> dict[str, npt.NDArray]:
    """The machine-readable arrays: ``source`` [H, W] uint8 (index into ``sources``),
    ``confidence`` and ``synthesised`` [H, W] float16 in [0, 1], and the source names."""
    return {
        "source": prov.source,
        "confidence": prov.confidence.astype(np.float16),
        "synthesised": prov.synthesised.astype(np.float16),
        "sources": np.array(SOURCES),
    }
