"""Denoise and finetune (paper section 3.1, step 2): the VQ-VAE-2-style image denoiser
(``vqvae``, ``quantize``), its file format (``io``) and the finetune of a NeRF on denoised
renders (``finetune``)."""

from model.denoise.finetune import (
           DenoiseConfig,
           DenoiseResult,
           FinetuneConfig,
           denoise_and_finetune,
           denoise_and_finetune_prior,
           finetune_on_views,
           ring_poses,
)
from model.denoise.io import load_denoiser, save_denoiser
from model.denoise.vqvae import DenoiserConfig, VQVAE2Denoiser, denoise_renders

__all__ = ["DenoiseConfig", "DenoiseResult", "DenoiserConfig", "FinetuneConfig", "VQVAE2Denoiser", "denoise_and_finetune",
           "denoise_and_finetune_prior", "denoise_renders", "finetune_on_views", "load_denoiser", "ring_poses", "save_denoiser"]
