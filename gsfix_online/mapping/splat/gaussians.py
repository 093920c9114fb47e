"""The Gaussian map: parameters, their activations, and structural edits (add, remove, select).

Parameters live in an ``nn.ParameterDict`` whose keys follow gsplat's convention, so gsplat's
``DefaultStrategy`` and our own densification work on ``GaussianMap.params`` directly:

======== ============== =========================================================
key      shape          meaning (stored raw; the activation is applied in the graph)
======== ============== =========================================================
means    [N, 3]         world position, metres
scales   [N, 3]         log of the standard deviations along the local axes, log-metres
quats    [N, 4]         rotation w, x, y, z (Hamilton), any length: normalised when read
opacities [N]           logit of the opacity
sh0      [N, 1, C]      degree-0 spherical-harmonic colour: rgb = 0.5 + SH_C0 * sh0
shN      [N, K - 1, C]  higher SH bands, K = (sh_degree + 1)^2 ([N, 0, C] at degree 0)
======== ============== =========================================================

C is 3 for colour scenes and 1 for grayscale scenes. Structural edits replace the parameters
and, when given the optimizers (one per key, as gsplat's strategies expect), keep Adam's
moments of the surviving Gaussians and start new ones at zero.

Beside the parameters every Gaussian carries its provenance (``meta``, not optimised; kept
through add, remove, select and snapshots): ``origin`` [N] uint8, :data:`ORIGIN_OBSERVED` for
one grown from an observed frame, :data:`ORIGIN_REPAIRED` for one grown from a repaired view
(distillation's seeds: a surface nobody saw), and ``observations`` [N] int32, how many input
frames saw it (the mapper counts it in every frame's render). Beside them ``max_log_scale``
[N] float32 bounds each Gaussian's log-scales (log-metres, every axis; +inf: unbounded, as for
everything grown from an input frame): the optimizer clamps to it after every step, so that a
seed grown for a repaired view keeps to its footprint (``MapperConfig.distill_scale_growth``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor, nn

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))
PARAM_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")
MAX_SH_DEGREE = 4
QUAT_EPS = 1e-12  # |q|^2 below this reads as the identity rotation (a zero quaternion has none)
ORIGINS = ("observed", "repaired")  # a Gaussian's origin, by its index in this tuple
ORIGIN_OBSERVED, ORIGIN_REPAIRED = 0, 1
# per Gaussian, not optimised
META_DTYPES = {"origin": torch.uint8, "observations": torch.int32, "max_log_scale": torch.float32}
UNBOUNDED = float("inf")  # max_log_scale of a Gaussian whose scale is not bounded


def num_sh_bases(sh_degree: int) -> int:
    return (sh_degree + 1) ** 2


def rgb_to_sh0(rgb: Tensor) -> Tensor:  # [..., C] in [0, 1] -> [..., C]
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:  # [..., C] -> [..., C], not clamped
    return sh0 * SH_C0 + 0.5


def normalize_quats(quats: Tensor) -> Tensor:  # [N, 4] -> [N, 4] unit, w, x, y, z
    """Differentiable normalisation; a zero (or non-finite-free but tiny) quaternion becomes identity."""
    sq = (quats * quats).sum(-1, keepdim=True)
    degenerate = sq < QUAT_EPS
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    safe = torch.where(degenerate, identity, quats)
    return safe * torch.rsqrt(torch.where(degenerate, torch.ones_like(sq), sq))


class GaussianMapError(ValueError):
    """Parameters given to a GaussianMap have the wrong shape, dtype or values."""


def _as_tensor(x: Tensor | npt.ArrayLike, name: str, device: torch.device) -> Tensor:
    t = x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))
    if not t.is_floating_point():
        raise GaussianMapError(f"{name} must be floating point, got {t.dtype}")
    t = t.detach().to(device=device, dtype=torch.float32)
    if not torch.isfinite(t).all():
        raise GaussianMapError(f"{name} contains NaN or inf")
    return t


def _meta(
    x: int | Tensor | npt.ArrayLike, name: str, m: int, device: torch.device, top: int
) -> Tensor:  # [m] of META_DTYPES[name]
    t = x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))
    if t.is_floating_point() or t.dtype == torch.bool or t.ndim > 1:
        raise GaussianMapError(
            f"{name} must be an integer or integer [M], got {t.dtype} {list(t.shape)}"
        )
    if t.ndim == 1 and len(t) != m:
        raise GaussianMapError(f"{name} must be [{m}], got {list(t.shape)}")
    if t.numel() and (int(t.min()) < 0 or int(t.max()) > top):
        raise GaussianMapError(
            f"{name} must lie in [0, {top}], got [{int(t.min())}, {int(t.max())}]"
        )
    return t.to(device=device, dtype=META_DTYPES[name]).expand(m).clone()


def _bound(x: float | Tensor | npt.ArrayLike, m: int, device: torch.device) -> Tensor:
    """``max_log_scale`` for M Gaussians: one for all or [M], a number or +inf, never NaN."""
    t = x.detach().cpu().float() if isinstance(x, Tensor) else torch.as_tensor(np.float32(x))
    if t.ndim > 1 or (t.ndim == 1 and len(t) != m):
        raise GaussianMapError(f"max_log_scale must be a number or [{m}], got {list(t.shape)}")
    if t.numel() and bool(torch.isnan(t).any()):
        raise GaussianMapError("max_log_scale must not be NaN")
    return t.to(device).expand(m).clone()


class GaussianMap:
    """A set of 3D Gaussians with SH colour of degree ``sh_degree`` and ``channels`` channels."""

    def __init__(self, sh_degree: int = 0, channels: int = 3, device: str | torch.device = "cpu"):
        if not (isinstance(sh_degree, int) and 0 <= sh_degree <= MAX_SH_DEGREE):
            raise GaussianMapError(
                f"sh_degree must be an int in [0, {MAX_SH_DEGREE}], got {sh_degree!r}"
            )
        if channels not in (1, 3):
            raise GaussianMapError(
                f"channels must be 1 (grayscale) or 3 (colour), got {channels!r}"
            )
        self.sh_degree = sh_degree
        self.channels = channels
        dev = torch.device(device)
        k = num_sh_bases(sh_degree)
        shapes = {
            "means": (0, 3),
            "scales": (0, 3),
            "quats": (0, 4),
            "opacities": (0,),
            "sh0": (0, 1, channels),
            "shN": (0, k - 1, channels),
        }
        self.params = nn.ParameterDict(
            {key: nn.Parameter(torch.zeros(shape, device=dev)) for key, shape in shapes.items()}
        )
        # per Gaussian provenance (module doc), aligned with the parameters
        self.meta: dict[str, Tensor] = {
            k: torch.zeros(0, dtype=t, device=dev) for k, t in META_DTYPES.items()
        }

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def from_tensors(
        cls,
        means: Tensor | npt.ArrayLike,  # [N, 3] metres
        log_scales: Tensor | npt.ArrayLike,  # [N, 3] log-metres
        quats: Tensor | npt.ArrayLike,  # [N, 4] w, x, y, z
        opacity_logits: Tensor | npt.ArrayLike,  # [N]
        sh0: Tensor | npt.ArrayLike,  # [N, 1, C]
        shN: Tensor | npt.ArrayLike | None = None,  # [N, K - 1, C]; None = zeros
        sh_degree: int = 0,
        device: str | torch.device = "cpu",
    ) -> GaussianMap:
        sh0_t = torch.as_tensor(np.asarray(sh0)) if not isinstance(sh0, Tensor) else sh0
        if sh0_t.ndim != 3 or sh0_t.shape[1] != 1:
            raise GaussianMapError(f"sh0 must be [N, 1, C], got {list(sh0_t.shape)}")
        gmap = cls(sh_degree=sh_degree, channels=int(sh0_t.shape[2]), device=device)
        gmap.add(means, log_scales, quats, opacity_logits, sh0, shN)
        return gmap

    # -- sizes and raw views ------------------------------------------------------------------

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def num_gaussians(self) -> int:
        return len(self)

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def num_bases(self) -> int:
        return num_sh_bases(self.sh_degree)

    def __repr__(self) -> str:
        return f"GaussianMap(n={len(self)}, sh_degree={self.sh_degree}, channels={self.channels})"

    # -- activations (differentiable) ---------------------------------------------------------

    @property
    def means(self) -> Tensor:  # [N, 3] metres
        return self.params["means"]

    @property
    def scales(self) -> Tensor:  # [N, 3] metres (exp of the log-scales)
        return torch.exp(self.params["scales"])

    @property
    def quats(self) -> Tensor:  # [N, 4] unit w, x, y, z
        return normalize_quats(self.params["quats"])

    @property
    def opacities(self) -> Tensor:  # [N] in (0, 1)
        return torch.sigmoid(self.params["opacities"])

    @property
    def sh(self) -> Tensor:  # [N, K, C] all SH coefficients, band-major as gsplat expects
        return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)

    @property
    def origin(self) -> Tensor:  # [N] uint8 index into ORIGINS
        return self.meta["origin"]

    @property
    def observations(self) -> Tensor:  # [N] int32 input frames that saw each Gaussian
        return self.meta["observations"]

    @property
    def max_log_scale(self) -> Tensor:  # [N] float32 log-metres, +inf = unbounded
        return self.meta["max_log_scale"]

    def repaired(self) -> Tensor:  # [N] bool
        """Which Gaussians were grown from a repaired view (synthesised, not observed)."""
        return self.meta["origin"] == ORIGIN_REPAIRED

    def set_meta(self, meta: Mapping[str, Tensor]) -> None:
        """Replace the per-Gaussian provenance (e.g. after a densification that cloned and
        split the parameters and these alike); each must be [N] of its dtype. Without
        ``max_log_scale`` (a file from before it) no Gaussian is bounded."""
        for k, t in META_DTYPES.items():
            if k == "max_log_scale" and k not in meta:
                v = torch.full((len(self),), UNBOUNDED)
            else:
                v = meta[k]  # KeyError: origin, observations
            if tuple(v.shape) != (len(self),):
                raise GaussianMapError(f"{k} must be [{len(self)}], got {list(v.shape)}")
            self.meta[k] = v.to(device=self.device, dtype=t)

    # -- structural edits ---------------------------------------------------------------------

    def add(
        self,
        means: Tensor | npt.ArrayLike,  # [M, 3] metres
        log_scales: Tensor | npt.ArrayLike,  # [M, 3] log-metres
        quats: Tensor | npt.ArrayLike,  # [M, 4] w, x, y, z
        opacity_logits: Tensor | npt.ArrayLike,  # [M]
        sh0: Tensor | npt.ArrayLike,  # [M, 1, C]
        shN: Tensor | npt.ArrayLike | None = None,  # [M, K - 1, C]; None = zeros
        optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
        origin: int | Tensor | npt.ArrayLike = ORIGIN_OBSERVED,  # one for all, or [M]
        observations: int | Tensor | npt.ArrayLike = 0,  # one for all, or [M]
        max_log_scale: float | Tensor | npt.ArrayLike = UNBOUNDED,  # one for all, or [M]
    ) -> Tensor:
        """Append M Gaussians; returns their indices [M]. Optimizer moments of new rows are zero."""
        dev = self.device
        new = {
            "means": _as_tensor(means, "means", dev),
            "scales": _as_tensor(log_scales, "log_scales", dev),
            "quats": _as_tensor(quats, "quats", dev),
            "opacities": _as_tensor(opacity_logits, "opacity_logits", dev),
            "sh0": _as_tensor(sh0, "sh0", dev),
        }
        if new["means"].ndim != 2 or new["means"].shape[1] != 3:
            raise GaussianMapError(f"means must be [M, 3], got {list(new['means'].shape)}")
        m = new["means"].shape[0]
        k, c = self.num_bases, self.channels
        new["shN"] = (
            torch.zeros((m, k - 1, c), device=dev) if shN is None else _as_tensor(shN, "shN", dev)
        )
        expected = {
            "means": (m, 3),
            "scales": (m, 3),
            "quats": (m, 4),
            "opacities": (m,),
            "sh0": (m, 1, c),
            "shN": (m, k - 1, c),
        }
        names = {"scales": "log_scales", "opacities": "opacity_logits"}
        for key, shape in expected.items():
            if tuple(new[key].shape) != shape:
                raise GaussianMapError(
                    f"{names.get(key, key)} must be {list(shape)}, got {list(new[key].shape)}"
                )
        meta = {
            "origin": _meta(origin, "origin", m, dev, len(ORIGINS) - 1),
            "observations": _meta(observations, "observations", m, dev, 2**31 - 1),
            "max_log_scale": _bound(max_log_scale, m, dev),
        }
        start = len(self)
        for key, v in meta.items():
            self.meta[key] = torch.cat([self.meta[key], v])
        self._replace(
            lambda key, p: torch.cat([p, new[key]]),
            lambda key, s: torch.cat(
                [s, torch.zeros((m, *s.shape[1:]), dtype=s.dtype, device=dev)]
            ),
            optimizers,
        )
        return torch.arange(start, start + m, device=dev)

    def remove(
        self,
        mask: Tensor,  # [N] bool, True = remove
        optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
    ) -> int:
        """Remove the Gaussians where ``mask`` is True; returns how many were removed."""
        mask = self._check_mask(mask)
        keep = ~mask
        self._replace(lambda key, p: p[keep], lambda key, s: s[keep], optimizers)
        self.meta = {k: v[keep] for k, v in self.meta.items()}
        return int(mask.sum())

    def select(self, index: Tensor) -> GaussianMap:  # [N] bool or [M] long
        """A new map (detached copies) of the selected Gaussians."""
        if index.dtype == torch.bool:
            index = self._check_mask(index)
        elif index.dtype not in (torch.int32, torch.int64) or index.ndim != 1:
            raise GaussianMapError(
                f"index must be bool [N] or integer [M], got {index.dtype} {list(index.shape)}"
            )
        out = GaussianMap(self.sh_degree, self.channels, self.device)
        for key in PARAM_KEYS:
            out.params[key] = nn.Parameter(self.params[key].detach()[index].clone())
        out.meta = {k: v[index].clone() for k, v in self.meta.items()}
        return out

    def _check_mask(self, mask: Tensor) -> Tensor:
        if (
            not isinstance(mask, Tensor)
            or mask.dtype != torch.bool
            or tuple(mask.shape) != (len(self),)
        ):
            got = (
                f"{mask.dtype} {list(mask.shape)}"
                if isinstance(mask, Tensor)
                else type(mask).__name__
            )
            raise GaussianMapError(f"mask must be a bool tensor [{len(self)}], got {got}")
        return mask.to(self.device)

    def _replace(
        self,
        param_fn: Callable[[str, Tensor], Tensor],
        state_fn: Callable[[str, Tensor], Tensor],
        optimizers: Mapping[str, torch.optim.Optimizer] | None,
    ) -> None:
        """Swap every parameter for ``param_fn(key, old)`` and carry optimizer state along."""
        for key in PARAM_KEYS:
            old = self.params[key]
            new = nn.Parameter(param_fn(key, old.detach()), requires_grad=old.requires_grad)
            if optimizers is not None and key in optimizers:
                opt = optimizers[key]
                assert len(opt.param_groups) == 1 and len(opt.param_groups[0]["params"]) == 1
                state = opt.state.pop(old, None)
                if state:
                    opt.state[new] = {
                        name: (v if name == "step" or v.ndim == 0 else state_fn(key, v))
                        for name, v in state.items()
                    }
                opt.param_groups[0]["params"] = [new]
            self.params[key] = new

    # -- snapshots ----------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Detached CPU copies of every parameter and the provenance (``origin``,
        ``observations``, ``max_log_scale``) plus ``sh_degree`` and ``channels``."""
        out: dict[str, Any] = {k: self.params[k].detach().cpu().clone() for k in PARAM_KEYS}
        out.update({k: v.cpu().clone() for k, v in self.meta.items()})
        out["sh_degree"] = self.sh_degree
        out["channels"] = self.channels
        return out

    @classmethod
    def from_state_dict(
        cls, state: Mapping[str, Any], device: str | torch.device = "cpu"
    ) -> GaussianMap:
        missing = [k for k in (*PARAM_KEYS, "sh_degree", "channels") if k not in state]
        if missing:
            raise GaussianMapError(f"state dict lacks {', '.join(missing)}")
        gmap = cls(int(state["sh_degree"]), int(state["channels"]), device)
        if state["sh0"].shape[2:] != (gmap.channels,):
            raise GaussianMapError(
                f"state dict sh0 has {list(state['sh0'].shape)} for {gmap.channels} channels"
            )
        # a snapshot from before provenance: every Gaussian observed, never counted
        gmap.add(*(state[k] for k in PARAM_KEYS), origin=state.get("origin", ORIGIN_OBSERVED),
                 observations=state.get("observations", 0),
                 max_log_scale=state.get("max_log_scale", UNBOUNDED))  # fmt: skip
        return gmap

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Replace this map's contents (and degree/channels) by ``state``; optimizers must be rebuilt."""
        other = GaussianMap.from_state_dict(state, self.device)
        self.sh_degree, self.channels, self.params = other.sh_degree, other.channels, other.params
        self.meta = other.meta
