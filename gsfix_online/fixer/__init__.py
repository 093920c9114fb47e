"""GSFixer: the latent diffusion model that repairs a view from its mesh render and its 3DGS
render, its codecs and model sources, mask augmentation, fine-tuning and DDIM inference."""
