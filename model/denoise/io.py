"""The trained denoiser's file format: a folder with ``denoiser.safetensors`` (weights and
codebook buffers, float32) and ``denoiser.json`` (its config, the prior it was trained on,
training provenance). Weights are safetensors, never pickle.
"""

from __future__ import annotations

import json
from pathlib import Path

from safetensors.torch import load_file, save_file

from model.denoise.vqvae import DenoiserConfig, VQVAE2Denoiser
from model.nerf import config

DENOISER_WEIGHTS = "denoiser.safetensors"
DENOISER_META = "denoiser.json"
DENOISER_FORMAT = 1


def save_denoiser(folder: Path, denoiser: VQVAE2Denoiser, extra: dict | None = None) -> Path:
    """Write ``denoiser`` into ``folder`` (created if needed) with ``extra`` metadata; returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tensors = {k: (v.float() if v.is_floating_point() else v).detach().contiguous().cpu() for k, v in denoiser.state_dict().items()}
    save_file(tensors, str(folder / DENOISER_WEIGHTS))
    meta = {"format": DENOISER_FORMAT, "denoiser": config.to_dict(denoiser.cfg), **(extra or {})}
    (folder / DENOISER_META).write_text(json.dumps(meta, indent=2))
    return folder


def read_denoiser_meta(folder: Path) -> dict:
    """The metadata ``save_denoiser`` wrote, with a clear error when the folder holds no denoiser."""
    folder = Path(folder)
    for name in (DENOISER_WEIGHTS, DENOISER_META):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"{folder} holds no trained denoiser ({name} is missing); run `hypnerf train-denoiser` first")
    try:
        meta = json.loads((folder / DENOISER_META).read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{folder / DENOISER_META} is not valid JSON ({error}); train the denoiser again") from error
    if meta.get("format") != DENOISER_FORMAT:
        raise ValueError(f"{folder / DENOISER_META} has format {meta.get('format')!r}, this code reads {DENOISER_FORMAT}; train the denoiser again")
    return meta


def load_denoiser(folder: Path, device=None) -> tuple[VQVAE2Denoiser, dict]:
    """The denoiser in ``folder`` (eval mode, on ``device``) and its metadata."""
    meta = read_denoiser_meta(folder)
    denoiser = VQVAE2Denoiser(config.from_dict(DenoiserConfig, meta["denoiser"]))
    state = load_file(str(Path(folder) / DENOISER_WEIGHTS))
    missing = set(denoiser.state_dict()) ^ set(state)
    if missing:
        raise ValueError(f"{Path(folder) / DENOISER_WEIGHTS} does not match {DENOISER_META} (tensors {sorted(missing)[:4]}...); train the denoiser again")
    denoiser.load_state_dict(state)
    return denoiser.to(device or "cpu").eval(), meta
