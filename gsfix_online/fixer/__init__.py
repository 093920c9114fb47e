"""GSFixer: the latent diffusion model that repairs a view from its mesh render and its 3DGS
render, its codecs and model sources, mask augmentation, fine-tuning and DDIM inference.

- ``config.py``: FixerConfig (model source, mask policy, training, inference)
- ``codec.py``: exact pixel-unshuffle codec (default) and the frozen SD2 VAE
- ``model.py``: ``widen_conv_in`` and the GSFixer U-Net wrapper (no text)
- ``sources.py``: ``build_default`` / ``load_sd2``, the empty-prompt cache; ``loader.py``: ``load_fixer``
- ``checkpoint.py``: atomic, versioned checkpoints with a manifest
- ``masks.py``: procedural, disocclusion and alpha-hole masks; the augmentation policy
- ``train.py``: ``LatentCache`` and ``Trainer`` (DDPM noise-prediction MSE, Adam)
- ``inference.py``: ``repair`` (deterministic DDIM)
- ``samples.py``, ``triplets.py``, ``trainer_policy.py``, ``validation.py``: training data and policy

Submodules import torch, diffusers and OpenCV; this package's import does not.
"""
