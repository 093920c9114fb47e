"""Versioned GSFixer checkpoints, written atomically.

Layout of a checkpoint root::

    ROOT/latest                  name of the newest complete checkpoint, e.g. "step_000120"
    ROOT/step_000120/manifest.json   format, step, source, mode, configs, codec, base model
    ROOT/step_000120/unet.safetensors
    ROOT/step_000120/embedding.safetensors
    ROOT/step_000120/trainer.pt      optional: optimizer and generator state, to resume

A checkpoint is written into a temporary folder beside its final name and renamed into place,
then ``latest`` is replaced by a temp file + ``os.replace``, so a reader (or a crash) only ever
sees whole checkpoints. Only the U-Net is saved: the codec is weight-free (default) or the frozen
base VAE (SD2, found again through the manifest's base path).

The manifest records each file's size and SHA-256; loading a root checks them, and a checkpoint
that fails the check (a bit flip, a truncated copy, a full disk) is reported in one line and the
newest older checkpoint that passes is used instead. Nothing is unpickled: weights are
safetensors, and ``trainer.pt`` loads with ``weights_only=True``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import pickle  # only for its UnpicklingError: weights_only loads refuse objects with it
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from gsfix_online.core.config import build, to_dict
from gsfix_online.core.io import atomic_write_text
from gsfix_online.fixer.codec import codec_from_spec
from gsfix_online.fixer.config import ModelConfig
from gsfix_online.fixer.model import GSFixer
from gsfix_online.fixer.sources import FixerBundle, _diffusers, load_sd2

logger = logging.getLogger(__name__)

FORMAT = "gsfixer-checkpoint/1"
LATEST = "latest"


class CheckpointError(ValueError):
    """A checkpoint folder fails its size or checksum check (one line naming the file)."""


@dataclass
class LoadedCheckpoint:
    bundle: FixerBundle
    step: int
    manifest: dict[str, Any]
    trainer_state: dict[str, Any] | None  # None when saved without one
    path: Path


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def verify_checkpoint(ckpt: Path) -> None:
    """Check every file the manifest lists against its recorded size and SHA-256 (checkpoints
    written before the manifest held them pass unchecked); raises :class:`CheckpointError`."""
    try:
        manifest = json.loads((ckpt / "manifest.json").read_text())
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{ckpt / 'manifest.json'}: unreadable manifest ({exc})") from None
    files = manifest.get("files", {}) if isinstance(manifest, dict) else None
    if not isinstance(files, dict):
        raise CheckpointError(f"{ckpt / 'manifest.json'}: 'files' must be a mapping")
    for name, rec in files.items():
        f = ckpt / name
        if not f.is_file():
            raise CheckpointError(f"{f}: missing")
        size = f.stat().st_size
        if size != rec["bytes"]:
            raise CheckpointError(f"{f}: {size} bytes, the manifest says {rec['bytes']}")
        if _sha256(f) != rec["sha256"]:
            raise CheckpointError(f"{f}: SHA-256 differs from the manifest (corrupt)")


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save_checkpoint(
    root: str | os.PathLike[str],
    bundle: FixerBundle,
    step: int,
    model_cfg: ModelConfig,
    trainer_state: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
    keep: int = 3,
    weights_dtype: torch.dtype | None = None,  # e.g. float16 for a shipped base; None = as is
) -> Path:
    """Write ``ROOT/step_NNNNNN`` atomically, point ``latest`` at it, keep the newest ``keep``.

    Loading casts the weights back to the model's dtype, so a float16 file loads into float32.
    """
    from safetensors.torch import save_file

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    name = f"step_{step:06d}"
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=root))
    try:
        unet = bundle.model.unet
        state = {
            k: v.detach().to(weights_dtype or v.dtype).contiguous().cpu()
            for k, v in unet.state_dict().items()
        }
        save_file(state, str(tmp / "unet.safetensors"))
        emb = bundle.model.prompt_embedding.detach().contiguous().cpu()
        save_file({"embedding": emb}, str(tmp / "embedding.safetensors"))
        if trainer_state is not None:
            torch.save(trainer_state, tmp / "trainer.pt")
        files = {
            f.name: {"bytes": f.stat().st_size, "sha256": _sha256(f)} for f in sorted(tmp.iterdir())
        }
        manifest = {
            "format": FORMAT,
            "step": step,
            "source": bundle.source,
            "mode": bundle.model.mode,
            # as the model is fed: a checkpoint is repaired with what it was trained on
            "model_config": to_dict(
                dataclasses.replace(model_cfg, gs_condition=bundle.model.gs_condition)
            ),
            "unet_config": {k: v for k, v in dict(unet.config).items() if not k.startswith("_")},
            "scheduler_config": bundle.scheduler_config,
            "base": bundle.base,
            "extra": extra or {},
            "files": files,
        }
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2, default=list))
        for f in tmp.iterdir():
            _fsync_file(f)
        final = root / name
        if final.exists():  # the same step saved again: replace it whole
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    atomic_write_text(root / LATEST, name + "\n")
    _prune(root, keep)
    return final


def _prune(root: Path, keep: int) -> None:
    done = sorted(p for p in root.glob("step_*") if (p / "manifest.json").is_file())
    for old in done[:-keep] if keep > 0 else []:
        shutil.rmtree(old, ignore_errors=True)


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """A checkpoint folder, or a root whose ``latest`` names one."""
    p = Path(path)
    if (p / "manifest.json").is_file():
        return p
    if (p / LATEST).is_file():
        return p / (p / LATEST).read_text().strip()
    raise FileNotFoundError(
        f"{p} is neither a GSFixer checkpoint nor a root with a '{LATEST}' file"
    )


def _candidates(path: Path) -> list[Path]:
    """The checkpoint ``path`` names, then (for a root) the older complete ones, newest first."""
    first = resolve_checkpoint(path)
    if first.parent != path:
        return [first]
    older = sorted(
        (p for p in path.glob("step_*") if (p / "manifest.json").is_file() and p != first),
        reverse=True,
    )
    return [first, *older]


def load_checkpoint(
    path: str | os.PathLike[str], map_location: str | torch.device = "cpu"
) -> LoadedCheckpoint:
    """Load the model (and trainer state, if saved) of a checkpoint folder or root.

    A root's ``latest`` checkpoint that fails :func:`verify_checkpoint` or does not load is
    logged as an error and the newest older one that does is used; a folder named directly must
    pass itself. Raises :class:`CheckpointError` when none does.
    """
    candidates = _candidates(Path(path))
    problems = []
    for ckpt in candidates:
        try:
            loaded = _load_one(ckpt, map_location)
        except (
            OSError,
            ValueError,
            RuntimeError,
            KeyError,
            TypeError,
            pickle.UnpicklingError,
        ) as exc:
            problem = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            problems.append(f"{ckpt.name}: {problem}")
            logger.error("checkpoint %s is unusable: %s", ckpt, problem)
            continue
        if ckpt != candidates[0]:
            logger.warning("using the previous good checkpoint %s instead", ckpt)
        return loaded
    raise CheckpointError(f"{path}: no usable checkpoint ({'; '.join(problems)})")


def _load_one(ckpt: Path, map_location: str | torch.device) -> LoadedCheckpoint:
    from safetensors.torch import load_file

    verify_checkpoint(ckpt)
    manifest = json.loads((ckpt / "manifest.json").read_text())
    if manifest.get("format") != FORMAT:
        raise ValueError(f"{ckpt}: unknown checkpoint format {manifest.get('format')!r}")
    raw_cfg = json.loads(json.dumps(manifest["model_config"]))
    raw_cfg.setdefault("default", {}).setdefault("residual", False)  # before the option existed
    model_cfg = build(ModelConfig, base=raw_cfg)
    embedding = load_file(str(ckpt / "embedding.safetensors"))["embedding"]
    if manifest["source"] == "sd2":
        base_cfg = dataclasses.replace(model_cfg, source="sd2", path=manifest["base"]["path"])
        bundle = load_sd2(base_cfg)
    else:
        codec = codec_from_spec(manifest["base"]["codec"])
        unet = _diffusers().UNet2DConditionModel(**manifest["unet_config"])
        residual = model_cfg.default.residual and model_cfg.source == "default"
        model = GSFixer(unet, manifest["mode"], codec.latent_channels, embedding, residual)
        sched = manifest["scheduler_config"]
        bundle = FixerBundle(model, codec, sched, "default", manifest["base"])
    bundle.model.gs_condition = model_cfg.gs_condition  # fed as it was trained, either source
    state = load_file(str(ckpt / "unet.safetensors"))
    bundle.model.unet.load_state_dict(state)
    trainer_state = None
    if (ckpt / "trainer.pt").is_file():
        # weights_only: tensors and plain containers, never arbitrary pickled objects
        trainer_state = torch.load(
            ckpt / "trainer.pt", map_location=map_location, weights_only=True
        )
    return LoadedCheckpoint(bundle, int(manifest["step"]), manifest, trainer_state, ckpt)
