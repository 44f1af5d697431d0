"""The bundle's query network: prompts and images -> joint embeddings -> codes (ONNX Runtime), and
retrieval of training instances by image embedding.

The embedders (``model.prior.embedders``: MiniLM for text, EfficientNet-Lite0 for images, or CLIP)
run in torch and are loaded on first use, since loading them takes seconds and the server starts
without them. Each is checked against the version the query network was trained with (weights and
preprocessing digest in ``query.json``): another version would give embeddings the network has
never seen. The MLP runs in ONNX Runtime (``query.onnx``); codes are snapped to the nearest
codebook entry, shape and colour separately, in the codebook-standardised units the network was
trained in, as ``model.prior.query.snap_codes`` does, because a point between codes decodes to a
faded blend of chairs. Retrieval ranks the instances by the distance of their codes to the codes
predicted from the image, as ``model.prior.query.nearest_instances`` does. The bank
(``embeddings.npy``: one image embedding per instance, ``bank``) is checked against the
instances and kept for clients that compare embeddings themselves (``model.prior.query.retrieve``).
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open

from model.bundle.manifest import (
    COLOR_INPUT,
    EMBEDDING_INPUT,
    EMBEDDINGS,
    QUERY_ONNX,
    SHAPE_INPUT,
    BundleError,
)
from model.bundle.runtime import onnx_session
from model.prior.colour_words import PromptColour, palette_prompt
from model.prior.embedders import embed_queries, embed_texts, load_embedder
from model.prior.query import (
    QUERY_META,
    QUERY_WEIGHTS,
    InputSlot,
    colour_wearers,
    slot_for,
    slot_modalities,
)


class QueryModel:
    """Text and images to codes ``(shape [S], color [C])`` and to the nearest training instances.

    Joint embeddings are float32 ``[E]``: one slot per embedder (``slots``), a query filling the
    slots it has. ``shape_book [I, S]`` and ``color_book [I, C]`` are the bundle's per-instance codes,
    ``instance_colours`` the palette colour each instance's caption names (None where it names none),
    ``rendered_colours`` each instance's palette shares in renders of its own codes (from the export).
    """

    def __init__(self, folder: Path, shape_book: np.ndarray, color_book: np.ndarray, *, threads: int | None = None,
                 instance_colours: list[str | None] | None = None, rendered_colours: list[dict[str, float]] | None = None):
        self.folder = Path(folder)
        meta = json.loads((self.folder / QUERY_META).read_text(encoding="utf-8"))
        self.slots = [InputSlot.from_json(slot) for slot in meta["inputs"]]
        self.input_dim = sum(slot.dim for slot in self.slots)
        self.shape_book, self.color_book = shape_book, color_book
        self.instance_colours = list(instance_colours) if instance_colours is not None else [None] * len(shape_book)
        self.rendered_colours = rendered_colours
        with safe_open(str(self.folder / QUERY_WEIGHTS), framework="pt") as weights:
            scale = weights.get_tensor("code_scale").float().numpy()
        self._shape_scale, self._color_scale = scale[: shape_book.shape[1]], scale[shape_book.shape[1] :]
        self.bank = np.load(self.folder / EMBEDDINGS)
        image = self.slot("image")
        if self.bank.shape != (len(shape_book), image.dim) or self._color_scale.shape[0] != color_book.shape[1]:
            raise BundleError(f"{self.folder / EMBEDDINGS} or {QUERY_WEIGHTS} does not match the bundle's instances and codes; re-export the bundle")
        self._session = onnx_session(self.folder / QUERY_ONNX, threads)
        self._embedders: dict[str, object] = {}
        self._lock = threading.Lock()

    @property
    def modalities(self) -> tuple[str, ...]:
        return slot_modalities(self.slots)

    def slot(self, modality: str) -> InputSlot:
        found = slot_for(self.slots, modality)
        if found is not None:
            return found
        raise ValueError(f"this bundle's query network reads {self.modalities}, not {modality}; export one trained with a {modality} embedder")

    def _embedder(self, modality: str):
        slot = self.slot(modality)
        with self._lock:
            if slot.name not in self._embedders:
                embedder = load_embedder(slot.name)
                if slot.version and embedder.version() != slot.version:
                    raise BundleError(
                        f"the installed {slot.name} embedder is version {embedder.version()}, but the bundle's query network was trained "
                        f"on version {slot.version}; install the embedder package the bundle was made with, or train and export the query network again"
                    )
                self._embedders[slot.name] = embedder
            return self._embedders[slot.name]

    def _joint(self, modality: str, embedding: torch.Tensor) -> np.ndarray:
        slot = self.slot(modality)
        joint = np.zeros(self.input_dim, dtype=np.float32)
        joint[slot.offset : slot.offset + slot.dim] = embedding.reshape(-1).float().numpy()
        return joint

    def embed_text(self, text: str) -> np.ndarray:
        """The joint embedding ``[E]`` of a prompt, its colour words read as palette colours
        (``model.prior.colour_words``: the text encoder knows few colour names)."""
        return self._text_joint(palette_prompt(text))

    def _text_joint(self, read: PromptColour) -> np.ndarray:
        return self._joint("text", embed_texts(self._embedder("text"), [read.prompt]))

    def embed_image(self, rgba) -> np.ndarray:
        """The joint embedding ``[E]`` of a straight-alpha RGBA (or RGB) image ``[H, W, 4]`` in [0, 1]."""
        image = torch.as_tensor(np.asarray(rgba, dtype=np.float32))
        if image.ndim != 3:
            raise ValueError(f"embed one image [H, W, 4] (or [H, W, 3]) at a time, got shape {list(image.shape)}")
        return self._joint("image", embed_queries(self._embedder("image"), image[None]))

    def _check(self, embedding) -> np.ndarray:
        joint = np.asarray(embedding, dtype=np.float32).reshape(-1)
        if joint.shape[0] != self.input_dim or not np.isfinite(joint).all():
            raise ValueError(f"a joint embedding has {self.input_dim} finite numbers, got {joint.shape[0]} (use embed_text or embed_image)")
        return joint

    def codes(self, embedding, snap: bool = True, colour: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Codes ``(shape [S], color [C])`` of a joint embedding; with ``snap`` each is the nearest
        codebook entry, the colour among the instances wearing palette ``colour`` when any does
        (``model.prior.query.colour_wearers``: captioned with it and, where any is, dominated by
        it in renders of their own codes)."""
        shape, color = self._session.run([SHAPE_INPUT, COLOR_INPUT], {EMBEDDING_INPUT: self._check(embedding)[None]})
        shape, color = shape[0], color[0]
        if snap:
            wearers = colour_wearers(self.instance_colours, colour, self.rendered_colours)
            colours = self.color_book[wearers] if wearers else self.color_book
            shape, color = _nearest(shape, self.shape_book, self._shape_scale), _nearest(color, colours, self._color_scale)
        return shape, color

    def text_codes(self, text: str, snap: bool = True) -> tuple[np.ndarray, np.ndarray, PromptColour]:
        """Codes of a prompt and what was read from it (``model.prior.colour_words``): its colour
        words read as palette colours, and the colour it names constraining the snapped colour code."""
        read = palette_prompt(text)
        return (*self.codes(self._text_joint(read), snap, read.palette), read)

    def retrieve(self, embedding, k: int = 5) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` instances whose codes are nearest the codes the query network predicts from the
        image part of a joint embedding: ``(instance rows [k], similarities [k])``, best first. The
        similarity is ``exp(-d)``, ``d`` the mean squared distance in standardised code units over
        shape and colour. Ranking by predicted codes retrieves better than comparing embeddings
        with a per-instance bank (BENCHMARKS.md: 99.3% against 88.7% top-1 on new poses)."""
        slot = self.slot("image")
        joint = self._check(embedding)
        if not joint[slot.offset : slot.offset + slot.dim].any():
            raise ValueError("retrieval reads the image part of an embedding and this one has none; embed an image with embed_image")
        image_only = np.zeros_like(joint)
        image_only[slot.offset : slot.offset + slot.dim] = joint[slot.offset : slot.offset + slot.dim]
        shape, color = self.codes(image_only, snap=False)
        distance = code_distance(shape, self.shape_book, self._shape_scale) + code_distance(color, self.color_book, self._color_scale)
        order = np.argsort(distance, kind="stable")[: min(k, len(distance))]
        return order, np.exp(-distance[order])


def code_distance(code: np.ndarray, book: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Mean squared distance ``[I]`` from ``code [D]`` to each row of ``book [I, D]`` in units of ``scale [D]``."""
    return (((book - code) / scale) ** 2).mean(axis=1)


def _nearest(code: np.ndarray, book: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The row of ``book [I, D]`` nearest ``code [D]`` in units of ``scale [D]``."""
    return book[int(code_distance(code, book, scale).argmin())].copy()
