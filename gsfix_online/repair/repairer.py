"""GSFixer on one view at a time: uint8 renders in, a uint8 repaired image out.

Holds the model bundle and which checkpoint it came from; swapping in a newer checkpoint is
:meth:`ViewRepairer.use`. No sockets, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from gsfix_online.fixer.config import MODE_CONDITIONS, FixerConfig
from gsfix_online.repair.provenance import GS_REPAIRED_SHARE


@dataclass(frozen=True)
class RepairOutput:
    image: npt.NDArray[np.uint8]  # [H, W, 3] RGB
    model_version: int  # trainer checkpoint version; 0 = the base model
    model_step: int  # optimizer steps of that checkpoint


# The guessed surface replaces the inpainted depth only within this factor of it. Planes are
# extended without end, and one the view does not bound (a bulkhead with an opening, a plane
# oriented the wrong way, a wall the fit missed) would put seeds metres off: with a fit that
# missed a tank wall, one of 32 novel views was 148 % off unguarded and 8.6 % with the guard,
# where inpainting is 5.7 % (tank seed 1, view 002). Where the planes hold, inpainting is off by
# 6.5-16.9 % (median per input) and the guard keeps the planes
# (benchmarks/results/guessed_planes_cpu.md).
GUESS_RANGE = 2.0


def seed_depth(
    mesh_depth: npt.NDArray[np.floating],  # [H, W] z-depth of the mesh render, m
    mesh_valid: npt.NDArray[np.bool_],  # [H, W] the mesh render hit a surface
    fill_empty: bool,
    guessed: npt.NDArray[np.floating] | None = None,  # [H, W] m, 0 = none (mesh_planes)
) -> npt.NDArray[np.float32]:  # [H, W] m, 0 = no seed
    """Depth at which distillation may seed Gaussians for a repaired view: the mesh's where it
    has a surface; with ``fill_empty``, elsewhere too: the surface guessed for the parts the mesh
    never saw (``guessed``, the mesh's planes extended, the same for every view) where there is
    one within ``GUESS_RANGE`` of the inpainted depth, else depth inpainted from the mesh depth around it (Navier-Stokes, which stays within
    the range of its border, unlike Telea on float depth), so that what GSFixer inpainted in
    never-observed parts can enter the map."""
    valid = np.asarray(mesh_valid, bool)
    depth = np.where(valid, np.asarray(mesh_depth, np.float32), np.float32(0.0))
    if guessed is not None and np.shape(guessed) != valid.shape:
        raise ValueError(f"guessed depth must be [{valid.shape[0]}, {valid.shape[1]}] like the "
                         f"mesh depth, got {list(np.shape(guessed))}")  # fmt: skip
    if not fill_empty or valid.all():
        return depth.astype(np.float32)
    filled = depth
    if valid.any():
        import cv2

        filled = cv2.inpaint(depth, (~valid).astype(np.uint8), 5, cv2.INPAINT_NS)
    if guessed is not None:
        g = np.asarray(guessed, np.float32)
        take = ~valid & (g > 0)
        if valid.any():  # within GUESS_RANGE of the inpainted depth: else the plane is not there
            take &= (g <= GUESS_RANGE * filled) & (g * GUESS_RANGE >= filled)
        filled = np.where(take, g, filled)
    return np.asarray(filled, np.float32)


def distill_mask(
    gs_alpha: npt.NDArray[np.floating],  # [H, W] 3DGS render opacity of the view
    alpha_min: float,
    mode: str,  # "holes", "delivered" or "all"
    dilate_px: int = 3,
    replaced: npt.NDArray[np.bool_] | None = None,  # [H, W] ("delivered") not the 3DGS render
    synthesised: npt.NDArray[np.floating] | None = None,  # [H, W] render's share from repairs
) -> npt.NDArray[np.uint8] | None:  # [H, W] 255 = fit the repair here; None = everywhere
    """Which pixels of a repaired view distillation fits: with ``holes``, those the 3DGS map
    does not explain (opacity below ``alpha_min``, or ``provenance.GS_REPAIRED_SHARE`` of its
    colour or more made by Gaussians grown from other repaired views: ``synthesised``, a hole the
    map has filled, not content it observed, as the view's provenance says) and a ``dilate_px`` band around them, so the map's observed parts keep what the
    keyframes taught them; with ``delivered``, also the covered pixels where the delivered view
    is not the 3DGS render (``replaced``: where the choice per region took GSFixer or the mesh
    there), so the map learns what was delivered."""
    if mode == "all":
        return None
    if mode not in ("holes", "delivered"):
        raise ValueError(f"distill mask must be 'holes', 'delivered' or 'all', got {mode!r}")
    hole = np.asarray(gs_alpha) < alpha_min
    if synthesised is not None:
        if np.shape(synthesised) != hole.shape:
            raise ValueError(f"synthesised must be [{hole.shape[0]}, {hole.shape[1]}] like "
                             f"gs_alpha, got {list(np.shape(synthesised))}")  # fmt: skip
        hole = hole | (np.asarray(synthesised) >= GS_REPAIRED_SHARE)
    if mode == "delivered":
        if replaced is None or np.shape(replaced) != hole.shape:
            raise ValueError(f"mode 'delivered' needs replaced [{hole.shape[0]}, {hole.shape[1]}]")
        hole = hole | np.asarray(replaced, bool)
    hole = hole.astype(np.uint8)
    if dilate_px > 0:
        import cv2

        hole = cv2.dilate(hole, np.ones((2 * dilate_px + 1,) * 2, np.uint8))
    return hole * np.uint8(255)


def _is_gray(img: npt.NDArray[np.uint8]) -> bool:  # [H, W, 3]: all channels equal
    return bool(
        np.array_equal(img[..., 0], img[..., 1]) and np.array_equal(img[..., 0], img[..., 2])
    )


def _tensor(img: npt.NDArray[np.uint8], gray: bool = False) -> Any:
    """[H, W, 3] uint8 -> [1, C, H, W] in [0, 1]; C = 1 with ``gray`` (its first channel)."""
    import torch

    x = np.array(img[..., :1] if gray else img)  # a copy: read-only views
    return torch.from_numpy(x).permute(2, 0, 1)[None].float() / 255.0


def _check_ref(
    ref_color: npt.NDArray[np.uint8] | None,
    ref_valid: npt.NDArray[np.bool_] | None,
    shape: tuple[int, ...],  # (H, W) of the renders
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.bool_]]:
    """The warp checked, or an empty one (black, no pixels) for None."""
    h, w = shape
    if ref_color is None and ref_valid is None:
        return np.zeros((h, w, 3), np.uint8), np.zeros((h, w), bool)
    if ref_color is None or ref_valid is None:
        raise ValueError("ref_color and ref_valid must be given together")
    if ref_color.dtype != np.uint8 or ref_color.shape != (h, w, 3):
        raise ValueError(
            f"ref_color must be uint8 [{h}, {w}, 3], got {ref_color.dtype} {list(ref_color.shape)}"
        )
    if ref_valid.dtype != np.bool_ or ref_valid.shape != (h, w):
        raise ValueError(
            f"ref_valid must be bool [{h}, {w}], got {ref_valid.dtype} {list(ref_valid.shape)}"
        )
    return ref_color, ref_valid


class ViewRepairer:
    def __init__(self, cfg: FixerConfig) -> None:
        self.cfg = cfg
        self.bundle: Any = None
        self.version = -1  # -1: no model yet
        self.step = 0
        self.repaired = 0

    @property
    def ready(self) -> bool:
        return self.bundle is not None

    def load_base(self) -> None:
        from gsfix_online.fixer.loader import load_fixer

        self.use(load_fixer(self.cfg.model), version=0, step=0)

    def load_checkpoint(self, path: str, version: int) -> None:
        from gsfix_online.fixer.checkpoint import load_checkpoint

        loaded = load_checkpoint(path)
        self.use(loaded.bundle, version=version, step=loaded.step)

    def use(self, bundle: Any, version: int, step: int) -> None:
        bundle.model.eval()
        self.bundle, self.version, self.step = bundle, version, step

    def repair(
        self,
        gs_color: npt.NDArray[np.uint8],  # [H, W, 3] 3DGS render
        mesh_color: npt.NDArray[np.uint8],  # [H, W, 3] mesh render
        ref_color: npt.NDArray[np.uint8] | None = None,  # [H, W, 3] the view's reference warp
        ref_valid: npt.NDArray[np.bool_] | None = None,  # [H, W] its pixels
    ) -> RepairOutput:
        """GSFixer's repair of one view. A ``mesh+gs+ref`` model takes the view's reference warp;
        without one (None: no reference frame saw the view) its reference slot is the mesh
        render, as for a warp without pixels. Other modes ignore the warp."""
        from gsfix_online.fixer.inference import repair

        if not self.ready:
            raise RuntimeError("no GSFixer model loaded yet")
        for name, img in (("gs_color", gs_color), ("mesh_color", mesh_color)):
            if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                raise ValueError(
                    f"{name} must be uint8 [H, W, 3], got {img.dtype} {list(img.shape)}"
                )
        if gs_color.shape != mesh_color.shape:
            raise ValueError(f"renders differ in size: {gs_color.shape} vs {mesh_color.shape}")
        conds = MODE_CONDITIONS[self.bundle.model.mode]
        with_ref = "ref" in conds
        if with_ref:
            ref_color, ref_valid = _check_ref(ref_color, ref_valid, gs_color.shape[:2])
        # A grayscale rig's renders carry one value in all three channels: repaired as
        # grayscale, they come back grayscale. The model, trained on colour scenes too, tints
        # them otherwise (a beige haze where it inpaints; +0.03 dB mean PSNR on the two gray
        # scenes of seeds 94-99 once gone: benchmarks/results/gray_repair_cpu.json)
        given = (("mesh", mesh_color), ("gs", gs_color), ("ref", ref_color))
        used = [img for name, img in given if name in conds]
        gray = all(_is_gray(img) for img in used)  # type: ignore[arg-type]
        kw: dict[str, Any] = {}
        if with_ref:
            import torch

            kw["image_ref"] = _tensor(ref_color, gray)  # type: ignore[arg-type]
            kw["ref_valid"] = torch.from_numpy(np.array(ref_valid))[None, None]
        res = repair(
            self.bundle,
            _tensor(mesh_color, gray) if "mesh" in conds else None,
            _tensor(gs_color, gray) if "gs" in conds else None,
            self.cfg.inference,
            **kw,
        )
        img = res.images[0].permute(1, 2, 0).numpy()  # [H, W, 1 | 3]
        out = np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
        out = np.repeat(out, 3, axis=2) if out.shape[2] == 1 else out
        self.repaired += 1
        return RepairOutput(np.ascontiguousarray(out), self.version, self.step)


def fill_skipped(
    gs: npt.NDArray[np.uint8],  # [H, W, 3] 3DGS render
    gs_alpha: npt.NDArray[np.floating],  # [H, W]
    mesh: npt.NDArray[np.uint8],  # [H, W, 3] mesh render
    mesh_depth: npt.NDArray[np.floating],  # [H, W] m, 0 = no surface
    mesh_valid: npt.NDArray[np.bool_],  # [H, W]
    alpha_min: float = 0.5,
    dilate_px: int = 3,
    fill_empty: bool = True,
    synthesised: npt.NDArray[np.floating] | None = None,  # [H, W] (distill_mask's)
) -> dict[str, npt.NDArray[Any]] | None:
    """The repair of a view that the map explains (the planner skipped GSFixer for it): mesh
    fill + OpenCV Telea, which is the 3DGS render wherever it covers the view, with the mask
    and seed depth that let distillation close the map's few holes there (and keep what other
    views' repairs grew where the view shows it). None: no holes."""
    from gsfix_online.repair.baselines import inpaint_telea, mesh_fill

    alpha = np.asarray(gs_alpha, np.float32)
    if not (alpha < alpha_min).any():
        return None
    valid = np.asarray(mesh_valid, bool)
    fill = mesh_fill(gs, alpha, mesh, valid, alpha_min)
    mask = distill_mask(alpha, alpha_min, "holes", dilate_px, synthesised=synthesised)
    assert mask is not None
    return {
        "color": inpaint_telea(fill.image, fill.missing),
        "mask": mask,
        "depth": seed_depth(mesh_depth, valid, fill_empty),
    }
